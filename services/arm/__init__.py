"""The simulated arm: the arm simulator, its IK controller, teach mode and the ``psm arm`` service.

* :mod:`services.arm.controller` — command validation, IK law, limit clamps (pure);
* :mod:`services.arm.sim` — :class:`~services.arm.sim.ArmSim`: fixed-step integration and the
  watchdog brake (pure, no bus);
* :mod:`services.arm.teach` / :mod:`services.arm.demos` — guided demonstrations to MCAP and
  the end-effector trajectory extraction;
* :mod:`services.arm.service` — the ``psm arm`` process on Zenoh;
* :mod:`services.arm.probe` — ``psm arm probe``, a trivial controller for tests and benchmarks.

The robot model (URDF, kinematics) and the arm's bus protocol (``ArmState``/``ArmCommand``
builders and parsers, the decoded command types) are in :mod:`services.robot`, shared with the
services that control or watch the arm. See ``docs/arm.md``.
"""
