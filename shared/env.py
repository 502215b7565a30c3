"""The exploration task as a Gymnasium environment (``cogexplore/Explore-v0``).

One step: hold one of five moving commands for ``control_period_s``, then read the depth
camera. Reward +1 (r_move) for a collision-free move, -100 (r_ter) on collision, which ends
the episode (``terminated``). A collision is either the paper's rule -- the minimum valid
depth falls below l_s = 0.55 m -- or the robot body touching an obstacle; ``info`` reports
the cause. Reaching the step cap is ``truncated``, never ``terminated``, so value targets
bootstrap through it.

    import shared.env, gymnasium as gym
    env = gym.make("cogexplore/Explore-v0", world="paper-indoor", speed_table="test")
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from shared.config import ACTION_NAMES, NUM_ACTIONS, SPEED_TABLES, EnvConfig, SensorConfig
from shared.robot import Robot, build_model
from shared.sensor import DepthCamera
from shared.world import World, load_world

ENV_ID = "cogexplore/Explore-v0"


def min_valid_depth(depth_m: np.ndarray) -> float:
    """Smallest non-zero depth in the image (inf if no pixel has a return)."""
    valid = depth_m[depth_m > 0]
    return float(valid.min()) if valid.size else math.inf


class ExploreEnv(gym.Env):
    """Depth-only exploration in a MuJoCo indoor world with a TurtleBot-like robot.

    Construct with an ``EnvConfig`` and/or keyword overrides of its fields
    (``world=``, ``speed_table=``, ``start_index=``, ``max_episode_steps=``, ...) and an
    optional ``SensorConfig`` (or a dict of its fields). ``world`` may also be a prebuilt
    :class:`World`.
    """

    metadata = {"render_modes": ["depth_array"], "render_fps": 2}

    def __init__(self, config: EnvConfig | None = None, sensor: SensorConfig | dict | None = None,
                 render_mode: str | None = None, **overrides: Any):
        world_obj = overrides.pop("world", None)
        if isinstance(world_obj, World):
            overrides["world"] = world_obj.name
        elif world_obj is not None:
            overrides["world"] = world_obj
        cfg = dataclasses.replace(config or EnvConfig(), **overrides)
        if isinstance(sensor, dict):
            sensor = SensorConfig(**sensor)
        self.env_config = cfg
        self.sensor_config = sensor or SensorConfig()
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode {render_mode!r} not in {self.metadata['render_modes']}")
        self.render_mode = render_mode

        self.world = world_obj if isinstance(world_obj, World) else load_world(cfg.world)
        if cfg.start_index is not None and cfg.start_index >= len(self.world.starts):
            raise ValueError(f"start_index {cfg.start_index} out of range: world {self.world.name!r} "
                             f"has {len(self.world.starts)} starts")
        self.model = build_model(self.world.mjcf, cfg, self.sensor_config)
        self.data = mujoco.MjData(self.model)
        self.robot = Robot(self.model, self.data)
        self.camera = DepthCamera(self.model, self.sensor_config)
        self.angular_rps, self.linear_mps = SPEED_TABLES[cfg.speed_table]

        s = self.sensor_config
        self.observation_space = gym.spaces.Box(0.0, s.max_range_m, (s.height, s.width), np.float32)
        self.action_space = gym.spaces.Discrete(NUM_ACTIONS)

        self._depth = np.zeros((s.height, s.width), np.float32)
        self._start_index = 0
        self._start_xy = (0.0, 0.0)
        self._last_xy = (0.0, 0.0)
        self._path_length = 0.0
        self._steps = 0
        self._random_start = False
        self._clear_cells: np.ndarray | None = None  # cells a random start may use, built on first need
        self._grid = None

    # -- Gymnasium API ------------------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self.camera.reseed(int(self.np_random.integers(2**63)))
        options = options or {}
        index = options.get("start_index", self.env_config.start_index)
        n_starts = len(self.world.starts)
        if index is None:
            index = int(self.np_random.integers(n_starts))
        if not (isinstance(index, (int, np.integer)) and 0 <= index < n_starts):
            raise ValueError(f"start_index {index!r} out of range [0, {n_starts})")
        start = self.world.starts[int(index)]
        pose = None  # a random free pose (it leaves the robot there and its image in self._depth)
        fixed = "start_index" in options or self.env_config.start_index is not None
        if not fixed and self.env_config.random_start_prob > 0 and \
                self.np_random.random() < self.env_config.random_start_prob:
            pose = self._random_free_pose()
        self._random_start = pose is not None
        if pose is None:
            pose = (start.x, start.y, start.yaw)
            self.robot.set_pose(*pose)
            self._depth = self.camera.capture(self.data)
        x, y, _ = pose
        self._start_index = int(index)
        self._start_xy = self._last_xy = (x, y)
        self._path_length = 0.0
        self._steps = 0
        return self._depth, self._info(None, min_valid_depth(self._depth))

    def step(self, action):
        if not (isinstance(action, (int, np.integer)) and 0 <= int(action) < NUM_ACTIONS):
            raise ValueError(f"action {action!r} is not one of 0..{NUM_ACTIONS - 1} ({', '.join(ACTION_NAMES)})")
        cfg = self.env_config
        touched = self.robot.drive(self.linear_mps, self.angular_rps[int(action)], cfg.substeps)
        self._depth = self.camera.capture(self.data)
        self._steps += 1
        x, y, _ = self.robot.pose()
        self._path_length += math.hypot(x - self._last_xy[0], y - self._last_xy[1])
        self._last_xy = (x, y)

        min_depth = min_valid_depth(self._depth)
        cause = "contact" if touched else ("depth" if min_depth < cfg.collision_distance_m else None)
        terminated = cause is not None
        truncated = not terminated and self._steps >= cfg.max_episode_steps
        reward = cfg.reward_collision if terminated else cfg.reward_move
        return self._depth, float(reward), terminated, truncated, self._info(cause, min_depth)

    def render(self):
        if self.render_mode == "depth_array":
            return self._depth.copy()
        return None

    def close(self):
        self.camera.close()

    # -- helpers ---------------------------------------------------------------------

    def _random_free_pose(self, tries: int = 50) -> tuple[float, float, float] | None:
        """Move the robot to a random pose ``random_start_clearance_m`` from every obstacle whose
        first image (kept in ``self._depth``) is above the collision threshold with a 10 cm
        margin; None when no such pose turns up (the caller then places the robot)."""
        if self._clear_cells is None:
            from shared.maps import clearance_map, occupancy_grid

            self._grid = occupancy_grid(self.world, 0.05)
            clearance = clearance_map(self._grid.occupied, self._grid.resolution_m)
            self._clear_cells = np.argwhere(clearance >= self.env_config.random_start_clearance_m)
        if len(self._clear_cells) == 0:
            return None
        half = self._grid.resolution_m / 2
        for _ in range(tries):
            iy, ix = self._clear_cells[self.np_random.integers(len(self._clear_cells))]
            cx, cy = self._grid.cell_to_world(ix, iy)
            pose = (float(cx + self.np_random.uniform(-half, half)), float(cy + self.np_random.uniform(-half, half)),
                    float(self.np_random.uniform(-math.pi, math.pi)))
            self.robot.set_pose(*pose)
            depth = self.camera.capture(self.data)
            if min_valid_depth(depth) >= self.env_config.collision_distance_m + 0.1:
                self._depth = depth
                return pose
        return None

    def _info(self, cause: str | None, min_depth: float) -> dict[str, Any]:
        x, y, yaw = self.robot.pose()
        return {
            "pose": (x, y, yaw),
            "start_index": self._start_index,
            "random_start": self._random_start,
            "collision_cause": cause,
            "min_depth_m": min_depth,
            "distance_from_start_m": math.hypot(x - self._start_xy[0], y - self._start_xy[1]),
            "path_length_m": self._path_length,
            "step": self._steps,
        }


if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="shared.env:ExploreEnv")
