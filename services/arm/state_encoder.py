"""The arm's per-tick ``ArmState`` serialiser, compiled (:func:`services.arm.kernel.encode_arm_state`).

Byte for byte the output of :class:`services.robot.protocol.StateEncoder` (protobuf's own
serialiser), in one compiled call: the constant fields (joint names, frame, period) are
serialised once, the rest is written straight from the snapshot's arrays.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from services.arm import kernel
from services.arm.sim import ArmSnapshot
from services.bus.messages import ArmState

#: The largest value of the uint32 ``rejected_commands`` (the count saturates there).
_UINT32_MAX = 2**32 - 1


def _field_bytes(**fields: object) -> np.ndarray:
    """The serialised bytes of the given ``ArmState`` fields alone (uint8)."""
    return np.frombuffer(ArmState(**fields).SerializeToString(), dtype=np.uint8).copy()


class CompiledStateEncoder:
    """Serialises :class:`~services.arm.sim.ArmSnapshot` s as ``ArmState`` bytes equal to
    ``state_message(...).SerializeToString()`` (``stamp_ns`` = sim time). Not thread-safe."""

    def __init__(self, joint_names: Sequence[str], frame_id: str, dt_s: float) -> None:
        self._names = _field_bytes(joint_names=list(joint_names))
        self._frame = _field_bytes(frame_id=frame_id)
        self._period = _field_bytes(dt_s=dt_s)
        n = len(joint_names)
        # Room for the largest message of n joints (encode_arm_state checks it at every call).
        size = self._names.size + self._frame.size + self._period.size + 3 * (8 * n + 11) + 6 * 38 + 48
        self._buf = np.empty(size, dtype=np.uint8)

    def encode(
        self, snap: ArmSnapshot, *, watchdog_tripped: bool = False, rejected_commands: int = 0
    ) -> bytes:
        """The serialised ``ArmState`` of ``snap``.

        Raises:
            ValueError: ``snap`` has more joints than the encoder was made for.
        """
        ee = snap.ee_packed
        if ee is None:
            e = snap.ee
            ee = np.concatenate((e.position, e.quat_xyzw, e.linear_velocity, e.angular_velocity,
                                 e.linear_acceleration, e.angular_acceleration))
        n = kernel.encode_arm_state(
            self._buf, self._names, self._frame, self._period, snap.time_ns, snap.tick,
            snap.q, snap.dq, snap.ddq, ee, snap.braking, watchdog_tripped,
            min(rejected_commands, _UINT32_MAX),
        )
        if n < 0:
            raise ValueError(f"ArmState of {snap.q.shape[0]} joints: the encoder was made for fewer")
        return self._buf[:n].tobytes()
