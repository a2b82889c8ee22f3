"""Child process of ``test_signal_safe_inbox``: waits on an inbox in short timed waits (as the
arm's loop does) until SIGTERM; SIGUSR1 only interrupts the waits."""

from __future__ import annotations

import contextlib
import queue
import signal
import sys
import threading

from services.arm.service import command_inbox

stop = threading.Event()
signal.signal(signal.SIGUSR1, lambda *_: None)
signal.signal(signal.SIGTERM, lambda *_: stop.set())
inbox = queue.SimpleQueue() if sys.argv[1:] == ["simple"] else command_inbox()
print("ready", flush=True)
while not stop.is_set():
    with contextlib.suppress(queue.Empty):
        inbox.get(timeout=0.0005)
