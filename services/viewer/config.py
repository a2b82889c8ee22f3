"""Configuration of the live viewer (``psm view``): the ``[viewer]`` table on top of the shared
bus settings::

    [viewer]
    host = "127.0.0.1"          # the WebSocket server's address (0.0.0.0: every interface)
    port = 8765                 # Foxglove's default
    [viewer.max_rate_hz]        # per message type, merged with the defaults; 0 = unthrottled
    "foxglove.CompressedImage" = 10.0
    "psm.ArmState" = 50.0

The rate limits are per stream (one key), chosen by the stream's message type (its schema,
named by the sample's encoding), so no key is written here: every camera's images get the
``foxglove.CompressedImage`` limit, each on its own.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, field_validator

from services.bus.config import Section, ServiceConfig, StrList
from services.bus.messages import (
    ArmCommand,
    ArmState,
    CollisionPrediction,
    CompressedImage,
    FrameTransforms,
    schema_name_of,
)

__all__ = ["DEFAULT_MAX_RATE_HZ", "ViewerConfig", "ViewerSection"]

#: Rates a live view needs of the streams that are faster than that [Hz]: images at 10 Hz, the
#: 500 Hz control loop (state, command, collision prediction) and the arm's transforms at 50 Hz
#: (a 3-D panel or a plot refreshes at 60 Hz at most). Every other type is forwarded unthrottled.
DEFAULT_MAX_RATE_HZ: dict[str, float] = {
    schema_name_of(CompressedImage): 10.0,
    schema_name_of(ArmState): 50.0,
    schema_name_of(ArmCommand): 50.0,
    schema_name_of(CollisionPrediction): 50.0,
    schema_name_of(FrameTransforms): 50.0,
}


class ViewerSection(Section):
    """The ``[viewer]`` table (units in the field descriptions)."""

    host: str = Field(
        "127.0.0.1", min_length=1,
        description="address the Foxglove WebSocket server binds to (0.0.0.0: every interface; "
        "the server has no authentication: anyone who reaches it sees the whole cell)",
    )
    port: int = Field(8765, ge=0, le=65535, description="WebSocket port (0: any free port, logged)")
    key_exprs: StrList = Field(
        default_factory=list, description="key expressions to forward ([] = the whole cell, <prefix>/**)"
    )
    history: bool = Field(
        True,
        description="fetch the latched streams' last samples (goals, obstacles, scene) from their "
        "publishers at start, and send a latched stream's last sample to each client that subscribes",
    )
    max_rate_hz: dict[str, float] = Field(
        default_factory=lambda: dict(DEFAULT_MAX_RATE_HZ),
        description="per-stream rate limit by message type (full protobuf name) [Hz]; merged with "
        "the defaults (psm.ArmState, psm.ArmCommand, psm.CollisionPrediction, "
        "foxglove.FrameTransforms 50, foxglove.CompressedImage 10); 0 = unthrottled",
    )
    log_time: Literal["stamp", "receive"] = Field(
        "stamp",
        description="a message's log time in Foxglove: its own stamp (as publish_time in the "
        "recordings; in lockstep the arm's stamps are sim time from 0 while others are wall "
        "clock) or the time the viewer received it (one wall-clock timeline)",
    )
    poll_period_s: float = Field(
        0.01, gt=0.0, le=1.0,
        description="the forwarding thread takes the received samples every this long [s]: the "
        "delay a forwarded sample may add; Zenoh's threads only fill a ring of queue_size samples",
    )
    client_backlog: int = Field(
        256, ge=1, le=100_000,
        description="messages queued per client; a slow client loses its oldest data messages",
    )

    @field_validator("max_rate_hz")
    @classmethod
    def _rates(cls, value: dict[str, float]) -> dict[str, float]:
        from services.bus.messages import MESSAGE_TYPES

        for name, hz in value.items():
            if name not in MESSAGE_TYPES:
                raise ValueError(
                    f"unknown message type {name!r} (known: {', '.join(sorted(MESSAGE_TYPES))})")
            if not math.isfinite(hz) or hz < 0:
                raise ValueError(f"{name}: a rate must be a finite number >= 0 Hz (0 = unthrottled), "
                                 f"got {hz}")
        return {**DEFAULT_MAX_RATE_HZ, **value}

    @field_validator("key_exprs")
    @classmethod
    def _key_exprs(cls, value: list[str]) -> list[str]:
        from services.bus.messages import InvalidKeyError, validate_key_expr

        try:
            return [validate_key_expr(k) for k in value]
        except InvalidKeyError as exc:
            raise ValueError(str(exc)) from None

    def period_ns(self, schema_name: str) -> int:
        """The shortest interval between two forwarded samples of one stream of this type [ns]
        (0: unthrottled)."""
        hz = self.max_rate_hz.get(schema_name, 0.0)
        return round(1e9 / hz) if hz > 0 else 0


class ViewerConfig(ServiceConfig):
    """Config of ``psm view``: bus settings + ``[viewer]``."""

    viewer: ViewerSection = Field(default_factory=ViewerSection)
