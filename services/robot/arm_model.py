"""The arm's 3-D model for Foxglove: the URDF's link geometry as one ``SceneUpdate``.

The arm publishes it once, latched, on ``<prefix>/viz/arm``
(:attr:`~services.bus.messages.Keys.arm_model`); the link frames it refers to are the child
frames of the arm's ``FrameTransforms`` (:func:`~services.robot.protocol.frame_transforms`), so the
3-D panel moves each link with its transform.

* :func:`link_geometries` — the geometry objects of the robot's (reduced) geometry model, each
  attached to the BODY frame of its link, with its pose in that frame;
* :func:`decimate` — vertex-clustering simplification of a triangle mesh (numpy only);
* :func:`glb_bytes` / :func:`glb_mesh` — one mesh as binary glTF 2.0 (``model/gltf-binary``) and
  back;
* :func:`arm_model_scene` — the ``SceneUpdate``: one entity ``arm/<link>`` per link
  (``frame_locked``, ``frame_id`` = the link's frame), a ``ModelPrimitive`` with embedded binary
  glTF per mesh at the geometry's pose in the link frame, cubes / spheres / cylinders for the
  URDF's primitive shapes; every mesh is decimated with one common cell size, the smallest that
  keeps the glTF data within ``max_bytes``.

Why glTF and not STL: glTF is indexed (12 bytes per vertex and 6 per triangle against 50 per
triangle in STL, so 4x the triangles in one budget) and its up axis is fixed by its spec (y-up,
which Foxglove turns z-up), where an STL is read y-up or z-up by a setting of the 3-D panel
("Mesh up axis"). The Panda's visual meshes of ``example-robot-data`` (Collada, 10 MB of XML)
have 135k triangles; measured sizes in docs/foxglove.md. Everything here runs once, at the arm's
start.

Example::

    robot = RobotModel.load()
    model = arm_model_scene(robot, stamp_ns=0, kind="visual", max_bytes=1_500_000)
    model.message.ByteSize()       # the glTF data (<= 1.5 MB) + about 200 bytes per link
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import pinocchio as pin
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from numpy.typing import NDArray

from services.bus.messages import SceneUpdate
from services.robot.model import RobotModel
from services.robot.rotations import quat_xyzw_from_matrix

__all__ = [
    "GLB_MEDIA_TYPE",
    "ArmModel",
    "LinkGeometry",
    "arm_model_scene",
    "decimate",
    "glb_bytes",
    "glb_mesh",
    "link_geometries",
]

#: Media type of the embedded meshes (binary glTF 2.0).
GLB_MEDIA_TYPE = "model/gltf-binary"

_GLB_MAGIC = 0x46546C67  # "glTF"
_CHUNK_JSON = 0x4E4F534A  # "JSON"
_CHUNK_BIN = 0x004E4942  # "BIN\0"

#: Cell sizes tried by the decimation [m]: none, then 0.5 mm growing by 25 % per step (to 0.4 m).
_CELLS_M = (0.0, *(0.0005 * 1.25**k for k in range(31)))

GeometryKind = Literal["mesh", "box", "sphere", "cylinder", "capsule"]


@dataclass(frozen=True)
class LinkGeometry:
    """One geometry object of the robot, in the frame of the link that carries it.

    ``vertices`` ``(V, 3)`` [m] and ``triangles`` ``(T, 3)`` (vertex indices, counter-clockwise
    seen from outside) for a mesh, empty otherwise; ``size`` ``(3,)`` [m] for a primitive: the
    full edge lengths of a box, the diameter thrice for a sphere, (diameter, diameter, length)
    for a cylinder or capsule (axis along z; a capsule's length is that of its cylinder part).
    """

    link: str  #: the link's frame name (a child frame of the arm's FrameTransforms)
    name: str  #: the geometry object's name in the URDF model
    kind: GeometryKind
    pose: pin.SE3  #: the geometry's placement in the link frame
    rgba: tuple[float, float, float, float]
    vertices: NDArray[np.float64]
    triangles: NDArray[np.int64]
    size: NDArray[np.float64]


def _link_frame(model: pin.Model, geom: pin.GeometryObject) -> int:
    """The BODY frame a geometry object belongs to: its ``parentFrame`` when that is a BODY
    frame on the same joint, else the first BODY frame of its joint."""
    fid = int(geom.parentFrame)
    if 0 <= fid < len(model.frames):
        f = model.frames[fid]
        if f.type == pin.FrameType.BODY and f.parentJoint == geom.parentJoint:
            return fid
    for i, f in enumerate(model.frames):
        if f.type == pin.FrameType.BODY and f.parentJoint == geom.parentJoint:
            return i
    raise ValueError(f"geometry {geom.name!r}: no link frame on joint {geom.parentJoint}")


def link_geometries(robot: RobotModel, geometry: pin.GeometryModel) -> tuple[list[LinkGeometry], list[str]]:
    """The objects of ``geometry`` (built for ``robot.model``, e.g. by
    :meth:`RobotModel.visual_geometry`) as :class:`LinkGeometry`, and the names of those of a
    kind this module does not convert (convex hulls, planes, ...)."""
    model = robot.model
    out: list[LinkGeometry] = []
    skipped: list[str] = []
    for go in geometry.geometryObjects:
        fid = _link_frame(model, go)
        frame = model.frames[fid]
        # Both placements are relative to the parent joint.
        pose = frame.placement.actInv(go.placement)
        shape = go.geometry
        rgba = tuple(float(c) for c in go.meshColor)
        none_v, none_t = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
        kind: GeometryKind
        size = np.zeros(3)
        vertices, triangles = none_v, none_t
        if hasattr(shape, "num_tris") and hasattr(shape, "tri_indices"):
            kind = "mesh"
            vertices = np.array(shape.vertices(), dtype=float).reshape(-1, 3)
            triangles = np.array(
                [(t[0], t[1], t[2]) for t in map(shape.tri_indices, range(shape.num_tris))],
                dtype=np.int64,
            ).reshape(-1, 3)
        elif type(shape).__name__ == "Box":
            kind, size = "box", 2.0 * np.array(shape.halfSide, dtype=float)
        elif type(shape).__name__ == "Sphere":
            kind, size = "sphere", np.full(3, 2.0 * float(shape.radius))
        elif type(shape).__name__ in ("Cylinder", "Capsule"):
            kind = "cylinder" if type(shape).__name__ == "Cylinder" else "capsule"
            d = 2.0 * float(shape.radius)
            size = np.array([d, d, 2.0 * float(shape.halfLength)])
        else:
            skipped.append(go.name)
            continue
        out.append(LinkGeometry(frame.name, go.name, kind, pose, rgba, vertices, triangles, size))  # type: ignore[arg-type]
    return out, skipped


def decimate(
    vertices: NDArray[np.float64], triangles: NDArray[np.int64], cell_m: float
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Vertex-clustering simplification: the vertices in one cube of edge ``cell_m`` [m] of a
    grid become one, at their mean; triangles left with fewer than three distinct corners and
    repeated triangles are removed; the others keep their winding. ``cell_m <= 0`` returns the
    mesh unchanged. ``vertices`` ``(V, 3)`` [m], ``triangles`` ``(T, 3)``; returns the new
    ``(V', 3)`` and ``(T', 3)`` with every vertex used."""
    if cell_m <= 0.0 or len(triangles) == 0:
        return vertices, triangles
    _, cluster = _unique_rows(np.floor(vertices / cell_m))
    tri = cluster[triangles]
    keep = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
    tri = tri[keep]
    # One triangle per set of corners, whatever its winding (the first one met).
    first, _ = _unique_rows(np.sort(tri, axis=1))
    tri = tri[np.sort(first)]
    used, tri_new = np.unique(tri, return_inverse=True)
    counts = np.bincount(cluster, minlength=int(cluster.max()) + 1).astype(float)
    means = np.stack(
        [np.bincount(cluster, weights=vertices[:, i], minlength=counts.size) for i in range(3)], axis=1
    ) / np.maximum(counts, 1.0)[:, None]
    return means[used], tri_new.reshape(-1, 3).astype(np.int64)


def _unique_rows(rows: NDArray[Any]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """For integer triples ``(N, 3)``: the index of the first of each distinct row (in the
    rows' sorted order) and each row's number among the distinct ones ``(N,)``. Rows within
    ±2**20 are packed into one int64 each first (``np.unique`` on them is ~10x faster than on
    rows)."""
    r = rows.astype(np.int64)
    if r.size and -(1 << 20) <= r.min() and r.max() < 1 << 20:
        c = r + (1 << 20)
        keys = (c[:, 0] << 42) | (c[:, 1] << 21) | c[:, 2]
        _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    else:
        _, first, inverse = np.unique(r, axis=0, return_index=True, return_inverse=True)
    return first, inverse.reshape(-1)


def glb_bytes(
    vertices: NDArray[np.float64],
    triangles: NDArray[np.int64],
    rgba: tuple[float, float, float, float] = (0.9, 0.9, 0.9, 1.0),
) -> bytes:
    """A binary glTF 2.0 (``model/gltf-binary``) of one triangle mesh: ``vertices`` ``(V, 3)``
    [m] in the robot's z-up frame, ``triangles`` ``(T, 3)`` (indices into ``vertices``),
    one material of base colour ``rgba`` (non-metallic, rough).

    glTF is y-up (its spec); a viewer turns it z-up (Foxglove rotates every glTF scene by +90°
    about x), so the positions are stored as ``(x, z, -y)``. Positions are float32, indices
    uint16 when V < 65536 (else uint32); no normals: the viewer shades the facets flat.
    Size: 12·V + 6·T (or 12·T) bytes plus about 700 bytes of header and JSON.
    """
    pos = np.empty((len(vertices), 3), dtype="<f4")
    pos[:, 0], pos[:, 1], pos[:, 2] = vertices[:, 0], vertices[:, 2], -vertices[:, 1]
    small = len(vertices) < 65536
    idx = triangles.astype("<u2" if small else "<u4").reshape(-1)
    pos_b, idx_b = pos.tobytes(), idx.tobytes()
    idx_b += b"\0" * (-len(idx_b) % 4)
    lo = pos.min(axis=0).tolist() if len(pos) else [0.0] * 3
    hi = pos.max(axis=0).tolist() if len(pos) else [0.0] * 3
    doc = {
        "asset": {"version": "2.0", "generator": "psm-dataflow services.robot.arm_model"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0, "mode": 4}]}],
        "materials": [{
            "pbrMetallicRoughness": {
                "baseColorFactor": [float(c) for c in rgba], "metallicFactor": 0.0, "roughnessFactor": 1.0
            },
            "doubleSided": True,
        }],
        "buffers": [{"byteLength": len(pos_b) + len(idx_b)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(pos_b), "target": 34962},
            {"buffer": 0, "byteOffset": len(pos_b), "byteLength": idx.nbytes, "target": 34963},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(pos), "type": "VEC3", "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5123 if small else 5125, "count": idx.size, "type": "SCALAR"},
        ],
    }
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    body = pos_b + idx_b
    total = 12 + 8 + len(js) + 8 + len(body)
    return b"".join((
        struct.pack("<III", _GLB_MAGIC, 2, total),
        struct.pack("<II", len(js), _CHUNK_JSON), js,
        struct.pack("<II", len(body), _CHUNK_BIN), body,
    ))


