"""The learner's measuring sticks: oracle, reachable floor, where the knot is decided."""
