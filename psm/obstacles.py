"""Obstacle geometry for the collision stop: validated obstacles, their compiled (inflated,
vectorised) form and the segment test that triggers the controller's eq. 15 braking.

Pure numpy/scipy. Conventions (the bus's ``Obstacle`` message, without its types):

* an :class:`Obstacle` is a ``"box"`` (``size`` = full edge lengths x, y, z), a ``"sphere"``
  (``size[0]`` = diameter) or a ``"cylinder"`` (``size[0]`` = diameter, ``size[2]`` = height, axis
  along the local z); ``position (3,) [m]`` is the centre, ``orientation (4,)`` the quaternion
  ``(x, y, z, w)`` of the local frame in the world, ``velocity (3,) [m/s]`` that of the centre;
* :func:`compile_obstacles` inflates every obstacle by a safety margin ``m`` [m]: a sphere's radius
  becomes ``r + m`` (exactly the Minkowski sum with a ball of radius ``m``), a cylinder's radius
  ``r + m`` and its half height ``h/2 + m`` (square rims), a box's half extents ``h + m`` (square
  edges and corners). The box and cylinder are thus supersets of the Minkowski sums (at a box
  corner the inflated box reaches ``√3 m`` instead of ``m``): conservative;
* :func:`segment_check` is the collision condition of the stop: does the straight segment from
  the current end-effector position to the goal pass through an inflated obstacle? If so it
  returns the first obstacle hit along the segment and the per-axis stop positions for
  :meth:`psm.controller.PSMController.set_stops`;
* :func:`stopping_check` is its complement for a path that bends away from that segment: the same
  test on the end effector's stopping path (along its velocity, over :func:`stopping_distance`).

Semantics of the test (``docs/obstacles.md`` has the derivations):

* **hit**: the segment overlaps the *open* inflated obstacle over a length > :data:`GRAZE_TOL_M`.
  A grazing segment (tangent to a sphere or cylinder, running along a face, touching an edge or a
  corner, ending on the surface) is therefore a miss, deterministically: the inflated surface is
  itself ``m`` away from the obstacle. A zero-length segment (start = goal) hits only if the
  start is inside;
* **inside**: the start lies in the open inflated obstacle. Then ``collision`` and ``inside`` are
  true, the entry fraction, distance and time to collision are 0, ``normal`` is the outward normal
  of the nearest surface and the axes whose motion towards the goal goes deeper (``n_a d_a < 0``)
  stop where they are (``stop = start``); the others go on (moving out);
* **stop axes** (start outside): the stop keeps the point out of the inflated obstacle while the
  stopped axes do not pass their stop coordinates and the other axes go on, by a separating
  axis-aligned plane. If the start is outside the obstacle's world axis-aligned bounding box
  (AABB), only the axis through whose face the segment enters that AABB stops, at that face:
  holding one coordinate outside the AABB's slab keeps the point outside the AABB whatever the
  other axes do (for an axis-aligned box the AABB is the box and the face is the entered face,
  which is the behaviour of the paper's experiment: the heading axis holds while the others go on
  until the segment clears). If the start is inside the AABB (near a sphere's or cylinder's
  "corner"), the tangent plane at the entry point ``e`` with outward normal ``n`` separates
  instead: the axes with ``n_a d_a < 0`` (``d`` = goal − start) stop at
  ``start_a + μ (e_a − start_a)``, ``μ = (n·d) / Σ_stopped n_a d_a ∈ (0, 1]``, which keeps
  ``n·(x − e) ≥ 0`` as long as the other axes move towards the goal;
* **moving obstacles**: over the horizon ``[0, H]`` an obstacle moving at ``v`` is replaced by
  ``k = ⌈|v| H / step⌉`` copies at the times ``(i + ½) H / k`` (``i = 0..k−1``), each inflated
  further by ``|v| H / (2k) ≤ step/2``: every position of the obstacle during the horizon lies
  inside one copy, so the union of the copies covers the swept volume (conservative). The first
  copy hit along the segment wins; ``H = 0`` tests the obstacles where they are now.

The test is vectorised over all obstacles in one shape-parametric formulation: each shape is
the intersection of three slabs and one "radial" quadric in its local frame (a box has no
quadric, a sphere no slabs, a cylinder one slab and a 2-D quadric), so one pass of numpy
operations tests every obstacle whatever its shape. Above :data:`BROAD_PHASE_MIN` elements a
broad phase (segment vs bounding sphere) selects the candidates first; below it the exact test of
all elements is cheaper, numpy's per-call overhead dominating at that size.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from psm.errors import ParameterError

FloatArray = NDArray[np.float64]

#: Shapes of an obstacle (the bus's Obstacle.Shape without UNSPECIFIED).
SHAPES: tuple[str, ...] = ("box", "sphere", "cylinder")

#: Stable reasons of :class:`ObstacleError` (the obstacle monitor counts them).
REASON_ID = "id"
REASON_SHAPE = "shape"
REASON_NAN = "nan"
REASON_SIZE = "size"
REASON_ORIENTATION = "orientation"
REASON_DIMS = "dims"
REASON_RANGE = "range"
REASONS: tuple[str, ...] = (
    REASON_ID, REASON_SHAPE, REASON_NAN, REASON_SIZE, REASON_ORIENTATION, REASON_DIMS, REASON_RANGE
)

#: Positions and sizes beyond this [m], speeds beyond :data:`MAX_SPEED_MPS`, are not a robot
#: cell's obstacles (finite, but e.g. 1e308: the geometry would overflow): rejected as "range".
MAX_EXTENT_M = 1000.0
MAX_SPEED_MPS = 100.0

#: A quaternion whose norm differs from 1 by more than this is rejected (else it is normalised).
QUAT_NORM_TOL = 1e-3

#: A segment must overlap the open inflated obstacle over more than this length to be a hit [m].
GRAZE_TOL_M = 1e-9

#: Below this length [m] a segment is a point (start = goal): only containment is tested.
POINT_TOL_M = 1e-12

#: Default maximum spacing of the predicted copies of a moving obstacle [m].
SWEEP_STEP_M = 0.02

_KIND = {"box": 0, "sphere": 1, "cylinder": 2}


class ObstacleError(ParameterError):
    """An obstacle is invalid. ``reason`` is one of :data:`REASONS` (stable, short, for counting);
    ``field`` names the offending field."""

    def __init__(self, reason: str, field_name: str, message: str) -> None:
        super().__init__(f"obstacle {field_name}: {message}")
        self.reason = reason
        self.field = field_name


def _vec(value: ArrayLike, n: int, name: str) -> FloatArray:
    """``value`` as a float array ``(n,)``; :class:`ObstacleError` ("dims"/"nan") otherwise."""
    try:
        a = np.array(value, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise ObstacleError(REASON_DIMS, name, f"must be {n} numbers") from exc
    if a.shape != (n,):
        raise ObstacleError(REASON_DIMS, name, f"must have {n} components, got {a.size}")
    if not np.all(np.isfinite(a)):
        raise ObstacleError(REASON_NAN, name, "contains NaN or inf")
    return a


@dataclass(frozen=True)
class Obstacle:
    """One obstacle, validated on construction (raises :class:`ObstacleError`).

    Attributes:
        id: non-empty name, reported back by the checks.
        shape: one of :data:`SHAPES`.
        position: ``(3,) [m]`` centre in the world (robot base) frame.
        orientation: ``(4,)`` unit quaternion ``(x, y, z, w)`` of the local frame (normalised
            here; a norm further than :data:`QUAT_NORM_TOL` from 1 is an error).
        size: ``(3,) [m]`` box: full edge lengths; sphere: ``size[0]`` = diameter; cylinder:
            ``size[0]`` = diameter, ``size[2]`` = height along the local z. The components a shape
            uses must be > 0; the others are ignored (but must be finite).
        velocity: ``(3,) [m/s]`` velocity of the centre (default at rest).
    """

    id: str
    shape: str
    position: FloatArray
    orientation: FloatArray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))
    size: FloatArray = field(default_factory=lambda: np.ones(3))
    velocity: FloatArray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or not self.id:
            raise ObstacleError(REASON_ID, "id", "must be a non-empty string")
        if self.shape not in SHAPES:
            raise ObstacleError(REASON_SHAPE, "shape", f"must be one of {SHAPES}, got {self.shape!r}")
        position = _vec(self.position, 3, "position")
        quat = _vec(self.orientation, 4, "orientation")
        size = _vec(self.size, 3, "size")
        velocity = _vec(self.velocity, 3, "velocity")
        norm = float(np.linalg.norm(quat))
        if abs(norm - 1.0) > QUAT_NORM_TOL:
            raise ObstacleError(REASON_ORIENTATION, "orientation", f"quaternion norm {norm:.6g} is not 1")
        if max(float(np.abs(position).max()), float(np.abs(size).max())) > MAX_EXTENT_M:
            raise ObstacleError(REASON_RANGE, "position", f"position or size beyond {MAX_EXTENT_M:g} m")
        if float(np.linalg.norm(velocity)) > MAX_SPEED_MPS:
            raise ObstacleError(REASON_RANGE, "velocity", f"speed beyond {MAX_SPEED_MPS:g} m/s")
        used = {"box": (0, 1, 2), "sphere": (0,), "cylinder": (0, 2)}[self.shape]
        if any(size[i] <= 0.0 for i in used):
            raise ObstacleError(REASON_SIZE, "size", f"{self.shape} size {size.tolist()} must be > 0")
        for name, arr in (("position", position), ("orientation", quat / norm), ("size", size),
                          ("velocity", velocity)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def rotation(self) -> FloatArray:
        """``(3, 3)`` rotation matrix of the local frame in the world."""
        return Rotation.from_quat(self.orientation).as_matrix()


def validate_obstacle(
    id: str,
    shape: str,
    position: ArrayLike,
    orientation: ArrayLike = (0.0, 0.0, 0.0, 1.0),
    size: ArrayLike = (1.0, 1.0, 1.0),
    velocity: ArrayLike = (0.0, 0.0, 0.0),
) -> Obstacle:
    """Build an :class:`Obstacle` from plain values (raises :class:`ObstacleError`)."""
    return Obstacle(id, shape, position, orientation, size, velocity)  # type: ignore[arg-type]


@dataclass(frozen=True)
class BoxGroup:
    """The compiled boxes: ``index (B,)`` into the obstacle list, ``centre (B, 3) [m]``,
    ``rotation (B, 3, 3)``, inflated ``half_extents (B, 3) [m]``."""

    index: NDArray[np.intp]
    centre: FloatArray
    rotation: FloatArray
    half_extents: FloatArray


@dataclass(frozen=True)
class SphereGroup:
    """The compiled spheres: ``index (S,)``, ``centre (S, 3) [m]``, inflated ``radius (S,) [m]``."""

    index: NDArray[np.intp]
    centre: FloatArray
    radius: FloatArray


@dataclass(frozen=True)
class CylinderGroup:
    """The compiled cylinders: ``index (C,)``, ``centre (C, 3) [m]``, unit ``axis (C, 3)``,
    inflated ``radius (C,) [m]`` and ``half_height (C,) [m]``."""

    index: NDArray[np.intp]
    centre: FloatArray
    axis: FloatArray
    radius: FloatArray
    half_height: FloatArray


#: Radius standing for "no quadric" (a box): finite so that 0 · r² stays 0 in the vector code.
_NO_RADIUS = 1e100


@dataclass(frozen=True)
class _Elements:
    """The shape-parametric arrays the segment test runs on, one row per element (an obstacle,
    or one predicted copy of a moving obstacle). ``E`` elements:

    ``owner (E,)`` obstacle index; ``centre (E, 3) [m]``; ``rotation (E, 3, 3)`` (local → world);
    ``half (E, 3) [m]`` slab half widths in the local frame (inf = no slab); ``radial (E, 3)`` 0/1
    weights of the local axes in the quadric ``Σ w_a x_a² < r²`` (all 0 = none); ``radius (E,)
    [m]`` (``_NO_RADIUS`` = none); ``radius2 (E,)``; ``aabb_half (E, 3) [m]`` world AABB half
    extents; ``bound (E,) [m]`` bounding-sphere radius about the centre.

    Component-major copies for the vectorised test (axis first, so that sums over the three
    local axes add three contiguous rows): ``rt_h (4, 3E)``, whose column ``a E + e`` is the
    local axis ``a`` of element ``e`` in the world over ``−(Rᵀ c)_a`` (so ``[x, 1] @ rt_h`` gives
    every element's local coordinates of the point ``x`` and ``[d, 0] @ rt_h`` those of the
    direction ``d``, in one product), ``half_cm (3, E)``, ``radial_cm (3, E)``.
    """

    owner: NDArray[np.intp]
    centre: FloatArray
    rotation: FloatArray
    half: FloatArray
    radial: FloatArray
    radius: FloatArray
    radius2: FloatArray
    aabb_half: FloatArray
    bound: FloatArray
    rt_h: FloatArray = field(init=False)
    bounds_template: FloatArray = field(init=False)
    half_cm: FloatArray = field(init=False)
    radial_cm: FloatArray = field(init=False)

    def __post_init__(self) -> None:
        E = self.owner.shape[0]
        # rotation[e, :, a] is local axis a in the world: column a E + e of rt_h.
        rt_h = np.empty((4, 3 * E))
        rt_h[:3] = self.rotation.transpose(1, 2, 0).reshape(3, 3 * E)
        rt_h[3] = -np.einsum("eia,ei->ae", self.rotation, self.centre).reshape(3 * E)
        # Parameter bounds of the test: rows 0-2 the slabs, 3 the quadric (filled by _narrow).
        bounds = np.empty((2, 4, E))
        for name, arr in (("rt_h", rt_h), ("bounds_template", bounds),
                          ("half_cm", np.ascontiguousarray(self.half.T)),
                          ("radial_cm", np.ascontiguousarray(self.radial.T))):
            object.__setattr__(self, name, arr)

    def subset(self, idx: NDArray[np.intp]) -> _Elements:
        """The elements ``idx`` only."""
        return _Elements(self.owner[idx], self.centre[idx], self.rotation[idx], self.half[idx],
                         self.radial[idx], self.radius[idx], self.radius2[idx], self.aabb_half[idx],
                         self.bound[idx])


def _elements(
    kind: NDArray[np.intp], centre: FloatArray, rotation: FloatArray, half: FloatArray,
    radius: FloatArray, owner: NDArray[np.intp],
) -> _Elements:
    """Build the element arrays from per-element shape parameters: ``kind (E,)`` (0 box, 1 sphere,
    2 cylinder), ``half (E, 3)`` inflated box half extents (box) or ``[·, ·, half height]``
    (cylinder), ``radius (E,)`` inflated radius (sphere, cylinder)."""
    E = kind.shape[0]
    is_box, is_sph, is_cyl = kind == 0, kind == 1, kind == 2
    slab = np.full((E, 3), np.inf)
    slab[is_box] = half[is_box]
    slab[is_cyl, 2] = half[is_cyl, 2]
    radial = np.zeros((E, 3))
    radial[is_sph] = 1.0
    radial[is_cyl, :2] = 1.0
    rad = np.where(is_box, _NO_RADIUS, radius)
    absR = np.abs(rotation)
    aabb = np.empty((E, 3))
    # Box: |R| h. Sphere: r per axis. Cylinder with axis u: h|u_a| + r sqrt(1 − u_a²).
    aabb[is_box] = np.einsum("eij,ej->ei", absR[is_box], half[is_box])
    aabb[is_sph] = radius[is_sph, None]
    u = rotation[is_cyl, :, 2]
    aabb[is_cyl] = (half[is_cyl, 2, None] * np.abs(u)
                    + radius[is_cyl, None] * np.sqrt(np.clip(1.0 - u * u, 0.0, 1.0)))
    bound = np.empty(E)
    bound[is_box] = np.linalg.norm(half[is_box], axis=1)
    bound[is_sph] = radius[is_sph]
    bound[is_cyl] = np.hypot(radius[is_cyl], half[is_cyl, 2])
    return _Elements(owner, centre, rotation, slab, radial, rad, rad * rad, aabb, bound)


class CompiledObstacles:
    """Obstacles inflated by ``margin_m`` and laid out for vectorised tests.

    Attributes:
        ids: obstacle ids in input order (``obstacle_index`` of the checks indexes this).
        margin_m: the inflation [m].
        boxes, spheres, cylinders: the per-shape groups (:class:`BoxGroup`, ...).
        velocity: ``(N, 3) [m/s]`` per obstacle, in input order.
        shapes: shape names in input order.
    """

    def __init__(
        self,
        ids: tuple[str, ...],
        shapes: tuple[str, ...],
        margin_m: float,
        centre: FloatArray,
        rotation: FloatArray,
        half: FloatArray,
        radius: FloatArray,
        velocity: FloatArray,
    ) -> None:
        """Low-level constructor (use :func:`compile_obstacles` or :meth:`at`): per obstacle
        ``centre (N, 3)``, ``rotation (N, 3, 3)``, inflated ``half (N, 3)`` (box half extents;
        cylinder half height in column 2), inflated ``radius (N,)``, ``velocity (N, 3)``."""
        self.ids = ids
        self.shapes = shapes
        self.margin_m = float(margin_m)
        self.velocity = velocity
        self._centre, self._rotation, self._half, self._radius = centre, rotation, half, radius
        self._kind = np.array([_KIND[s] for s in shapes], dtype=np.intp)
        n = len(ids)
        idx = np.arange(n, dtype=np.intp)
        b, s, c = (idx[self._kind == k] for k in (0, 1, 2))
        self.boxes = BoxGroup(b, centre[b], rotation[b], half[b])
        self.spheres = SphereGroup(s, centre[s], radius[s])
        self.cylinders = CylinderGroup(c, centre[c], rotation[c, :, 2], radius[c], half[c, 2])
        self._static = _elements(self._kind, centre, rotation, half, radius, idx)
        self._speed = np.linalg.norm(velocity, axis=1) if n else np.zeros(0)
        self._sweeps: dict[tuple[float, float], _Elements] = {}

    def __len__(self) -> int:
        return len(self.ids)

    def at(self, t_s: float) -> CompiledObstacles:
        """The same obstacles predicted ``t_s`` [s] ahead: centres moved by ``velocity · t_s``."""
        return CompiledObstacles(self.ids, self.shapes, self.margin_m, self._centre + self.velocity * t_s,
                                 self._rotation, self._half, self._radius, self.velocity)

    def elements(self, horizon_s: float = 0.0, sweep_step_m: float = SWEEP_STEP_M) -> _Elements:
        """The elements covering every obstacle over ``[0, horizon_s]`` (see the module doc):
        each moving obstacle becomes ``⌈|v| H / step⌉`` copies at mid-interval times, inflated by
        ``|v| H / (2k)``. Cached per ``(horizon_s, sweep_step_m)``."""
        if horizon_s <= 0.0 or not np.any(self._speed > 0.0):
            return self._static
        key = (float(horizon_s), float(sweep_step_m))
        cached = self._sweeps.get(key)
        if cached is not None:
            return cached
        travel = self._speed * horizon_s
        k = np.maximum(1, np.ceil(travel / sweep_step_m)).astype(np.intp)
        k[travel == 0.0] = 1
        owner = np.repeat(np.arange(len(self.ids), dtype=np.intp), k)
        first = np.cumsum(k) - k
        i = np.arange(owner.shape[0]) - first[owner]  # copy number within its obstacle
        t = (i + 0.5) * horizon_s / k[owner]
        t[travel[owner] == 0.0] = 0.0
        grow = travel[owner] / (2.0 * k[owner])  # |v| H / (2k): half the spacing of the copies
        centre = self._centre[owner] + self.velocity[owner] * t[:, None]
        half = self._half[owner] + grow[:, None]
        radius = self._radius[owner] + grow
        el = _elements(self._kind[owner], centre, self._rotation[owner], half, radius, owner)
        self._sweeps[key] = el
        return el


def compile_obstacles(obstacles: Sequence[Obstacle], margin_m: float = 0.0) -> CompiledObstacles:
    """Inflate ``obstacles`` by ``margin_m`` [m] (≥ 0; see the module doc per shape) and lay them
    out for :func:`segment_check`. Ids keep the input order (duplicates are allowed; the first
    hit reports its own index)."""
    if not (math.isfinite(margin_m) and margin_m >= 0.0):
        raise ParameterError(f"margin_m must be a finite number >= 0, got {margin_m}")
    n = len(obstacles)
    centre = np.zeros((n, 3))
    rotation = np.zeros((n, 3, 3))
    half = np.zeros((n, 3))
    radius = np.zeros(n)
    velocity = np.zeros((n, 3))
    if n:
        quats = np.array([o.orientation for o in obstacles])
        rotation[:] = Rotation.from_quat(quats).as_matrix().reshape(n, 3, 3)
    for i, o in enumerate(obstacles):
        centre[i] = o.position
        velocity[i] = o.velocity
        if o.shape == "box":
            half[i] = 0.5 * o.size + margin_m
        elif o.shape == "sphere":
            radius[i] = 0.5 * o.size[0] + margin_m
            rotation[i] = np.eye(3)  # a sphere's orientation is irrelevant
        else:
            radius[i] = 0.5 * o.size[0] + margin_m
            half[i, 2] = 0.5 * o.size[2] + margin_m
    return CompiledObstacles(tuple(o.id for o in obstacles), tuple(o.shape for o in obstacles), margin_m,
                             centre, rotation, half, radius, velocity)


class SegmentHit(NamedTuple):
    """Result of :func:`segment_check` (an immutable named tuple: cheap to build at every tick).

    Attributes:
        collision: the segment enters an inflated obstacle (or starts inside one).
        obstacle_index: index of the first obstacle hit in the compiled list (-1 if none).
        obstacle_id: its id ("" if none).
        entry_fraction: where the segment enters, in ``[0, 1]`` (0 if inside; nan if none).
        entry_point: ``(3,) [m]`` start + fraction · (goal − start) (nan if none).
        normal: ``(3,)`` unit outward normal of the entered surface in the world (inside: of the
            nearest surface; nan if none).
        stop_position: ``(3,) [m]`` per-axis stop for ``PSMController.set_stops``; NaN = the axis
            goes on (all NaN if none).
        inside: the start is inside the inflated obstacle.
        distance_m: start → entry along the segment [m] (0 if inside; inf if none).
        time_to_collision_s: ``distance_m`` / the EE speed along the segment [s] if a velocity is
            given and points towards the goal; 0 if inside; else inf.
    """

    collision: bool
    obstacle_index: int
    obstacle_id: str
    entry_fraction: float
    entry_point: FloatArray
    normal: FloatArray
    stop_position: FloatArray
    inside: bool
    distance_m: float
    time_to_collision_s: float


_NAN3 = np.full(3, np.nan)
_NAN3.setflags(write=False)
_NO_HIT = SegmentHit(False, -1, "", math.nan, _NAN3, _NAN3, _NAN3, False, math.inf, math.inf)


#: Above this many elements a broad phase (segment vs bounding sphere) selects the candidates
#: first; below it the exact test of every element in one pass is cheaper (numpy's per-call
#: overhead dominates at this size, not the arithmetic).
BROAD_PHASE_MIN = 256


_SLAB_SIGN = np.array([-1.0, 1.0]).reshape(2, 1, 1)
_ROOT_SIGN = np.array([1.0, -1.0]).reshape(2, 1)


def _narrow(p: FloatArray, d: FloatArray, el: _Elements) -> tuple[
        FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Exact test of the segment ``p + t d`` (``t ∈ [0, 1]``) against every element's open shape.

    Each shape is ``{x : |x_a| < h_a for a = 0..2, Σ w_a x_a² < r²}`` in its local frame, so the
    line is inside over ``t_in < t < t_out`` with ``t_in`` the largest entry parameter of the
    three slabs and the quadric and ``t_out`` the smallest exit; the segment's own bounds 0 and
    1 clip that to ``lo < t < hi``. Call it under ``np.errstate(divide="ignore", invalid="ignore")``.

    Returns ``t_in (E,)``, ``t_out (E,)``, ``lo (E,)`` = ``max(t_in, 0)``, ``hi (E,)`` =
    ``min(t_out, 1)``, ``B (2, 4, E)`` the entry (``B[0]``) and exit (``B[1]``) parameters of the
    constraints (rows: three slabs, the quadric) and ``M (2, 3, E)`` the local start
    ``Rᵀ (p − c)`` (``M[0]``) and direction ``Rᵀ d`` (``M[1]``), component-major. A line that
    misses a quadric, or lies in a slab's boundary plane, gets NaN parameters: every comparison
    with them is False, i.e. a miss (a grazing line).
    """
    E = el.owner.shape[0]
    pd = np.zeros((2, 4))
    pd[0, :3] = p
    pd[0, 3] = 1.0
    pd[1, :3] = d
    M = (pd @ el.rt_h).reshape(2, 3, E)  # Rᵀ (p − c) and Rᵀ d of every element
    f = M[0]
    g = M[1]
    B = el.bounds_template.copy()
    # Slabs: entry (-sign(g) h - f)/g, exit (sign(g) h - f)/g. With g_a = 0 the division gives
    # -inf/+inf when |f_a| < h_a (inside for every t), an empty interval when outside, NaN on the
    # boundary plane; an absent slab (h = inf) gives (-inf, inf).
    np.divide(_SLAB_SIGN * np.copysign(el.half_cm, g) - f, g, out=B[:, :3])
    # Quadric a t² + 2 b t + c < 0 with a = gᵀWg, b = fᵀWg, c = fᵀWf − r²: roots −(b ± √(b² − ac))/a.
    # a gets 1e-300 so that a line parallel to a cylinder's axis (a = 0) is inside for all t when
    # c < 0 (roots at ±1e150 √|c|) and misses when c > 0 (NaN); a box (W = 0, r = 1e100) is
    # inside for all t.
    G = np.einsum("iae,jae->ije", M * el.radial_cm, M)  # (2, 2, E): [[fWf, fWg], [gWf, gWg]]
    b = G[0, 1]
    a = G[1, 1] + 1e-300
    sq = np.sqrt(b * b - a * (G[0, 0] - el.radius2))
    np.multiply(b + _ROOT_SIGN * sq, -1.0 / a, out=B[:, 3])
    t_in = B[0].max(axis=0)
    t_out = B[1].min(axis=0)
    return t_in, t_out, np.maximum(t_in, 0.0), np.minimum(t_out, 1.0), B, M


