"""Constant-velocity Kalman filter for a 3-D point, with outlier gating and a lost timeout.

State ``x = [p (3), v (3)]`` in metres and metres/second; the measurement is the position only.
Process noise is the continuous white-acceleration model, per axis ``i`` with spectral density
``q_i`` (m²/s³):

    Q_i(dt) = q_i · [[dt³/3, dt²/2], [dt²/2, dt]]        (position i, velocity i)

``q_i`` adapts to how the head moves (manoeuvre adaptation on the innovations): every measurement
updates an exponential average ``ε_i`` (time constant ``adapt_time_constant_s``) of
the normalised squared innovation ``y_i² / S_ii`` (expectation 1 when the model fits; clipped at
the gate), and

    q_i = clip(accel_psd · max(1, ε_i)^adapt_exponent, accel_psd, accel_psd_max)

A still or slowly moving head keeps ``q_i`` at the small ``accel_psd``, so the noisy depth axis
(the face-size measurement) is averaged over many frames; a head that moves faster than that model
allows makes its innovations grow and ``q_i`` rises, on that axis only, until the filter follows.
With ``accel_psd_max <= accel_psd`` the filter is the plain constant-``q`` one.

Time is always the *frame* time in seconds (sim time or camera time), never the wall clock, so a
replayed recording gives the same estimates.
"""

from __future__ import annotations

import enum

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import ConfigDict, Field
from scipy.stats import chi2

from psm.errors import ParameterError
from services.bus.config import Section

FloatArray = NDArray[np.float64]


class UpdateResult(enum.Enum):
    """What :meth:`ConstantVelocityKalman.update` did with a measurement."""

    INITIALISED = "initialised"  #: first measurement (or first after lost): state reset to it
    ACCEPTED = "accepted"  #: fused
    REJECTED = "rejected"  #: outside the Mahalanobis gate, ignored
    REINITIALISED = "reinitialised"  #: too many consecutive rejections: the target jumped


class KalmanParams(Section):
    """Filter tuning (the tracker's ``[goal_tracker.filter]`` table)."""

    model_config = ConfigDict(frozen=True)

    accel_psd: float = Field(
        1e-4, ge=0.0,
        description="q, white-acceleration spectral density of a still or slowly moving head (the "
        "floor of the adaptive q) [m^2/s^3]",
    )
    accel_psd_max: float = Field(
        0.05, ge=0.0,
        description="cap of the adaptive q when the head moves faster than accel_psd allows; <= "
        "accel_psd: constant q [m^2/s^3]",
    )
    adapt_time_constant_s: float = Field(
        0.6, gt=0.0,
        description="time constant of the average of the normalised innovations that adapts q [s]",
    )
    adapt_exponent: float = Field(
        4.0, ge=0.0,
        description="q = accel_psd * max(1, mean normalised innovation)^this (per axis)",
    )
    initial_velocity_sigma: float = Field(
        0.5, gt=0.0, description="velocity 1-sigma at (re)initialisation [m/s]"
    )
    gate_probability: float = Field(
        0.999, gt=0.0, lt=1.0,
        description="chi-square (3 dof) probability of the Mahalanobis gate; a measurement with "
        "d^2 above the quantile is rejected as an outlier",
    )
    max_consecutive_rejections: int = Field(
        5, ge=1, description="restart the filter from the measurement after N rejections in a row"
    )
    lost_timeout_s: float = Field(
        0.5, gt=0.0, description="no accepted measurement for this long (frame time) -> lost [s]"
    )

    @property
    def gate_d2(self) -> float:
        """Mahalanobis-squared gate threshold (chi-square quantile, 3 dof)."""
        return float(chi2.ppf(self.gate_probability, df=3))


