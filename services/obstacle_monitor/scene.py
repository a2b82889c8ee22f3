"""Obstacles between the bus messages and :mod:`psm.obstacles`, and their Foxglove 3-D scene.

* :func:`obstacle_from_message` — an :class:`~services.bus.messages.Obstacle` message as a
  validated :class:`psm.obstacles.Obstacle` (raises :class:`~psm.obstacles.ObstacleError` with a
  stable ``reason``); an unset orientation is the identity;
* :func:`obstacle_message` / :func:`obstacle_set_message` — the other way (``<prefix>/obstacles``);
* :func:`scene_update` — a foxglove ``SceneUpdate`` (``<prefix>/viz/scene``) with one entity per
  obstacle: the obstacle itself (opaque) and its inflated safety volume (translucent), so a
  recording shows both in the 3-D panel.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion

from psm.obstacles import REASON_SHAPE, Obstacle, ObstacleError
from services.bus.messages import Obstacle as ObstacleMsg
from services.bus.messages import ObstacleSet, SceneUpdate

__all__ = ["obstacle_from_message", "obstacle_message", "obstacle_set_message", "scene_update", "shape_enum"]

_SHAPE_OF = {ObstacleMsg.BOX: "box", ObstacleMsg.SPHERE: "sphere", ObstacleMsg.CYLINDER: "cylinder"}
_ENUM_OF = {v: k for k, v in _SHAPE_OF.items()}

#: Colours (r, g, b, a) of the obstacles and of their inflated safety volumes.
OBSTACLE_RGBA = (0.85, 0.35, 0.2, 1.0)
INFLATED_RGBA = (0.85, 0.35, 0.2, 0.25)


def shape_enum(shape: str) -> int:
    """The ``Obstacle.Shape`` value of a shape name."""
    return _ENUM_OF[shape]


def obstacle_from_message(msg: ObstacleMsg) -> Obstacle:
    """The validated obstacle of a message (raises :class:`ObstacleError`)."""
    shape = _SHAPE_OF.get(msg.shape)
    if shape is None:
        raise ObstacleError(REASON_SHAPE, "shape", f"unknown shape {int(msg.shape)}")
    p, s, v = msg.position, msg.size, msg.velocity
    if msg.HasField("orientation"):
        o = msg.orientation
        quat = np.array([o.x, o.y, o.z, o.w])
    else:
        quat = np.array([0.0, 0.0, 0.0, 1.0])
    return Obstacle(
        msg.id, shape, np.array([p.x, p.y, p.z]), quat, np.array([s.x, s.y, s.z]), np.array([v.x, v.y, v.z])
    )


def obstacle_message(ob: Obstacle, out: ObstacleMsg | None = None) -> ObstacleMsg:
    """``ob`` as a bus message (filled into ``out`` if given)."""
    m = ObstacleMsg() if out is None else out
    m.id = ob.id
    m.shape = _ENUM_OF[ob.shape]
    m.position.x, m.position.y, m.position.z = (float(c) for c in ob.position)
    m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w = (float(c) for c in ob.orientation)
    m.size.x, m.size.y, m.size.z = (float(c) for c in ob.size)
    m.velocity.x, m.velocity.y, m.velocity.z = (float(c) for c in ob.velocity)
    return m


def obstacle_set_message(
    obstacles: Iterable[Obstacle], stamp_ns: int, seq: int, frame_id: str
) -> ObstacleSet:
    """The latched ``ObstacleSet`` of the current obstacles."""
    msg = ObstacleSet(stamp_ns=stamp_ns, seq=seq, frame_id=frame_id)
    for ob in obstacles:
        obstacle_message(ob, msg.obstacles.add())
    return msg


def _pose(prim: object, ob: Obstacle) -> None:
    pose = prim.pose  # type: ignore[attr-defined]
    pose.position.x, pose.position.y, pose.position.z = (float(c) for c in ob.position)
    q = pose.orientation
    q.x, q.y, q.z, q.w = (float(c) for c in ob.orientation)


def _colour(prim: object, rgba: tuple[float, float, float, float]) -> None:
    c = prim.color  # type: ignore[attr-defined]
    c.r, c.g, c.b, c.a = rgba


def _add_primitive(
    entity: SceneEntity, ob: Obstacle, grow: float, rgba: tuple[float, float, float, float]
) -> None:
    """One primitive of ``ob`` grown by ``grow`` [m] on every side (the monitor's inflation)."""
    size = np.asarray(ob.size, dtype=float)
    if ob.shape == "box":
        prim = entity.cubes.add()
        full = size + 2.0 * grow
    elif ob.shape == "sphere":
        prim = entity.spheres.add()
        d = size[0] + 2.0 * grow
        full = np.array([d, d, d])
    else:
        prim = entity.cylinders.add()
        d = size[0] + 2.0 * grow
        full = np.array([d, d, size[2] + 2.0 * grow])
        prim.bottom_scale = prim.top_scale = 1.0
    _pose(prim, ob)
    prim.size.x, prim.size.y, prim.size.z = (float(c) for c in full)
    _colour(prim, rgba)


def scene_update(
    obstacles: Sequence[Obstacle],
    margin_m: float,
    stamp_ns: int,
    frame_id: str,
    removed: Iterable[str] = (),
) -> SceneUpdate:
    """A ``SceneUpdate``: entity ``obstacle/<id>`` per obstacle (the obstacle and, if
    ``margin_m`` > 0, its inflated volume) and a deletion per id in ``removed``."""
    msg = SceneUpdate()
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    for oid in removed:
        d = msg.deletions.add()
        d.timestamp.seconds, d.timestamp.nanos = sec, nsec
        d.type = SceneEntityDeletion.MATCHING_ID
        d.id = f"obstacle/{oid}"
    for ob in obstacles:
        e = msg.entities.add()
        e.timestamp.seconds, e.timestamp.nanos = sec, nsec
        e.frame_id = frame_id
        e.id = f"obstacle/{ob.id}"
        md = e.metadata.add()
        md.key, md.value = "shape", ob.shape
        _add_primitive(e, ob, 0.0, OBSTACLE_RGBA)
        if margin_m > 0.0:
            _add_primitive(e, ob, margin_m, INFLATED_RGBA)
    return msg
