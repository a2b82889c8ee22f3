"""Access control through the real router (``psm serve router`` with ``router.access_control``
on loopback): who may connect, who may move the arm, that every role still does its job
(latched history, liveliness, status, obstacle commands), that denials and refused logins are
in the router's log at its default level; the roles table, the secrets command, the config
errors and the log filter on their own; the feeding stack under access control."""

from __future__ import annotations

import stat
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from services.bus.acl import ROLE_NAMES, acl_config, permissions, roles, roles_markdown
from services.bus.credentials import USERS_FILE, password_file, write_secrets
from services.bus.messages import ArmCommand, Goal, Keys, ObstacleCommand, encoding_for
from services.supervisor import free_port

from .helpers import ROOT, Proc, client_config, one_error_line, port_open, run_psm, wait_for

KEYS = Keys("psm")


# --------------------------------------------------------------------------------------------
# The bus under access control
# --------------------------------------------------------------------------------------------


@dataclass
class AclBus:
    """A router with access control and the credentials of every role."""

    endpoint: str
    secrets: Path
    router: Proc

    def overrides(self, role: str, password: Path | None = None) -> dict[str, Any]:
        """Config overrides of a client session authenticating as ``role``."""
        return {"zenoh.mode": "client", "zenoh.user": role,
                "zenoh.password_file": str(password or password_file(self.secrets, role))}

    def env(self, role: str, password: Path | None = None) -> dict[str, str]:
        """The environment of a ``psm`` command authenticating as ``role``."""
        return {"PSM_ZENOH__USER": role,
                "PSM_ZENOH__PASSWORD_FILE": str(password or password_file(self.secrets, role))}

    def session(self, role: str) -> Any:
        """A zenoh client session (the project's ``open_session``) as ``role``."""
        from services.bus.runtime import open_session

        return open_session(client_config(self.endpoint, **self.overrides(role)).zenoh)

    def cli(self) -> list[str]:
        """``psm`` flags joining this bus as a client."""
        return ["--connect", self.endpoint, "--mode", "client", "--no-multicast"]

    def log(self) -> str:
        """The router's own log lines (stderr)."""
        return self.router.stderr()

    def wait_log(self, text: str, timeout_s: float = 10.0) -> bool:
        """Wait until ``text`` is in the router's log."""
        return wait_for(lambda: text in self.log(), timeout_s, 0.05)


@pytest.fixture
def acl_bus(procs: Callable[..., Proc], tmp_path: Path) -> Iterator[AclBus]:
    secrets_dir = write_secrets(tmp_path / "secrets").out_dir
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    p = procs(["-m", "services.cli", "serve", "router", "--listen", ep, "--no-multicast",
               "--set", "router.access_control=true",
               "--set", f'router.users_file="{secrets_dir / USERS_FILE}"'], "router")
    ok = wait_for(lambda: (port_open(port) and "router listening" in p.stderr()) or not p.alive(), 20.0)
    assert ok and p.alive(), f"router did not start: {p.stderr()}"
    yield AclBus(ep, secrets_dir, p)


def _denial(user: str, action: str, flow: str, key: str) -> str:
    return f"access denied user='{user}' action='{action}' flow='{flow}' key='{key}'"


pytestmark = pytest.mark.integration


def test_no_credentials_and_a_wrong_password_are_refused_and_logged(
    acl_bus: AclBus, tmp_path: Path
) -> None:
    result = run_psm("status", *acl_bus.cli(), timeout_s=60)
    assert "cannot connect" in one_error_line(result, "psm status")
    assert acl_bus.wait_log("login refused reason='no credentials'"), acl_bus.log()

    wrong = tmp_path / "wrong.password"
    wrong.write_text("not-the-password\n")
    result = run_psm("status", *acl_bus.cli(), env=acl_bus.env("planner", wrong), timeout_s=60)
    assert "as user 'planner'" in one_error_line(result, "psm status")
    assert acl_bus.wait_log("login refused reason='invalid password'"), acl_bus.log()

    result = run_psm("status", *acl_bus.cli(), env=acl_bus.env("mallory", wrong), timeout_s=60)
    assert "as user 'mallory'" in one_error_line(result, "psm status")
    assert acl_bus.wait_log("login refused reason='unknown user'"), acl_bus.log()

    from services.bus.errors import BusError
    from services.bus.runtime import open_session

    with pytest.raises(BusError, match="refused the credentials"):
        open_session(client_config(acl_bus.endpoint, **acl_bus.overrides("arm", wrong)).zenoh)