class ConstantVelocityKalman:
    """Constant-velocity filter of one 3-D point; see the module docstring for the model."""

    def __init__(self, params: KalmanParams | None = None) -> None:
        self.params = params or KalmanParams()
        self._gate = self.params.gate_d2
        self.x: FloatArray = np.zeros(6)
        self.P: FloatArray = np.eye(6)
        self.t: float | None = None  #: time (s) of the current state, None until initialised
        self.last_update_t: float | None = None
        self.rejections = 0
        self.last_d2 = 0.0
        #: (3,) exponential average of the per-axis normalised squared innovation y_i²/S_ii
        self.nis: FloatArray = np.ones(3)

    @property
    def initialised(self) -> bool:
        """True once a measurement has set the state (and until :meth:`reset`)."""
        return self.t is not None

    @property
    def position(self) -> FloatArray:
        """Estimated position (3,), metres."""
        return self.x[:3].copy()

    @property
    def velocity(self) -> FloatArray:
        """Estimated velocity (3,), m/s."""
        return self.x[3:].copy()

    @property
    def position_cov(self) -> FloatArray:
        """3×3 position covariance, m²."""
        return self.P[:3, :3].copy()

    def reset(self) -> None:
        """Forget the state (the target is lost)."""
        self.t = None
        self.last_update_t = None
        self.rejections = 0

    @staticmethod
    def transition(dt: float) -> FloatArray:
        """F(dt), 6×6."""
        f = np.eye(6)
        f[:3, 3:] = dt * np.eye(3)
        return f

    @property
    def accel_psd(self) -> FloatArray:
        """The current per-axis spectral density q_i (3,), m²/s³ (see the module docstring)."""
        p = self.params
        q0 = p.accel_psd
        q = q0 * np.maximum(1.0, self.nis) ** p.adapt_exponent
        return np.clip(q, q0, max(q0, p.accel_psd_max))

    def process_noise(self, dt: float) -> FloatArray:
        """Q(dt), 6×6, for the white-acceleration model with the current per-axis q_i."""
        d = np.diag(self.accel_psd)
        return np.block([[dt**3 / 3 * d, dt**2 / 2 * d], [dt**2 / 2 * d, dt * d]])

    def initialise(self, t: float, z: ArrayLike, r: ArrayLike) -> None:
        """Start at position ``z`` (3,) with covariance ``r`` (3×3) and zero velocity."""
        self.x = np.concatenate([np.asarray(z, dtype=float).reshape(3), np.zeros(3)])
        self.P = np.zeros((6, 6))
        self.P[:3, :3] = np.asarray(r, dtype=float)
        self.P[3:, 3:] = self.params.initial_velocity_sigma**2 * np.eye(3)
        self.t = float(t)
        self.last_update_t = float(t)
        self.rejections = 0
        self.nis = np.ones(3)

    def predict(self, t: float) -> None:
        """Propagate the state to time ``t`` (s). A ``t`` earlier than the state is ignored
        (out-of-order frame), so time never runs backwards."""
        if self.t is None:
            return
        dt = float(t) - self.t
        if dt <= 0:
            return
        f = self.transition(dt)
        self.x = f @ self.x
        self.P = f @ self.P @ f.T + self.process_noise(dt)
        self.t = float(t)

    def mahalanobis2(self, z: ArrayLike, r: ArrayLike) -> float:
        """d² of measurement ``z`` with covariance ``r`` against the current prediction."""
        y = np.asarray(z, dtype=float).reshape(3) - self.x[:3]
        s = self.P[:3, :3] + np.asarray(r, dtype=float)
        return float(y @ np.linalg.solve(s, y))

    def update(self, t: float, z: ArrayLike, r: ArrayLike) -> UpdateResult:
        """Predict to ``t`` then fuse measurement ``z`` (3,) with covariance ``r`` (3×3), gated."""
        z = np.asarray(z, dtype=float).reshape(3)
        r = np.asarray(r, dtype=float).reshape(3, 3)
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(r))):
            raise ParameterError("measurement contains NaN or inf")
        if self.t is None:
            self.initialise(t, z, r)
            return UpdateResult.INITIALISED
        dt = max(0.0, float(t) - self.t)
        self.predict(t)
        s = self.P[:3, :3] + r
        y = z - self.x[:3]
        d2 = float(y @ np.linalg.solve(s, y))
        self.last_d2 = d2
        # Manoeuvre adaptation: every measurement's per-axis normalised innovation, clipped at
        # the gate, so a rejected one (a manoeuvre the small q cannot follow, or an outlier)
        # raises q at most by a bounded step instead of being ignored until the filter restarts.
        alpha = min(1.0, dt / self.params.adapt_time_constant_s)
        self.nis += alpha * (np.minimum(y**2 / np.diag(s), self._gate) - self.nis)
        if d2 > self._gate:
            self.rejections += 1
            if self.rejections >= self.params.max_consecutive_rejections:
                self.initialise(t, z, r)
                return UpdateResult.REINITIALISED
            return UpdateResult.REJECTED
        gain = np.linalg.solve(s, self.P[:3, :]).T  # K = P Hᵀ S⁻¹ (S symmetric)
        self.x = self.x + gain @ y
        i_kh = np.eye(6)
        i_kh[:, :3] -= gain
        # Joseph form keeps P symmetric positive semi-definite.
        self.P = i_kh @ self.P @ i_kh.T + gain @ r @ gain.T
        self.last_update_t = float(t)
        self.rejections = 0
        return UpdateResult.ACCEPTED

    def is_lost(self, t: float) -> bool:
        """True when not initialised or no measurement was accepted within the lost timeout."""
        if self.last_update_t is None:
            return True
        return float(t) - self.last_update_t > self.params.lost_timeout_s
