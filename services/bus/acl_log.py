"""The router's access-control log: every denial and refused login as a WARNING line.

zenoh (1.10) logs an access-control decision only at TRACE, on the target
``zenoh::net::routing::interceptor::access_control``, and logs the *allowed* messages on the
same target at the same level (one line per message routed: ``Using cached result: <zid> is
authorized to Put (ingress) on psm/arm/state``); a refused login is a DEBUG line of
``zenoh_transport::unicast::establishment::accept``. A tracing filter selects targets and
levels, never messages, so the router turns these two targets up (:data:`ZENOH_LOG_DIRECTIVES`)
and reads zenoh's output itself: zenoh writes its log to stdout, which :class:`AclLog` points at
a pipe read by a thread. The thread drops the allowed decisions, reports each denial as one
project log line naming the subject, the message type and the key, and passes every other line
through to the real stdout::

    ... WARNING router: access denied user='goal_tracker' action='put' flow='ingress'
        key='psm/arm/command' zid='9d82c931...'
        subject='Interface(lo)+Username(goal_tracker)+Transport(Tcp)+9d82c931...' suppressed=0
    ... WARNING router: login refused reason='invalid password' remote='tcp/127.0.0.1:45748'
        zid='481240b7...'

(one line each, wrapped here).

zenoh's decisions are cached per key expression: when a session first uses a key, zenoh
computes the permission of all nine message types for it, logging each (those lines are not
attempts, and are skipped: :meth:`AclLog.feed` tracks these blocks per thread); afterwards each
message logs the cached decision with the session's id only, so the subject is taken from the
session's earlier lines. A denial that repeats (a publisher at 500 Hz) is logged once per
:attr:`AclLog.repeat_s` per (user, message type, flow, key) with the count of the ones in
between (``suppressed``). The thread reads what the pipe holds every :attr:`AclLog.batch_s`
(50 ms) instead of waking up for each of zenoh's lines; the pipe (1 MiB) holds well over that
much. Its write end is non-blocking: if the thread fell behind, zenoh's log lines would be
dropped, the router's traffic never waits for its log.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import re
import threading
import time
from typing import BinaryIO

__all__ = ["ACCEPT_TARGET", "ACL_TARGET", "ZENOH_LOG_DIRECTIVES", "AclLog"]

#: zenoh's tracing target of access-control decisions (all at TRACE).
ACL_TARGET = "zenoh::net::routing::interceptor::access_control"
#: zenoh's tracing target of the transport handshake (a refused login is a DEBUG line).
ACCEPT_TARGET = "zenoh_transport::unicast::establishment::accept"
#: What the router adds to zenoh's log filter (``RUST_LOG``) when access control is on.
ZENOH_LOG_DIRECTIVES = (f"{ACL_TARGET}=trace", f"{ACCEPT_TARGET}=trace")

_ANSI = re.compile(rb"\x1b\[[0-9;]*m")
_LINE = re.compile(
    r"^\S+\s+(?P<level>TRACE|DEBUG|INFO|WARN|ERROR)\s+(?:\S+\s+)?ThreadId\((?P<tid>\d+)\)\s+"
    r"(?P<target>[\w:]+): (?P<msg>.*)$"
)
_BLOCK = re.compile(r"^ACL \((?P<flow>ingress|egress)\): caching permissions for `(?P<key>.*)` \.\.\.$")
_DECISION = re.compile(
    r"^(?P<zid>[0-9a-f]+) on (?P<subject>\S+) is (?P<verdict>authorized|unauthorized) to "
    r"(?P<action>.+?) \((?P<flow>ingress|egress)\) on (?P<key>.+)$"
)
_CACHED = re.compile(
    r"^Using cached result: (?P<zid>[0-9a-f]+) is (?P<verdict>authorized|unauthorized) to "
    r"(?P<action>.+?) \((?P<flow>ingress|egress)\) on (?P<key>.+)$"
)
_NO_SUBJECT = re.compile(r"^(?P<zid>[0-9a-f]+) did not match any configured ACL subject")
_USERNAME = re.compile(r"Username\(([^)]*)\)")
_CERT_CN = re.compile(r"CertCommonName\(([^)]*)\)")
_HANDSHAKE = re.compile(r"^Establishment Accept (?P<step>\w+): \S+ => (?P<remote>\S+?)\.? ")
_HELLO_ZID = re.compile(r"InitSyn\(InitSyn \{[^}]*?zid: (?P<zid>[0-9a-f]+)")
_LOGIN_REASONS = {
    "Invalid password.": "invalid password",
    "Invalid user.": "unknown user",
    "Expected extension.": "no credentials",
}

#: zenoh's message names in its log -> the ACL config's message types.
_ACTIONS = {
    "Put": "put",
    "Delete": "delete",
    "Query": "query",
    "Reply": "reply",
    "Declare Subscriber": "declare_subscriber",
    "Undeclare Subscriber": "declare_subscriber",
    "Declare/Undeclare Subscriber": "declare_subscriber",
    "Declare Queryable": "declare_queryable",
    "Undeclare Queryable": "declare_queryable",
    "Declare/Undeclare Queryable": "declare_queryable",
    "Liveliness Token": "liveliness_token",
    "Undeclare Liveliness Token": "liveliness_token",
    "Declare/Undeclare Liveliness Token": "liveliness_token",
    "Liveliness Query": "liveliness_query",
    "Declare Liveliness Subscriber": "declare_liveliness_subscriber",
    "Undeclare Liveliness Subscriber": "declare_liveliness_subscriber",
}
#: The order in which zenoh computes a key's cached permissions (its ``Cache`` fields).
_BLOCK_ORDER = {
    "Query": 0,
    "Reply": 1,
    "Put": 2,
    "Delete": 3,
    "Declare/Undeclare Subscriber": 4,
    "Declare/Undeclare Queryable": 5,
    "Declare/Undeclare Liveliness Token": 6,
    "Liveliness Query": 7,
    "Declare Liveliness Subscriber": 8,
}
_PIPE_SIZE = 1 << 20  # bytes of zenoh log the pipe holds while the reader is busy or waits
_READ_BYTES = 1 << 18
_F_SETPIPE_SZ = 1031


def _key_of(text: str) -> str:
    """A key from zenoh's log: ``psm/a`` or, for undeclarations, ``Some(psm/a)``."""
    text = text.strip()
    if text.startswith("Some(") and text.endswith(")"):
        return text[5:-1]
    return text