@pytest.mark.parametrize("intruder", ["goal_tracker", "operator"])
def test_only_the_planner_moves_the_arm(acl_bus: AclBus, intruder: str) -> None:
    import zenoh

    key = KEYS.arm_command.key
    arm = acl_bus.session("arm")
    ticks: list[int] = []
    arm.declare_subscriber(key, lambda s: ticks.append(ArmCommand.FromString(s.payload.to_bytes()).tick))

    def publisher(session: Any) -> Any:
        pub = session.declare_publisher(key, encoding=zenoh.Encoding(encoding_for(ArmCommand)))
        # Every role learns of the subscribers, so the intruder's commands do leave it: the
        # router is the one that drops them (and logs it).
        assert wait_for(lambda: pub.matching_status.matching, 10.0)
        return pub

    other = acl_bus.session(intruder)
    planner = acl_bus.session("planner")
    try:
        bad = publisher(other)
        for i in range(20):
            bad.put(ArmCommand(tick=1000 + i, mode=ArmCommand.CARTESIAN_ACCELERATION).SerializeToString())
            time.sleep(0.005)
        good = publisher(planner)
        for i in range(5):
            good.put(ArmCommand(tick=i, mode=ArmCommand.CARTESIAN_ACCELERATION).SerializeToString())
        assert wait_for(lambda: len(ticks) >= 5, 10.0), ticks
        time.sleep(0.3)
        assert ticks == [0, 1, 2, 3, 4]  # the planner's, none of the intruder's
        assert acl_bus.wait_log(_denial(intruder, "put", "ingress", key)), acl_bus.log()
        # 20 denied puts, one line (the repetitions are counted, logged at most every 10 s).
        assert acl_bus.log().count(_denial(intruder, "put", "ingress", key)) == 1
    finally:
        for s in (other, planner, arm):
            s.close()


def test_latched_history_liveliness_and_status_work_under_access_control(acl_bus: AclBus) -> None:
    from services.bus.runtime import Service

    def service(role: str, name: str) -> Service:
        cfg = client_config(acl_bus.endpoint, **acl_bus.overrides(role))
        return Service(name, cfg)

    tracker = service("goal_tracker", "goal_tracker").start()
    monitor = service("obstacle_monitor", "obstacle_monitor").start()
    late: list[Service] = []
    try:
        tracker.publisher(KEYS.goal("person")).put(Goal(stamp_ns=5, seq=7, name="person"))
        from services.bus.messages import ObstacleSet

        monitor.publisher(KEYS.obstacles).put(ObstacleSet(stamp_ns=5, seq=3))
        time.sleep(0.5)
        # Late joiners: the planner and the recorder get the latched samples from the
        # publishers' caches, and see the tracker's liveliness token.
        got: dict[str, list[tuple[str, int]]] = {"planner": [], "recorder": []}
        alive: dict[str, bool] = {}
        planner = service("planner", "planner")
        planner.subscribe(KEYS.goals_all, lambda m, k: got["planner"].append((k, m.seq)))
        planner.watch_liveliness(["goal_tracker"], lambda n, a: alive.__setitem__(n, a))
        late.append(planner.start())
        recorder = service("recorder", "recorder")
        for topic in (KEYS.goals_all, KEYS.obstacles):
            recorder.subscribe(topic, lambda m, k: got["recorder"].append((k, m.seq)))
        late.append(recorder.start())
        assert wait_for(lambda: alive.get("goal_tracker") is True, 10.0), acl_bus.log()
        assert wait_for(lambda: len(got["recorder"]) >= 2 and got["planner"], 10.0), (got, acl_bus.log())
        assert got["planner"] == [("psm/goals/person", 7)]
        assert sorted(got["recorder"]) == [("psm/goals/person", 7), ("psm/obstacles", 3)]

        # The operator lists the services with their status.
        result = run_psm("status", *acl_bus.cli(), env=acl_bus.env("operator"), timeout_s=60)
        assert result.returncode == 0, result.stderr
        for name in ("goal_tracker", "obstacle_monitor", "planner", "recorder", "router"):
            assert name in result.stdout, result.stdout
        assert "RUNNING" in result.stdout

        tracker.close()
        assert wait_for(lambda: alive.get("goal_tracker") is False, 10.0)
        assert "access denied" not in acl_bus.log(), acl_bus.log()
    finally:
        for s in (*late, monitor, tracker):
            s.close()


