"""The simulated world: ``world`` (scenes and start poses), ``robot``, ``sensor`` (the depth camera),
``env`` (the Gymnasium task) and ``maps`` (occupancy grids, coverage, heatmaps)."""
