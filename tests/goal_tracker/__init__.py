"""Tests of the goal tracker (services/goal_tracker)."""