def glb_mesh(data: bytes) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The mesh of a :func:`glb_bytes` file back: vertices ``(V, 3)`` [m] in the z-up frame and
    triangles ``(T, 3)``; ``ValueError`` when the bytes are not such a file."""
    if len(data) < 20:
        raise ValueError(f"{len(data)} bytes: not a binary glTF")
    magic, version, total = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC or version != 2 or total != len(data):
        raise ValueError("not a binary glTF 2.0 file of this length")
    jlen, jtype = struct.unpack_from("<II", data, 12)
    doc = json.loads(data[20 : 20 + jlen])
    blen, btype = struct.unpack_from("<II", data, 20 + jlen)
    if jtype != _CHUNK_JSON or btype != _CHUNK_BIN:
        raise ValueError("binary glTF chunks are not JSON then BIN")
    body = data[28 + jlen : 28 + jlen + blen]
    prim = doc["meshes"][0]["primitives"][0]

    def array(accessor: int, dtype: str, width: int) -> NDArray[Any]:
        acc = doc["accessors"][accessor]
        view = doc["bufferViews"][acc["bufferView"]]
        n = acc["count"] * width
        return np.frombuffer(body, dtype=dtype, count=n, offset=view["byteOffset"])

    pos = array(prim["attributes"]["POSITION"], "<f4", 3).reshape(-1, 3).astype(float)
    idx_type = {5123: "<u2", 5125: "<u4"}[doc["accessors"][prim["indices"]]["componentType"]]
    tri = array(prim["indices"], idx_type, 1).astype(np.int64).reshape(-1, 3)
    return np.stack([pos[:, 0], -pos[:, 2], pos[:, 1]], axis=1), tri


@dataclass(frozen=True)
class ArmModel:
    """The arm model's ``SceneUpdate`` and how it was made."""

    message: SceneUpdate
    cell_m: float  #: the decimation cell [m] (0 = the meshes as loaded, welded)
    triangles_in: int  #: triangles of the meshes as loaded
    triangles_out: int  #: triangles sent
    mesh_bytes: int  #: bytes of glTF data in the message
    skipped: tuple[str, ...]  #: geometry objects of kinds not converted


