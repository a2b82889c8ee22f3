"""Kinesthetic-teaching simulation: the arm is guided along an end-effector path and the run is
recorded to MCAP at the control rate (500 Hz by default), like the paper's teaching sessions.

* :class:`ViaPointPath` — minimum-jerk (quintic) motion through via-points with optional via
  velocities, plus seeded human-like tremor (physiological 8–12 Hz tremor and slow drift).
* :class:`RecordedPath` — a sampled path ``t (T,), X (T, 3)`` (e.g. from motion capture).
* :func:`teach` — simulate the guided arm (the "person" is a stiff Cartesian PD on the path,
  realised through the arm's own IK controller and limits) and return the :class:`ArmSnapshot`
  sequence; :func:`write_teach_mcap` writes it with the bus's message types, keys and schemas.
* reading a recording back into the end-effector trajectory is
  :func:`services.robot.recordings.ee_trajectory`
  ``t (T,), X (T, 3)`` by forward kinematics from the recorded joint positions (as the paper
  does; the published EE pose is not used).

Everything here is deterministic for a given seed: the same inputs give byte-identical files.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from services.arm.sim import ArmSim, ArmSimConfig, ArmSnapshot
from services.robot.model import RobotModel
from services.robot.protocol import Command, CommandMode, frame_transforms, state_message
from services.robot.recordings import TEACH_METADATA
from services.robot.rotations import quat_xyzw_from_matrix


class Path3D(Protocol):
    """A desired end-effector path: ``sample(t) -> (x, v, a)``, each ``(T, 3)``."""

    duration: float

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (m), velocity (m/s), acceleration (m/s²) at times ``t (T,)`` (s)."""
        ...


def _quintic(
    p0: np.ndarray,
    v0: np.ndarray,
    a0: np.ndarray,
    p1: np.ndarray,
    v1: np.ndarray,
    a1: np.ndarray,
    T: float,
) -> np.ndarray:
    """Coefficients ``(6, 3)`` (ascending powers of τ) of the quintic with the given boundary
    position/velocity/acceleration over duration ``T`` — the minimum-jerk segment."""
    p0, v0, a0, p1, v1, a1 = (np.asarray(x, dtype=float) for x in (p0, v0, a0, p1, v1, a1))
    c0, c1, c2 = p0, v0, a0 / 2.0
    d = p1 - (c0 + c1 * T + c2 * T**2)
    dv = v1 - (c1 + 2 * c2 * T)
    da = a1 - 2 * c2
    M = np.array([[T**3, T**4, T**5], [3 * T**2, 4 * T**3, 5 * T**4], [6 * T, 12 * T**2, 20 * T**3]])
    c345 = np.linalg.solve(M, np.vstack([d, dv, da]))
    return np.vstack([c0, c1, c2, c345])


@dataclass
class Tremor:
    """Human-like hand tremor added to a guided path (seeded, band-limited noise).

    Attributes:
        amplitude_m: RMS amplitude of the physiological tremor band, m.
        band_hz: frequency band of the tremor, Hz.
        drift_m: RMS amplitude of the slow drift band, m.
        drift_band_hz: frequency band of the drift, Hz.
        seed: random seed.
    """

    amplitude_m: float = 2e-4
    band_hz: tuple[float, float] = (8.0, 12.0)
    drift_m: float = 1e-3
    drift_band_hz: tuple[float, float] = (0.3, 1.5)
    seed: int = 0

    def signal(self, t: np.ndarray) -> np.ndarray:
        """Tremor displacement ``(T, 3)`` in m at uniform times ``t (T,)``, tapered to zero at
        both ends (the hand is at rest when the demonstration starts and ends)."""
        rng = np.random.default_rng(self.seed)
        n = t.size
        out = np.zeros((n, 3))
        if n < 4:
            return out
        dt = float(t[1] - t[0])
        freqs = np.fft.rfftfreq(n, dt)
        for amp, (lo, hi) in ((self.amplitude_m, self.band_hz), (self.drift_m, self.drift_band_hz)):
            if amp <= 0:
                continue
            spec = rng.normal(size=(freqs.size, 3)) + 1j * rng.normal(size=(freqs.size, 3))
            spec[(freqs < lo) | (freqs > hi)] = 0.0
            sig = np.fft.irfft(spec, n, axis=0)
            rms = np.sqrt(np.mean(sig**2, axis=0))
            out += sig * (amp / np.where(rms > 0, rms, 1.0))
        # Smooth taper (C2) over 0.25 s at each end.
        T = float(t[-1] - t[0])
        ramp = min(0.25, T / 4)
        s_in = np.clip((t - t[0]) / ramp, 0.0, 1.0)
        s_out = np.clip((t[-1] - t) / ramp, 0.0, 1.0)

        def smooth(s: np.ndarray) -> np.ndarray:
            return s**3 * (10 - 15 * s + 6 * s**2)

        return out * (smooth(s_in) * smooth(s_out))[:, None]


