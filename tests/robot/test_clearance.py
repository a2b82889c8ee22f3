"""Whole-arm clearance (services.robot.clearance): distances against an independent computation
(point to the convex hull of a link's hull vertices, by a small QP in scipy), the closest link,
the broad phase against brute force, penetration, margin and cutoff."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from psm.obstacles import Obstacle, validate_obstacle
from services.robot.clearance import ArmClearance
from services.robot.model import RobotModel


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.load()


@pytest.fixture(scope="module")
def arm(robot: RobotModel) -> ArmClearance:
    return ArmClearance(robot, margin_m=0.0, cutoff_m=math.inf)


def sphere(id: str, centre, radius: float) -> Obstacle:
    return validate_obstacle(id, "sphere", centre, size=(2.0 * radius, 0.0, 0.0))


def hull_vertices_world(arm: ArmClearance, robot: RobotModel, q: np.ndarray, link: str) -> np.ndarray:
    """World coordinates ``(V, 3)`` of the hull vertices of every geometry of ``link`` at ``q``."""
    gm = robot.collision_geometry()
    gd = pin.GeometryData(gm)
    data = robot.model.createData()
    pin.updateGeometryPlacements(robot.model, data, gm, gd, q)
    out = []
    for i, go in enumerate(gm.geometryObjects):
        if robot.model.frames[go.parentFrame].name != link:
            continue
        g = go.geometry
        if hasattr(g, "halfSide"):  # a box (the fingers): its corners
            pts = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * g.halfSide
        else:
            g.buildConvexRepresentation(False)
            pts = np.asarray(g.convex.points())
        M = gd.oMg[i]
        out.append(pts @ M.rotation.T + M.translation)
    return np.vstack(out)


def point_to_hull(c: np.ndarray, V: np.ndarray) -> float:
    """Distance from ``c`` to the convex hull of ``V`` by min ‖Vᵀλ − c‖², λ ≥ 0, Σλ = 1."""
    n = V.shape[0]
    res = minimize(lambda lam: float(np.sum((lam @ V - c) ** 2)), np.full(n, 1.0 / n),
                   jac=lambda lam: 2.0 * V @ (lam @ V - c), bounds=[(0.0, 1.0)] * n,
                   constraints=[{"type": "eq", "fun": lambda lam: lam.sum() - 1.0}], method="SLSQP",
                   options={"ftol": 1e-14, "maxiter": 500})
    return math.sqrt(max(res.fun, 0.0))


def test_collision_geometry_is_reduced_like_the_model(robot: RobotModel) -> None:
    gm = robot.collision_geometry()
    assert gm.ngeoms == 17
    names = {robot.model.frames[go.parentFrame].name for go in gm.geometryObjects}
    assert {"panda_link0", "panda_hand", "panda_leftfinger", "panda_rightfinger"} <= names
    assert max(go.parentJoint for go in gm.geometryObjects) == robot.model.njoints - 1


def test_sphere_below_the_base_matches_the_hull_distance(arm: ArmClearance, robot: RobotModel) -> None:
    q = robot.named_poses["ready"]
    centre, r = np.array([0.02, -0.01, -0.30]), 0.05
    arm.set_obstacles([sphere("s", centre, r)])
    res = arm.check(q)
    assert res.link == "panda_link0" and res.obstacle_id == "s"
    V = hull_vertices_world(arm, robot, q, "panda_link0")
    expected = point_to_hull(centre, V) - r
    assert res.min_distance_m == pytest.approx(expected, abs=1e-5)
    # Bounds that need no optimiser: the bottom plane below, the nearest vertex above.
    assert V[:, 2].min() - centre[2] - r - 1e-9 <= res.min_distance_m
    assert res.min_distance_m <= np.linalg.norm(V - centre, axis=1).min() - r + 1e-9
    # The witness points: on the sphere, and as far apart as the distance (before the margin).
    assert np.linalg.norm(res.witness_obstacle - centre) == pytest.approx(r, abs=1e-6)
    gap = np.linalg.norm(res.witness_arm - res.witness_obstacle)
    assert gap == pytest.approx(res.min_distance_m, abs=1e-6)


@pytest.mark.parametrize("link", ["panda_link3", "panda_link5", "panda_hand"])
def test_sphere_beside_a_link_matches_the_hull_distance(arm: ArmClearance, robot: RobotModel,
                                                        link: str) -> None:
    q = robot.named_poses["ready"]
    V = hull_vertices_world(arm, robot, q, link)
    # A sphere 10 cm beyond the link's hull, outwards from the robot's vertical axis.
    mid = V.mean(axis=0)
    out = np.array([mid[0], mid[1], 0.0])
    out = out / np.linalg.norm(out) if np.linalg.norm(out) > 1e-6 else np.array([1.0, 0.0, 0.0])
    far = V[np.argmax(V @ out)]
    centre = np.array([far[0], far[1], mid[2]]) + 0.13 * out
    r = 0.03
    arm.set_obstacles([sphere("s", centre, r)])
    res = arm.check(q)
    li = arm.link_names.index(link)
    assert res.per_link[li] == pytest.approx(point_to_hull(centre, V) - r, abs=1e-5)


def test_closest_link_near_the_fingers(arm: ArmClearance, robot: RobotModel) -> None:
    q = robot.named_poses["ready"]
    tcp, _ = robot.fk(q)
    arm.set_obstacles([sphere("s", tcp - np.array([0.0, 0.0, 0.08]), 0.02)])
    res = arm.check(q)
    assert res.link in ("panda_leftfinger", "panda_rightfinger")
    assert res.min_distance_m == pytest.approx(float(np.min(res.per_link)))
    assert res.min_distance_m > 0.0


def _random_obstacles(rng: np.random.Generator, n: int) -> list[Obstacle]:
    obs = []
    for i in range(n):
        shape = ("box", "sphere", "cylinder")[i % 3]
        p = rng.uniform([-0.8, -0.8, -0.1], [0.8, 0.8, 1.1])
        obs.append(Obstacle(f"o{i}", shape, p, Rotation.random(random_state=rng).as_quat(),
                            rng.uniform(0.03, 0.3, 3)))
    return obs


@pytest.mark.parametrize("cutoff", [math.inf, 0.3])
def test_broad_phase_equals_brute_force(robot: RobotModel, cutoff: float) -> None:
    rng = np.random.default_rng(5)
    arm = ArmClearance(robot, margin_m=0.02, cutoff_m=cutoff)
    for trial in range(12):
        arm.set_obstacles(_random_obstacles(rng, int(rng.integers(1, 25))))
        q = rng.uniform(robot.limits.lower, robot.limits.upper)
        fast, brute = arm.check(q), arm.check_brute(q)
        np.testing.assert_allclose(fast.per_link, brute.per_link, atol=1e-9, err_msg=f"trial {trial}")
        assert fast.link_names == brute.link_names
        if math.isfinite(brute.min_distance_m):
            assert fast.min_distance_m == pytest.approx(brute.min_distance_m, abs=1e-9)
            assert fast.link == brute.link
            if fast.obstacle_id != brute.obstacle_id:  # two obstacles at the same distance
                assert fast.min_distance_m == pytest.approx(brute.min_distance_m, abs=1e-12)
        else:
            assert fast.min_distance_m == math.inf and fast.link == "" and fast.obstacle_id == ""
        assert fast.pairs_evaluated <= brute.pairs_evaluated
        finite = np.isfinite(fast.per_link)
        assert np.all(fast.per_link[finite] <= cutoff)


@pytest.mark.parametrize("cutoff", [math.inf, 0.3])
def test_the_smallest_distance_alone_equals_the_per_link_check(robot: RobotModel, cutoff: float) -> None:
    rng = np.random.default_rng(11)
    arm = ArmClearance(robot, margin_m=0.02, cutoff_m=cutoff)
    fewer = 0
    for trial in range(20):
        arm.set_obstacles(_random_obstacles(rng, int(rng.integers(1, 25))))
        q = rng.uniform(robot.limits.lower, robot.limits.upper)
        full, alone = arm.check(q), arm.check(q, per_link=False)
        assert alone.min_distance_m == full.min_distance_m, f"trial {trial}"
        assert (alone.link, alone.obstacle_id) == (full.link, full.obstacle_id), f"trial {trial}"
        np.testing.assert_array_equal(alone.witness_arm, full.witness_arm)
        np.testing.assert_array_equal(alone.witness_obstacle, full.witness_obstacle)
        assert alone.pairs_evaluated <= full.pairs_evaluated
        fewer += alone.pairs_evaluated < full.pairs_evaluated
        if full.link:
            closest = full.link_names.index(full.link)
            assert alone.per_link[closest] == full.per_link[closest]
            others = np.delete(alone.per_link, closest)
            assert np.isnan(others).all()
    assert fewer >= 5  # the global bound prunes pairs the per-link one must evaluate


def test_penetration_is_not_positive_and_the_margin_subtracts(robot: RobotModel) -> None:
    q = robot.named_poses["ready"]
    plain = ArmClearance(robot, margin_m=0.0, cutoff_m=math.inf)
    V = hull_vertices_world(plain, robot, q, "panda_link4")
    inside = sphere("in", V.mean(axis=0), 0.03)
    plain.set_obstacles([inside])
    pen = plain.check(q)
    assert pen.min_distance_m <= 0.0 and pen.link == "panda_link4"
    with_margin = ArmClearance(robot, margin_m=0.05, cutoff_m=math.inf)
    with_margin.set_obstacles([inside])
    assert with_margin.check(q).min_distance_m == pytest.approx(pen.min_distance_m - 0.05, abs=1e-9)
    box = validate_obstacle("b", "box", (0.6, 0.0, 0.3), size=(0.1, 0.1, 0.1))
    plain.set_obstacles([box])
    with_margin.set_obstacles([box])
    expected = plain.check(q).min_distance_m - 0.05
    assert with_margin.check(q).min_distance_m == pytest.approx(expected, abs=1e-9)


def test_cutoff_reports_inf_honestly_and_moving_obstacles_are_placed(robot: RobotModel) -> None:
    q = robot.named_poses["ready"]
    arm = ArmClearance(robot, margin_m=0.0, cutoff_m=0.2)
    arm.set_obstacles([sphere("far", (3.0, 0.0, 0.5), 0.1)])
    res = arm.check(q)
    assert res.min_distance_m == math.inf and res.link == "" and res.obstacle_id == ""
    assert np.all(np.isinf(res.per_link)) and res.pairs_evaluated == 0
    assert np.isnan(res.witness_arm).all()
    mover = validate_obstacle("m", "sphere", (3.0, 0.0, 0.5), size=(0.2, 0, 0), velocity=(-1.0, 0.0, 0.0))
    arm.set_obstacles([mover], t_s=2.5)  # predicted at x = 0.5
    assert math.isfinite(arm.check(q).min_distance_m)
    arm.set_obstacles([])
    assert arm.check(q).min_distance_m == math.inf
    with pytest.raises(ValueError):
        ArmClearance(robot, margin_m=-1.0)
    with pytest.raises(ValueError):
        ArmClearance(robot, cutoff_m=0.0)


def test_bvh_meshes_are_never_closer_than_their_hulls(robot: RobotModel) -> None:
    rng = np.random.default_rng(9)
    hull = ArmClearance(robot, cutoff_m=math.inf)
    mesh = ArmClearance(robot, cutoff_m=math.inf, convex=False)
    obs = _random_obstacles(rng, 6)
    hull.set_obstacles(obs)
    mesh.set_obstacles(obs)
    q = robot.named_poses["ready"]
    h, m = hull.check(q), mesh.check(q)
    outside = h.per_link > 1e-3
    assert np.all(m.per_link[outside] >= h.per_link[outside] - 1e-6)


def test_speed_bound_covers_every_hull_vertex(arm: ArmClearance, robot: RobotModel) -> None:
    rng = np.random.default_rng(4)
    links = set(arm.link_names)
    for _ in range(5):
        q = rng.uniform(robot.limits.lower, robot.limits.upper)
        dq = rng.uniform(-1.0, 1.0, robot.n)
        h = 1e-6
        fastest = 0.0
        for link in links:
            a = hull_vertices_world(arm, robot, q, link)
            b = hull_vertices_world(arm, robot, q + h * dq, link)
            fastest = max(fastest, float(np.max(np.linalg.norm(b - a, axis=1))) / h)
        bound = arm.speed_bound(q, dq)
        assert fastest <= bound + 1e-4
        assert bound < 3.0 * fastest + 0.5  # a bound, but not a useless one
    assert arm.speed_bound(robot.named_poses["ready"], np.zeros(robot.n)) == 0.0
