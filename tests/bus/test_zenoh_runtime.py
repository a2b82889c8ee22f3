"""Zenoh's thread pools (``zenoh.runtime``): the setting, its validation, and its effect on a
process's threads."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from services.bus.config import ConfigError, ServiceConfig, ZenohConfig, load_config
from services.bus.runtime import ZENOH_RUNTIME_APPLIED_ENV, ZENOH_RUNTIME_ENV, apply_zenoh_runtime

DEFAULT = "(rx: (handover: app), acc: (handover: app))"


def test_the_setting_is_zenohs_syntax_and_empty_means_zenohs_defaults() -> None:
    assert ZenohConfig().runtime_setting() == DEFAULT
    assert ZenohConfig(runtime={}).runtime_setting() == ""
    cfg = ZenohConfig(runtime={"app": {"worker_threads": 2}, "tx": {"max_blocking_threads": 4}})
    assert cfg.runtime_setting() == "(app: (worker_threads: 2), tx: (max_blocking_threads: 4))"


@pytest.mark.parametrize(("value", "field"), [
    ({"rx": {"handover": "rx"}}, "zenoh.runtime.rx.handover"),
    ({"rx": {"handover": "app"}, "app": {"handover": "tx"}}, "zenoh.runtime.rx.handover"),
    ({"rx": {"handover": "bogus"}}, "zenoh.runtime.rx.handover"),
    ({"rx": {"threads": 2}}, "zenoh.runtime.rx.threads"),
    ({"udp": {}}, "zenoh.runtime.udp"),
    ({"app": {"worker_threads": 0}}, "zenoh.runtime.app.worker_threads"),
])
def test_a_bad_runtime_is_one_error_naming_the_field(value: dict, field: str) -> None:
    """Zenoh itself would panic on these at the first session (a Rust backtrace)."""
    with pytest.raises(ConfigError) as err:
        load_config(ServiceConfig, env={"PSM_ZENOH__RUNTIME": json.dumps(value)})
    assert field in str(err.value), str(err.value)


def test_applying_it_sets_zenohs_variable_and_an_empty_one_removes_only_what_it_set(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv(ZENOH_RUNTIME_ENV, raising=False)
    monkeypatch.delenv(ZENOH_RUNTIME_APPLIED_ENV, raising=False)
    apply_zenoh_runtime(ZenohConfig())
    assert os.environ[ZENOH_RUNTIME_ENV] == DEFAULT
    apply_zenoh_runtime(ZenohConfig(runtime={}))  # inherited from a parent that applied it
    assert ZENOH_RUNTIME_ENV not in os.environ and ZENOH_RUNTIME_APPLIED_ENV not in os.environ
    monkeypatch.setenv(ZENOH_RUNTIME_ENV, "(app: (worker_threads: 3))")  # the user's own
    apply_zenoh_runtime(ZenohConfig(runtime={}))
    assert os.environ[ZENOH_RUNTIME_ENV] == "(app: (worker_threads: 3))"


_THREADS = """
import json, os, sys
from services.bus.config import ZenohConfig
from services.bus.runtime import open_session
from services.supervisor import free_port
import threading, time
runtime = json.loads(sys.argv[1])
ep = [f"tcp/127.0.0.1:{free_port()}"]
a = open_session(ZenohConfig(mode="peer", listen=ep, multicast=False, runtime=runtime))
b = open_session(ZenohConfig(mode="peer", connect=ep, multicast=False, runtime=runtime))
got = threading.Event()
sub = a.declare_subscriber("t/x", lambda s: got.set())
deadline = time.monotonic() + 20
while not got.is_set() and time.monotonic() < deadline:
    b.put("t/x", b"1")
    got.wait(0.05)
names = sorted(open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task"))
b.close()
a.close()
print(json.dumps([got.is_set(), names]))
"""


def _zenoh_threads(runtime: dict) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in (ZENOH_RUNTIME_ENV, ZENOH_RUNTIME_APPLIED_ENV)}
    out = subprocess.run([sys.executable, "-c", _THREADS, json.dumps(runtime)], capture_output=True,
                         text=True, timeout=60, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    delivered, names = json.loads(out.stdout.splitlines()[-1])
    assert delivered
    return [n for n in names if n.split("-")[0] in ("rx", "acc", "app", "tx", "net")]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/task")
def test_the_default_runs_receive_and_accept_work_on_the_application_thread() -> None:
    """Two linked sessions with the default open no receive or accept threads of their own (a
    sample still crosses the link); with Zenoh's defaults (``{}``) there are two receive
    threads and an accept thread."""
    default = _zenoh_threads(ZenohConfig().model_dump()["runtime"])
    assert not [n for n in default if n.startswith(("rx-", "acc-"))], default
    assert "app-0" in default
    zenohs = _zenoh_threads({})
    assert {"rx-0", "rx-1", "acc-0"} <= set(zenohs), zenohs
