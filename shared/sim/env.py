"""The exploration task as a Gymnasium environment (``cogexplore/Explore-v0``).

One step: hold one of five moving commands for ``control_period_s``, then read the depth
camera. Reward +1 (r_move) for a collision-free move, -100 (r_ter) on collision, which ends
the episode (``terminated``). A collision is either the paper's rule -- the minimum valid
depth falls below l_s = 0.55 m -- or the robot body touching an obstacle; ``info`` reports
the cause. Reaching the step cap is ``truncated``, never ``terminated``, so value targets
bootstrap through it. Either way the episode has ended: as Gymnasium's ``Env.step`` asks, the next
step needs a ``reset`` first, and one without it is an :class:`EnvError` (it drove on from inside
the collision and reported it again, or past the cap).

Importing this module registers the Gymnasium ids (``shared.sim.gym_register``, which also says
how the TimeLimit and the env's own step cap meet)::

    import shared.sim.env, gymnasium as gym
    env = gym.make("cogexplore/Explore-v0", world="paper-indoor", speed_table="test")

Render modes: ``depth_array`` (the (H, W) image) and ``rgb_array`` (``shared.sim.render``: the
depth colour-mapped beside a top-down map with the robot and its path this episode), one frame
per step, so ``render_fps`` is ``1 / control_period_s``.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import zlib
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from shared.config import (
    ACTION_NAMES,
    FAILURE_STARTS_KEPT,
    NEW_AREA_CAP_M2,
    NUM_ACTIONS,
    PROCEDURAL_PREFIX,
    SPEED_TABLES,
    EnvConfig,
    SensorConfig,
    section_from_dict,
    is_finite_number,
)
from shared.depth import range_gate
from shared.errors import CogexploreError
from shared.sim.gym_register import ENV_ID  # noqa: F401  (re-exported; the import registers the ids)
from shared.sim.robot import MAX_TWIST_MPS, MAX_TWIST_RPS, Robot, build_model
from shared.sim.sensor import DepthCamera, floor_depths_m
from shared.sim.world import World, WorldError, canonical_world_name, check_starts_fit, load_world

MAP_RESOLUTION_M = 0.05
"""Cell side of the occupancy grid that random starts and ``rgb_array`` frames use."""
START_DEPTH_MARGIN_M = 0.1
"""A drawn start (random or jittered) must see nothing nearer than the collision distance plus this."""
START_DRAW_TRIES = 100
"""Draws of a jittered start before the reset gives up (``reset(options={"start_jitter": ...})``)."""
FAILURE_START_TRIES = 20
"""Draws of a failure start (a remembered collision, a step back from it, a jitter) before the reset
starts the episode as it would without them (``EnvConfig.failure_start_prob``)."""
MAX_START_JITTER_M = 10.0
MAX_START_JITTER_DEG = 180.0
"""Bounds of the ``start_jitter`` reset option: wider than any world's start needs (a protocol's are at
most 2 m), and 180 degrees already draws any heading."""
RESET_OPTIONS = ("start_index", "start_jitter")
"""The ``reset`` options the env takes (see :class:`ExploreEnv`); any other is refused, not ignored."""
log = logging.getLogger("cogexplore.env")


class EnvError(CogexploreError):
    """A start index, command, render mode or snapshot the environment cannot take (a ValueError,
    as Gymnasium expects of bad arguments)."""


def _start_jitter(value: Any) -> tuple[float, float] | None:
    """The ``start_jitter`` reset option as (metres, degrees); None when absent or zero."""
    if value is None:
        return None
    ok = isinstance(value, (tuple, list)) and len(value) == 2 and all(
        isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
        and math.isfinite(v) and v >= 0 for v in value) \
        and value[0] <= MAX_START_JITTER_M and value[1] <= MAX_START_JITTER_DEG  # numpy's draw overflows past ~1e308
    if not ok:
        raise EnvError(f"start_jitter {value!r}: expected (metres, degrees), metres in [0, {MAX_START_JITTER_M:g}] "
                       f"and degrees in [0, {MAX_START_JITTER_DEG:g}]")
    jitter_m, jitter_deg = float(value[0]), float(value[1])
    return (jitter_m, jitter_deg) if jitter_m > 0 or jitter_deg > 0 else None


def _check_floor(cfg: EnvConfig, sensor: SensorConfig) -> None:
    """EnvError if a bare floor reads nearer than the collision distance anywhere in the image:
    every step would end in a depth collision."""
    seen = range_gate(floor_depths_m(sensor), sensor.min_range_m, sensor.max_range_m)
    seen = seen[seen > 0]
    if seen.size and float(seen.min()) < cfg.collision_distance_m:
        raise EnvError(f"the bare floor reads {float(seen.min()):.2f} m in the depth image (camera "
                       f"{sensor.mount_height_m:g} m high, vfov_deg {sensor.vfov_deg:g}), nearer than "
                       f"collision_distance_m {cfg.collision_distance_m:g}, so every step would end in a "
                       "collision: raise sensor.mount_height_m, narrow sensor.vfov_deg or lower "
                       "env.collision_distance_m")


def min_valid_depth(depth_m: np.ndarray) -> float:
    """Smallest non-zero depth in the image (inf if no pixel has a return)."""
    valid = depth_m[depth_m > 0]
    return float(valid.min()) if valid.size else math.inf


@dataclasses.dataclass
class _Scene:
    """One world's MuJoCo model with the robot, its data and camera, and (built on first need)
    the cells a random start may use."""

    world: World
    model: mujoco.MjModel
    data: mujoco.MjData
    robot: Robot
    camera: DepthCamera
    robot_radius_m: float
    """A jittered start's centre must be this far from obstacles on the map."""
    start_clearance_m: float
    """A random start's cell must be this far from obstacles (``random_start_clearance_m``)."""
    _free: tuple[Any, np.ndarray, np.ndarray] | None = None
    _canvas: Any = None
    _coverage: Any = None
    _map_expert: Any = None

    def map_expert(self, cfg: EnvConfig, sensor: SensorConfig) -> Any:
        """The world's map expert at ``cfg``'s speeds (``shared.expert.expert.CommandExpert``), built
        once per world."""
        if self._map_expert is None:
            from shared.expert.expert import CommandExpert

            self._map_expert = CommandExpert(self.world, cfg, sensor)
        return self._map_expert

    @classmethod
    def build(cls, world: World, cfg: EnvConfig, sensor: SensorConfig) -> "_Scene":
        """The scene of ``world``; WorldError if an episode would end at its first step somewhere."""
        check_starts_fit(world, cfg, sensor)
        model = build_model(world.mjcf, cfg, sensor)
        data = mujoco.MjData(model)
        return cls(world, model, data, Robot(model, data), DepthCamera(model, sensor),
                   cfg.robot_radius_m, cfg.random_start_clearance_m)

    def free_space(self) -> tuple[Any, np.ndarray, np.ndarray]:
        """The occupancy grid, the (ny, nx) bool map of the cells at least ``robot_radius_m`` from
        every obstacle cell and the row-major flat indices (int32) of the cells at least
        ``start_clearance_m`` from one, built once per world.

        Only these two thresholds of the clearance map are ever read, so the float64 map itself is
        not kept: with it (and the cells as int64 (iy, ix) pairs) a procedural world held ~0.7 MB,
        and an actor keeps a hundred worlds."""
        if self._free is None:
            from shared.sim.maps import clearance_map, occupancy_grid

            grid = occupancy_grid(self.world, MAP_RESOLUTION_M)
            # Exact below the larger threshold, which bounds its cost in a vast world.
            cap = max(self.robot_radius_m, self.start_clearance_m)
            clearance = clearance_map(grid.occupied, grid.resolution_m, cap)
            # A grid holds at most 25M cells (maps.empty_grid), so int32 indexes any of them.
            self._free = (grid, clearance >= self.robot_radius_m,
                          np.flatnonzero(clearance >= self.start_clearance_m).astype(np.int32))
        return self._free

    def coverage(self) -> Any:
        """The world's ``shared.sim.maps.CoverageTracker`` (the novelty reward's), on the map grid."""
        if self._coverage is None:
            from shared.sim.maps import CoverageTracker, occupancy_grid

            self._coverage = CoverageTracker(occupancy_grid(self.world, MAP_RESOLUTION_M), self.camera.cfg)
        return self._coverage

    def canvas(self) -> Any:
        """The world's top-down map for ``rgb_array`` frames (a ``shared.sim.render.MapCanvas``)."""
        if self._canvas is None:
            from shared.sim.maps import occupancy_grid
            from shared.sim.render import MapCanvas

            self._canvas = MapCanvas(occupancy_grid(self.world, MAP_RESOLUTION_M))
        return self._canvas


