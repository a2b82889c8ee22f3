"""Whole-arm clearance: the minimum distance between the arm's collision geometry at a joint
state and every obstacle, per link, with coal (GJK/EPA).

Method (``docs/obstacles.md`` has the figures):

* **geometry**: the URDF's collision geometry, reduced like :class:`~services.robot.model.RobotModel`
  (fingers locked). Each mesh is replaced by its convex hull (coal's ``buildConvexRepresentation``);
  primitive shapes (the Panda's finger boxes) are kept. Distances are exact with respect to the
  hulls: a hull contains its mesh, so the hull distance is a lower bound of the mesh distance
  (conservative);
* **obstacles**: coal ``Box`` / ``Sphere`` / ``Cylinder`` of their real size (the bus's
  :class:`~psm.obstacles.Obstacle` semantics); the safety margin ``m`` is subtracted from the
  distance, ``d_m = d − m``, which is exactly the distance to the obstacle inflated by a ball of
  radius ``m`` (rounded corners) whenever ``d ≥ 0``;
* **penetration**: coal returns a signed distance for shape pairs (``enable_signed_distance``): the
  negative penetration depth when a hull and an obstacle overlap, so ``min_distance_m ≤ −m`` there
  and ``≤ 0`` whenever the hull is within the margin;
* **broad phase**: every geometry and obstacle has a bounding sphere (centre, radius ``r``); the
  lower bound ``|c_g − c_o| − r_g − r_o`` of a pair's distance decides the order of the exact
  pairs (ascending) and skips a pair when it cannot improve its link's minimum found so far, or
  when it is beyond the report cutoff. Per-link values are therefore exact up to the cutoff, and
  ``inf`` beyond it (never a guess).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import coal
import numpy as np
import pinocchio as pin

from psm.obstacles import Obstacle
from services.robot.model import RobotModel


@dataclass(frozen=True)
class ClearanceResult:
    """Result of :meth:`ArmClearance.check`.

    Attributes:
        min_distance_m: ``[m]`` smallest distance − margin over all links (``inf`` if no pair is
            within the cutoff); ≤ 0 means inside the margin, < −margin penetrating.
        link: name of the closest link ("" if none within the cutoff).
        obstacle_id: id of the closest obstacle ("").
        per_link: ``(L,) [m]`` each link's distance − margin, exact when ≤ ``cutoff_m``, else inf;
            from :meth:`ArmClearance.check` with ``per_link=False``, NaN for every link but the
            closest (not computed).
        link_names: ``(L,)`` the links, in model order.
        witness_arm: ``(3,) [m]`` closest point on the arm's hull, world frame (nan if none).
        witness_obstacle: ``(3,) [m]`` closest point on the (not inflated) obstacle (nan).
        pairs_evaluated: exact (GJK) distance computations done by this check.
    """

    min_distance_m: float
    link: str
    obstacle_id: str
    per_link: np.ndarray
    link_names: tuple[str, ...]
    witness_arm: np.ndarray
    witness_obstacle: np.ndarray
    pairs_evaluated: int


def _obstacle_shape(o: Obstacle) -> tuple[coal.CollisionGeometry, float]:
    """The coal shape of ``o`` (real size) and its bounding-sphere radius [m]."""
    if o.shape == "box":
        return coal.Box(*map(float, o.size)), 0.5 * float(np.linalg.norm(o.size))
    if o.shape == "sphere":
        r = 0.5 * float(o.size[0])
        return coal.Sphere(r), r
    r, h = 0.5 * float(o.size[0]), float(o.size[2])
    return coal.Cylinder(r, h), math.hypot(r, 0.5 * h)


class ArmClearance:
    """Minimum distance between the arm and a set of obstacles, per link.

    Args:
        robot: the arm (its :meth:`~RobotModel.collision_geometry` is used).
        margin_m: ``[m]`` safety margin subtracted from every distance (≥ 0).
        cutoff_m: ``[m]`` distances (after the margin) above this are not computed exactly and
            reported as inf (> 0; ``inf`` computes every link's exact distance).
        convex: use the convex hulls of the meshes (default); ``False`` keeps the BVH meshes
            (exact w.r.t. the meshes, about 100× slower; for comparisons).
    """

    def __init__(self, robot: RobotModel, margin_m: float = 0.0, cutoff_m: float = 1.0,
                 convex: bool = True) -> None:
        if not (math.isfinite(margin_m) and margin_m >= 0.0):
            raise ValueError(f"margin_m must be a finite number >= 0, got {margin_m}")
        if not cutoff_m > 0.0:
            raise ValueError(f"cutoff_m must be > 0, got {cutoff_m}")
        self.robot = robot
        self.margin_m = float(margin_m)
        self.cutoff_m = float(cutoff_m)
        self._model = robot.model
        self._data = self._model.createData()
        self._geom_model = robot.collision_geometry()
        self._geom_data = pin.GeometryData(self._geom_model)
        shapes: list[coal.CollisionGeometry] = []
        centres: list[np.ndarray] = []  # bounding-sphere centre in the parent joint's frame
        radii: list[float] = []
        joints: list[int] = []
        link_of: list[int] = []
        names: list[str] = []
        for go in self._geom_model.geometryObjects:
            g = go.geometry
            if convex and isinstance(g, coal.BVHModelBase):
                g.buildConvexRepresentation(False)
                g = g.convex
            g.computeLocalAABB()
            shapes.append(g)
            centres.append(go.placement.act(np.array(g.aabb_center, dtype=float)))
            radii.append(float(g.aabb_radius))
            joints.append(int(go.parentJoint))
            link = self._model.frames[go.parentFrame].name
            if link not in names:
                names.append(link)
            link_of.append(names.index(link))
        self._shapes = shapes
        self._local_centre = np.array(centres)  # (G, 3)
        self._geom_radius = np.array(radii)  # (G,)
        self._joint = np.array(joints, dtype=np.intp)
        self._moving_joints = sorted(set(joints) - {0})
        # The geometries on a moving joint, and the row of that joint in _moving_joints.
        self._on_moving = np.flatnonzero(self._joint != 0)
        self._joint_row = np.searchsorted(self._moving_joints, self._joint[self._on_moving])
        self._link_of = np.array(link_of, dtype=np.intp)
        self.link_names: tuple[str, ...] = tuple(names)
        self._request = coal.DistanceRequest()
        self._request.enable_signed_distance = True
        self._result = coal.DistanceResult()
        self.set_obstacles([])

    @property
    def n_geometries(self) -> int:
        """Number of collision geometries of the arm."""
        return len(self._shapes)

    def set_obstacles(self, obstacles: Sequence[Obstacle], t_s: float = 0.0) -> None:
        """Replace the obstacles; each is placed at ``position + velocity · t_s`` [m]."""
        self._obstacles = list(obstacles)
        self._obs_shapes = []
        self._obs_tf = []
        centres = np.zeros((len(obstacles), 3))
        radii = np.zeros(len(obstacles))
        for i, o in enumerate(obstacles):
            shape, r = _obstacle_shape(o)
            c = o.position + o.velocity * t_s
            self._obs_shapes.append(shape)
            self._obs_tf.append(coal.Transform3s(o.rotation, c))
            centres[i] = c
            radii[i] = r
        self._obs_centre = centres
        self._obs_radius = radii
        # One coal distance functor per (geometry, obstacle) pair, built when first needed.
        self._functors: dict[tuple[int, int], coal.ComputeDistance] = {}

    def _placements(self, q: np.ndarray) -> np.ndarray:
        """Update the geometry placements for ``q (n,)`` and return the bounding-sphere centres
        ``(G, 3) [m]`` in the world."""
        pin.forwardKinematics(self._model, self._data, q)
        pin.updateGeometryPlacements(self._model, self._data, self._geom_model, self._geom_data)
        world = self._local_centre.copy()  # joint 0 (the fixed base) is the world
        placements = [self._data.oMi[j] for j in self._moving_joints]
        rotation = np.array([M.rotation for M in placements])[self._joint_row]  # (G', 3, 3)
        translation = np.array([M.translation for M in placements])[self._joint_row]  # (G', 3)
        moving = self._on_moving
        world[moving] = np.einsum("gij,gj->gi", rotation, self._local_centre[moving]) + translation
        return world

    def _distance(self, g: int, o: int) -> float:
        """Exact signed distance [m] of geometry ``g`` (current placement) to obstacle ``o``."""
        f = self._functors.get((g, o))
        if f is None:
            f = coal.ComputeDistance(self._shapes[g], self._obs_shapes[o])
            self._functors[(g, o)] = f
        self._result.clear()
        return float(f(self._geom_data.oMg[g], self._obs_tf[o], self._request, self._result))

    def lower_bounds(self, q: np.ndarray) -> np.ndarray:
        """``(G, M) [m]`` bounding-sphere lower bounds of every pair's distance at ``q`` (before
        the margin)."""
        cg = self._placements(np.asarray(q, dtype=float))
        diff = cg[:, None, :] - self._obs_centre[None, :, :]
        centre_distance = np.sqrt(np.einsum("gmi,gmi->gm", diff, diff))
        return centre_distance - self._geom_radius[:, None] - self._obs_radius[None, :]

    def check(self, q: np.ndarray, per_link: bool = True) -> ClearanceResult:
        """Clearance at joint state ``q (n,) [rad]`` with the broad phase (see the module doc).

        ``per_link=False`` computes the smallest distance and its link, obstacle and witness
        points only (the same values as with ``per_link``): a pair is skipped once its lower bound
        reaches the smallest distance found so far over all links, not that of its own link, so
        far fewer pairs are evaluated; ``per_link`` of the result is NaN but for the closest link.
        """
        L = len(self.link_names)
        best = np.full(L, np.inf)  # raw (before the margin) per link
        M = len(self._obstacles)
        if M == 0:
            return self._result_from(best, -1, -1, None, None, 0)
        lb = self.lower_bounds(q)
        cut = self.cutoff_m + self.margin_m  # raw cutoff
        flat = lb.ravel()
        order = np.argsort(flat, kind="stable")
        n_in = int(np.searchsorted(flat[order], cut, side="right"))
        G_link = self._link_of
        best_g = best_o = -1
        best_all = math.inf
        w_arm = w_obs = None
        evaluated = 0
        for k in order[:n_in].tolist():
            if not per_link and flat[k] >= best_all:
                break  # ascending bounds: no later pair can come closer than best_all
            g, o = divmod(k, M)
            link = G_link[g]
            if flat[k] >= best[link]:
                continue  # cannot improve this link's minimum
            d = self._distance(g, o)
            evaluated += 1
            if d < best[link]:
                best[link] = d
                if d < best_all:
                    best_all, best_g, best_o = d, g, o
                    w_arm = np.array(self._result.getNearestPoint1())
                    w_obs = np.array(self._result.getNearestPoint2())
        if not per_link and best_g >= 0:
            closest = G_link[best_g]
            best[np.arange(L) != closest] = np.nan
        return self._result_from(best, best_g, best_o, w_arm, w_obs, evaluated)

    def speed_bound(self, q: np.ndarray, dq: np.ndarray) -> float:
        """Upper bound [m/s] of the speed of every point of the arm's collision geometry at joint
        state ``q, dq (n,)`` [rad, rad/s]: per geometry ``|v_c| + |ω| r`` with ``v_c`` the velocity
        of its bounding-sphere centre, ``ω`` its angular velocity and ``r`` its radius (a point at
        distance ≤ r from the centre moves at ``|v_c + ω × (p − c)| ≤ |v_c| + |ω| r``)."""
        q, dq = np.asarray(q, dtype=float), np.asarray(dq, dtype=float)
        pin.forwardKinematics(self._model, self._data, q, dq)
        vel = self._data.v
        # Body twists [linear; angular] in each joint's own frame (joint 0, the base, is at rest).
        twists = np.array([vel[j].vector for j in range(self._model.njoints)])  # (J, 6)
        lin, ang = twists[self._joint, :3], twists[self._joint, 3:]  # per geometry (G, 3)
        centre = lin + np.cross(ang, self._local_centre)
        speed = np.sqrt(np.einsum("gi,gi->g", centre, centre))
        speed += np.sqrt(np.einsum("gi,gi->g", ang, ang)) * self._geom_radius
        return float(speed.max())

    def check_brute(self, q: np.ndarray) -> ClearanceResult:
        """Clearance at ``q`` by every (geometry, obstacle) pair, no broad phase (the reference)."""
        self._placements(np.asarray(q, dtype=float))
        best = np.full(len(self.link_names), np.inf)
        best_g = best_o = -1
        best_all = math.inf
        w_arm = w_obs = None
        for g in range(len(self._shapes)):
            for o in range(len(self._obstacles)):
                d = self._distance(g, o)
                link = self._link_of[g]
                best[link] = min(best[link], d)
                if d < best_all:
                    best_all, best_g, best_o = d, g, o
                    w_arm = np.array(self._result.getNearestPoint1())
                    w_obs = np.array(self._result.getNearestPoint2())
        return self._result_from(best, best_g, best_o, w_arm, w_obs, len(self._shapes) * len(self._obstacles))

    def _result_from(self, best_raw: np.ndarray, g: int, o: int, w_arm: np.ndarray | None,
                     w_obs: np.ndarray | None, evaluated: int) -> ClearanceResult:
        per_link = best_raw - self.margin_m
        per_link[per_link > self.cutoff_m] = np.inf
        nan3 = np.full(3, np.nan)
        # With the other links not computed (NaN), the closest is the link of geometry g.
        if g < 0:
            link = -1
        else:
            link = int(self._link_of[g]) if np.isnan(per_link).any() else int(np.argmin(per_link))
        if link < 0 or not math.isfinite(float(per_link[link])):
            return ClearanceResult(math.inf, "", "", per_link, self.link_names, nan3, nan3.copy(), evaluated)
        return ClearanceResult(float(per_link[link]), self.link_names[link], self._obstacles[o].id, per_link,
                               self.link_names, w_arm if w_arm is not None else nan3,
                               w_obs if w_obs is not None else nan3.copy(), evaluated)