@dataclass
class ViaPointPath:
    """Minimum-jerk motion through via-points.

    Attributes:
        points: via-points ``(K, 3)`` in m, base frame (first = start, last = goal).
        durations: leg durations ``(K-1,)`` in s.
        velocities: velocities at the via-points ``(K, 3)`` in m/s; ``None`` = rest at both
            ends and a smooth pass-through (central difference) at interior via-points.
    """

    points: np.ndarray
    durations: np.ndarray
    velocities: np.ndarray | None = None
    duration: float = field(init=False)

    def __post_init__(self) -> None:
        P = np.asarray(self.points, dtype=float)
        D = np.asarray(self.durations, dtype=float)
        if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] < 2:
            raise ValueError("points must have shape (K, 3) with K >= 2")
        if D.shape != (P.shape[0] - 1,) or np.any(D <= 0) or not np.all(np.isfinite(D)):
            raise ValueError("durations must be K-1 positive values")
        if self.velocities is None:
            V = np.zeros_like(P)
            for i in range(1, P.shape[0] - 1):
                V[i] = (P[i + 1] - P[i - 1]) / (D[i - 1] + D[i])
        else:
            V = np.asarray(self.velocities, dtype=float)
            if V.shape != P.shape:
                raise ValueError("velocities must have the same shape as points")
        self.points, self.durations, self.velocities = P, D, V
        self._knots = np.concatenate([[0.0], np.cumsum(D)])
        zero = np.zeros(3)
        self._coef = [
            _quintic(P[i], V[i], zero, P[i + 1], V[i + 1], zero, float(D[i])) for i in range(len(D))
        ]
        self.duration = float(self._knots[-1])

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration ``(T, 3)`` at times ``t (T,)`` s (clamped to the
        path's time span)."""
        t = np.clip(np.asarray(t, dtype=float), 0.0, self.duration)
        idx = np.clip(np.searchsorted(self._knots, t, side="right") - 1, 0, len(self._coef) - 1)
        tau = t - self._knots[idx]
        C = np.stack(self._coef)[idx]  # (T, 6, 3)
        powers = np.stack([tau**k for k in range(6)], axis=1)  # (T, 6)
        dpow = np.stack([k * tau ** max(k - 1, 0) for k in range(6)], axis=1)
        ddpow = np.stack([k * (k - 1) * tau ** max(k - 2, 0) for k in range(6)], axis=1)
        x = np.einsum("tk,tkd->td", powers, C)
        v = np.einsum("tk,tkd->td", dpow, C)
        a = np.einsum("tk,tkd->td", ddpow, C)
        return x, v, a


@dataclass
class RecordedPath:
    """A sampled end-effector path ``t (T,)`` s, ``X (T, 3)`` m, interpolated with a cubic
    spline (velocity and acceleration from its derivatives)."""

    t: np.ndarray
    X: np.ndarray
    duration: float = field(init=False)

    def __post_init__(self) -> None:
        from scipy.interpolate import CubicSpline

        t = np.asarray(self.t, dtype=float)
        X = np.asarray(self.X, dtype=float)
        if t.ndim != 1 or X.shape != (t.size, 3) or t.size < 4:
            raise ValueError("recorded path needs t (T,) and X (T, 3) with T >= 4")
        if np.any(np.diff(t) <= 0) or not np.all(np.isfinite(X)):
            raise ValueError("recorded path needs increasing times and finite positions")
        self.t, self.X = t - t[0], X
        self._spline = CubicSpline(self.t, X, bc_type="clamped")
        self.duration = float(self.t[-1])

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration ``(T, 3)`` at times ``t (T,)``."""
        t = np.clip(np.asarray(t, dtype=float), 0.0, self.duration)
        s = self._spline
        return s(t), s(t, 1), s(t, 2)


@dataclass
class TeachConfig:
    """How the guided demonstration is simulated.

    Attributes:
        dt_ns: control/recording period, ns (2 ms = the paper's 500 Hz).
        kp: stiffness of the guiding hand, 1/s² (m/s² per m of path error).
        kd: damping of the guiding hand, 1/s.
        rest_before_s: time at rest before the motion, s.
        rest_after_s: time at rest after the motion, s.
        tremor: tremor model (``None`` = none).
        rotation: EE orientation held during the demonstration ``(3, 3)``; ``None`` = the
            start pose's orientation (the Panda's ``ready`` pose: hand pointing down).
        seed_pose: joint vector or named pose seeding the start IK.
    """

    dt_ns: int = 2_000_000
    kp: float = 900.0
    kd: float = 60.0
    rest_before_s: float = 0.3
    rest_after_s: float = 0.5
    tremor: Tremor | None = field(default_factory=Tremor)
    rotation: np.ndarray | None = None
    seed_pose: str | Sequence[float] = "ready"


def teach(robot: RobotModel, path: Path3D, config: TeachConfig | None = None) -> list[ArmSnapshot]:
    """Simulate a guided demonstration; returns one snapshot per tick (rest, motion, rest).

    The arm starts at rest at the path's first point (solved by IK from ``seed_pose``); at each
    tick the "hand" commands ``ẍ = ẍ_d + kd (ẋ_d − ẋ) + kp (x_d − x)`` toward the path plus
    tremor, through the arm's IK controller and joint limits.
    """
    cfg = config or TeachConfig()
    dt = cfg.dt_ns * 1e-9
    x0 = path.sample(np.array([0.0]))[0][0]
    q0 = robot.solve_ik(x0, cfg.rotation, cfg.seed_pose)
    sim = ArmSim(robot, ArmSimConfig(dt_s=cfg.dt_ns * 1e-9, start_pose=list(q0)))
    quat = quat_xyzw_from_matrix(sim.snapshot().ee.rotation)
    n_before = round(cfg.rest_before_s / dt)
    n_motion = int(np.ceil(path.duration / dt))
    n_after = round(cfg.rest_after_s / dt)
    n_total = n_before + n_motion + n_after + 1
    t_path = (np.arange(n_total) - n_before) * dt
    xd, vd, ad = path.sample(t_path)
    if cfg.tremor is not None:
        tr = cfg.tremor.signal(t_path)
        # Differentiate the tremor numerically (it is smooth: band-limited and tapered).
        trv = np.gradient(tr, dt, axis=0)
        tra = np.gradient(trv, dt, axis=0)
        xd, vd, ad = xd + tr, vd + trv, ad + tra
    out = [sim.snapshot()]
    for k in range(n_total - 1):
        s = sim.snapshot()
        acc = ad[k] + cfg.kd * (vd[k] - s.ee.linear_velocity) + cfg.kp * (xd[k] - s.ee.position)
        if not sim.submit(Command(sim.tick, CommandMode.CARTESIAN, acc, quat)):
            raise RuntimeError(f"teach command rejected: {sim.last_rejection}")
        out.append(sim.step())
    return out


class _Writer:
    """Deterministic MCAP writer using the bus's keys, encodings and protobuf schemas (the same
    channel layout the recorder produces)."""

    def __init__(self, path: Path, library: str) -> None:
        from mcap.writer import CompressionType, Writer

        from services.bus.messages import file_descriptor_set

        self._fdset = file_descriptor_set
        self._fh = path.open("wb")
        self._w = Writer(self._fh, chunk_size=256 * 1024, compression=CompressionType.ZSTD)
        self._w.start(profile="", library=library)
        self._channels: dict[str, int] = {}
        self._seq: dict[int, int] = {}

    def metadata(self, name: str, data: dict[str, str]) -> None:
        self._w.add_metadata(name, data)

    def write(self, key: str, msg: Any, log_time_ns: int, publish_time_ns: int) -> None:
        from services.bus.messages import encoding_for, schema_name_of

        ch = self._channels.get(key)
        if ch is None:
            name = schema_name_of(msg)
            sid = self._w.register_schema(name=name, encoding="protobuf", data=self._fdset(name))
            ch = self._w.register_channel(
                topic=key,
                message_encoding="protobuf",
                schema_id=sid,
                metadata={"zenoh_encoding": encoding_for(type(msg))},
            )
            self._channels[key] = ch
            self._seq[ch] = 0
        self._seq[ch] += 1
        self._w.add_message(
            channel_id=ch,
            log_time=log_time_ns,
            data=msg.SerializeToString(),
            publish_time=publish_time_ns,
            sequence=self._seq[ch],
        )

    def close(self) -> None:
        self._w.finish()
        self._fh.close()


def quantize_snapshot(snap: ArmSnapshot, bits: int) -> ArmSnapshot:
    """A copy of ``snap`` with every array rounded to a multiple of ``2**-bits``."""
    scale = float(2**bits)

    def q(a: np.ndarray) -> np.ndarray:
        return np.round(a * scale) / scale

    ee = snap.ee
    return dataclasses.replace(
        snap,
        q=q(snap.q),
        dq=q(snap.dq),
        ddq=q(snap.ddq),
        ee=dataclasses.replace(
            ee,
            position=q(ee.position),
            quat_xyzw=q(ee.quat_xyzw),
            linear_velocity=q(ee.linear_velocity),
            angular_velocity=q(ee.angular_velocity),
            linear_acceleration=q(ee.linear_acceleration),
            angular_acceleration=q(ee.angular_acceleration),
        ),
    )


def write_teach_mcap(
    out: str | Path,
    robot: RobotModel,
    snapshots: Sequence[ArmSnapshot],
    *,
    prefix: str = "psm",
    frame_id: str = "base",
    transforms_rate_hz: float = 10.0,
    every: int = 1,
    metadata: dict[str, Any] | None = None,
    start_time_ns: int = 0,
    quantize_bits: int | None = None,
) -> Path:
    """Write a teach run as MCAP: :class:`ArmState` on ``<prefix>/arm/state`` for every
    ``every``-th snapshot and ``FrameTransforms`` on ``<prefix>/arm/transforms`` at
    ``transforms_rate_hz`` (sim time). Log and publish times are ``start_time_ns`` + sim time.
    A metadata record ``psm.teach`` stores the robot (URDF file name, EE frame, joints), the
    rate and ``metadata``. ``quantize_bits`` rounds every stored number to a multiple of
    ``2**-quantize_bits`` (20 bits ≈ 1 µrad / 1 µm, finer than a joint encoder) so the files
    compress to about half their size. Returns the path.
    """
    from services.bus.messages import Keys

    keys = Keys(prefix)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not snapshots:
        raise ValueError("no snapshots to write")
    dt_ns = snapshots[1].time_ns - snapshots[0].time_ns if len(snapshots) > 1 else 0
    w = _Writer(out, "psm-dataflow teach")
    try:
        meta = {
            "urdf": Path(robot.urdf_path).name,
            "ee_frame": robot.ee_frame,
            "joint_names": ",".join(robot.joint_names),
            "frame_id": frame_id,
            "dt_s": repr(dt_ns * every * 1e-9),
            "rate_hz": repr(1e9 / (dt_ns * every)) if dt_ns else "0",
        }
        meta.update({k: v if isinstance(v, str) else json.dumps(v) for k, v in (metadata or {}).items()})
        w.metadata(TEACH_METADATA, meta)
        tf_every = (
            max(1, round(1e9 / (transforms_rate_hz * dt_ns))) if transforms_rate_hz > 0 and dt_ns else 0
        )
        frames = robot.body_frame_ids()
        names = list(robot.joint_names)
        for i, snap in enumerate(snapshots):
            t_ns = start_time_ns + snap.time_ns
            if i % every == 0:
                if quantize_bits is not None:
                    snap = quantize_snapshot(snap, quantize_bits)
                msg = state_message(snap, names, frame_id, dt_ns * every * 1e-9)
                w.write(keys.arm_state.key, msg, t_ns, t_ns)
            if tf_every and i % tf_every == 0:
                robot.fk(snap.q)
                tf = frame_transforms(robot, frames, snap.time_ns, frame_id)
                w.write(keys.arm_transforms.key, tf, t_ns, t_ns)
    finally:
        w.close()
    return out



def load_path_file(path: str | Path) -> Path3D:
    """Read a path description.

    * ``.json``: ``{"points": [[x, y, z], ...], "durations": [s, ...],
      "velocities": [[vx, vy, vz], ...] (optional)}`` → :class:`ViaPointPath`;
    * ``.csv``: rows ``t, x, y, z`` (s, m; header line allowed) → :class:`RecordedPath`.
    """
    p = Path(path)
    if p.suffix.lower() == ".json":
        spec = json.loads(p.read_text())
        try:
            return ViaPointPath(
                np.array(spec["points"], dtype=float),
                np.array(spec["durations"], dtype=float),
                None if spec.get("velocities") is None else np.array(spec["velocities"]),
            )
        except KeyError as exc:
            raise ValueError(f"{p}: missing key {exc}") from None
    if p.suffix.lower() == ".csv":
        data = np.genfromtxt(p, delimiter=",", comments="#", skip_header=0)
        data = data[~np.isnan(data).any(axis=1)] if data.ndim == 2 else data
        if data.ndim != 2 or data.shape[1] != 4:
            raise ValueError(f"{p}: expected rows 't, x, y, z'")
        return RecordedPath(data[:, 0], data[:, 1:])
    raise ValueError(f"{p}: unsupported path file (use .json via-points or .csv t,x,y,z)")
