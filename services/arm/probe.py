"""``psm arm probe``: a trivial controller for the arm that answers every ``ArmState`` with an
``ArmCommand`` at once.

Used by the integration tests and ``benchmarks/arm.py`` (and handy for poking a running arm)::

    psm arm probe --pattern sine --connect tcp/127.0.0.1:7447 --no-multicast
    python -m services.arm.probe --pattern sine ...      # the same, without the psm command line

The patterns (:data:`services.arm.cli.PROBE_PATTERNS`, listed by ``psm arm probe --help``)
compute the command from the state only, so a lockstep run is deterministic. The reply is
computed and published on Zenoh's receive thread (no queue hop) to keep the loop latency
minimal. ``--stop-after-tick N`` stops answering from tick N on (the process stays up, like a
hung planner).
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np

from services.arm.cli import PROBE_PATTERNS
from services.bus.config import ServiceConfig, config_from_args
from services.bus.messages import ArmCommand, ArmState, decode
from services.bus.runtime import Service, ServiceApp, receive_thread_handler, run_service
from services.robot.protocol import cartesian_command, joint_command

#: The pattern names (described in :data:`services.arm.cli.PROBE_PATTERNS`).
PATTERNS: tuple[str, ...] = tuple(PROBE_PATTERNS)


class Probe:
    """Computes the reply to each state (see module docstring); not thread-safe by itself."""

    def __init__(
        self,
        pattern: str,
        *,
        accel: Sequence[float] = (0.0, 0.0, 0.0),
        joint_accel: Sequence[float] = (),
        amplitude: float = 0.05,
        frequency: float = 0.5,
        kp: float = 100.0,
        kd: float = 20.0,
        source: str = "probe",
    ) -> None:
        if pattern not in PATTERNS:
            raise ValueError(f"unknown pattern {pattern!r}")
        self.pattern = pattern
        self.accel = np.asarray(accel, dtype=float)
        self.joint_accel = list(joint_accel)
        self.amplitude = amplitude
        self.omega = 2 * math.pi * frequency
        self.kp, self.kd = kp, kd
        self.source = source
        self.seq = 0
        self._x0: np.ndarray | None = None
        self._t0_ns = 0  # sim time of the first state (a realtime arm's sim time is UNIX time)
        self._quat: list[float] | None = None

    def reply(self, state: ArmState) -> ArmCommand | bytes:
        """The command answering ``state`` (raw bytes for the undecodable ``bad`` case).
        Plain float arithmetic (no numpy): this runs once per tick on Zenoh's thread."""
        self.seq += 1
        p = state.ee_position
        x, y, z = p.x, p.y, p.z
        if self._x0 is None:
            o = state.ee_orientation
            self._x0 = np.array([x, y, z])
            self._t0_ns = int(state.sim_time_ns)
            self._quat = [o.x, o.y, o.z, o.w]
        x0, y0, z0 = (float(c) for c in self._x0)
        v = state.ee_linear_velocity
        pat = self.pattern
        if pat == "joint":
            return joint_command(state, self.joint_accel, seq=self.seq, source=self.source)
        if pat == "bad":
            return self._bad(state)
        kp, kd = self.kp, self.kd
        if pat == "accel":
            acc = self.accel.tolist()
        elif pat == "hold":
            acc = [kp * (x0 - x) - kd * v.x, kp * (y0 - y) - kd * v.y, kp * (z0 - z) - kd * v.z]
        else:  # sine
            t = (state.sim_time_ns - self._t0_ns) * 1e-9
            w, A = self.omega, self.amplitude
            s, c = math.sin(w * t), math.cos(w * t)
            yd, vyd, ayd = y0 + A * s, A * w * c, -A * w * w * s
            acc = [
                kp * (x0 - x) - kd * v.x,
                ayd + kd * (vyd - v.y) + kp * (yd - y),
                kp * (z0 - z) - kd * v.z,
            ]
        return cartesian_command(state, acc, self._quat, seq=self.seq, source=self.source)

    def _bad(self, state: ArmState) -> ArmCommand | bytes:
        kind = self.seq % 8
        nan = float("nan")
        if kind == 0:
            return cartesian_command(state, [nan, 0.0, 0.0], self._quat, seq=self.seq)
        if kind == 1:
            return cartesian_command(state, [0.0, float("inf"), 0.0], self._quat, seq=self.seq)
        if kind == 2:
            return cartesian_command(state, [1e3, 0.0, 0.0], self._quat, seq=self.seq)
        if kind == 3:
            return cartesian_command(state, [0.1, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], seq=self.seq)
        if kind == 4:
            return joint_command(state, [1.0, 2.0], seq=self.seq)
        if kind == 5:
            return ArmCommand(stamp_ns=state.stamp_ns, tick=state.tick, seq=self.seq)
        if kind == 6:
            return joint_command(state, [nan] * len(state.q), seq=self.seq)
        return b"\xff\xff\xff\xff not a protobuf"


def run(args: argparse.Namespace) -> int:
    """Run the probe with parsed arguments (:func:`~services.arm.cli.add_probe_arguments`)
    until SIGINT/SIGTERM or ``--max-runtime``; returns the exit code.

    Raises:
        services.bus.config.ConfigError: a bad bus configuration (before joining the bus).
    """
    cfg = config_from_args(ServiceConfig, args)
    probe = Probe(
        args.pattern,
        accel=args.accel,
        joint_accel=args.joint_accel,
        amplitude=args.amplitude,
        frequency=args.frequency,
        source=args.name,
    )
    return run_service(_ProbeService(cfg, probe, args))


class _ProbeService(ServiceApp):
    """Answers every arm state with the probe's command, on Zenoh's receive thread."""

    def __init__(self, cfg: ServiceConfig, probe: Probe, args: argparse.Namespace) -> None:
        super().__init__(cfg)
        self.name = args.name
        self.probe = probe
        self.args = args

    def setup(self, svc: Service) -> None:
        from services.threads import set_realtime_priority

        args, probe = self.args, self.probe
        problem = set_realtime_priority(args.rt_priority)
        if problem:
            svc.log.warning(problem)
        keys = svc.keys
        pub = svc.publisher(keys.arm_command)
        lock = threading.Lock()
        stop_tick = args.stop_after_tick

        def on_state(sample: Any) -> None:
            try:
                state = decode(sample.payload.to_bytes(), str(sample.encoding), ArmState)
            except ValueError as exc:
                svc.record_rejection(keys.arm_state.key, str(exc), getattr(exc, "kind", "malformed"))
                return
            assert isinstance(state, ArmState)
            if 0 <= stop_tick <= state.tick:
                return
            with lock:
                reply = probe.reply(state)
            if isinstance(reply, bytes):
                pub.put_bytes(reply)
            else:
                pub.put(reply)

        sub = svc.session.declare_subscriber(
            keys.arm_state.key, receive_thread_handler(on_state)
        )
        svc.on_close(sub.undeclare)
        svc.log.info("probe running", extra={"pattern": args.pattern})

    def loop(self, svc: Service) -> None:
        svc.wait(self.args.max_runtime or None)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m services.arm.probe ARGS``: the same as ``psm arm probe ARGS`` (and as
    ``python -m services.arm arm probe ARGS``); returns the exit code."""
    from services.arm.cli import register
    from services.cli import module_main

    rest = sys.argv[1:] if argv is None else list(argv)
    return module_main(register, "python -m services.arm", ["arm", "probe", *rest])

if __name__ == "__main__":
    sys.exit(main())
