"""A real Docker engine for the compose tests: the image built once per session, projects
started from the committed compose files, torn down with ``down -v`` whatever happens.

Without an engine (or compose) the tests skip, except when ``PSM_REQUIRE_DOCKER=1`` (CI): then
they fail. The arm's host runs with ``compose.lockstep.yaml``: the stack on the lockstep clock,
so a run is decided by what the services do, not by how loaded the machine is (on this 2-core
machine the realtime stack in containers needs most of both cores, and a slower CI machine
made the control loop miss its deadlines). Real-time scheduling in a container
(``compose.realtime.yaml``) is checked on its own (:func:`realtime_probe`).
``PSM_BASE_IMAGE`` picks the image's base (``.ci/run`` builds ``psm-base:bookworm`` when the
public one cannot be pulled)."""

from __future__ import annotations

import functools
import json
import os
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCKER_DIR = ROOT / "docker"
IMAGE_TAG = "test"
#: The image's user (docker/Dockerfile).
IMAGE_UID = 10001


def _run(cmd: list[str], timeout_s: float, **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False, **kw)  # type: ignore[call-overload]


#: The compose implementations the stack must work with, by name: the ``docker compose`` v2
#: plugin and the ``docker-compose`` 1.29 that Debian 12 ships (``docker/install-compose-v2.sh``
#: installs the plugin beside it).
COMPOSE_VERSIONS = {"v2": (["docker", "compose"], "2."), "1.29": (["docker-compose"], "1.29")}


@functools.cache
def compose_commands() -> dict[str, list[str]]:
    """The implementations of :data:`COMPOSE_VERSIONS` installed here, by name, v2 first."""
    found = {}
    for name, (cmd, version) in COMPOSE_VERSIONS.items():
        if not shutil.which(cmd[0]):
            continue
        res = _run([*cmd, "version", "--short"], 30)
        if res.returncode == 0 and res.stdout.strip().lstrip("v").startswith(version):
            found[name] = cmd
    return found


def _unavailable(reason: str) -> None:
    if os.environ.get("PSM_REQUIRE_DOCKER") == "1":
        pytest.fail(f"PSM_REQUIRE_DOCKER=1 but {reason}")
    pytest.skip(reason)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Engine:
    """The compose command and the environment every project of the session uses."""

    compose: list[str]  # v2 when installed, else 1.29
    env: dict[str, str]
    #: Every implementation installed (:func:`compose_commands`).
    composes: dict[str, list[str]] = field(default_factory=dict)


REALTIME_FILE = "compose.realtime.yaml"
LOCKSTEP_FILE = "compose.lockstep.yaml"


def realtime_probe(env: dict[str, str]) -> str:
    """``""`` when a container of the image with compose.realtime.yaml's grants switches to
    SCHED_FIFO as the image's user, else why not."""
    import yaml

    svc = next(iter(yaml.safe_load((DOCKER_DIR / REALTIME_FILE).read_text())["services"].values()))
    code = "import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))"
    res = _run(["docker", "run", "--rm", "--cap-add", "SYS_NICE",
                "--cpu-rt-period", str(svc["cpu_rt_period"]), "--cpu-rt-runtime", str(svc["cpu_rt_runtime"]),
                "--entrypoint", svc["command"][0], f"psm-dataflow:{IMAGE_TAG}", "-c", code], 120, env=env)
    return "" if res.returncode == 0 else (res.stderr.strip().splitlines() or ["failed"])[-1]


@pytest.fixture(scope="session")
def engine(tmp_path_factory: pytest.TempPathFactory) -> Engine:
    """A running engine with compose and the image built (skips/fails as the module says)."""
    if not shutil.which("docker"):
        _unavailable("no docker client")
    if _run(["docker", "info", "--format", "{{.ServerVersion}}"], 60).returncode != 0:
        _unavailable("no Docker engine running")
    composes = compose_commands()
    if not composes:
        _unavailable("neither `docker compose` v2 nor `docker-compose` 1.29")
    compose = next(iter(composes.values()))
    env = dict(os.environ)
    env["PSM_IMAGE_TAG"] = IMAGE_TAG
    # The credentials of every role, readable by the containers' user alone.
    secrets_dir = tmp_path_factory.mktemp("secrets")
    from services.bus.credentials import write_secrets

    write_secrets(secrets_dir, owner=(IMAGE_UID, IMAGE_UID) if os.getuid() == 0 else None)
    env["PSM_SECRETS_DIR"] = str(secrets_dir)
    env.setdefault("PSM_BASE_IMAGE", "python:3.11-slim")
    if os.getuid() != 0:
        env["PSM_UID"], env["PSM_GID"] = str(os.getuid()), str(os.getgid())
    t0 = time.monotonic()
    build = _run([*compose, "-f", str(DOCKER_DIR / "compose.yaml"), "-p", "psmbuild", "build", "router"],
                 1200, env=env, cwd=DOCKER_DIR)
    assert build.returncode == 0, f"image build failed:\n{build.stdout[-3000:]}\n{build.stderr[-3000:]}"
    print(f"image built in {time.monotonic() - t0:.1f} s")
    return Engine(compose, env, composes)