def test_the_operator_changes_obstacles_and_never_moves_the_arm(acl_bus: AclBus) -> None:
    from services.bus.runtime import Service

    cfg = client_config(acl_bus.endpoint, **acl_bus.overrides("obstacle_monitor"))
    monitor = Service("obstacle_monitor", cfg)
    commands: list[ObstacleCommand] = []
    monitor.subscribe(KEYS.obstacles_command, lambda m, k: commands.append(m))
    monitor.start()
    try:
        result = run_psm("obstacle", "add", "post", "--shape", "sphere", "--size", "0.08",
                         "--position", "0.4", "0.2", "0.5", *acl_bus.cli(),
                         env=acl_bus.env("operator"), timeout_s=60)
        assert result.returncode == 0, result.stderr
        assert "no obstacle monitor subscribed" not in result.stderr
        assert wait_for(lambda: bool(commands), 10.0)
        assert commands[0].action == ObstacleCommand.ADD and commands[0].obstacle.id == "post"
        # The tracker may not change obstacles.
        result = run_psm("obstacle", "clear", *acl_bus.cli(), env=acl_bus.env("goal_tracker"),
                         timeout_s=60)
        assert acl_bus.wait_log(_denial("goal_tracker", "put", "ingress", KEYS.obstacles_command.key))
        time.sleep(0.3)
        assert len(commands) == 1
    finally:
        monitor.close()


def _openssl_pki(d: Path, names: list[str]) -> None:
    """A self-signed CA (``ca.pem``) and, for each name, a key and a certificate with that
    common name signed by it (``<name>.key``, ``<name>.pem``; X.509 v3 with the loopback as
    subject alternative name: rustls accepts no v1 certificate)."""
    import subprocess

    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True, timeout=60)

    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem",
        "-days", "2", "-subj", "/CN=psm-test-ca")
    (d / "v3.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    for n in names:
        run("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{n}.key", "-out", f"{n}.csr",
            "-subj", f"/CN={n}")
        run("x509", "-req", "-in", f"{n}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
            "-CAcreateserial", "-out", f"{n}.pem", "-days", "2", "-extfile", "v3.ext")


@pytest.mark.skipif(__import__("shutil").which("openssl") is None, reason="needs the openssl CLI")
def test_tls_client_certificates_name_the_role(procs: Callable[..., Proc], tmp_path: Path) -> None:
    """The option for an untrusted network (docs/security.md): TLS with client certificates
    (mTLS); the access control also knows each role by its certificate's common name."""
    import json

    import zenoh

    from services.bus.errors import BusError
    from services.bus.runtime import open_session

    _openssl_pki(tmp_path, ["router", "arm", "planner", "goal_tracker"])
    ca = str(tmp_path / "ca.pem")

    def tls_file(name: str, side: str) -> str:
        tls: dict[str, object] = {"root_ca_certificate": ca, "enable_mtls": True}
        if name:
            tls[f"{side}_private_key"] = str(tmp_path / f"{name}.key")
            tls[f"{side}_certificate"] = str(tmp_path / f"{name}.pem")
        path = tmp_path / f"{name or 'nocert'}-{side}.json5"
        path.write_text(json.dumps({"transport": {"link": {"tls": tls}}}))
        return str(path)

    # One user without a role: whatever a session may do comes from its certificate.
    (tmp_path / "users.txt").write_text("device:device-password\n")
    (tmp_path / "device.password").write_text("device-password\n")
    port = free_port()
    router = procs(["-m", "services.cli", "serve", "router", "--listen", f"tls/127.0.0.1:{port}",
                    "--no-multicast", "--set", f'zenoh.config_file="{tls_file("router", "listen")}"',
                    "--set", "router.access_control=true",
                    "--set", f'router.users_file="{tmp_path / "users.txt"}"'], "router")
    assert wait_for(lambda: "router listening" in router.stderr() or not router.alive(), 20.0)
    assert router.alive(), router.stderr()

    def session(cert: str) -> Any:
        cfg = client_config(f"tls/localhost:{port}", **{
            "zenoh.mode": "client", "zenoh.config_file": tls_file(cert, "connect"),
            "zenoh.user": "device", "zenoh.password_file": str(tmp_path / "device.password")})
        return open_session(cfg.zenoh)

    with pytest.raises(BusError):
        session("")  # no client certificate: the TLS handshake fails
    key = KEYS.arm_command.key
    arm = session("arm")
    got: list[bytes] = []
    arm.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes()))
    senders = {"goal_tracker": session("goal_tracker"), "planner": session("planner")}
    try:
        for tick, s in enumerate(senders.values(), 1):  # the tracker's tick 1, the planner's 2
            pub = s.declare_publisher(key, encoding=zenoh.Encoding(encoding_for(ArmCommand)))
            assert wait_for(lambda p=pub: p.matching_status.matching, 10.0)
            pub.put(ArmCommand(tick=tick).SerializeToString())
        assert wait_for(lambda: bool(got), 10.0)
        time.sleep(0.3)
        assert got == [ArmCommand(tick=2).SerializeToString()]
        assert wait_for(lambda: "cert_common_name='goal_tracker' action='put'" in router.stderr(), 10.0)
    finally:
        for s in (*senders.values(), arm):
            s.close()


