"""Measurements of a simulated scene for tests (importable from any test: pytest puts tests/ on
sys.path for its conftest.py)."""

from __future__ import annotations

import mujoco

from shared.sim.env import ExploreEnv
from shared.sim.robot import FLOOR_GEOM, ROBOT_GEOM


def robot_gap_m(env: ExploreEnv) -> float:
    """The exact distance from the robot's body to the nearest obstacle (MuJoCo's geom distance)."""
    model, data = env.model, env.data
    robot = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, ROBOT_GEOM)
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, FLOOR_GEOM)
    return min(mujoco.mj_geomDistance(model, data, robot, g, 10.0, None)
               for g in range(model.ngeom) if g not in (robot, floor))