_Mesh = tuple[NDArray[np.float64], NDArray[np.int64]]

#: Vertices closer than this are one (the Collada meshes repeat a position per facet normal) [m].
_WELD_M = 1e-6


def _weld(vertices: NDArray[np.float64], triangles: NDArray[np.int64]) -> _Mesh:
    """The mesh with repeated vertex positions (to :data:`_WELD_M`) merged, triangles kept."""
    first, inverse = _unique_rows(np.round(vertices / _WELD_M))
    return vertices[first], inverse[triangles]


def _fit(geoms: Sequence[LinkGeometry], max_bytes: int) -> tuple[float, list[_Mesh], list[bytes]]:
    """The smallest cell of :data:`_CELLS_M` whose decimated meshes fit ``max_bytes`` as glTF
    (bisection: the size falls as the cell grows), those meshes and their glTF bytes."""
    welded = [_weld(g.vertices, g.triangles) for g in geoms]

    def build(k: int) -> tuple[list[_Mesh], list[bytes], int]:
        ms = [decimate(v, t, _CELLS_M[k]) for v, t in welded]
        data = [glb_bytes(v, t, g.rgba) for (v, t), g in zip(ms, geoms, strict=True)]
        return ms, data, sum(len(d) for d in data)

    lo, hi = 0, len(_CELLS_M) - 1
    best_m, best_d, size = build(hi)
    if size > max_bytes:
        raise ValueError(
            f"the arm's meshes need {size} bytes at a {_CELLS_M[hi]:.3f} m cell: more than "
            f"max_bytes={max_bytes}"
        )
    while lo < hi:
        mid = (lo + hi) // 2
        ms, data, size = build(mid)
        if size <= max_bytes:
            hi, best_m, best_d = mid, ms, data
        else:
            lo = mid + 1
    return _CELLS_M[hi], best_m, best_d