@dataclass
class Project:
    """One compose project: its files, name and environment."""

    engine: Engine
    name: str
    files: list[str]
    env: dict[str, str] = field(default_factory=dict)
    compose: list[str] | None = None  # None: the engine's

    def cmd(self, *args: str, timeout_s: float = 300.0) -> subprocess.CompletedProcess[str]:
        argv = [*(self.compose or self.engine.compose), "-p", self.name]
        for f in self.files:
            argv += ["-f", str(DOCKER_DIR / f)]
        return _run([*argv, *args], timeout_s, env={**self.engine.env, **self.env}, cwd=DOCKER_DIR)

    def container(self, service: str) -> str:
        """The container id of ``service``, running or exited (v2 lists only running ones
        without ``-a``)."""
        out = self.cmd("ps", "-a", "-q", service, timeout_s=60).stdout.split()
        assert out, f"no container for {service} in {self.name}"
        return out[0]

    def inspect(self, service: str) -> dict[str, object]:
        res = _run(["docker", "inspect", self.container(service)], 60)
        return json.loads(res.stdout)[0]  # type: ignore[no-any-return]

    def health(self, service: str) -> str:
        state = self.inspect(service)["State"]
        assert isinstance(state, dict)
        if state.get("Health"):
            return str(state["Health"]["Status"])
        return str(state.get("Status"))

    def logs(self, service: str) -> str:
        res = _run(["docker", "logs", self.container(service)], 60)
        return res.stdout + res.stderr

    def wait_healthy(self, services: list[str], timeout_s: float) -> float:
        """Wait until every service is healthy; returns the time it took [s]."""
        t0 = time.monotonic()
        deadline = t0 + timeout_s
        status: dict[str, str] = {}
        while time.monotonic() < deadline:
            status = {s: self.health(s) for s in services}
            if all(v == "healthy" for v in status.values()):
                return time.monotonic() - t0
            assert "unhealthy" not in status.values(), f"unhealthy: {status}"
            time.sleep(1.0)
        pytest.fail(f"not healthy within {timeout_s:.0f} s: {status}")

    def wait_exit(self, service: str, timeout_s: float) -> int:
        """Wait for ``service`` to exit (not restarting); returns its exit code."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            info = self.inspect(service)
            state = info["State"]
            assert isinstance(state, dict)
            if state.get("Status") == "exited":
                return int(state["ExitCode"])
            if info.get("RestartCount"):
                pytest.fail(f"{service} failed and was restarted:\n{self.logs(service)[-4000:]}")
            time.sleep(1.0)
        pytest.fail(f"{service} still running after {timeout_s:.0f} s:\n{self.logs(service)[-4000:]}")

    def wait_log(
        self, service: str, text: str, timeout_s: float, *, seen: int = 0,
        context: Sequence[tuple[Project, str]] = (),
    ) -> float:
        """Wait until ``text`` is in the logs of ``service`` more than ``seen`` times; returns
        the time it took [s]. On a timeout the failure shows the tail of that log and of every
        ``(project, service)`` in ``context``."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            if self.logs(service).count(text) > seen:
                return time.monotonic() - t0
            time.sleep(0.25)
        tails = [f"--- {self.name}/{service}:\n{self.logs(service)[-4000:]}"]
        tails += [f"--- {p.name}/{s}:\n{p.logs(s)[-6000:]}" for p, s in context]
        pytest.fail(f"{text!r} not in the {service} log within {timeout_s:.0f} s:\n" + "\n".join(tails))


@pytest.fixture
def project_factory(engine: Engine, tmp_path: Path) -> Iterator[object]:
    """Make projects; every one made is taken down with ``down -v`` at the end."""
    made: list[Project] = []

    def make(name: str, files: list[str], env: dict[str, str] | None = None,
             compose: str | None = None) -> Project:
        """``compose``: the implementation to run it with (a :data:`COMPOSE_VERSIONS` name;
        None: the engine's). One that is not installed skips the test, or fails it in CI."""
        if "compose.yaml" in files:
            files = [*files, LOCKSTEP_FILE]
        command = None
        if compose is not None:
            if compose not in engine.composes:
                _unavailable(f"compose {compose} is not installed (docker/install-compose-v2.sh)")
            command = engine.composes[compose]
        p = Project(engine, f"{name}{os.getpid()}", files, dict(env or {}), command)
        made.append(p)
        return p

    yield make
    for p in reversed(made):
        res = p.cmd("down", "-v", "-t", "5", timeout_s=180)
        if res.returncode != 0:
            print(f"down {p.name}: {res.stderr[-2000:]}")


def host_dir(path: Path) -> Path:
    """A host directory the containers' user can write."""
    path.mkdir(parents=True, exist_ok=True)
    if os.getuid() == 0:
        os.chown(path, IMAGE_UID, IMAGE_UID)
    return path
