"""fem: the 2D finite-element model of tissue, stones and probe contact. A pure library: no robot, no planner."""