def _pose(prim: object, M: pin.SE3) -> None:
    pose = prim.pose  # type: ignore[attr-defined]
    p = M.translation
    pose.position.x, pose.position.y, pose.position.z = float(p[0]), float(p[1]), float(p[2])
    x, y, z, w = quat_xyzw_from_matrix(M.rotation).tolist()
    q = pose.orientation
    q.x, q.y, q.z, q.w = x, y, z, w


def _colour(prim: object, rgba: tuple[float, float, float, float]) -> None:
    c = prim.color  # type: ignore[attr-defined]
    c.r, c.g, c.b, c.a = rgba


def _add_primitive(entity: SceneEntity, g: LinkGeometry) -> None:
    """A box, sphere, cylinder or capsule (a cylinder and a sphere at each end) of ``g``."""
    if g.kind == "box":
        prim = entity.cubes.add()
    elif g.kind == "sphere":
        prim = entity.spheres.add()
    else:
        prim = entity.cylinders.add()
        prim.bottom_scale = prim.top_scale = 1.0
    _pose(prim, g.pose)
    prim.size.x, prim.size.y, prim.size.z = (float(c) for c in g.size)
    _colour(prim, g.rgba)
    if g.kind == "capsule":
        d, half = float(g.size[0]), 0.5 * float(g.size[2])
        for end in (-half, half):
            cap = entity.spheres.add()
            _pose(cap, g.pose * pin.SE3(np.eye(3), np.array([0.0, 0.0, end])))
            cap.size.x = cap.size.y = cap.size.z = d
            _colour(cap, g.rgba)


