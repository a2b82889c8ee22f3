"""The image's pins (docker/requirements.txt, written by docker/pin-requirements.sh) cover the
``services`` extra of pyproject.toml: every requirement is pinned, at a version it allows."""

from __future__ import annotations

import tomllib

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from tests.deploy.conftest import DOCKER_DIR, ROOT


def test_every_services_requirement_is_pinned_at_an_allowed_version() -> None:
    extra = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    pins: dict[str, str] = {}
    for line in (DOCKER_DIR / "requirements.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            name, _, version = line.partition("==")
            pins[canonicalize_name(name)] = version
    for text in extra["services"]:
        req = Requirement(text)
        name = canonicalize_name(req.name)
        assert name in pins, f"docker/requirements.txt does not pin {req.name} (docker/pin-requirements.sh)"
        assert req.specifier.contains(pins[name], prereleases=True), (req, pins[name])
    assert pins["foxglove-sdk"] == "0.30.3"