class ExploreEnv(gym.Env):
    """Depth-only exploration in a MuJoCo indoor world with a TurtleBot-like robot.

    Construct with an ``EnvConfig`` and/or keyword overrides of its fields
    (``world=``, ``speed_table=``, ``start_index=``, ``max_episode_steps=``, ...) and an
    optional ``SensorConfig`` (or a dict of its fields). ``world`` may also be a prebuilt
    :class:`World`. Refused at construction, in one line: an unknown field, a camera that sees the
    bare floor nearer than ``collision_distance_m``, a robot radius that puts it in contact at a start
    or a camera that sees an obstacle nearer than ``collision_distance_m`` from one.

    ``reset`` options: ``start_index`` (a named start; default the config's, else a random one)
    and ``start_jitter`` ``(metres, degrees)``: the start moved by a uniform draw within
    ±metres in x and y and ±degrees in heading (the env's ``np_random``, so the reset seed fixes
    it), drawn again while the robot would touch an obstacle (on the map: less than its radius
    from an occupied cell; in MuJoCo: a contact) or its first image holds a depth below
    ``collision_distance_m + START_DEPTH_MARGIN_M``; EnvError naming the start after
    ``START_DRAW_TRIES`` draws. Without the option, the config's ``start_jitter_m`` /
    ``start_jitter_deg`` (training's) apply, unless the options fix ``start_index``; an explicit
    ``start_jitter`` (None: the exact pose) always wins. A start with no clear draw under the
    config's jitter is played from its exact pose, with a warning (once per start), not an error.
    A random free start is never jittered, and a jitter of zero draws nothing, so the episodes are
    those of an env without it. A failure start (``EnvConfig.failure_start_prob``: near a pose an
    earlier episode passed before its collision, in its world) is drawn before both, with the
    config's jitter; the info's ``random_start`` and ``failure_start`` say which an episode had.
    """

    metadata = {"render_modes": ["depth_array", "rgb_array"], "render_fps": 2}  # fps of the default 0.5 s period

    def __init__(self, config: EnvConfig | None = None, sensor: SensorConfig | dict | None = None,
                 render_mode: str | None = None, **overrides: Any):
        world_obj = overrides.pop("world", None)
        if isinstance(world_obj, World):
            overrides["world"] = world_obj.name
        elif world_obj is not None:
            overrides["world"] = world_obj
        if not isinstance(config, (EnvConfig, type(None))):
            raise EnvError(f"config must be an EnvConfig, got {type(config).__name__}")
        if not isinstance(sensor, (SensorConfig, dict, type(None))):
            raise EnvError(f"sensor must be a SensorConfig or a dict of its fields, got {type(sensor).__name__}")
        # As a preset's sections are read: an unknown field is a ConfigError, not a TypeError.
        cfg = section_from_dict(EnvConfig, overrides, config or EnvConfig(), "env")
        if isinstance(sensor, dict):
            sensor = section_from_dict(SensorConfig, sensor, SensorConfig(), "sensor")
        self.env_config = cfg
        self.sensor_config = sensor or SensorConfig()
        _check_floor(cfg, self.sensor_config)
        self.metadata = {**type(self).metadata, "render_fps": 1.0 / cfg.control_period_s}
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise EnvError(f"render_mode {render_mode!r} not in {self.metadata['render_modes']}")
        self.render_mode = render_mode

        world = world_obj if isinstance(world_obj, World) else load_world(cfg.world)
        if cfg.start_index is not None and cfg.start_index >= len(world.starts):
            raise EnvError(f"start_index {cfg.start_index} out of range: world {world.name!r} "
                             f"has {len(world.starts)} starts")
        self._main_scene = _Scene.build(world, cfg, self.sensor_config)
        self._scenes = {world.name: self._main_scene}  # extra worlds are built when first drawn
        # Under the names their Worlds carry ('procedural:007' is 'procedural:7'), by which scenes
        # and remembered failures are found.
        self._extra_world_names = tuple(dict.fromkeys(canonical_world_name(n) for n in cfg.extra_world_names)) \
            if cfg.extra_world_prob > 0 else ()
        for name in self._extra_world_names:
            if not name.startswith(PROCEDURAL_PREFIX):  # procedural names are checked by the config
                load_world(name)  # a bad name or a broken file fails here, not episodes into a run
        self._scene = self._main_scene  # the world of the episode now playing
        self.angular_rps, self.linear_mps = SPEED_TABLES[cfg.speed_table]

        s = self.sensor_config
        self.observation_space = gym.spaces.Box(0.0, s.max_range_m, (s.height, s.width), np.float32)
        self.action_space = gym.spaces.Discrete(NUM_ACTIONS)

        self._depth = np.zeros((s.height, s.width), np.float32)
        self._start_index = 0
        self._start_xy = (0.0, 0.0)
        self._last_xy = (0.0, 0.0)
        self._trail: list[tuple[float, float]] = []  # the episode's (x, y), start first, for rgb_array
        self._path_length = 0.0
        self._steps = 0
        self._needs_reset = True
        self._ended: str | None = None
        """How the episode ended (a collision, the step cap), None while it plays: stepping on needs a reset."""
        self._random_start = False
        self._failure_start_now = False
        # The poses of the episode's last steps and the collisions kept with theirs (failure_start_prob).
        self._recent_poses: collections.deque = collections.deque(maxlen=cfg.failure_start_back_steps + 1)
        self._failures: collections.deque = collections.deque(maxlen=FAILURE_STARTS_KEPT)
        self._trapped = False  # no way out from the pose (kept with reward_trap_penalty > 0 only)
        self._noise_seed: int | None = None  # drawn at each seeded reset
        self._unjitterable: set[tuple[str, int]] = set()  # (world, start) warned of: no clear jittered draw

    def share_extra_worlds(self, index: int, count: int) -> None:
        """Play only this env's share of ``env.extra_worlds``: every ``count``-th one from ``index``
        (actor ``index`` of a fleet of ``count``; the fleet together plays them all, each world built
        in one process instead of in every one). With fewer worlds than ``count``, all of them."""
        if not (isinstance(count, int) and count >= 1 and isinstance(index, int) and 0 <= index < count):
            raise EnvError(f"share_extra_worlds: index {index!r} of count {count!r}")
        if len(self._extra_world_names) >= count:
            self._extra_world_names = self._extra_world_names[index::count]

    # -- Gymnasium API ------------------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._needs_reset = True  # until this reset is through: a failed one leaves no episode to step
        if seed is not None:
            self._noise_seed = int(self.np_random.integers(2**63))
            for name, scene in self._scenes.items():
                scene.camera.reseed(self._camera_seed(name))
        options = {} if options is None else options
        if not isinstance(options, dict):
            raise EnvError(f"reset options must be a dict, got {type(options).__name__}")
        unknown = [k for k in options if k not in RESET_OPTIONS]
        if unknown:  # a misspelt start_index would silently give random starts
            raise EnvError(f"reset options {', '.join(map(repr, unknown))}: the env takes {', '.join(RESET_OPTIONS)}")
        fixed = "start_index" in options or self.env_config.start_index is not None
        pose = None  # a random free or failure start's pose (the robot is there, its image in self._depth)
        if not fixed and self._failures and self.np_random.random() < self.env_config.failure_start_prob:
            pose = self._failure_start()
        self._failure_start_now = pose is not None
        if pose is None:
            scene = self._main_scene
            extra = self._extra_world_names
            if not fixed and extra and self.np_random.random() < self.env_config.extra_world_prob:
                scene = self._extra_scene(extra[int(self.np_random.integers(len(extra)))]) or scene
            self._scene = scene
        index = options.get("start_index", self.env_config.start_index)
        n_starts = len(self.world.starts)
        if index is None:
            index = int(self.np_random.integers(n_starts))
        if not (isinstance(index, (int, np.integer)) and 0 <= index < n_starts):
            raise EnvError(f"start_index {index!r} out of range [0, {n_starts})")
        start = self.world.starts[int(index)]
        jitter, jitter_is_the_callers = self._episode_jitter(options)
        self._random_start = False
        if pose is None and not fixed and self.env_config.random_start_prob > 0 and \
                self.np_random.random() < self.env_config.random_start_prob:
            pose = self._random_free_pose()
            self._random_start = pose is not None
        if pose is None and jitter is not None:
            try:
                pose = self._jittered_start(int(index), *jitter)
            except EnvError as exc:
                # A caller's jitter is a condition it asked for (the test protocol); training's is
                # a variation, and one tight start in one of many worlds must not end the run.
                if jitter_is_the_callers:
                    raise
                if (self.world.name, int(index)) not in self._unjitterable:
                    self._unjitterable.add((self.world.name, int(index)))
                    log.warning("env.start_jitter: %s; its episodes start at the exact pose", exc)
        if pose is None:
            pose = (start.x, start.y, start.yaw)
            self.robot.set_pose(*pose)
            self._depth = self.camera.capture(self.data)
        x, y, yaw = pose
        if self.env_config.reward_trap_penalty > 0:  # starting in a trap is not entering one
            self._trapped = self._no_way_out(x, y, yaw)
        if self.env_config.reward_new_area_per_m2 > 0:  # the first view is the start's, not a reward
            self._scene.coverage().reset()
            self._scene.coverage().observe(x, y, yaw, self._depth)
        self._start_index = int(index)
        self._start_xy = self._last_xy = (x, y)
        self._trail = [(x, y)]
        self._recent_poses.clear()
        self._recent_poses.append((x, y, yaw))
        self._path_length = 0.0
        self._steps = 0
        self._ended = None
        self._needs_reset = False
        return self._depth, self._info(None, min_valid_depth(self._depth))

    def step(self, action):
        if not (isinstance(action, (int, np.integer)) and 0 <= int(action) < NUM_ACTIONS):
            raise EnvError(f"action {action!r} is not one of 0..{NUM_ACTIONS - 1} ({', '.join(ACTION_NAMES)})")
        return self.step_twist(self.linear_mps, self.angular_rps[int(action)])

    def step_twist(self, linear_mps: float, angular_rps: float):
        """One control period at any (forward m/s, turn rad/s) command, with :meth:`step`'s return
        and collision rule: what a robot base does with a ROS ``cmd_vel`` Twist (``cogexplore
        sim-robot``). ``step(a)`` is ``step_twist`` at the speed table's command ``a``. EnvError beyond
        the robot's ``MAX_TWIST_MPS`` and ``MAX_TWIST_RPS``."""
        if not (is_finite_number(linear_mps) and is_finite_number(angular_rps)
                and abs(linear_mps) <= MAX_TWIST_MPS and abs(angular_rps) <= MAX_TWIST_RPS):
            raise EnvError(f"twist ({linear_mps!r} m/s, {angular_rps!r} rad/s): both must be numbers within "
                           f"±{MAX_TWIST_MPS:g} m/s and ±{MAX_TWIST_RPS:g} rad/s")
        if self._needs_reset:  # the robot would drive from wherever MuJoCo put it, a wall perhaps
            raise EnvError("step before reset: call env.reset() first")
        if self._ended is not None:  # it would drive on from inside the collision, or past the cap
            raise EnvError(f"step after the episode ended ({self._ended}): call env.reset() first")
        cfg = self.env_config
        touched = self.robot.drive(float(linear_mps), float(angular_rps), cfg.substeps)
        self._depth = self.camera.capture(self.data)
        self._steps += 1
        x, y, yaw = self.robot.pose()
        self._path_length += math.hypot(x - self._last_xy[0], y - self._last_xy[1])
        self._last_xy = (x, y)
        self._trail.append((x, y))

        min_depth = min_valid_depth(self._depth)
        cause = "contact" if touched else ("depth" if min_depth < cfg.collision_distance_m else None)
        terminated = cause is not None
        truncated = not terminated and self._steps >= cfg.max_episode_steps
        if terminated or truncated:
            self._ended = "a collision" if terminated else f"truncated at its {cfg.max_episode_steps}-step cap"
        reward = cfg.reward_collision if terminated else cfg.reward_move
        if cfg.failure_start_prob > 0:  # off, the step keeps no poses
            self._recent_poses.append((x, y, yaw))
            if terminated:
                self._remember_failure()
        if cfg.reward_new_area_per_m2 > 0 and not terminated:
            new_area_m2 = self._scene.coverage().observe(x, y, yaw, self._depth)
            reward += cfg.reward_new_area_per_m2 * min(new_area_m2, NEW_AREA_CAP_M2)
        if cfg.reward_trap_penalty > 0 and not terminated:
            was_trapped, self._trapped = self._trapped, self._no_way_out(x, y, yaw)
            if self._trapped and not was_trapped:  # charged once, on the step that enters
                reward -= cfg.reward_trap_penalty
        return self._depth, float(reward), terminated, truncated, self._info(cause, min_depth)

    def map_expert(self) -> Any:
        """The privileged map expert of the world now playing, at this env's speeds: the trap
        reward's judge of a way out, and the guided episodes' and teacher labels' commands
        (``shared.expert.expert.ExpertGuide``). Training only: it reads the map, never the image."""
        return self._scene.map_expert(self.env_config, self.sensor_config)

    def _no_way_out(self, x: float, y: float, yaw: float) -> bool:
        return not self.map_expert().has_way_out(x, y, yaw, self.env_config.trap_horizon_steps)

    def snapshot(self) -> tuple[Any, ...]:
        """The episode's state now (robot physics, step count, path, image, the floor seen for the
        novelty reward, whether the pose has a way out for the trap reward): :meth:`restore` puts
        the episode back exactly there, so a planner can try several commands from one pose
        (shared.learning.demos), ended or not as it was then (one taken before a collision plays
        on after it). Only within the episode and world it was taken in; the sensor's noise draws
        (``SensorConfig.noise_std_m``) are not rewound."""
        seen = self._scene.coverage().seen if self.env_config.reward_new_area_per_m2 > 0 else None
        return (self._scene, self.robot.state(), self._steps, self._path_length, self._last_xy,
                self._depth.copy(), tuple(self._trail), seen, self._trapped, self._ended)

    def restore(self, snapshot: tuple[Any, ...]) -> None:
        """Return to a :meth:`snapshot` of the current episode (one of another world is refused, the env
        as it was)."""
        if snapshot[0] is not self._scene:
            raise EnvError("a snapshot can only be restored in the episode's own world")
        scene, state, self._steps, self._path_length, self._last_xy, depth, trail, seen, self._trapped, \
            self._ended = snapshot
        if seen is not None:
            scene.coverage().restore(seen)
        self.robot.set_state(state)
        self._depth = depth.copy()
        self._trail = list(trail)

    def render(self):
        if self.render_mode == "depth_array":
            return self._depth.copy()
        if self.render_mode == "rgb_array":
            return self._scene.canvas().frame(self._depth, self.sensor_config.max_range_m, self._trail,
                                              self.robot.pose(), self.env_config.robot_radius_m)
        return None

    def close(self):
        for scene in self._scenes.values():
            scene.camera.close()

    @property
    def main_world(self) -> World:
        """``env.world``'s World; ``self.world`` is the world of the episode now playing."""
        return self._main_scene.world

    # The episode's world and its MuJoCo model, data, robot and camera.
    world = property(lambda self: self._scene.world)
    model = property(lambda self: self._scene.model)
    data = property(lambda self: self._scene.data)
    robot = property(lambda self: self._scene.robot)
    camera = property(lambda self: self._scene.camera)

    # -- helpers ---------------------------------------------------------------------

    def _episode_jitter(self, options: dict) -> tuple[tuple[float, float] | None, bool]:
        """The start jitter of the episode being reset, and whether the caller chose it: the
        ``start_jitter`` option when given (None too: the caller asks for the exact pose), none
        for a start the caller fixes, the config's otherwise."""
        if "start_jitter" in options:
            return _start_jitter(options["start_jitter"]), True
        if "start_index" in options:
            return None, True
        return _start_jitter((self.env_config.start_jitter_m, self.env_config.start_jitter_deg)), False

    def _extra_scene(self, name: str) -> _Scene | None:
        """The scene of extra world ``name``, built on first use; None (and the world is dropped
        from the draw, with a warning) when it cannot be built: a training run goes on."""
        scene = self._scenes.get(name)
        if scene is None:
            try:
                world = load_world(name)
                scene = _Scene.build(world, self.env_config, self.sensor_config)
            except (WorldError, ValueError) as exc:
                log.warning("env.extra_worlds: dropping %r, which cannot be built (%s); its episodes "
                            "play %r", name, exc, self.main_world.name)
                self._extra_world_names = tuple(n for n in self._extra_world_names if n != name)
                return None
            self._scenes[name] = scene
            if self._noise_seed is not None:
                scene.camera.reseed(self._camera_seed(name))
        return scene

    def _camera_seed(self, name: str) -> int:
        """The depth-noise seed of world ``name`` after a seeded reset: the same whichever worlds
        were built before, so a seed replays the same episodes on a fresh or a used env."""
        if name == self.main_world.name:
            return self._noise_seed
        return int(np.random.default_rng([self._noise_seed, zlib.crc32(name.encode())]).integers(2**63))

    def _random_free_pose(self, tries: int = 50) -> tuple[float, float, float] | None:
        """Move the robot to a random pose ``random_start_clearance_m`` from every obstacle whose
        first image (kept in ``self._depth``) is above the collision threshold with a 10 cm
        margin; None when no such pose turns up (the caller then places the robot)."""
        grid, _, clear_cells = self._scene.free_space()
        if len(clear_cells) == 0:
            return None
        half = grid.resolution_m / 2
        for _ in range(tries):
            iy, ix = divmod(int(clear_cells[self.np_random.integers(len(clear_cells))]), grid.shape[1])
            cx, cy = grid.cell_to_world(ix, iy)
            pose = (float(cx + self.np_random.uniform(-half, half)), float(cy + self.np_random.uniform(-half, half)),
                    float(self.np_random.uniform(-math.pi, math.pi)))
            self.robot.set_pose(*pose)
            depth = self.camera.capture(self.data)
            if min_valid_depth(depth) >= self.env_config.collision_distance_m + START_DEPTH_MARGIN_M:
                self._depth = depth
                return pose
        return None

    def _jittered_start(self, index: int, jitter_m: float, jitter_deg: float) -> tuple[float, float, float]:
        """Move the robot to a clear pose drawn around start ``index`` (see the class docstring);
        its first image is left in ``self._depth``."""
        cfg = self.env_config
        start = self.world.starts[index]
        pose = self._clear_pose_near((start.x, start.y, start.yaw), jitter_m, jitter_deg, START_DRAW_TRIES)
        if pose is not None:
            return pose
        raise EnvError(f"start {index + 1} of world {self.world.name!r}: none of {START_DRAW_TRIES} poses drawn "
                       f"within ±{jitter_m:g} m and ±{jitter_deg:g}° of it keeps {cfg.robot_radius_m:g} m from "
                       f"obstacles with nothing in view nearer than "
                       f"{cfg.collision_distance_m + START_DEPTH_MARGIN_M:g} m")

    def _clear_pose_near(self, base: tuple[float, float, float], jitter_m: float, jitter_deg: float,
                         tries: int) -> tuple[float, float, float] | None:
        """Move the robot to a pose drawn within ±jitter_m in x and y and ±jitter_deg in heading of
        ``base`` that keeps the robot's radius from obstacles (map and contact) with nothing in view
        nearer than the collision distance plus a margin; its first image is left in
        ``self._depth``. None after ``tries`` draws (one, of the exact pose, without a jitter)."""
        cfg = self.env_config
        grid, fits, _ = self._scene.free_space()
        half_yaw = math.radians(jitter_deg)
        for _ in range(tries if jitter_m > 0 or jitter_deg > 0 else 1):
            dx, dy = self.np_random.uniform(-jitter_m, jitter_m, 2)
            pose = (float(base[0] + dx), float(base[1] + dy),
                    float(base[2] + self.np_random.uniform(-half_yaw, half_yaw)))
            ix, iy = grid.world_to_cell(pose[0], pose[1])
            if not grid.contains(ix, iy) or not fits[iy, ix]:
                continue
            self.robot.set_pose(*pose)
            if self.robot.touching_obstacle():
                continue
            depth = self.camera.capture(self.data)
            if min_valid_depth(depth) >= cfg.collision_distance_m + START_DEPTH_MARGIN_M:
                self._depth = depth
                return pose
        return None

    def _remember_failure(self) -> None:
        """Keep the poses the episode passed before its collision (``failure_start_prob``)."""
        before = tuple(self._recent_poses)[:-1]  # the last is the collision's own pose
        if before:
            self._failures.append((self.world.name, before))

    def _failure_start(self) -> tuple[float, float, float] | None:
        """Move the robot (and the episode's world) to a clear pose near one a remembered episode
        passed 1 to ``failure_start_back_steps`` steps before its collision; None when no draw is
        clear (the caller then picks the episode's world as without failure starts)."""
        cfg = self.env_config
        jitter = _start_jitter((cfg.start_jitter_m, cfg.start_jitter_deg)) or (0.0, 0.0)
        for _ in range(FAILURE_START_TRIES):  # a pose one step from the wall is often too near: draw again
            world_name, before = self._failures[int(self.np_random.integers(len(self._failures)))]
            base = before[-int(self.np_random.integers(1, len(before) + 1))]
            self._scene = self._scenes[world_name]
            pose = self._clear_pose_near(base, *jitter, tries=1)
            if pose is not None:
                return pose
        return None

    def _info(self, cause: str | None, min_depth: float) -> dict[str, Any]:
        x, y, yaw = self.robot.pose()
        return {
            "pose": (x, y, yaw),
            "world": self.world.name,
            "start_index": self._start_index,
            "random_start": self._random_start,
            "failure_start": self._failure_start_now,
            "collision_cause": cause,
            "min_depth_m": min_depth,
            "distance_from_start_m": math.hypot(x - self._start_xy[0], y - self._start_xy[1]),
            "path_length_m": self._path_length,
            "step": self._steps,
        }
