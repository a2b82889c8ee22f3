"""Errors of the bus layer that a user can act on, each with a one-line message.

:class:`BusError` is what :func:`services.bus.runtime.open_session` raises when Zenoh refuses
to open a session (an unreachable router, an endpoint already in use, a malformed endpoint);
the ``psm`` command line prints it as ``psm <command>: error: <message>`` with exit code 2.
:func:`zenoh_reason` turns Zenoh's error text (which carries Rust source locations) into that
one line.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

__all__ = ["BusError", "session_error", "zenoh_reason"]


class BusError(RuntimeError):
    """The bus cannot be used as asked: a Zenoh session that does not open, a replay that
    would command a live arm, a recording that cannot be written. ``str(err)`` is one line."""


_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")
_JSON5_MSG = re.compile(r'msg:\s*"((?:[^"\\]|\\.)*)"')
_OS_ERROR = re.compile(r"([A-Za-z][A-Za-z ]+?) \(os error \d+\)")


def zenoh_reason(exc: BaseException) -> str:
    """Zenoh's error message without Rust source locations and JSON5 wrappers, on one line,
    e.g. ``Unable to connect to any of [Single(tcp/127.0.0.1:7599)]!``."""
    text = str(exc)
    m = _JSON5_MSG.search(text)
    if m:
        text = m.group(1)
    text = _RUST_LOCATION.sub("", text)
    return " ".join(text.split()).strip()


def session_error(
    exc: BaseException, mode: str, connect: Sequence[str], listen: Sequence[str], *,
    user: str = "", zid: str = "",
) -> BusError:
    """A :class:`BusError` naming the endpoint(s) a failed ``zenoh.open`` was about.

    Args:
        exc: the ``zenoh.ZError`` raised by ``zenoh.open`` or by building the config.
        mode: the session mode (``peer``, ``client``, ``router``).
        connect: the configured connect endpoints, e.g. ``["tcp/127.0.0.1:7447"]``.
        listen: the configured listen endpoints.
        user: the user the session authenticates as (``""``: none). A router that refuses
            the credentials closes the connection during the handshake, which zenoh reports
            like an unreachable endpoint, so the message then names the credentials too.
        zid: the session's fixed zenoh id (``""``: zenoh's random one). A router refuses a
            second session with the id of one already connected, in the same way, so the
            message then names the id.
    """
    reason = zenoh_reason(exc)
    low = reason.lower()
    os_err = _OS_ERROR.search(reason)
    if "listener" in low or "bind" in low:
        why = os_err.group(1).lower() if os_err else reason
        where = ", ".join(listen) or "the default endpoint"
        return BusError(f"cannot listen on {where} ({mode} mode): {why}")
    if "unable to connect" in low:
        where = ", ".join(connect) or "any endpoint"
        if zid:
            return BusError(
                f"cannot connect to {where} ({mode} mode) as zenoh id {zid}: a session with "
                "this id is already connected there (the prefix's clock sampler: one synthetic "
                "camera on the arm's clock per prefix), or nothing answered there"
            )
        if user:
            return BusError(
                f"cannot connect to {where} ({mode} mode) as user {user!r}: nothing answered "
                "there or the router refused the credentials (is the router running and "
                "reachable? are zenoh.user and zenoh.password_file the ones in its users_file?)"
            )
        return BusError(
            f"cannot connect to {where} ({mode} mode): nothing answered there "
            "(is the router running and reachable? does it require authentication: "
            "zenoh.user and zenoh.password_file?)"
        )
    eps = [f"connect {', '.join(connect)}"] if connect else []
    eps += [f"listen {', '.join(listen)}"] if listen else []
    detail = f", {'; '.join(eps)}" if eps else ""
    return BusError(f"cannot open a zenoh session ({mode} mode{detail}): {reason}")