# --------------------------------------------------------------------------------------------
# The feeding stack under access control
# --------------------------------------------------------------------------------------------


@pytest.mark.timeout(400)
def test_the_feeding_task_completes_under_access_control(tmp_path: Path) -> None:
    from tests.stack_helpers import check_task, up

    rc, log, summary = up(tmp_path, "stack.access_control=true")
    assert rc == 0, log
    check_task(summary, log)
    run = tmp_path / "run"
    router_log = (run / "router.log").read_text()
    assert "access_control=True" in router_log
    assert "access denied" not in router_log and "login refused" not in router_log, router_log[-3000:]
    for role in ROLE_NAMES:
        f = password_file(run / "secrets", role)
        assert stat.S_IMODE(f.stat().st_mode) == 0o600
        assert f.read_text().strip() not in log + router_log  # never printed


# --------------------------------------------------------------------------------------------
# The roles table, the secrets, the configuration, the log filter
# --------------------------------------------------------------------------------------------


def _who(flow: str, message: str, key: str) -> set[str]:
    """The roles allowed ``message`` (``flow``) on exactly the rule key ``key``."""
    return {name for name, role in roles(KEYS).items()
            if any(p.flow == flow and p.message == message and p.key == key
                   for p in permissions(role, KEYS))}


@pytest.mark.parametrize(
    ("key", "publishers"),
    [
        (KEYS.arm_command.key, {"planner"}),
        (KEYS.arm_state.key, {"arm"}),
        (KEYS.goals_all.key, {"goal_tracker"}),
        (KEYS.collision.key, {"obstacle_monitor"}),
        (KEYS.obstacles.key, {"obstacle_monitor"}),
        (KEYS.obstacles_command.key, {"operator"}),
        (KEYS.planner_goal.key, {"planner"}),
        (KEYS.camera_images_all.key, {"camera", "goal_tracker"}),
    ],
)
def test_least_privilege_publishers(key: str, publishers: set[str]) -> None:
    assert _who("ingress", "put", key) == publishers
    # Nobody may put on the whole prefix, nor on a key it does not own through a wildcard.
    assert _who("ingress", "put", KEYS.all.key) == set()


def test_every_rule_key_is_valid_and_every_role_has_its_own_health() -> None:
    import zenoh

    conf = acl_config(KEYS)
    assert conf["default_permission"] == "deny"
    for rule in conf["rules"]:  # type: ignore[union-attr]
        for k in rule["key_exprs"]:
            zenoh.KeyExpr(k)
    for name, role in roles(KEYS).items():
        allowed = permissions(role, KEYS)
        triples = [(p.flow, p.message, p.key) for p in allowed]
        for service in role.services:
            assert ("ingress", "put", KEYS.status(service).key) in triples
            assert any(p.message == "liveliness_token" and p.key == KEYS.liveliness(service).key
                       for p in allowed), name
    # Latched topics need their own @adv rules (no wildcard matches the verbatim chunk).
    assert not zenoh.KeyExpr(KEYS.all.key).intersects("psm/goals/person/@adv/pub/x/1/_")
    assert "psm/goals/*/@adv/**" in {p.key for p in permissions(roles(KEYS)["planner"], KEYS)}


def test_the_security_doc_shows_the_roles_table() -> None:
    doc = (ROOT / "docs" / "security.md").read_text()
    assert roles_markdown(KEYS) in doc, "docs/security.md: paste services.bus.acl.roles_markdown(Keys('psm'))"


