"""A solid cylinder struck along the table, rolled to the table's edge and into a basket (pure numpy).

The physics of the cylinder-rolling experiment (:mod:`experiments.cylinder`), in the plane of
the motion: ``y`` along the table towards its edge, ``z`` up, table top at ``z = 0``. The
cylinder's axis is along ``x``; it is struck on its back face by the end effector, whose path
``(t, x, v)`` is given (the robot's controller holds its path through the contact: the arm is
position controlled and the contact lasts one control tick, so the effector's own velocity change
is not fed back into its path).

Model, each part with its closed form (the tests in ``tests/experiments/test_rolling.py`` check
them):

* **Contact.** The effector is a vertical finger plate whose lowest point is at ``z_e``: below the
  cylinder's top (``z_e < 2r``) and within its length it touches the back face at the height
  ``h = max(z_e, r)`` above the table, at ``y_c - sqrt(r² - (h - r)²)``. When it reaches the face
  moving faster than the cylinder's surface there, a horizontal impulse of the two-body collision
  with restitution ``e`` acts (:func:`collide`): effector mass ``m_e`` against the cylinder's
  effective mass at the contact, ``1/m_eff = 1/m + (h - r)²/I`` (a free rigid body: the table's
  friction is finite, not impulsive). ``Δv = J/m`` and ``Δω = J (h - r)/I``. The cylinder is then
  placed against the plate (no penetration).
* **Slipping to rolling.** A slipping cylinder (``s = v - ω r ≠ 0``) feels kinetic friction
  ``μ m g`` against the slip: ``v̇ = -μ g sgn s``, ``ω̇ = μ m g r sgn s / I``, so the slip decays at
  ``μ g (1 + m r²/I) = 3 μ g`` until it rolls. The angular momentum about the ground contact line,
  ``m v r + I ω``, is conserved through it: a cylinder hit at its centre height with ``v₀`` rolls
  on at ``v₀ / (1 + I/(m r²)) = 2 v₀ / 3`` (:func:`rolling_speed_after_slip`).
* **Rolling resistance.** Rolling without slipping, the normal force acts ``b = c_rr r`` ahead of
  the contact line (``c_rr`` the rolling-resistance coefficient). About the contact line
  ``(I + m r²) α = -m g b``: the deceleration is ``a_rr = c_rr g / (1 + I/(m r²)) = 2 c_rr g / 3``
  for a solid cylinder (:attr:`Cylinder.rolling_deceleration`).
* **Over the edge.** A cylinder rolling onto the table's edge at ``v₀`` pivots about the edge
  (rolling) until the normal force vanishes: ``cos θ = (3 v₀²/(g r) + 4) / 7`` (``θ = 0`` when
  ``v₀² ≥ g r``), at the speed ``sqrt(g r cos θ)``, tangent to its path (:func:`edge_departure`).
* **Flight and basket.** Its centre then flies ballistically from
  ``(y_edge + r sin θ, r cos θ)``. It lands in the basket when the centre comes down through the
  rim's height inside the opening shrunk by ``r`` on both sides (the whole cylinder inside) without
  having touched the near rim's top edge before (:func:`flight`); otherwise it falls short (into
  the gap between table and basket, or onto the near rim) or overshoots (onto or past the far
  rim). A cylinder that stops before the edge stays on the table.

Units: m, s, kg, m/s, rad/s throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "Basket",
    "Cylinder",
    "Flight",
    "G",
    "StrikeResult",
    "StrikeScene",
    "collide",
    "edge_departure",
    "flight",
    "landing_window",
    "outcome_for_release",
    "roll",
    "rolling_speed_after_slip",
    "simulate_strike",
]

FloatArray = NDArray[np.float64]

#: Gravitational acceleration [m/s²].
G = 9.81

#: Outcomes of a strike.
LANDED = "landed"
STOPPED = "stopped on the table"
SHORT = "fell short"
OVER = "overshot"
MISSED = "not touched"


def _positive(name: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be a finite number > 0, got {value}")


@dataclass(frozen=True)
class Cylinder:
    """A solid cylinder rolled along ``y``: ``radius`` [m], ``length`` [m] (its axis along ``x``),
    ``mass`` [kg], ``rolling_resistance`` ``c_rr = b/r`` [-] and table ``friction`` ``μ`` [-]."""

    radius: float = 0.04
    length: float = 0.12
    mass: float = 0.42
    rolling_resistance: float = 0.015
    friction: float = 0.4

    def __post_init__(self) -> None:
        for name in ("radius", "length", "mass", "rolling_resistance", "friction"):
            _positive(name, getattr(self, name))

    @property
    def inertia(self) -> float:
        """Moment of inertia about the axis, ``m r²/2`` [kg m²]."""
        return 0.5 * self.mass * self.radius**2

    @property
    def inertia_ratio(self) -> float:
        """``I / (m r²)`` = 1/2 for a solid cylinder."""
        return self.inertia / (self.mass * self.radius**2)

    @property
    def rolling_deceleration(self) -> float:
        """Deceleration rolling without slipping, ``c_rr g / (1 + I/(m r²))`` [m/s²]."""
        return self.rolling_resistance * G / (1.0 + self.inertia_ratio)

    def effective_mass(self, h: float) -> float:
        """Mass a horizontal impulse at height ``h`` [m] above the table meets: ``1/m + (h-r)²/I``
        inverted [kg] (``m`` at the centre's height)."""
        d = h - self.radius
        return 1.0 / (1.0 / self.mass + d * d / self.inertia)


@dataclass(frozen=True)
class Basket:
    """The table's edge at ``edge_y`` and a basket beyond it: its opening from ``near_y`` to
    ``far_y`` [m], its rim at ``rim_z`` [m] (below the table top, ``z = 0``)."""

    edge_y: float = 0.80
    near_y: float = 0.83
    far_y: float = 1.00
    rim_z: float = -0.25

    def __post_init__(self) -> None:
        if not (self.edge_y <= self.near_y < self.far_y):
            raise ValueError(
                f"basket: need edge_y <= near_y < far_y, got {self.edge_y}, {self.near_y}, {self.far_y}"
            )
        if not (math.isfinite(self.rim_z) and self.rim_z < 0.0):
            raise ValueError(f"rim_z must be below the table top (< 0), got {self.rim_z}")


@dataclass(frozen=True)
class StrikeScene:
    """The cylinder at rest with its centre at ``(x, y) = start`` [m] on the table, the basket,
    the effector's mass along ``y`` ``effector_mass`` [kg] and the contact's ``restitution``."""

    cylinder: Cylinder = field(default_factory=Cylinder)
    basket: Basket = field(default_factory=Basket)
    start: tuple[float, float] = (0.45, -0.06)
    effector_mass: float = 1.87
    restitution: float = 0.3

    def __post_init__(self) -> None:
        _positive("effector_mass", self.effector_mass)
        if not (0.0 <= self.restitution <= 1.0):
            raise ValueError(f"restitution must be in [0, 1], got {self.restitution}")
        if self.start[1] + self.cylinder.radius >= self.basket.edge_y:
            raise ValueError("start: the cylinder must lie on the table, before its edge")


def collide(v1: float, v2: float, m1: float, m2: float, e: float) -> tuple[float, float]:
    """Velocities after a 1-D collision of body 1 (``v1`` [m/s], ``m1`` [kg]) hitting body 2 with
    restitution ``e``: momentum conserved, relative speed reversed and scaled by ``e``.
    Returns ``(v1', v2')``; bodies moving apart (``v1 <= v2``) are returned unchanged."""
    if v1 <= v2:
        return v1, v2
    j = (1.0 + e) * m1 * m2 / (m1 + m2) * (v1 - v2)
    return v1 - j / m1, v2 + j / m2


def rolling_speed_after_slip(cyl: Cylinder, v: float, omega: float) -> float:
    """Rolling speed [m/s] a cylinder at ``v`` [m/s], ``omega`` [rad/s] reaches once friction has
    ended the slip: ``(m v r + I ω) / (m r + I / r)`` (angular momentum about the contact line)."""
    r = cyl.radius
    return (cyl.mass * v * r + cyl.inertia * omega) / (cyl.mass * r + cyl.inertia / r)


def roll(cyl: Cylinder, v0: float, t: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Distance [m] and speed [m/s] at times ``t (N,)`` [s] of a cylinder rolling (no slip) from
    ``v0 >= 0`` [m/s], decelerated by rolling resistance until it stops."""
    a = cyl.rolling_deceleration
    t = np.asarray(t, float)
    t_stop = v0 / a
    tc = np.minimum(t, t_stop)
    return v0 * tc - 0.5 * a * tc * tc, np.maximum(v0 - a * t, 0.0)


def edge_departure(v0: float, radius: float) -> tuple[float, float]:
    """Angle ``θ`` [rad] from the vertical at which a solid cylinder rolling onto an edge at
    ``v0`` [m/s] leaves it, and its centre's speed [m/s] then (pivoting without slipping)."""
    c = 1.0 if v0 * v0 >= G * radius else (3.0 * v0 * v0 / (G * radius) + 4.0) / 7.0
    theta = math.acos(min(1.0, c))
    speed = v0 if c >= 1.0 else math.sqrt(G * radius * c)
    return theta, speed


@dataclass(frozen=True)
class Flight:
    """A flight from the edge: departure angle ``theta`` [rad] and speed [m/s], the centre's
    start ``(y0, z0)`` [m] and velocity ``(vy, vz)`` [m/s], where the centre crosses the rim's
    height ``y_rim`` [m] (at ``t_rim`` [s]), the closest approach of the cylinder's surface to the
    near rim's edge before that ``near_clearance`` [m] (negative: touched), and the ``outcome``."""

    theta: float
    speed: float
    y0: float
    z0: float
    vy: float
    vz: float
    t_rim: float
    y_rim: float
    near_clearance: float
    outcome: str

    def path(self, n: int = 60, extra_drop: float = 0.05) -> FloatArray:
        """The centre's path ``(n, 2)`` [m] (y, z) until ``extra_drop`` below the rim's height."""
        t_end = self.t_rim + extra_drop / max(abs(self.vz) + G * self.t_rim, 1e-6)
        t = np.linspace(0.0, t_end, n)
        return np.column_stack([self.y0 + self.vy * t, self.z0 + self.vz * t - 0.5 * G * t * t])


def flight(cyl: Cylinder, basket: Basket, v_edge: float) -> Flight:
    """The cylinder leaving the edge rolling at ``v_edge > 0`` [m/s]: departure, ballistic
    flight of its centre, and whether it lands in the basket (see the module docstring)."""
    r = cyl.radius
    theta, speed = edge_departure(v_edge, r)
    y0 = basket.edge_y + r * math.sin(theta)
    z0 = r * math.cos(theta)
    vy, vz = speed * math.cos(theta), -speed * math.sin(theta)
    # The centre reaches the rim's height: z0 + vz t - g t²/2 = rim_z.
    dz = z0 - basket.rim_z
    t_rim = (vz + math.sqrt(vz * vz + 2.0 * G * dz)) / G
    y_rim = y0 + vy * t_rim
    # Closest approach of the centre to the near rim's edge on [0, t_rim]: the squared distance
    # is a quartic in t; its minimum is at an end or at a real root of its derivative (a cubic).
    py, pz = y0 - basket.near_y, z0 - basket.rim_z
    cubic = [0.5 * G * G, -1.5 * G * vz, vy * vy + vz * vz - G * pz, py * vy + pz * vz]
    cands = [0.0, t_rim] + [
        float(c.real) for c in np.roots(cubic) if abs(c.imag) < 1e-9 and 0.0 < c.real < t_rim
    ]
    dist = min(math.hypot(py + vy * tc, pz + vz * tc - 0.5 * G * tc * tc) for tc in cands)
    near_clearance = dist - r
    if y_rim > basket.far_y - r:
        outcome = OVER
    elif y_rim < basket.near_y + r or near_clearance < 0.0:
        outcome = SHORT
    else:
        outcome = LANDED
    return Flight(theta, speed, y0, z0, vy, vz, t_rim, y_rim, near_clearance, outcome)


def outcome_for_release(scene: StrikeScene, y_release: float, v_release: float) -> tuple[str, float]:
    """Outcome of a cylinder rolling (no slip) from centre position ``y_release`` [m] at
    ``v_release`` [m/s], and its speed at the edge [m/s] (0 when it stops on the table)."""
    cyl, basket = scene.cylinder, scene.basket
    d = basket.edge_y - y_release
    v2 = v_release * v_release - 2.0 * cyl.rolling_deceleration * max(d, 0.0)
    if v_release <= 0.0 or v2 <= 0.0:
        return STOPPED, 0.0
    v_edge = math.sqrt(v2)
    return flight(cyl, basket, v_edge).outcome, v_edge


def landing_window(
    scene: StrikeScene, y_release: float, v_max: float = 3.0, tol: float = 1e-5
) -> tuple[float | None, float | None]:
    """The rolling speeds at ``y_release`` [m] that land the cylinder, ``(v_lo, v_hi)`` [m/s]
    (bisection to ``tol``; ``(None, None)`` when none below ``v_max`` does). The outcome goes
    stopped → short → landed → overshot as the speed grows (the landing point moves out
    monotonically), so the window is one interval."""
    vs = np.linspace(0.0, v_max, 601)[1:]
    outs = [outcome_for_release(scene, y_release, float(v))[0] for v in vs]
    idx = [i for i, o in enumerate(outs) if o == LANDED]
    if not idx:
        return None, None

    def edge(lo: float, hi: float, lo_lands: bool) -> float:
        while hi - lo > tol:
            mid = 0.5 * (lo + hi)
            if (outcome_for_release(scene, y_release, mid)[0] == LANDED) == lo_lands:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)

    i0, i1 = idx[0], idx[-1]
    v_lo = edge(float(vs[i0 - 1]) if i0 > 0 else 0.0, float(vs[i0]), False)
    v_hi = edge(float(vs[i1]), float(vs[i1 + 1]), True) if i1 + 1 < len(vs) else v_max
    return v_lo, v_hi


@dataclass
class StrikeResult:
    """A simulated strike.

    ``t (N,)`` [s] the effector's clock; ``y (N,)`` [m], ``v (N,)`` [m/s], ``omega (N,)`` [rad/s]
    the cylinder's centre, speed and spin on the table over it (NaN once it left the table).
    ``meet_index``: the effector's sample at the first contact (None: never touched);
    ``contacts``: samples with an impulse; ``release_index``: the last one; ``y_release`` [m],
    ``v_release`` [m/s]: the cylinder's centre and its rolling speed (once the slip of the impulse
    has ended) after that last impulse; ``v_edge`` [m/s] its speed at the edge; ``flight`` (None if it
    stopped or was never touched); ``outcome``; ``path (M, 2)`` the centre's ``(y, z)`` [m] from
    rest to the landing."""

    t: FloatArray
    y: FloatArray
    v: FloatArray
    omega: FloatArray
    meet_index: int | None
    contacts: list[int]
    release_index: int | None
    y_release: float
    v_release: float
    v_edge: float
    flight: Flight | None
    outcome: str
    path: FloatArray

    @property
    def landed(self) -> bool:
        """Whether the cylinder landed in the basket."""
        return self.outcome == LANDED


def simulate_strike(scene: StrikeScene, t: FloatArray, x_e: FloatArray, v_e: FloatArray) -> StrikeResult:
    """Strike the cylinder with the effector path ``t (N,)`` [s], ``x_e (N, 3)`` [m],
    ``v_e (N, 3)`` [m/s] (only ``y`` pushes; ``x`` and ``z`` decide whether and where it touches),
    then let it roll (closed form) to the edge and fly (see the module docstring)."""
    t = np.asarray(t, float)
    x_e = np.asarray(x_e, float)
    v_e = np.asarray(v_e, float)
    if t.ndim != 1 or x_e.shape != (len(t), 3) or v_e.shape != (len(t), 3) or len(t) < 2:
        raise ValueError(
            f"need t (N,), x_e (N, 3), v_e (N, 3) with N >= 2, got {t.shape}, {x_e.shape}, {v_e.shape}"
        )
    cyl, basket = scene.cylinder, scene.basket
    r, m, inertia = cyl.radius, cyl.mass, cyl.inertia
    slip_rate = cyl.friction * G * (1.0 + m * r * r / inertia)  # d|s|/dt while slipping
    a_rr = cyl.rolling_deceleration
    n = len(t)
    ys = np.full(n, np.nan)
    vs = np.full(n, np.nan)
    ws = np.full(n, np.nan)
    y, v, w = scene.start[1], 0.0, 0.0
    y_release, v_release = y, 0.0
    contacts: list[int] = []
    on_table = True
    for i in range(n):
        if i > 0:
            dt = t[i] - t[i - 1]
            s = v - w * r
            if abs(s) > 1e-12:  # slipping: kinetic friction until the slip is gone
                t_slip = min(dt, abs(s) / slip_rate)
                sg = math.copysign(1.0, s)
                y += v * t_slip - 0.5 * cyl.friction * G * sg * t_slip * t_slip
                v -= cyl.friction * G * sg * t_slip
                w += cyl.friction * m * G * r * sg / inertia * t_slip
                if t_slip < dt:  # the slip ended inside the step: rolling from here
                    w = v / r
                rest = dt - t_slip
            else:
                rest = dt
            if rest > 0.0 and v > 0.0:  # rolling: rolling resistance
                t_roll = min(rest, v / a_rr)
                y += v * t_roll - 0.5 * a_rr * t_roll * t_roll
                v = max(v - a_rr * rest, 0.0)
                w = v / r
            if y >= basket.edge_y:
                on_table = False
                break
        xe, ye, ze = x_e[i]
        if ze < 2.0 * r and abs(xe - scene.start[0]) <= 0.5 * cyl.length:
            h = max(ze, r)
            face = y - math.sqrt(max(r * r - (h - r) ** 2, 0.0))
            surface_v = v + w * (h - r)  # the face's horizontal velocity at height h
            if ye >= face and v_e[i, 1] > surface_v:
                m_eff = cyl.effective_mass(h)
                _, v_face = collide(
                    float(v_e[i, 1]), surface_v, scene.effector_mass, m_eff, scene.restitution
                )
                j = (v_face - surface_v) * m_eff
                v += j / m
                w += j * (h - r) / inertia
                y += ye - face
                contacts.append(i)
                y_release, v_release = y, max(rolling_speed_after_slip(cyl, v, w), 0.0)
        ys[i], vs[i], ws[i] = y, v, w
    meet = contacts[0] if contacts else None
    release = contacts[-1] if contacts else None
    # After the effector's path: end any slip, then roll on in closed form.
    if abs(v - w * r) > 1e-12:
        v = max(rolling_speed_after_slip(cyl, v, w), 0.0)
    path_table = np.column_stack([ys[np.isfinite(ys)], np.full(int(np.isfinite(ys).sum()), r)])
    if not contacts:
        return StrikeResult(t, ys, vs, ws, None, [], None, y, 0.0, 0.0, None, MISSED, path_table)
    v_edge = outcome_for_release(scene, y, v)[1] if on_table else v
    fl = flight(cyl, basket, v_edge) if v_edge > 0.0 else None
    y_end = basket.edge_y if fl is not None else y + v * v / (2.0 * a_rr)
    roll_path = np.column_stack([np.linspace(y, y_end, 20), np.full(20, r)])
    pieces = [path_table, roll_path]
    if fl is not None:
        arc = np.linspace(0.0, fl.theta, 10)
        pieces.append(np.column_stack([basket.edge_y + r * np.sin(arc), r * np.cos(arc)]))
        pieces.append(fl.path())
    return StrikeResult(
        t,
        ys,
        vs,
        ws,
        meet,
        contacts,
        release,
        y_release,
        v_release,
        v_edge,
        fl,
        fl.outcome if fl is not None else STOPPED,
        np.vstack(pieces),
    )
