"""The obstacle monitor (``psm obstacles``): the obstacle set, the paper's segment test and the
whole-arm clearance for every arm state, published as collision predictions for the planner."""
