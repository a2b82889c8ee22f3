"""The simulated arm: a Pinocchio robot model with a Cartesian-acceleration interface.

* :mod:`services.arm.robot` — URDF model, limits, kinematics (pure);
* :mod:`services.arm.controller` — commands, validation, IK law, limit clamps (pure);
* :mod:`services.arm.sim` — :class:`~services.arm.sim.ArmSim`: fixed-step integration and the
  watchdog brake (pure, no bus);
* :mod:`services.arm.teach` / :mod:`services.arm.demos` — guided demonstrations to MCAP and
  the end-effector trajectory extraction;
* :mod:`services.arm.service` — the ``psm arm`` process on Zenoh.

See ``docs/arm.md``.
"""
