"""A service stops cleanly under a storm of SIGTERMs (a supervisor's stop plus the parent-death
signal, a user's repeated Ctrl-C): the signal handler takes no lock, so a signal arriving while
another is being handled cannot deadlock the process."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from .helpers import Proc, wait_for

pytestmark = pytest.mark.integration


def test_a_storm_of_sigterms_stops_the_service_cleanly(router: str, tmp_path: Path) -> None:
    for attempt in range(3):
        p = Proc(["-m", "services.cli", "echo", "-q", "--connect", router, "--no-multicast",
                  "--mode", "client"], tmp_path, f"echo{attempt}")
        try:
            assert wait_for(lambda p=p: "session open" in p.stderr() or not p.alive(), 30), p.stderr()
            time.sleep(0.3)
            for _ in range(300):  # spaced, so that they are not merged into one pending signal
                if not p.alive():
                    break
                os.kill(p.pid, signal.SIGTERM)
                time.sleep(0.002)
            rc = p.wait(15)
            # the shutdown ran to its end (a SIGTERM after it, while the interpreter exits,
            # may still end the process with the default action)
            assert rc in (0, -signal.SIGTERM), p.stderr()
            assert "closed" in p.stderr() and "Traceback" not in p.stderr(), p.stderr()
        finally:
            p.stop()
