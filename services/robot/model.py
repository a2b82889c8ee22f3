"""Robot model: URDF loading, joint limits, forward kinematics, Jacobians and link placements
on top of Pinocchio.

Everything here is pure (no bus, no files written) and allocation-light so it can run inside a
1 kHz control loop. Conventions shared by every user of the model (the arm simulator, the teach
mode, the obstacle monitor, the planner):

* joint vectors ``q`` (rad), ``dq`` (rad/s), ``ddq`` (rad/s²) have shape ``(n,)`` where ``n`` is
  the number of actuated joints left after locking (7 for the Panda);
* Cartesian quantities are expressed in the robot base (world) frame, at the origin of the
  end-effector frame ("LOCAL_WORLD_ALIGNED" in Pinocchio's terms): positions in m, linear
  velocity m/s, linear acceleration m/s² (classical, i.e. the second time derivative of the
  position), angular velocity rad/s, angular acceleration rad/s²;
* quaternions are ``(x, y, z, w)`` with ``w >= 0`` (:mod:`services.robot.rotations`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

import numpy as np
import pinocchio as pin

#: Relative location of the Panda URDF inside the ``example-robot-data`` distribution.
_PANDA_URDF = "cmeel.prefix/share/example-robot-data/robots/panda_description/urdf/panda.urdf"

#: Number of directory levels from the Panda URDF up to the ``share`` directory that resolves its
#: ``package://example-robot-data/...`` mesh paths.
_PANDA_SHARE_UP = 5

#: End-effector frame of the default robot: the Panda hand's tool centre point.
PANDA_EE_FRAME = "panda_hand_tcp"

#: Joints of the default robot that are not controlled (the gripper fingers): locked at 0.
PANDA_LOCKED_JOINTS: tuple[str, ...] = ("panda_finger_joint1", "panda_finger_joint2")

#: Franka Emika Panda joint acceleration limits from the manufacturer's datasheet, rad/s².
PANDA_ACCEL_LIMITS: tuple[float, ...] = (15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0)

#: Named start poses of the Panda (rad). ``ready`` is the SRDF "default" state: hand pointing
#: down, 0.31 m in front of the base at 0.49 m height.
PANDA_NAMED_POSES: dict[str, tuple[float, ...]] = {
    "ready": (0.0, -0.785398, 0.0, -2.35619, 0.0, 1.5707, 0.785398),
    "home": (0.0, -0.3, 0.0, -1.8, 0.0, 1.5, 0.785398),
}


def panda_urdf_path() -> Path:
    """Path of the Franka Panda URDF shipped by the installed ``example-robot-data`` package."""
    try:
        dist = distribution("example-robot-data")
    except PackageNotFoundError as exc:  # pragma: no cover - dependency of the services extra
        raise FileNotFoundError("example-robot-data is not installed") from exc
    path = Path(str(dist.locate_file(_PANDA_URDF)))
    if not path.is_file():  # pragma: no cover - broken install
        raise FileNotFoundError(f"Panda URDF not found at {path}")
    return path


@dataclass(frozen=True)
class JointLimits:
    """Per-joint limits, each of shape ``(n,)``: position (rad), velocity (rad/s), acceleration
    (rad/s²)."""

    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray

    def contains(self, q: np.ndarray, dq: np.ndarray | None = None, tol: float = 1e-9) -> bool:
        """True if ``q`` (and ``dq`` if given) lie inside the limits (with tolerance ``tol``)."""
        ok = bool(np.all(q >= self.lower - tol) and np.all(q <= self.upper + tol))
        if dq is not None:
            ok = ok and bool(np.all(np.abs(dq) <= self.velocity + tol))
        return ok


@dataclass
class RobotModel:
    """A fixed-base serial arm loaded from a URDF, reduced to its controlled joints.

    Build it with :meth:`load`. ``model``/``data`` are the Pinocchio objects; ``ee_frame_id`` is
    the id of the end-effector frame; ``limits`` are the joint limits used by the controller.
    """

    model: pin.Model
    data: pin.Data
    ee_frame: str
    ee_frame_id: int
    limits: JointLimits
    urdf_path: str
    joint_names: tuple[str, ...]
    named_poses: dict[str, np.ndarray] = field(default_factory=dict)
    #: The URDF's model before locking (for the collision geometry) and the locked joints' ids in it.
    full_model: pin.Model | None = None
    locked_joint_ids: tuple[int, ...] = ()

    # ------------------------------------------------------------------ construction
    @classmethod
    def load(
        cls,
        urdf: str | Path | None = None,
        ee_frame: str | None = None,
        locked_joints: Sequence[str] | None = None,
        accel_limits: Sequence[float] | float | None = None,
        named_poses: Mapping[str, Sequence[float]] | None = None,
    ) -> RobotModel:
        """Load a URDF (default: the Franka Panda of ``example-robot-data``).

        Args:
            urdf: path of the URDF file; ``None`` for the Panda.
            ee_frame: end-effector frame name; default ``panda_hand_tcp`` for the Panda, else the
                last frame of the model.
            locked_joints: joints removed from control and fixed at their neutral value; default
                the Panda's fingers for the Panda, none otherwise.
            accel_limits: joint acceleration limits in rad/s² (a scalar or one per joint);
                default the Panda datasheet values for the Panda, else 10 rad/s².
            named_poses: extra named joint vectors (rad), shape ``(n,)`` each.

        Raises:
            ValueError: unknown frame/joint, a model with non-revolute/prismatic joints, bad
                limits.
            FileNotFoundError: the URDF file does not exist.
        """
        is_panda = urdf is None
        path = panda_urdf_path() if urdf is None else Path(urdf)
        if not path.is_file():
            raise FileNotFoundError(f"URDF not found: {path}")
        full = pin.buildModelFromUrdf(str(path))
        if locked_joints is None:
            locked_joints = PANDA_LOCKED_JOINTS if is_panda else ()
        lock_ids = []
        for name in locked_joints:
            if not full.existJointName(name):
                raise ValueError(f"locked joint {name!r} is not in {path.name}")
            lock_ids.append(full.getJointId(name))
        model = pin.buildReducedModel(full, lock_ids, pin.neutral(full)) if lock_ids else full
        if model.nq != model.nv:
            raise ValueError(
                "only revolute/prismatic joints are supported (found continuous or floating "
                "joints); lock them with locked_joints"
            )
        n = model.nv
        if ee_frame is None:
            ee_frame = PANDA_EE_FRAME if is_panda else model.frames[len(model.frames) - 1].name
        if not model.existFrame(ee_frame):
            raise ValueError(f"end-effector frame {ee_frame!r} is not in {path.name}")
        fid = model.getFrameId(ee_frame)

        lower = np.array(model.lowerPositionLimit, dtype=float)
        upper = np.array(model.upperPositionLimit, dtype=float)
        vel = np.array(model.velocityLimit, dtype=float)
        if accel_limits is None:
            acc = np.array(PANDA_ACCEL_LIMITS if is_panda else [10.0] * n, dtype=float)
        else:
            acc = np.broadcast_to(np.asarray(accel_limits, dtype=float), (n,)).copy()
        if acc.shape != (n,) or np.any(~np.isfinite(acc)) or np.any(acc <= 0):
            raise ValueError(f"accel_limits must be {n} positive finite values")
        if np.any(~np.isfinite(lower)) or np.any(~np.isfinite(upper)) or np.any(lower >= upper):
            raise ValueError("every joint needs finite position limits with lower < upper")
        if np.any(~np.isfinite(vel)) or np.any(vel <= 0):
            raise ValueError("every joint needs a positive finite velocity limit")
        limits = JointLimits(lower, upper, vel, acc)
        joint_names = tuple(model.names[i] for i in range(1, model.njoints))

        poses: dict[str, np.ndarray] = {}
        if is_panda:
            poses.update({k: np.array(v) for k, v in PANDA_NAMED_POSES.items()})
        poses["neutral"] = np.clip(pin.neutral(model), lower, upper)
        poses["middle"] = 0.5 * (lower + upper)
        for name, value in (named_poses or {}).items():
            arr = np.asarray(value, dtype=float)
            if arr.shape != (n,):
                raise ValueError(f"named pose {name!r} must have {n} joint values")
            poses[name] = arr
        return cls(
            model=model,
            data=model.createData(),
            ee_frame=ee_frame,
            ee_frame_id=fid,
            limits=limits,
            urdf_path=str(path),
            joint_names=joint_names,
            named_poses=poses,
            full_model=full,
            locked_joint_ids=tuple(lock_ids),
        )

    def __post_init__(self) -> None:
        self._zero_ddq = np.zeros(self.model.nv)  # the zero joint acceleration of update()

    def with_own_data(self) -> RobotModel:
        """The same robot with Pinocchio data of its own (the model is shared, read-only): for a
        second user of the robot in one process, e.g. the planner's kinematics beside the arm
        simulation's in an in-process run."""
        return replace(self, data=self.model.createData())

    def collision_geometry(self, package_dirs: Sequence[str | Path] | None = None) -> pin.GeometryModel:
        """The URDF's collision geometry, reduced like :attr:`model` (see :meth:`geometry`)."""
        return self.geometry(pin.GeometryType.COLLISION, package_dirs)

    def visual_geometry(self, package_dirs: Sequence[str | Path] | None = None) -> pin.GeometryModel:
        """The URDF's visual geometry, reduced like :attr:`model` (see :meth:`geometry`)."""
        return self.geometry(pin.GeometryType.VISUAL, package_dirs)

    def geometry(
        self, kind: pin.GeometryType, package_dirs: Sequence[str | Path] | None = None
    ) -> pin.GeometryModel:
        """The URDF's collision or visual geometry, reduced like :attr:`model` (the locked joints'
        bodies are attached to their parents at the locked value), so ``parentJoint``/
        ``parentFrame`` index :attr:`model`; each object's ``placement`` is relative to its parent
        joint, its mesh vertices (m) are in its own frame, scaled by ``meshScale``.

        Args:
            kind: ``pin.GeometryType.COLLISION`` or ``pin.GeometryType.VISUAL``.
            package_dirs: directories that resolve ``package://`` mesh paths; default: the
                ``share`` directory of ``example-robot-data`` for its URDFs, else the URDF's
                directory and its two parents.

        Raises:
            ValueError: the model was not built by :meth:`load` (no full model kept).
        """
        if self.full_model is None:
            raise ValueError("the robot's geometry needs the full model kept by RobotModel.load")
        path = Path(self.urdf_path)
        if package_dirs is None:
            package_dirs = [path.parents[i] for i in range(min(_PANDA_SHARE_UP, len(path.parents)))]
        dirs = [str(d) for d in package_dirs]
        full = self.full_model
        geom = pin.buildGeomFromUrdf(full, str(path), kind, package_dirs=dirs)
        if self.locked_joint_ids:
            _, geom = pin.buildReducedModel(full, geom, list(self.locked_joint_ids), pin.neutral(full))
        return geom

    @property
    def n(self) -> int:
        """Number of controlled joints."""
        return int(self.model.nv)

    def resolve_pose(self, pose: str | Sequence[float] | np.ndarray) -> np.ndarray:
        """Joint vector ``(n,)`` of a named pose or an explicit joint vector, checked against
        the position limits."""
        if isinstance(pose, str):
            if pose not in self.named_poses:
                raise ValueError(f"unknown pose {pose!r}; known: {', '.join(sorted(self.named_poses))}")
            q = self.named_poses[pose].copy()
        else:
            q = np.asarray(pose, dtype=float).copy()
        if q.shape != (self.n,) or not np.all(np.isfinite(q)):
            raise ValueError(f"start pose must be {self.n} finite joint values")
        if not self.limits.contains(q):
            raise ValueError("start pose is outside the joint position limits")
        return q

    # ------------------------------------------------------------------ kinematics
    def update(self, q: np.ndarray, dq: np.ndarray) -> None:
        """Compute placements, Jacobians and velocities for state ``(q, dq)`` into ``data``
        (with zero joint acceleration, so frame accelerations are the drift term J̇q̇)."""
        # One kinematics pass (placements, velocities, drift accelerations), then the joint
        # Jacobians from those placements (the q-less overload does not redo the pass).
        pin.forwardKinematics(self.model, self.data, q, dq, self._zero_ddq)
        pin.computeJointJacobians(self.model, self.data)
        pin.updateFramePlacement(self.model, self.data, self.ee_frame_id)

    def jacobian(self) -> np.ndarray:
        """End-effector Jacobian ``(6, n)`` [linear; angular] in the base frame at the EE origin,
        valid after :meth:`update`."""
        return pin.getFrameJacobian(self.model, self.data, self.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)

    def drift(self) -> np.ndarray:
        """The term J̇q̇ ``(6,)``: classical EE acceleration [linear; angular] at zero joint
        acceleration, valid after :meth:`update`."""
        return pin.getFrameClassicalAcceleration(
            self.model, self.data, self.ee_frame_id, pin.LOCAL_WORLD_ALIGNED
        ).vector

    def ee_velocity(self) -> np.ndarray:
        """EE twist ``(6,)`` [linear; angular] in the base frame, valid after :meth:`update`."""
        return pin.getFrameVelocity(self.model, self.data, self.ee_frame_id, pin.LOCAL_WORLD_ALIGNED).vector

    def ee_placement(self) -> pin.SE3:
        """EE placement in the base frame, valid after :meth:`update`."""
        return self.data.oMf[self.ee_frame_id]

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward kinematics: EE position ``(3,)`` (m) and rotation ``(3, 3)`` for ``q (n,)``."""
        pin.framesForwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        M = self.data.oMf[self.ee_frame_id]
        return M.translation.copy(), M.rotation.copy()

    def fk_positions(self, Q: np.ndarray) -> np.ndarray:
        """EE positions ``(T, 3)`` (m) for a batch of joint vectors ``Q (T, n)``."""
        Q = np.asarray(Q, dtype=float)
        out = np.empty((Q.shape[0], 3))
        fid = self.ee_frame_id
        for i in range(Q.shape[0]):
            pin.forwardKinematics(self.model, self.data, Q[i])
            out[i] = pin.updateFramePlacement(self.model, self.data, fid).translation
        return out

    def body_frame_ids(self) -> list[int]:
        """Ids of the model's link (BODY) frames, in model order."""
        return [i for i, f in enumerate(self.model.frames) if f.type == pin.FrameType.BODY]

    def link_poses(self, frame_ids: Sequence[int]) -> list[tuple[str, list[float]]]:
        """``(link_name, [x, y, z, qx, qy, qz, qw])`` of the given frames in the base frame
        (m; unit quaternion with ``qw ≥ 0``), valid after :meth:`update` or :meth:`fk`: the
        placements of the Foxglove transform tree, all parented to the base."""
        out: list[tuple[str, list[float]]] = []
        model, data = self.model, self.data
        for fid in frame_ids:
            pose = pin.SE3ToXYZQUAT(pin.updateFramePlacement(model, data, fid)).tolist()
            if pose[6] < 0.0:
                pose[3:] = [-pose[3], -pose[4], -pose[5], -pose[6]]
            out.append((model.frames[fid].name, pose))
        return out

    def solve_ik(
        self,
        position: np.ndarray,
        rotation: np.ndarray | None = None,
        q0: np.ndarray | str = "ready",
        *,
        iters: int = 500,
        tol: float = 1e-6,
        damping: float = 1e-3,
    ) -> np.ndarray:
        """Closed-loop (Gauss-Newton, damped) position IK, used for start poses.

        Args:
            position: target EE position ``(3,)`` in m.
            rotation: target EE rotation ``(3, 3)``; ``None`` keeps the orientation of ``q0``.
            q0: initial joint vector ``(n,)`` or a named pose; the null space stays close to it.
            iters: iteration cap.
            tol: stop when the pose error norm (m and rad) is below this.
            damping: Levenberg damping of the least-squares step.

        Returns:
            Joint vector ``(n,)`` inside the position limits.

        Raises:
            ValueError: the target cannot be reached to ``1e-4`` within the iteration cap.
        """
        q = self.resolve_pose(q0) if isinstance(q0, str) else np.asarray(q0, dtype=float).copy()
        target_R = self.fk(q)[1] if rotation is None else np.asarray(rotation, dtype=float)
        target = pin.SE3(target_R, np.asarray(position, dtype=float))
        lo, hi = self.limits.lower, self.limits.upper
        err = np.inf
        for _ in range(iters):
            pin.framesForwardKinematics(self.model, self.data, q)
            M = self.data.oMf[self.ee_frame_id]
            e = np.concatenate([target.translation - M.translation, pin.log3(target.rotation @ M.rotation.T)])
            err = float(np.linalg.norm(e))
            if err < tol:
                break
            J = pin.computeFrameJacobian(self.model, self.data, q, self.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)
            step = J.T @ np.linalg.solve(J @ J.T + damping * np.eye(6), e)
            q = np.clip(q + step, lo, hi)
        if err > 1e-4:
            raise ValueError(f"IK did not converge (pose error {err:.2e}) for target {position}")
        return q
