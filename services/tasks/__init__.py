"""Task configuration shared by the demonstrations and the planner.

* :mod:`services.tasks.feeding` — the feeding scene (positions of the neutral pose, spoon, bowl,
  person, cylinder) and the sub-task sequence, loaded from ``configs/feeding.toml``.
"""
