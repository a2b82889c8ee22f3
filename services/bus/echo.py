"""``psm echo``: print bus messages as they arrive (like ``ros2 topic echo``) and check them.

Subscribes to ``<prefix>/**`` (or the given key expressions) and decodes every sample with
:func:`services.bus.messages.decode`, checking that its type is the one the catalogue assigns to
its key (:meth:`Keys.topic_for_key`). Garbage payloads, unknown encodings and wrong types are
counted as ``rejected`` on the echo service's status and logged; the service keeps running.

Example::

    psm echo 'psm/goals/*' --connect tcp/127.0.0.1:7447 --no-multicast
"""

from __future__ import annotations

import sys
from typing import Any, TextIO

from pydantic import Field

from services.bus.config import Section, ServiceConfig, StrList
from services.bus.runtime import Service, ServiceApp

__all__ = ["EchoConfig", "EchoSection", "format_message", "run_echo"]


class EchoSection(Section):
    """``[echo]`` section."""

    key_exprs: StrList = Field(default_factory=list, description="key expressions (default <prefix>/**)")
    quiet: bool = Field(False, description="do not print messages, only count and check them")
    max_bytes_field: int = Field(32, ge=0, description="print at most this many bytes of a bytes field")


class EchoConfig(ServiceConfig):
    """Echo service configuration."""

    echo: EchoSection = Field(default_factory=EchoSection)


def format_message(key: str, msg: Any, max_bytes: int = 32) -> str:
    """One line: ``key type {json fields}`` with long bytes fields elided."""
    from google.protobuf.json_format import MessageToDict

    d = MessageToDict(msg, preserving_proto_field_name=True)
    for name, value in list(d.items()):
        if isinstance(value, str) and len(value) > max_bytes * 2 and name == "data":
            d[name] = f"<{len(value) * 3 // 4} bytes>"
    import json

    return f"{key} {msg.DESCRIPTOR.full_name} {json.dumps(d, separators=(',', ':'))}"


def run_echo(cfg: EchoConfig, out: TextIO | None = None) -> int:
    """Echo until SIGINT/SIGTERM; returns the exit code.

    Raises :class:`~services.bus.messages.InvalidKeyError` for an invalid key expression
    before joining the bus."""
    from services.bus.messages import Keys, validate_key_expr
    from services.bus.runtime import run_service

    key_exprs = [validate_key_expr(k) for k in cfg.echo.key_exprs] or [Keys(cfg.prefix).all.key]
    return run_service(_Echo(cfg, key_exprs, out or sys.stdout))


class _Echo(ServiceApp):
    """Subscribes to the key expressions, decodes and prints every sample."""

    name = "echo"

    def __init__(self, cfg: EchoConfig, key_exprs: list[str], out: TextIO) -> None:
        super().__init__(cfg)
        self.cfg = cfg
        self.key_exprs = key_exprs
        self.out = out

    def setup(self, svc: Service) -> None:
        from services.bus.messages import decode

        echo = self.cfg.echo

        def on_sample(raw: Any) -> None:
            topic = svc.keys.topic_for_key(raw.key)
            try:
                msg = decode(raw.payload, raw.encoding, topic.msg_type if topic else None)
            except ValueError as exc:
                svc.record_rejection(raw.key, str(exc), getattr(exc, "kind", "malformed"))
                return
            if not echo.quiet:
                print(format_message(raw.key, msg, echo.max_bytes_field), file=self.out, flush=True)

        for kx in self.key_exprs:
            svc.subscribe_raw(kx, on_sample)