def test_secrets_are_private_kept_and_replaced_with_force(tmp_path: Path) -> None:
    out = tmp_path / "s"
    first = write_secrets(out)
    assert len(first.written) == len(ROLE_NAMES) + 1 and not first.kept
    assert stat.S_IMODE(out.stat().st_mode) == 0o700
    users = (out / USERS_FILE).read_text().splitlines()
    for role in ROLE_NAMES:
        f = password_file(out, role)
        assert stat.S_IMODE(f.stat().st_mode) == 0o600
        assert f"{role}:{f.read_text().strip()}" in users
    assert stat.S_IMODE((out / USERS_FILE).stat().st_mode) == 0o600
    before = password_file(out, "planner").read_text()
    again = write_secrets(out)
    assert not again.written and password_file(out, "planner").read_text() == before
    forced = write_secrets(out, ["planner"], force=True)
    assert password_file(out, "planner").read_text() != before
    assert forced.written == [password_file(out, "planner"), out / USERS_FILE]
    assert (out / USERS_FILE).read_text() == f"planner:{password_file(out, 'planner').read_text().strip()}\n"

    result = run_psm("secrets", str(tmp_path / "cli"), "--roles", "arm", "operator")
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in (tmp_path / "cli").iterdir()) == [
        "arm.password", "operator.password", USERS_FILE]
    for p in (tmp_path / "cli").iterdir():
        assert p.read_text().strip().split(":")[-1] not in result.stdout


@pytest.mark.parametrize(
    ("args", "env", "expected"),
    [
        (["--set", "zenoh.user=arm"], {}, "zenoh.password_file: is required with user 'arm'"),
        (["--set", "zenoh.user=arm"], {"PSM_ZENOH__PASSWORD_FILE": "/nonexistent/arm.password"},
         "zenoh.password_file (from $PSM_ZENOH__PASSWORD_FILE): cannot read "
         "/nonexistent/arm.password: no such file or directory"),
        ([], {"PSM_ZENOH__PASSWORD_FILE": "x"}, "zenoh.user: is empty but password_file is set"),
    ],
)
def test_credential_errors_are_one_line(args: list[str], env: dict[str, str], expected: str) -> None:
    result = run_psm("status", "--connect", "tcp/127.0.0.1:9", "--no-multicast", *args, env=env)
    assert one_error_line(result, "psm status").startswith(expected)


def test_router_access_control_needs_a_users_file(tmp_path: Path) -> None:
    result = run_psm("serve", "router", "--set", "router.access_control=true")
    assert one_error_line(result, "psm serve router") == (
        "router.users_file: is required with access_control = true")
    bad = tmp_path / "users.txt"
    bad.write_text("planner\n")
    result = run_psm("serve", "router", "--set", f'router.users_file="{bad}"')
    assert one_error_line(result, "psm serve router") == (
        f"router.users_file: {bad} line 1: expected user:password")


def test_the_stack_checks_roles_and_client_mode(tmp_path: Path) -> None:
    from services.bus.config import ConfigError
    from services.stack import DEFAULT_STACK, load_stack

    stack = load_stack(DEFAULT_STACK, overrides={"stack.access_control": True}, env={})
    assert [p.name for p in stack.processes if not p.is_router] == [
        r for r in ROLE_NAMES if r not in ("viewer", "operator")]
    # The stack file's processes are peers; under access control each is a client of the
    # router, listening on nothing, in its config and in the environment psm up gives it.
    from services.supervisor import Supervisor

    peers = load_stack(DEFAULT_STACK, env={})
    sup = Supervisor(stack)
    sup.secrets_dir = tmp_path / "secrets"
    for p in stack.processes:
        if p.is_router:
            continue
        assert peers.configs[p.name].zenoh.mode == "peer", p.name
        assert peers.configs[p.name].zenoh.listen == ["tcp/127.0.0.1:0"], p.name
        assert stack.configs[p.name].zenoh.mode == "client", p.name
        assert stack.configs[p.name].zenoh.listen == [], p.name
        env = sup._env_of(p)
        assert (env["PSM_ZENOH__MODE"], env["PSM_ZENOH__LISTEN"]) == ("client", "[]"), p.name
        assert env["PSM_ZENOH__USER"] == p.name
    viewed = load_stack(DEFAULT_STACK, overrides={"stack.access_control": True}, env={}, view=True)
    assert sorted(p.name for p in viewed.processes if not p.is_router) == sorted(ROLE_NAMES[:-1])
    text = DEFAULT_STACK.read_text().replace('name = "camera"', 'name = "webcam"')
    (tmp_path / "stack.toml").write_text(text)
    with pytest.raises(ConfigError, match="'webcam' is no access-control role"):
        load_stack(tmp_path / "stack.toml", overrides={"stack.access_control": True}, env={})
    with pytest.raises(ConfigError, match=r"zenoh\.mode: must be 'client'"):
        load_stack(DEFAULT_STACK, overrides={"stack.access_control": True, "zenoh.mode": "peer"},
                   env={})


