"""A page opened in a real headless Chromium, driven over the Chrome DevTools Protocol.

The protocol runs over ``--remote-debugging-pipe`` (JSON messages separated by NUL bytes on file
descriptors 3 and 4 of the browser), so no WebSocket client and no TCP port are needed::

    page = open_page(Path("out/report.html"))
    page.images         # [(src, complete, naturalWidth), ...] of every <img>
    page.errors         # console errors, uncaught exceptions and failed loads, as text
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["BrowserError", "PageCheck", "chromium_path", "open_page"]

CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


class BrowserError(RuntimeError):
    """The browser could not be started or did not answer in time."""


@dataclass
class PageCheck:
    """What a page did once loaded: its images as ``(src, complete, naturalWidth)``, the error
    messages (console errors, exceptions, failed requests), the title and the number of
    ``<table>`` elements."""

    images: list[tuple[str, bool, int]] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    title: str = ""
    tables: int = 0


def chromium_path() -> str | None:
    """The Chromium (or Chrome) executable on PATH, or None."""
    for name in CANDIDATES:
        found = shutil.which(name)
        if found:
            return found
    return None


class _Pipe:
    """The two pipes of ``--remote-debugging-pipe``: requests in, responses and events out."""

    def __init__(self, proc: subprocess.Popen, to_browser: int, from_browser: int) -> None:
        self.proc = proc
        self.w, self.r = to_browser, from_browser
        self.buf = b""
        self.next_id = 0
        self.events: list[dict[str, Any]] = []

    def send(self, method: str, params: dict[str, Any] | None = None, session: str | None = None,
             timeout_s: float = 20.0) -> dict[str, Any]:
        self.next_id += 1
        msg: dict[str, Any] = {"id": self.next_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self.w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout_s
        while True:
            for m in self._read(deadline):
                if m.get("id") == self.next_id:
                    if "error" in m:
                        raise BrowserError(f"{method}: {m['error']}")
                    return m.get("result", {})
                self.events.append(m)

    def wait_event(self, method: str, timeout_s: float = 20.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while True:
            for i, m in enumerate(self.events):
                if m.get("method") == method:
                    return self.events.pop(i)
            self.events.extend(self._read(deadline))

    def _read(self, deadline: float) -> list[dict[str, Any]]:
        while b"\0" not in self.buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserError("the browser did not answer in time")
            ready, _, _ = select.select([self.r], [], [], min(left, 0.5))
            if not ready:
                if self.proc.poll() is not None:
                    raise BrowserError(f"the browser exited with code {self.proc.returncode}")
                continue
            chunk = os.read(self.r, 1 << 20)
            if not chunk:
                raise BrowserError("the browser closed its pipe")
            self.buf += chunk
        *msgs, self.buf = self.buf.split(b"\0")
        return [json.loads(m) for m in msgs if m]


_IMAGES_JS = (
    "JSON.stringify({images: Array.from(document.images).map(i => [i.getAttribute('src'), i.complete, "
    "i.naturalWidth]), title: document.title, tables: document.querySelectorAll('table').length})"
)


def open_page(page: Path, *, timeout_s: float = 60.0, settle_s: float = 0.3) -> PageCheck:
    """Load ``page`` (a local HTML file) in headless Chromium and report its images and errors.
    Raises :class:`BrowserError` when there is no browser or it does not answer within
    ``timeout_s`` [s]."""
    exe = chromium_path()
    if exe is None:
        raise BrowserError("no Chromium on PATH")
    to_r, to_w = os.pipe()
    from_r, from_w = os.pipe()
    # Keep the browser's ends off 3 and 4 so the redirections below cannot clobber them.
    to_r, from_w = (_above_4(fd) for fd in (to_r, from_w))
    profile = tempfile.mkdtemp(prefix="psm-chromium-")
    flags = [
        "--headless=new", "--remote-debugging-pipe", "--no-sandbox", "--disable-gpu",
        "--disable-dev-shm-usage", "--no-first-run", "--no-default-browser-check",
        "--disable-extensions", "--disable-background-networking", "--disable-sync",
        "--mute-audio", f"--user-data-dir={profile}", "about:blank",
    ]
    # The browser reads requests on fd 3 and writes on fd 4: bash moves the pipes there.
    script = f'exec "$0" "$@" 3<&{to_r} 4>&{from_w} {to_r}<&- {from_w}>&-'
    proc = subprocess.Popen(["bash", "-c", script, exe, *flags], pass_fds=(to_r, from_w),
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(to_r)
    os.close(from_w)
    pipe = _Pipe(proc, to_w, from_r)
    deadline = time.monotonic() + timeout_s
    try:
        target = pipe.send("Target.createTarget", {"url": "about:blank"}, timeout_s=timeout_s)
        session = pipe.send("Target.attachToTarget", {"targetId": target["targetId"], "flatten": True},
                            timeout_s=max(1.0, deadline - time.monotonic()))["sessionId"]
        for domain in ("Runtime", "Log", "Page", "Network"):
            pipe.send(f"{domain}.enable", session=session, timeout_s=max(1.0, deadline - time.monotonic()))
        pipe.send("Page.navigate", {"url": page.resolve().as_uri()}, session=session,
                  timeout_s=max(1.0, deadline - time.monotonic()))
        pipe.wait_event("Page.loadEventFired", timeout_s=max(1.0, deadline - time.monotonic()))
        url = page.resolve().as_uri()
        ready = "document.readyState === 'complete' && location.href === " + json.dumps(url)
        while not pipe.send("Runtime.evaluate", {"expression": ready, "returnByValue": True}, session=session,
                            timeout_s=max(1.0, deadline - time.monotonic()))["result"].get("value"):
            if time.monotonic() > deadline:
                raise BrowserError(f"{page} did not load in {timeout_s} s")
            time.sleep(0.05)
        time.sleep(settle_s)  # late console messages
        value = pipe.send("Runtime.evaluate", {"expression": _IMAGES_JS, "returnByValue": True},
                          session=session, timeout_s=max(1.0, deadline - time.monotonic()))
        data = json.loads(value["result"]["value"])
        check = PageCheck([(s, bool(c), int(w)) for s, c, w in data["images"]], [], data["title"],
                          int(data["tables"]))
        pipe.events.extend(_drain(pipe))
        for ev in pipe.events:
            method, params = ev.get("method", ""), ev.get("params", {})
            if method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
                check.errors.append("console: " + " ".join(str(a.get("value", a.get("description", "")))
                                                           for a in params.get("args", [])))
            elif method == "Runtime.exceptionThrown":
                check.errors.append("exception: " + str(params.get("exceptionDetails", {}).get("text", "")))
            elif method == "Log.entryAdded" and params.get("entry", {}).get("level") == "error":
                entry = params["entry"]
                check.errors.append(f"log: {entry.get('text', '')} {entry.get('url', '')}".strip())
            elif method == "Network.loadingFailed":
                check.errors.append(f"network: {params.get('errorText', '')} ({params.get('type', '')})")
        with contextlib.suppress(BrowserError):
            pipe.send("Browser.close", timeout_s=5.0)
        return check
    finally:
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
        os.close(to_w)
        os.close(from_r)
        shutil.rmtree(profile, ignore_errors=True)


def _above_4(fd: int) -> int:
    """``fd`` moved to a descriptor number above 4 (the original is closed)."""
    import fcntl

    if fd > 4:
        return fd
    new = fcntl.fcntl(fd, fcntl.F_DUPFD, 10)
    os.close(fd)
    return new


def _drain(pipe: _Pipe) -> list[dict[str, Any]]:
    """Events already sent by the browser (no waiting)."""
    out: list[dict[str, Any]] = []
    while True:
        ready, _, _ = select.select([pipe.r], [], [], 0)
        if not ready:
            return out
        chunk = os.read(pipe.r, 1 << 20)
        if not chunk:
            return out
        pipe.buf += chunk
        *msgs, pipe.buf = pipe.buf.split(b"\0")
        out.extend(json.loads(m) for m in msgs if m)
