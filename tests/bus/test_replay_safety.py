"""Replay never moves a live arm: command streams are left out unless ``--include-commands``,
and even then refused while an arm's liveliness token is alive on the target prefix, unless
``--force`` (real replayer processes on loopback, multicast off)."""

from __future__ import annotations

import threading
import time

import pytest

from services.bus.messages import Keys
from services.bus.runtime import RawSample, Service

from .fixture_data import PATH as FIXTURE
from .fixture_data import fixture_samples
from .helpers import bus_args, client_config, one_error_line, run_psm, wait_for

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

COMMAND_KEY = Keys("psm").arm_command.key
N_COMMANDS = sum(k == COMMAND_KEY for k, *_ in fixture_samples())


class _Listener:
    """A subscriber on ``<prefix>/**`` collecting every non-status sample."""

    def __init__(self, router: str, prefix: str = "psm") -> None:
        self.got: list[RawSample] = []
        self._lock = threading.Lock()
        self.svc = Service("listener", client_config(router)).start()
        self.svc.subscribe_raw(f"{prefix}/**", self._on)

    def _on(self, raw: RawSample) -> None:
        if "/status/" not in raw.key and "/alive/" not in raw.key:
            with self._lock:
                self.got.append(raw)

    def received_keys(self) -> list[str]:
        with self._lock:
            return [r.key for r in self.got]


def test_commands_are_not_replayed_unless_asked_for(router: str) -> None:
    assert Keys("psm").arm_command.is_command and Keys("psm").arm_command.commands == "arm"
    assert not any(t.is_command for t in Keys("psm").catalogue() if t.key != COMMAND_KEY)
    n_other = len(fixture_samples()) - N_COMMANDS
    listener = _Listener(router)
    try:
        time.sleep(0.5)
        r = run_psm("replay", str(FIXTURE), "--as-fast-as-possible", "--wait-subscribers", "5",
                    *bus_args(router))
        assert r.returncode == 0, r.stderr
        assert "not replaying command keys" in r.stderr
        assert wait_for(lambda: len(listener.received_keys()) >= n_other, 10)
        time.sleep(0.5)
        assert COMMAND_KEY not in listener.received_keys()
        assert len(listener.received_keys()) == n_other
        # asked for explicitly, with no arm alive: the commands go out
        listener.got.clear()
        r = run_psm("replay", str(FIXTURE), "--as-fast-as-possible", "--include-commands",
                    "--wait-subscribers", "5", *bus_args(router))
        assert r.returncode == 0, r.stderr
        assert wait_for(lambda: listener.received_keys().count(COMMAND_KEY) == N_COMMANDS, 10)
    finally:
        listener.svc.close()


def test_commands_to_a_live_arm_are_refused_unless_forced(router: str) -> None:
    from services.bus.runtime import open_session

    arm = open_session(client_config(router).zenoh)  # a fake arm: only its liveliness token
    token = arm.liveliness().declare_token(Keys("sim").liveliness("arm").key)
    listener = _Listener(router, "sim")
    try:
        time.sleep(0.5)
        # the arm lives on "sim": a replay remapped there is refused, nothing is published
        r = run_psm("replay", str(FIXTURE), "--as-fast-as-possible", "--include-commands",
                    "--remap-prefix", "psm=sim", *bus_args(router))
        msg = one_error_line(r, "psm replay")
        assert msg.startswith("refusing to replay psm/arm/command: sim/alive/arm is alive"), msg
        time.sleep(0.5)
        assert listener.received_keys() == []
        # the same replay onto the original prefix, where no arm lives, is allowed
        r = run_psm("replay", str(FIXTURE), "--as-fast-as-possible", "--include-commands",
                    *bus_args(router))
        assert r.returncode == 0, r.stderr
        # --force overrides the check
        r = run_psm("replay", str(FIXTURE), "--as-fast-as-possible", "--include-commands",
                    "--force", "--remap-prefix", "psm=sim", "--wait-subscribers", "5",
                    *bus_args(router))
        assert r.returncode == 0, r.stderr
        assert wait_for(lambda: listener.received_keys().count("sim/arm/command") == N_COMMANDS, 10)
    finally:
        listener.svc.close()
        token.undeclare()
        arm.close()


def test_an_arm_appearing_during_a_command_replay_stops_it(procs, router: str) -> None:  # type: ignore[no-untyped-def]
    from services.bus.runtime import open_session

    rp = procs(["-m", "services.cli", "replay", str(FIXTURE), "--include-commands", "--loop",
                *bus_args(router)], "replay")
    assert wait_for(lambda: "replaying" in rp.stderr() or not rp.alive(), 20), rp.stderr()
    assert rp.alive(), rp.stderr()
    arm = open_session(client_config(router).zenoh)
    token = arm.liveliness().declare_token(Keys("psm").liveliness("arm").key)
    try:
        assert rp.wait(20) == 2
    finally:
        token.undeclare()
        arm.close()
    err = [ln for ln in rp.stderr().splitlines() if ln.startswith("psm replay: error: ")]
    assert len(err) == 1 and "stopped the replay: psm/alive/arm appeared" in err[0], err