# zenoh's own lines (ANSI colours removed), as the router's zenoh 1.10 writes them.
_T = ("2026-12-02T03:48:17.562885Z TRACE  rx-1 ThreadId(09) "
      "zenoh::net::routing::interceptor::access_control: ")
_ZID = "8a4acc8a6b731ca47b41d79ea306e2b9"
_SUBJ = f"{_ZID} on Interface(lo)+Username(goal_tracker)+Transport(Tcp)+{_ZID}"
_BLOCK = [f"{_T}ACL (ingress): caching permissions for `psm/arm/command` ..."] + [
    f"{_T}{_SUBJ} is unauthorized to {a} (ingress) on psm/arm/command"
    for a in ("Query", "Reply", "Put", "Delete", "Declare/Undeclare Subscriber",
              "Declare/Undeclare Queryable", "Declare/Undeclare Liveliness Token",
              "Liveliness Query", "Declare Liveliness Subscriber")
]
_CACHED_DENY = (f"{_T}Using cached result: 8a4acc8a6b731ca47b41d79ea306e2b9 is unauthorized to "
                "Put (ingress) on psm/arm/command")
_CACHED_ALLOW = _CACHED_DENY.replace("unauthorized", "authorized")


def test_the_log_filter_reports_attempts_not_zenohs_cache(capsys: pytest.CaptureFixture[str]) -> None:
    import logging

    from services.bus.acl_log import AclLog

    records: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    log = logging.getLogger("psm.test_acl_log")
    log.addHandler(Keep())
    acl = AclLog(log, repeat_s=3600.0)
    for line in [*_BLOCK, _CACHED_ALLOW, "plain zenoh output"]:
        acl.feed(("\x1b[2m" + line + "\x1b[0m").encode())
    assert records == []  # computing the cache is no attempt; allowed traffic is not logged
    for _ in range(3):
        acl.feed(_CACHED_DENY.encode())
    assert len(records) == 1
    r = records[0].__dict__
    assert (r["user"], r["action"], r["flow"], r["key"]) == ("goal_tracker", "put", "ingress",
                                                            "psm/arm/command")
    assert acl.denied == {("goal_tracker", "put", "ingress", "psm/arm/command"): 3}
    acl.feed(f"{_T}{_SUBJ} is unauthorized to Declare Subscriber (egress) on psm/x".encode())
    assert records[-1].__dict__["action"] == "declare_subscriber" and len(records) == 2


def test_the_viewer_reads_the_cell_under_access_control(
    acl_bus: AclBus, procs: Callable[..., Proc]
) -> None:
    """``psm view`` logs in as the read-only ``viewer`` role: it gets a goal published before it
    started (the publisher's cache) and the live status, and the router denies nothing."""
    from services.bus.runtime import Service

    from .test_viewer import watch

    tracker = Service("goal_tracker", client_config(
        acl_bus.endpoint, **acl_bus.overrides("goal_tracker"))).start()
    try:
        tracker.publisher(KEYS.goal("person")).put(Goal(stamp_ns=5, seq=7, name="person"))
        port = free_port()
        viewer = procs(["-m", "services.cli", "view", "--port", str(port), *acl_bus.cli()], "viewer",
                       env=acl_bus.env("viewer"))
        assert wait_for(lambda: port_open(port) or not viewer.alive(), 30.0) and viewer.alive(), \
            viewer.stderr()
        seen = watch(port, 20.0, until=lambda r: {"psm/goals/person", "psm/status/viewer"} <= set(r.messages))
        assert [Goal.FromString(p).seq for _, _, p in seen.messages["psm/goals/person"]] == [7]
        assert "psm/status/viewer" in seen.messages, (seen.channels, viewer.stderr())
        assert "access denied" not in acl_bus.log(), acl_bus.log()
    finally:
        tracker.close()