def _entry_normal(f: list[float], g: list[float], t: float, slab_entries: list[float], quadric_last: bool,
                  el: _Elements, e: int) -> list[float]:
    """Local outward normal of the constraint of element ``e`` that the line ``f + t g`` (local
    frame, plain floats) enters last, at its entry parameter ``t``: the quadric's gradient if
    ``quadric_last``, else the face of the slab with the largest of ``slab_entries``."""
    if quadric_last:
        w = el.radial[e].tolist()
        x = [w[i] * (f[i] + t * g[i]) for i in range(3)]
        n = math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2])
        return [x[0] / n, x[1] / n, x[2] / n]
    ax = max(range(3), key=slab_entries.__getitem__)
    out = [0.0, 0.0, 0.0]
    out[ax] = -math.copysign(1.0, g[ax])
    return out


def _inside_normal(f: list[float], el: _Elements, e: int) -> list[float]:
    """Local outward normal of the surface of element ``e`` nearest to the inside point ``f``
    (local frame): the quadric's gradient or a slab face, whichever is shallower. On a cylinder's
    axis or at a sphere's centre the radial direction is arbitrary: local +x."""
    h = el.half[e].tolist()
    w = el.radial[e].tolist()
    slab = [abs(f[i]) - h[i] for i in range(3)]
    ax = max(range(3), key=slab.__getitem__)
    wf = [w[i] * f[i] for i in range(3)]
    rho = math.sqrt(wf[0] * wf[0] + wf[1] * wf[1] + wf[2] * wf[2])
    out = [0.0, 0.0, 0.0]
    if rho - float(el.radius[e]) > slab[ax]:
        if rho > 0.0:
            return [wf[0] / rho, wf[1] / rho, wf[2] / rho]
        out[0] = 1.0
        return out
    out[ax] = 1.0 if f[ax] >= 0.0 else -1.0
    return out


