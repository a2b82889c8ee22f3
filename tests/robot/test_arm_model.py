"""The arm's 3-D model for Foxglove (services.robot.arm_model): one entity per link in the frames
the arm's FrameTransforms move, glTF meshes that parse back to the loaded triangles, poses equal to
pinocchio's geometry placements, the size budget kept by decimation."""

from __future__ import annotations

import json
import struct

import numpy as np
import pinocchio as pin
import pytest

from services.robot.arm_model import (
    GLB_MEDIA_TYPE,
    arm_model_scene,
    decimate,
    glb_bytes,
    glb_mesh,
)
from services.robot.model import RobotModel
from services.robot.protocol import frame_transforms
from services.robot.rotations import matrix_from_quat_xyzw


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.load()


@pytest.fixture(scope="module")
def visual(robot: RobotModel) -> pin.GeometryModel:
    return robot.visual_geometry()


def _se3(pose: object) -> pin.SE3:
    p, o = pose.position, pose.orientation  # type: ignore[attr-defined]
    return pin.SE3(matrix_from_quat_xyzw(np.array([o.x, o.y, o.z, o.w])), np.array([p.x, p.y, p.z]))


def test_one_entity_per_link_in_the_frames_the_transforms_move(
    robot: RobotModel, visual: pin.GeometryModel
) -> None:
    model = arm_model_scene(robot, 1_500_000_000, "visual", 1_500_000, geometry=visual)
    links = [e.frame_id for e in model.message.entities]
    expected = ["panda_link0", *(f"panda_link{i}" for i in range(1, 8)), "panda_hand", "panda_leftfinger",
                "panda_rightfinger"]
    assert links == expected
    tf = frame_transforms(robot, robot.body_frame_ids(), 0, "base")
    assert set(links) <= {t.child_frame_id for t in tf.transforms}
    for e in model.message.entities:
        assert e.id == f"arm/{e.frame_id}" and e.frame_locked
        assert (e.timestamp.seconds, e.timestamp.nanos) == (1, 500_000_000)
        assert len(e.models) == 1 and e.models[0].media_type == GLB_MEDIA_TYPE
        assert (e.models[0].scale.x, e.models[0].scale.y, e.models[0].scale.z) == (1.0, 1.0, 1.0)
    assert not model.skipped


def test_meshes_parse_back_to_the_loaded_triangles(robot: RobotModel, visual: pin.GeometryModel) -> None:
    """Without decimation (a budget they fit) every glTF holds the triangles pinocchio loaded,
    at the loaded vertex positions (float32)."""
    model = arm_model_scene(robot, 0, "visual", 10_000_000, geometry=visual)
    assert model.cell_m == 0.0
    loaded = {go.name.rsplit("_", 1)[0]: go.geometry for go in visual.geometryObjects}
    for e in model.message.entities:
        v, t = glb_mesh(e.models[0].data)
        shape = loaded[e.frame_id]
        assert len(t) == shape.num_tris
        original = np.asarray(shape.vertices())
        tri_in = np.array([[x[0], x[1], x[2]] for x in map(shape.tri_indices, range(shape.num_tris))])
        np.testing.assert_allclose(v[t], original[tri_in], atol=1e-6)
    loaded_total = sum(g.geometry.num_tris for g in visual.geometryObjects)
    assert model.triangles_out == model.triangles_in == loaded_total


def test_poses_are_pinocchios_geometry_placements(robot: RobotModel) -> None:
    """At random joint values, link frame x primitive pose = pinocchio's placement of the
    geometry object, for the visual meshes and the collision primitives (the fingers' boxes)."""
    rng = np.random.default_rng(3)
    for kind in ("visual", "collision"):
        geometry = robot.geometry(pin.GeometryType.VISUAL if kind == "visual" else pin.GeometryType.COLLISION)
        model = arm_model_scene(robot, 0, kind, 1_500_000, geometry=geometry)  # type: ignore[arg-type]
        gdata = geometry.createData()
        poses = []
        for e in model.message.entities:
            poses += [(e.frame_id, p.pose) for p in (*e.models, *e.cubes, *e.spheres, *e.cylinders)]
        assert len(poses) == len(geometry.geometryObjects)
        for _ in range(3):
            q = rng.uniform(robot.limits.lower, robot.limits.upper)
            pin.framesForwardKinematics(robot.model, robot.data, q)
            pin.updateGeometryPlacements(robot.model, robot.data, geometry, gdata)
            # The entities list the geometry objects in their order (grouped by link, which
            # the URDF already does).
            for (link, pose), oMg in zip(poses, gdata.oMg, strict=True):
                world = robot.data.oMf[robot.model.getFrameId(link)] * _se3(pose)
                np.testing.assert_allclose(world.homogeneous, oMg.homogeneous, atol=1e-9)


