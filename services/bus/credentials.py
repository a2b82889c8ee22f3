"""Per-role credentials for the bus: ``psm secrets OUT_DIR [--roles ...] [--force]``.

Writes, for each role of :mod:`services.bus.acl` (default: all of them),
``OUT_DIR/<role>.password`` (a random ``secrets.token_urlsafe`` password, mode 0600) and
``OUT_DIR/users.txt``, the router's zenoh user/password dictionary (``<role>:<password>``
lines, mode 0600). A password file that exists is kept (``--force`` replaces it), so running a
deployment's set-up again does not lock out the services already running with the old
passwords; ``users.txt`` is rewritten from the password files when its content differs (the
router reads it when it starts). A deployment mounts ``<role>.password`` into the process of
that role (``PSM_ZENOH__USER=<role>``, ``PSM_ZENOH__PASSWORD_FILE=<file>``) and ``users.txt``
into the router (``PSM_ROUTER__USERS_FILE``); none of them is committed (docs/security.md).

Example::

    psm secrets out/secrets                 # every role
    psm secrets out/secrets --roles planner arm --force
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["USERS_FILE", "Secrets", "password_file", "write_secrets"]

#: The router's dictionary inside the secrets directory.
USERS_FILE = "users.txt"
_TOKEN_BYTES = 32


def password_file(out_dir: str | Path, role: str) -> Path:
    """Where the password of ``role`` is in a secrets directory."""
    return Path(out_dir) / f"{role}.password"


@dataclass
class Secrets:
    """What :func:`write_secrets` did: the files written and the ones kept."""

    out_dir: Path
    users_file: Path
    written: list[Path] = field(default_factory=list)
    kept: list[Path] = field(default_factory=list)


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` readable by its owner only (0600, also when it existed)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, text.encode())
    finally:
        os.close(fd)


def write_secrets(
    out_dir: str | Path,
    roles: Iterable[str] | None = None,
    *,
    force: bool = False,
    owner: tuple[int, int] | None = None,
) -> Secrets:
    """Create the password files of ``roles`` (default: every role) and the router's
    dictionary in ``out_dir`` (see the module docstring). ``owner`` (uid, gid): the files and
    the directory belong to that user (the containers' user when they run as another one than
    the deployer; needs root), still readable by it alone. Raises ``ValueError`` for an unknown
    role or an existing password file that is empty."""
    from services.bus.acl import ROLE_NAMES

    names = list(dict.fromkeys(roles if roles is not None else ROLE_NAMES))
    unknown = [r for r in names if r not in ROLE_NAMES]
    if unknown:
        raise ValueError(f"unknown role {unknown[0]!r} (roles: {', '.join(ROLE_NAMES)})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    os.chmod(out, 0o700)
    result = Secrets(out, out / USERS_FILE)
    lines = []
    for role in names:
        path = password_file(out, role)
        if path.exists() and not force:
            password = path.read_text(encoding="utf-8").strip()
            if not password:
                raise ValueError(f"{path} is empty (--force writes a new password)")
            result.kept.append(path)
        else:
            password = secrets.token_urlsafe(_TOKEN_BYTES)
            _write_private(path, password + "\n")
            result.written.append(path)
        lines.append(f"{role}:{password}\n")
    users = "".join(lines)
    old = result.users_file.read_text(encoding="utf-8") if result.users_file.exists() else None
    if old != users:
        _write_private(result.users_file, users)
        result.written.append(result.users_file)
    else:
        result.kept.append(result.users_file)
    if owner is not None:
        for path in [out, result.users_file, *(password_file(out, r) for r in names)]:
            os.chown(path, *owner)
    return result