def segment_check(
    start: ArrayLike,
    goal: ArrayLike,
    compiled: CompiledObstacles,
    horizon_s: float = 0.0,
    velocity: ArrayLike | None = None,
    sweep_step_m: float = SWEEP_STEP_M,
) -> SegmentHit:
    """The collision condition: does the segment ``start → goal`` enter an inflated obstacle?

    Args:
        start: ``(3,) [m]`` current end-effector position.
        goal: ``(3,) [m]`` goal position.
        compiled: the obstacles (:func:`compile_obstacles`).
        horizon_s: ``[s]`` obstacles are tested over their motion during ``[0, horizon_s]`` (0:
            where they are now); see the module doc.
        velocity: ``(3,) [m/s]`` the EE velocity, for ``time_to_collision_s`` (optional).
        sweep_step_m: ``[m]`` spacing of the predicted copies of a moving obstacle (> 0).

    Returns:
        :class:`SegmentHit` of the first obstacle hit along the segment (grazing is a miss; a
        start inside wins, at fraction 0; ties go to the lower obstacle index). Stop rule and
        semantics: module doc.
    """
    p = np.asarray(start, dtype=float)
    q = np.asarray(goal, dtype=float)
    if len(compiled) == 0:
        return _NO_HIT
    el = compiled.elements(horizon_s, sweep_step_m)
    d = q - p
    L2 = float(d @ d)
    L = math.sqrt(L2)
    if el.owner.shape[0] > BROAD_PHASE_MIN:
        # Broad phase: distance from each element's centre to the segment vs its bounding radius.
        wc = el.centre - p
        off = wc - np.clip((wc @ d) / L2, 0.0, 1.0)[:, None] * d if L2 > 0.0 else wc
        cand = np.flatnonzero(np.einsum("ij,ij->i", off, off) < el.bound * el.bound)
        if cand.shape[0] == 0:
            return _NO_HIT
        el = el.subset(cand)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_in, t_out, lo, hi, B, M = _narrow(p, d, el)
        if L > POINT_TOL_M:
            # Hit: overlap of [0, 1] with (t_in, t_out) longer than the grazing tolerance (NaN
            # parameters compare False: a miss); the first entry along the segment wins.
            key = np.where(hi - lo > GRAZE_TOL_M / L, lo, np.inf)
            j = int(key.argmin())
            if key[j] == np.inf:
                return _NO_HIT
            check_inside = key[j] == 0.0
        else:
            check_inside = True
        # Inside: the start is in the open shape, deeper than the grazing tolerance along the
        # line (a start on the surface, e.g. held at its stop, is outside); a point (L = 0) is
        # inside if in the open shape at all.
        tau = GRAZE_TOL_M / L if L > POINT_TOL_M else 0.0
        if check_inside:
            # A start inside wins over entries at fraction 0.
            inside_idx = ((t_in < -tau) & (t_out > tau)).nonzero()[0]
            if inside_idx.shape[0]:
                j = int(inside_idx[0])
            elif L <= POINT_TOL_M:
                return _NO_HIT
    entries = B[0, :, j].tolist()  # slabs, quadric (never NaN for a winner: NaN compares False)
    t_j = max(entries)
    inside = t_j < -tau and float(t_out[j]) > tau
    # The winner only, in plain floats (3-vectors are cheaper in Python than in numpy).
    f, g = M[:, :, j].tolist()
    owner = int(el.owner[j])
    R = el.rotation[j].tolist()
    pl = p.tolist()
    dl = d.tolist()
    stop = [math.nan, math.nan, math.nan]
    if inside:
        normal = _rotate(R, _inside_normal(f, el, j))
        for i in range(3):
            if normal[i] * dl[i] < 0.0:  # this axis's motion goes deeper: hold it
                stop[i] = pl[i]
        return SegmentHit(True, owner, compiled.ids[owner], 0.0, p.copy(), np.array(normal), np.array(stop),
                          True, 0.0, 0.0)
    frac = max(t_j, 0.0)
    entry = [pl[i] + frac * dl[i] for i in range(3)]
    slab_entries = entries[:3]
    quadric_last = entries[3] > max(slab_entries)
    normal = _rotate(R, _entry_normal(f, g, t_j, slab_entries, quadric_last, el, j))
    _stop_axes(pl, dl, entry, normal, el.centre[j].tolist(), el.aabb_half[j].tolist(), stop)
    dist = frac * L
    ttc = math.inf
    if velocity is not None:
        speed = float(np.asarray(velocity, dtype=float) @ d) / L
        if speed > 0.0:
            ttc = dist / speed
    return SegmentHit(True, owner, compiled.ids[owner], frac, np.array(entry), np.array(normal),
                      np.array(stop), False, dist, ttc)


