"""Goal tracker: a camera feed to a 3-D goal stream (face detection).

Pure parts (no bus): :mod:`.geometry` (pinhole box ↔ 3-D, camera → base), :mod:`.kalman`
(constant-velocity filter with gating and lost timeout), :mod:`.selection` (target kept across
frames), :mod:`.workspace` (reachability), :mod:`.detectors` (Haar / YuNet, reduced-resolution
full detection + ROI tracking), :mod:`.synthetic` (astronaut face on a known 3-D path) and
:mod:`.tracker` (``GoalTracker.process(frame, stamp_ns)``). I/O: :mod:`.sources` (device, file,
URL, topic, synthetic), :mod:`.service` (``psm track``, ``psm camera synth``), :mod:`.config`,
:mod:`.cli`; :mod:`.calibration` (chessboard). See ``docs/goal_tracker.md``.
"""