def test_collision_primitives_are_boxes_of_the_urdf_size(robot: RobotModel) -> None:
    geometry = robot.collision_geometry()
    model = arm_model_scene(robot, 0, "collision", 1_500_000, geometry=geometry)
    finger = next(e for e in model.message.entities if e.frame_id == "panda_leftfinger")
    boxes = [go.geometry for go in geometry.geometryObjects if go.name.startswith("panda_leftfinger")]
    assert len(finger.cubes) == len(boxes) == 4 and not finger.models
    for cube, box in zip(finger.cubes, boxes, strict=True):
        np.testing.assert_allclose([cube.size.x, cube.size.y, cube.size.z], 2.0 * np.asarray(box.halfSide))


def test_the_budget_is_kept_by_a_coarser_cell(robot: RobotModel, visual: pin.GeometryModel) -> None:
    full = arm_model_scene(robot, 0, "visual", 10_000_000, geometry=visual)
    small = arm_model_scene(robot, 0, "visual", 600_000, geometry=visual)
    assert small.mesh_bytes <= 600_000 < full.mesh_bytes
    assert small.cell_m > 0.0 and small.triangles_out < full.triangles_out
    assert small.message.ByteSize() <= 600_000 + 300 * len(small.message.entities)
    assert sum(len(glb_mesh(e.models[0].data)[1]) for e in small.message.entities) == small.triangles_out
    with pytest.raises(ValueError, match="max_bytes"):
        arm_model_scene(robot, 0, "visual", 1_000, geometry=visual)


def _sphere(radius: float, n_lat: int, n_lon: int) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere, triangles counter-clockwise seen from outside."""
    lat = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack(np.meshgrid(lat, lon, indexing="ij"), -1).reshape(-1, 2)
    s, c = np.sin(ring[:, 0]), np.cos(ring[:, 0])
    band = radius * np.stack([s * np.cos(ring[:, 1]), s * np.sin(ring[:, 1]), c], 1)
    v = np.vstack([[0, 0, radius], band, [0, 0, -radius]])
    idx = lambda i, j: 1 + i * n_lon + (j % n_lon)  # noqa: E731
    tris = [(0, idx(0, j), idx(0, j + 1)) for j in range(n_lon)]
    for i in range(n_lat - 2):
        for j in range(n_lon):
            a, b, c, d = idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)
            tris += [(a, b, c), (a, c, d)]
    last = len(v) - 1
    tris += [(idx(n_lat - 2, j), last, idx(n_lat - 2, j + 1)) for j in range(n_lon)]
    return v, np.array(tris)


def _outward(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    c = v[t]
    n = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    return np.einsum("ij,ij->i", n, c.mean(axis=1)) > 0.0


def test_decimation_keeps_the_surface_and_the_winding() -> None:
    v, t = _sphere(0.1, 60, 120)
    assert _outward(v, t).all()
    dv, dt = decimate(v, t, 0.02)
    assert len(dt) < len(t) / 10 and len(dv) == len(np.unique(dt))  # every vertex used
    r = np.linalg.norm(dv, axis=1)
    assert np.all(np.abs(r - 0.1) < 0.02 * np.sqrt(3))
    assert _outward(dv, dt).mean() > 0.95
    assert len({tuple(sorted(x)) for x in dt.tolist()}) == len(dt)  # no triangle twice
    same_v, same_t = decimate(v, t, 0.0)
    assert same_v is v and same_t is t


def test_glb_round_trip_and_layout() -> None:
    v, t = _sphere(0.05, 10, 20)
    data = glb_bytes(v, t, (0.1, 0.2, 0.3, 1.0))
    assert data[:4] == b"glTF" and len(data) % 4 == 0
    (jlen,) = struct.unpack_from("<I", data, 12)
    pos = json.loads(data[20 : 20 + jlen])["accessors"][0]
    # glTF is y-up: a z-up point (x, y, z) is stored as (x, z, -y).
    np.testing.assert_allclose(pos["max"], [v[:, 0].max(), v[:, 2].max(), -v[:, 1].min()], rtol=1e-6)
    v2, t2 = glb_mesh(data)
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_allclose(v2, v, atol=1e-7)
    with pytest.raises(ValueError):
        glb_mesh(data[:-4])