def stopping_distance(speed_mps: float, decel_mps2: float, dt_s: float) -> float:
    """How far a point moving at ``speed_mps`` [m/s] travels before it is at rest [m]: one control
    period ``dt_s`` [s] at that speed (the stop acts from the next tick) plus braking at
    ``decel_mps2`` [m/s²] (> 0), ``v²/(2a)``."""
    return speed_mps * dt_s + speed_mps * speed_mps / (2.0 * decel_mps2)


def stopping_check(
    start: ArrayLike,
    velocity: ArrayLike,
    compiled: CompiledObstacles,
    decel_mps2: float,
    dt_s: float,
    horizon_s: float = 0.0,
    sweep_step_m: float = SWEEP_STEP_M,
) -> SegmentHit:
    """The complement of :func:`segment_check` for a path that is not the straight segment to the
    goal: does the point's stopping path, the segment from ``start`` along ``velocity`` over
    :func:`stopping_distance`, enter an inflated obstacle? Same result and stop rule as
    :func:`segment_check` (the segment's end is where the point would come to rest).

    Args:
        start: ``(3,) [m]`` current end-effector position.
        velocity: ``(3,) [m/s]`` its velocity (at rest: never a hit).
        compiled: the obstacles (:func:`compile_obstacles`).
        decel_mps2: ``[m/s²]`` the deceleration the stop brakes with (> 0).
        dt_s: ``[s]`` the control period.
        horizon_s, sweep_step_m: moving obstacles, as in :func:`segment_check`.
    """
    p = np.asarray(start, dtype=float)
    v = np.asarray(velocity, dtype=float)
    speed = math.sqrt(float(v @ v))
    if speed == 0.0 or len(compiled) == 0:
        return _NO_HIT
    reach = stopping_distance(speed, decel_mps2, dt_s)
    el = compiled.elements(horizon_s, sweep_step_m)
    # Broad phase: every element's bounding sphere farther than the stopping path is a miss.
    off = el.centre - p
    if not bool(np.any(np.einsum("ij,ij->i", off, off) < (el.bound + reach) ** 2)):
        return _NO_HIT
    return segment_check(p, p + v * (reach / speed), compiled, horizon_s, v, sweep_step_m)


