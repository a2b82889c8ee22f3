"""The planner's task in Foxglove's 3-D panel: a ``SceneUpdate`` on ``<prefix>/viz/plan``.

:class:`PlanScene` keeps one ``SceneUpdate`` and changes it in place at the planner's status
rate (never on the control path), with four entities in the task's frame:

* ``plan/goal`` — the goal in use (offset included): a sphere and its name; no primitive while
  the step has no goal (held, lost);
* ``plan/segment`` — the straight segment from the end effector to that goal: the segment the
  obstacle monitor tests for collisions (the paper's test);
* ``plan/path`` — the end effector's path so far: a line strip of the positions seen at the
  status rate, a point added once the end effector moved ``min_step_m`` from the last one; at
  ``max_points`` every other point is dropped, so the whole path stays from its start, the older
  parts thinned the more the longer the run (bounded size, O(1) amortised work per update);
* ``plan/static_goals`` — the task's fixed positions (spoon, bowl, neutral, ...), spheres with
  their names, built once.

Example::

    scene = PlanScene("base", {"bowl": (0.5, -0.2, 0.1)}, max_points=400, min_step_m=0.002)
    msg = scene.update(stamp_ns, ee_position, goal_position, "bowl")   # the same message object
    publisher.put(msg)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from numpy.typing import ArrayLike, NDArray

from services.bus.messages import SceneUpdate

__all__ = ["GOAL_RGBA", "PATH_RGBA", "SEGMENT_RGBA", "STATIC_GOAL_RGBA", "PlanScene"]

#: Colours (r, g, b, a) of the goal in use, the segment, the path and the static goals.
GOAL_RGBA = (0.1, 0.75, 0.3, 0.9)
SEGMENT_RGBA = (1.0, 0.6, 0.1, 1.0)
PATH_RGBA = (0.2, 0.45, 0.95, 1.0)
STATIC_GOAL_RGBA = (0.6, 0.6, 0.6, 0.5)

GOAL_DIAMETER_M = 0.04
STATIC_GOAL_DIAMETER_M = 0.025
SEGMENT_THICKNESS_M = 0.004
PATH_THICKNESS_M = 0.003
LABEL_SIZE_M = 0.03


def _colour(target: object, rgba: tuple[float, float, float, float]) -> None:
    c = target.color  # type: ignore[attr-defined]
    c.r, c.g, c.b, c.a = rgba


def _identity(prim: object) -> None:
    prim.pose.orientation.w = 1.0  # type: ignore[attr-defined]


def _line(entity: SceneEntity, thickness_m: float, rgba: tuple[float, float, float, float]) -> LinePrimitive:
    line = entity.lines.add()
    line.type = LinePrimitive.LINE_STRIP
    line.thickness = thickness_m
    _identity(line)
    _colour(line, rgba)
    return line


class PlanScene:
    """The ``SceneUpdate`` of the planner's task, changed in place by :meth:`update`.

    Args:
        frame_id: the task's frame (the arm's base frame).
        static_goals: the task's fixed positions by name, ``(3,)`` each [m].
        max_points: most points of the path line strip (>= 2).
        min_step_m: the path gets a point once the end effector moved this far from the last
            one [m] (0: every update).
    """

    def __init__(
        self,
        frame_id: str,
        static_goals: Mapping[str, ArrayLike],
        max_points: int,
        min_step_m: float,
    ) -> None:
        if max_points < 2:
            raise ValueError("max_points must be at least 2")
        self.max_points = int(max_points)
        self.min_step_m = float(min_step_m)
        self._path = np.zeros((self.max_points, 3))  # the path's points [m], the first n used
        self.n_points = 0
        self.msg = SceneUpdate()
        self._goal, self._segment, self._path_e, self._static = (
            self._entity(frame_id, name)
            for name in ("plan/goal", "plan/segment", "plan/path", "plan/static_goals")
        )
        self._path_line = _line(self._path_e, PATH_THICKNESS_M, PATH_RGBA)
        for name, p in static_goals.items():
            x, y, z = (float(c) for c in np.asarray(p, dtype=float))
            s = self._static.spheres.add()
            s.pose.position.x, s.pose.position.y, s.pose.position.z = x, y, z
            s.pose.orientation.w = 1.0
            s.size.x = s.size.y = s.size.z = STATIC_GOAL_DIAMETER_M
            _colour(s, STATIC_GOAL_RGBA)
            t = self._static.texts.add()
            t.pose.position.x, t.pose.position.y, t.pose.position.z = x, y, z + STATIC_GOAL_DIAMETER_M
            t.pose.orientation.w = 1.0
            t.billboard, t.font_size, t.text = True, LABEL_SIZE_M, name
            _colour(t, (*STATIC_GOAL_RGBA[:3], 1.0))

    def _entity(self, frame_id: str, entity_id: str) -> SceneEntity:
        e = self.msg.entities.add()
        e.frame_id, e.id = frame_id, entity_id
        return e

    @property
    def path(self) -> NDArray[np.float64]:
        """The path's points ``(n, 3)`` [m] (a view)."""
        return self._path[: self.n_points]

    def _add_point(self, x: float, y: float, z: float) -> None:
        """Append ``(x, y, z)`` to the path if it moved ``min_step_m`` from the last point;
        halve the path first when it is full."""
        n = self.n_points
        if n:
            last = self._path[n - 1]
            dx, dy, dz = x - last[0], y - last[1], z - last[2]
            if dx * dx + dy * dy + dz * dz < self.min_step_m * self.min_step_m:
                return
        pts = self._path_line.points
        if n == self.max_points:
            # Every other point from the first: the whole path at half the resolution (the
            # newest point follows at once).
            keep = self._path[0:n:2].copy()
            n = len(keep)
            self._path[:n] = keep
            del pts[:]
            for px, py, pz in keep.tolist():
                q = pts.add()
                q.x, q.y, q.z = px, py, pz
        self._path[n] = x, y, z
        self.n_points = n + 1
        q = pts.add()
        q.x, q.y, q.z = x, y, z

    def update(
        self,
        stamp_ns: int,
        ee_position: Sequence[float],
        goal: Sequence[float] | None,
        goal_name: str,
    ) -> SceneUpdate:
        """The scene at ``stamp_ns`` [ns] (the stack's clock): the end effector at
        ``ee_position`` ``(3,)`` [m], heading to ``goal`` ``(3,)`` [m] named ``goal_name`` (None:
        no goal in use). Returns the kept message, changed in place: publish it before the next
        call."""
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        for e in self.msg.entities:
            e.timestamp.seconds, e.timestamp.nanos = sec, nsec
        x, y, z = (float(c) for c in ee_position)
        self._add_point(x, y, z)
        g = self._goal
        if goal is None:
            del g.spheres[:]
            del g.texts[:]
            del self._segment.lines[:]
            return self.msg
        gx, gy, gz = (float(c) for c in goal)
        if not g.spheres:
            s = g.spheres.add()
            s.pose.orientation.w = 1.0
            s.size.x = s.size.y = s.size.z = GOAL_DIAMETER_M
            _colour(s, GOAL_RGBA)
            t = g.texts.add()
            t.pose.orientation.w = 1.0
            t.billboard, t.font_size = True, LABEL_SIZE_M
            _colour(t, (*GOAL_RGBA[:3], 1.0))
            line = _line(self._segment, SEGMENT_THICKNESS_M, SEGMENT_RGBA)
            line.points.add()
            line.points.add()
        s, t = g.spheres[0], g.texts[0]
        s.pose.position.x, s.pose.position.y, s.pose.position.z = gx, gy, gz
        t.pose.position.x, t.pose.position.y, t.pose.position.z = gx, gy, gz + GOAL_DIAMETER_M
        t.text = goal_name
        a, b = self._segment.lines[0].points
        a.x, a.y, a.z = x, y, z
        b.x, b.y, b.z = gx, gy, gz
        return self.msg
