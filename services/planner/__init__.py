"""The planner: one PSM per sub-task of the feeding task, driven by the arm's states.

Built so far: :mod:`services.planner.models` (the models of a task's sub-tasks, learned from
their demonstrations or read from model files, cached by content). The service itself comes
with the planner issue.
"""