class AclLog:
    """Reads zenoh's log (see the module docstring) and reports denials to ``log``."""

    def __init__(
        self, log: logging.Logger, *, repeat_s: float = 10.0, batch_s: float = 0.05
    ) -> None:
        self.log = log
        #: A repeated denial is logged at most once per this many seconds.
        self.repeat_s = repeat_s
        #: The reader sleeps this long after reading what the pipe held [s].
        self.batch_s = batch_s
        #: Denials reported (each repetition counted), by (user or zid, action, flow, key).
        self.denied: dict[tuple[str, str, str, str], int] = {}
        self.logins_refused = 0
        #: Lines of zenoh's output read (allowed decisions included).
        self.lines = 0
        self._subjects: dict[str, str] = {}  # zid -> zenoh's subject text
        self._blocks: dict[str, tuple[str, str, int]] = {}  # thread -> (flow, key, last index)
        self._links: dict[str, tuple[str, str]] = {}  # thread -> (remote, zid) of its handshake
        self._last: dict[tuple[str, str, str, str], tuple[float, int]] = {}
        self._out: BinaryIO | None = None
        self._saved_fd = -1
        self._read_fd = -1
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ the pipe
    def start(self) -> None:
        """Point this process's stdout at a pipe read by a thread (before zenoh logs)."""
        r, w = os.pipe()
        with contextlib.suppress(OSError):
            fcntl.fcntl(w, _F_SETPIPE_SZ, _PIPE_SIZE)
        os.set_blocking(w, False)
        self._saved_fd = os.dup(1)
        self._out = os.fdopen(os.dup(self._saved_fd), "wb", buffering=0)
        os.dup2(w, 1)
        os.close(w)
        self._read_fd = r
        self._thread = threading.Thread(target=self._run, name="acl-log", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Give stdout back and let the thread finish what zenoh wrote."""
        if self._thread is None:
            return
        os.dup2(self._saved_fd, 1)  # the pipe's last write end closes: the thread sees EOF
        os.close(self._saved_fd)
        self._thread.join(timeout_s)
        self._thread = None
        if self._out is not None:
            with contextlib.suppress(OSError):
                self._out.close()
            self._out = None

    def _run(self) -> None:
        rest = b""
        while True:
            try:
                chunk = os.read(self._read_fd, _READ_BYTES)
            except OSError:
                break
            if not chunk:
                break
            lines = (rest + chunk).split(b"\n")
            rest = lines.pop()
            for line in lines:
                self.feed(line)
            if len(chunk) < _READ_BYTES:
                # Let zenoh's lines pile up in the pipe rather than waking up for each one
                # (a few thousand a second under load; one wake-up per line cost more than the
                # lines themselves). A denial is logged at most this much later.
                time.sleep(self.batch_s)
        if rest:
            self.feed(rest)
        os.close(self._read_fd)

    def _pass(self, raw: bytes) -> None:
        out = self._out
        if out is not None:
            with contextlib.suppress(OSError, ValueError):  # ValueError: closed by stop()
                out.write(raw + b"\n")

    # ------------------------------------------------------------------ parsing
    def feed(self, raw: bytes) -> None:
        """Handle one line of zenoh's output."""
        self.lines += 1
        # The bulk: allowed messages on a cached key, skipped before any parsing.
        if b"Using cached result" in raw and b" is authorized " in raw:
            return
        text = _ANSI.sub(b"", raw).decode("utf-8", "replace")
        m = _LINE.match(text)
        if m is None or m["target"] not in (ACL_TARGET, ACCEPT_TARGET):
            self._pass(raw)
            return
        if m["target"] == ACCEPT_TARGET:
            self._accept_line(m["tid"], m["msg"])
            return
        msg = m["msg"]
        tid = m["tid"]
        if (b := _BLOCK.match(msg)) is not None:
            self._blocks[tid] = (b["flow"], b["key"], -1)
            return
        if (d := _DECISION.match(msg)) is not None:
            self._subjects[d["zid"]] = d["subject"]
            if self._in_block(tid, d["action"], d["flow"], d["key"]):
                return
            if d["verdict"] == "unauthorized":
                self._denied(d["zid"], d["action"], d["flow"], _key_of(d["key"]))
            return
        self._blocks.pop(tid, None)
        if (c := _CACHED.match(msg)) is not None:
            if c["verdict"] == "unauthorized":
                self._denied(c["zid"], c["action"], c["flow"], _key_of(c["key"]))
            return
        if (n := _NO_SUBJECT.match(msg)) is not None:
            self.log.warning(
                "session matches no access-control role: everything it sends is denied",
                extra={"zid": n["zid"]},
            )
            return
        if m["level"] in ("INFO", "WARN", "ERROR"):
            self._pass(raw)

    def _in_block(self, tid: str, action: str, flow: str, key: str) -> bool:
        """Whether a decision line belongs to the permission cache zenoh is computing on this
        thread (not an attempt); keeps the block's state."""
        block = self._blocks.get(tid)
        index = _BLOCK_ORDER.get(action)
        if block is None or index is None or block[0] != flow or block[1] != key or index < block[2]:
            self._blocks.pop(tid, None)
            return False
        self._blocks[tid] = (flow, key, index)
        return True

    def _accept_line(self, tid: str, msg: str) -> None:
        """The handshake target: remember who the thread's handshake is with (the remote
        endpoint, the session id it announced), report a refused login."""
        hs = _HANDSHAKE.match(msg)
        if hs is not None:
            zid = _HELLO_ZID.search(msg)
            old = self._links.get(tid, ("", ""))
            if hs["step"] == "InitSyn" or hs["remote"] != old[0]:
                old = (hs["remote"], "")
            self._links[tid] = (hs["remote"], zid["zid"] if zid else old[1])
            return
        if not msg.startswith("UsrPwd extension"):
            return
        for needle, reason in _LOGIN_REASONS.items():
            if needle in msg:
                remote, zid = self._links.get(tid, ("?", ""))
                self.logins_refused += 1
                self.log.warning("login refused", extra={"reason": reason, "remote": remote,
                                                         "zid": zid or "?"})
                return

    def _denied(self, zid: str, action: str, flow: str, key: str) -> None:
        subject = self._subjects.get(zid, "")
        user = _USERNAME.search(subject)
        cn = _CERT_CN.search(subject)
        who = user.group(1) if user else (cn.group(1) if cn else "")
        message = _ACTIONS.get(action, action)
        ident = (who or zid, message, flow, key)
        self.denied[ident] = self.denied.get(ident, 0) + 1
        now = time.monotonic()
        last = self._last.get(ident)
        if last is not None and now - last[0] < self.repeat_s:
            self._last[ident] = (last[0], last[1] + 1)
            return
        suppressed = 0 if last is None else last[1]
        self._last[ident] = (now, 0)
        extra: dict[str, object] = {}
        if user:
            extra["user"] = user.group(1)
        if cn:
            extra["cert_common_name"] = cn.group(1)
        extra.update({"action": message, "flow": flow, "key": key, "zid": zid,
                      "subject": subject or "?", "suppressed": suppressed})
        self.log.warning("access denied", extra=extra)