def arm_model_scene(
    robot: RobotModel,
    stamp_ns: int,
    kind: Literal["visual", "collision"] = "visual",
    max_bytes: int = 1_500_000,
    geometry: pin.GeometryModel | None = None,
) -> ArmModel:
    """The arm's ``SceneUpdate``: entity ``arm/<link>`` per link that carries geometry, in that
    link's frame (``frame_locked``: it moves with the link's transform), stamped ``stamp_ns``
    [ns].

    Args:
        robot: the loaded robot.
        stamp_ns: the entities' timestamp [ns] (the arm's clock at its start).
        kind: the URDF's ``visual`` or ``collision`` geometry.
        max_bytes: budget of the embedded glTF data [bytes]; the meshes are decimated with
            the smallest common cell that fits (none if they fit as loaded).
        geometry: the geometry model to convert (default: ``robot``'s of ``kind``).

    Raises:
        ValueError: the meshes do not fit ``max_bytes`` even at the coarsest cell (0.4 m).
    """
    if geometry is None:
        geometry = robot.visual_geometry() if kind == "visual" else robot.collision_geometry()
    geoms, skipped = link_geometries(robot, geometry)
    meshes = [g for g in geoms if g.kind == "mesh"]
    cell, decimated, data = _fit(meshes, max_bytes)
    mesh_of = {id(g): (t, d) for g, (_, t), d in zip(meshes, decimated, data, strict=True)}
    msg = SceneUpdate()
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    entities: dict[str, SceneEntity] = {}
    mesh_bytes = triangles_out = 0
    for g in geoms:
        e = entities.get(g.link)
        if e is None:
            e = entities[g.link] = msg.entities.add()
            e.timestamp.seconds, e.timestamp.nanos = sec, nsec
            e.frame_id = g.link
            e.id = f"arm/{g.link}"
            e.frame_locked = True
            md = e.metadata.add()
            md.key, md.value = "link", g.link
        if g.kind != "mesh":
            _add_primitive(e, g)
            continue
        t, d = mesh_of[id(g)]
        m = e.models.add()
        _pose(m, g.pose)
        m.scale.x = m.scale.y = m.scale.z = 1.0  # the vertices are in metres, meshScale applied
        _colour(m, g.rgba)  # also the glTF's material: shown as embedded (override_color false)
        m.media_type = GLB_MEDIA_TYPE
        m.data = d
        mesh_bytes += len(d)
        triangles_out += len(t)
    return ArmModel(
        message=msg,
        cell_m=cell,
        triangles_in=sum(len(g.triangles) for g in meshes),
        triangles_out=triangles_out,
        mesh_bytes=mesh_bytes,
        skipped=tuple(skipped),
    )