def _rotate(R: list[list[float]], n: list[float]) -> list[float]:
    """``R n`` for a rotation ``R`` (3 rows of 3 floats) and a 3-vector, in plain floats."""
    return [R[0][0] * n[0] + R[0][1] * n[1] + R[0][2] * n[2],
            R[1][0] * n[0] + R[1][1] * n[1] + R[1][2] * n[2],
            R[2][0] * n[0] + R[2][1] * n[1] + R[2][2] * n[2]]


def _stop_axes(p: list[float], d: list[float], entry: list[float], normal: list[float], centre: list[float],
               aabb_half: list[float], stop: list[float]) -> None:
    """Fill ``stop`` (3 floats, NaN = goes on) for a segment ``p + t d`` entering at ``entry``
    through a surface of outward ``normal``, of an obstacle whose world AABB is
    ``centre ± aabb_half`` (module doc)."""
    # The AABB entry axis: the slab entered last. Only axes the start is outside of can be entered
    # (the others contain the start), and only when moving towards the box.
    best_a, best_t = -1, -math.inf
    for a in range(3):
        lo_b = centre[a] - aabb_half[a]
        hi_b = centre[a] + aabb_half[a]
        if (p[a] <= lo_b and d[a] > 0.0) or (p[a] >= hi_b and d[a] < 0.0):
            face = lo_b if d[a] > 0.0 else hi_b
            t = (face - p[a]) / d[a]
            if t > best_t:
                best_a, best_t = a, t
                stop_face = face
    if best_a >= 0:
        stop[best_a] = stop_face
        return
    # Start inside the AABB: the tangent plane at the entry point separates.
    nd = [normal[a] * d[a] for a in range(3)]
    s = sum(x for x in nd if x < 0.0)
    if s < 0.0:
        mu = min(1.0, (nd[0] + nd[1] + nd[2]) / s)
        for a in range(3):
            if nd[a] < 0.0:
                stop[a] = p[a] + mu * (entry[a] - p[a])
