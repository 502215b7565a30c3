"""Typed, frozen configuration for every part of cogexplore.

Each section is a frozen dataclass whose fields are documented where they are
declared and validated in ``__post_init__``; a bad value raises
:class:`ConfigError` naming the section, the field and what is allowed.
A *preset* is a TOML file (``shared/presets/<name>.toml`` or any path) with one
table per section; fields left out keep the defaults below, which are the
paper's values wherever the paper gives one.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Mapping, get_type_hints

import tomllib

import numpy as np

from shared.errors import CogexploreError
from shared.files import read_regular_file

PRESET_DIR = Path(__file__).with_name("presets")
DEFAULT_PRESET = "robust-40x30"
"""The preset a run starts from when none is named (``up``, the services, docker compose): the shipped
model's recipe (shared/pretrained/MODEL_CARD.md)."""


class ConfigError(CogexploreError):
    """A configuration value is missing, of the wrong type or out of range."""


def _check(cond: bool, section: str, name: str, value: Any, allowed: str) -> None:
    if not cond:
        shown = repr(value)
        if len(shown) > 80:  # a number of thousands of digits is no one-line error
            shown = f"{shown[:60]}... ({len(shown)} characters)"
        raise ConfigError(f"[{section}] {name} = {shown} is invalid: {allowed}")


def is_whole(x: Any) -> bool:
    """An integer (numpy's too), and not a bool (TOML's ``true`` is Python's 1)."""
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


MAX_INT = 2**63 - 1
"""The largest integer a count, step or index may be: TOML's integers are 64-bit, and past this a
count divided by a float (``train.total_updates / train.replay_ratio``) overflows."""
MAX_SEED = 2**53 - 1
"""The largest ``train.seed``: an actor seeds with ``seed * 1000 + its index``, which must stay
below the 2**64 that torch.manual_seed takes, and 2**53 stays exact in a JSON reader's float."""
MAX_REWARD = 1e6
"""The largest magnitude of ``env.reward_move`` and ``env.reward_collision``: transitions carry
rewards in float32, where beyond 3.4e38 a reward is infinite, and a TD target of 1e6 / (1 - gamma)
is already far past any useful scale."""


def is_count(x: Any, minimum: int = 0) -> bool:
    """A whole number (:func:`is_whole`) in [``minimum``, :data:`MAX_INT`]."""
    return is_whole(x) and minimum <= x <= MAX_INT


def is_finite_number(x: Any) -> bool:
    """A finite int or float (numpy's too), not a bool; an integer too large for a float is not one."""
    if not isinstance(x, (int, float, np.integer, np.floating)) or isinstance(x, (bool, np.bool_)):
        return False
    try:
        return math.isfinite(x)
    except OverflowError:  # an int of hundreds of digits
        return False


# ---------------------------------------------------------------------------
# World, robot, sensor, environment
# ---------------------------------------------------------------------------

SPEED_TABLES: dict[str, tuple[tuple[float, ...], float]] = {
    # name: (angular velocities in rad/s for left, half-left, straight, half-right, right;
    #        linear velocity in m/s) -- the paper's Table "Speeds of different moving commands".
    "train": ((1.4, 0.7, 0.0, -0.7, -1.4), 0.32),
    "test": ((1.2, 0.6, 0.0, -0.6, -1.2), 0.25),
}
ACTION_NAMES: tuple[str, ...] = ("left", "half-left", "straight", "half-right", "right")
NUM_ACTIONS = len(ACTION_NAMES)
FAILURE_STARTS_KEPT = 200
"""Collisions an env remembers for ``EnvConfig.failure_start_prob`` (the newest; each with the poses
before it)."""
FAILURE_STARTS_BACK_MAX = 100
"""The largest ``EnvConfig.failure_start_back_steps``."""
MAX_ACTION_HISTORY = 8
"""The most previous commands a network may read (``ModelConfig.action_history``); replay and the
policies keep this many, so any network of the range can learn from and act on them."""
MAX_FRAME_STACK = 4
"""The most depth images a network may read per step (``ModelConfig.frame_stack``)."""
MAX_SHIFT_AUGMENT_PX = 8
"""The largest random shift of a frame in the learner's batches (``DQNConfig.shift_augment_px``)."""
MAX_QUANTILES = 200
"""The most return quantiles per command a network may give (``ModelConfig.quantiles``)."""


def mirror_action(action: Any) -> Any:
    """The command for the left-right mirrored image (left <-> right, half-left <-> half-right);
    works on ints, numpy arrays and tensors."""
    return (NUM_ACTIONS - 1) - action


ALL_COMMANDS_MASK = (1 << NUM_ACTIONS) - 1
"""A bitmask of commands (bit a: command a) with every command set."""


def commands_mask(flags: Any) -> int:
    """The bitmask (bit a: command a) of a (5,) bool array."""
    flags = np.asarray(flags, dtype=bool).reshape(NUM_ACTIONS)
    return int((flags.astype(np.int64) << np.arange(NUM_ACTIONS)).sum())


def mask_commands(masks: Any) -> np.ndarray:
    """(..., 5) bool: the commands set in each bitmask of ``masks`` (integers in 0..31)."""
    return (np.asarray(masks, dtype=np.int64)[..., None] >> np.arange(NUM_ACTIONS)) & 1 == 1


@dataclass(frozen=True)
class SensorConfig:
    """Kinect-like depth camera."""

    width: int = 160
    """Image width in pixels (Kinect depth downsampled as in the paper: 160)."""
    height: int = 120
    """Image height in pixels (120)."""
    hfov_deg: float = 57.0
    """Horizontal field of view in degrees (Kinect: 57)."""
    vfov_deg: float = 43.0
    """Vertical field of view in degrees (Kinect: 43)."""
    max_range_m: float = 4.0
    """Returns farther than this read 0, as the paper's Kinect images do."""
    min_range_m: float = 0.0
    """Returns nearer than this read 0 (a real Kinect is blind below ~0.5 m; 0 keeps the
    paper's 0.55 m collision rule observable)."""
    mount_height_m: float = 0.35
    """Camera height above the floor. Must exceed tan(vfov/2) * l_s (~0.22 m) or the floor
    itself would read nearer than the collision threshold."""
    mount_forward_m: float = 0.0
    """Camera offset ahead of the robot's centre along its heading (default: over the centre)."""
    backend: str = "raycast"
    """'raycast' (mujoco.mj_multiRay, no OpenGL, deterministic) or 'gl' (MuJoCo renderer;
    needs MUJOCO_GL=egl or osmesa)."""
    noise_std_m: float = 0.0
    """Standard deviation of additive Gaussian depth noise in metres (0 = off); with
    ``noise_quadratic_per_m`` the part that does not grow with distance."""
    noise_quadratic_per_m: float = 0.0
    """Growth of the depth noise with distance z: sigma(z) = noise_std_m + noise_quadratic_per_m *
    max(z - 0.4 m, 0)^2, a Kinect's axial noise model (Nguyen et al. 2012: 0.0012 m and
    0.0019 / m; ``shared.sim.sensor.KINECT_NOISE_OFFSET_M``); 0 = the same sigma at every distance."""
    dropout_prob: float = 0.0
    """Probability that a valid pixel reads 0 (dropped return), per pixel and frame."""

    def noise_free(self) -> "SensorConfig":
        """The camera itself, without noise or dropped returns: what a network's weights file
        describes (a run's training noise is a training condition; the test protocol adds its own)."""
        return replace(self, noise_std_m=0.0, noise_quadratic_per_m=0.0, dropout_prob=0.0)

    def __post_init__(self) -> None:
        s = "sensor"
        for name in ("width", "height"):
            v = getattr(self, name)
            _check(is_whole(v) and 8 <= v <= 1024, s, name, v,
                   "an integer in [8, 1024]")
        for name in ("hfov_deg", "vfov_deg"):
            v = getattr(self, name)
            _check(is_finite_number(v) and 1.0 <= v <= 170.0, s, name, v, "degrees in [1, 170]")
        _check(is_finite_number(self.max_range_m) and 0.1 <= self.max_range_m <= 100, s, "max_range_m",
               self.max_range_m, "metres in [0.1, 100]")
        _check(is_finite_number(self.min_range_m) and 0 <= self.min_range_m < self.max_range_m, s,
               "min_range_m", self.min_range_m, "metres in [0, max_range_m)")
        _check(is_finite_number(self.mount_height_m) and 0.01 <= self.mount_height_m <= 3.0, s,
               "mount_height_m", self.mount_height_m, "metres in [0.01, 3]")
        _check(is_finite_number(self.mount_forward_m) and abs(self.mount_forward_m) <= 1.0, s,
               "mount_forward_m", self.mount_forward_m, "metres in [-1, 1]")
        _check(self.backend in ("raycast", "gl"), s, "backend", self.backend, "'raycast' or 'gl'")
        _check(is_finite_number(self.noise_std_m) and 0 <= self.noise_std_m <= 1.0, s, "noise_std_m",
               self.noise_std_m, "metres in [0, 1]")
        _check(is_finite_number(self.noise_quadratic_per_m) and 0 <= self.noise_quadratic_per_m <= 1.0, s,
               "noise_quadratic_per_m", self.noise_quadratic_per_m, "a number in [0, 1] (metres per m^2)")
        _check(is_finite_number(self.dropout_prob) and 0 <= self.dropout_prob < 1.0, s, "dropout_prob",
               self.dropout_prob, "a probability in [0, 1)")


PROCEDURAL_PREFIX = "procedural:"
"""World names ``procedural:<seed>`` are generated layouts (shared.sim.world.procedural_world)."""


def parse_number(value: object, what: str, *, minimum: float = 0.0, strict: bool = False, unit: str = "") -> float:
    """``value`` (a number, or text read as one) as a finite float >= ``minimum`` (> with ``strict``);
    ConfigError naming ``what`` otherwise: a NaN time would never pass, a negative one always has.
    ``unit`` words the error ("of seconds")."""
    try:
        number = float(value) if not isinstance(value, bool) else math.nan  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        number = math.nan
    if not (math.isfinite(number) and (number > minimum if strict else number >= minimum)):
        words = f"a number {unit} " if unit else "a number "
        raise ConfigError(f"{what} must be {words}{'>' if strict else '>='} {minimum:g}, got {value!r}".lstrip())
    return number


def is_procedural_seed(text: str) -> bool:
    """Whether ``text`` is a procedural world's seed: decimal digits, at most 18 (a seed of
    thousands of digits is no layout, and Python refuses to read one)."""
    return text.isascii() and text.isdigit() and len(text) <= 18


MAX_WORLD_LIST = 10_000
"""Most world names ``parse_world_list`` expands a list to."""


def parse_world_list(text: str) -> tuple[str, ...]:
    """``"paper-indoor, procedural:1000-1003"`` -> the names, seed ranges expanded, in order and
    without repeats; a procedural seed is written without leading zeros (``procedural:007`` is
    ``procedural:7``, the name its World carries), so lists compare by world. Only the syntax is
    checked here: the worlds are built when first played."""
    names: dict[str, None] = {}
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        procedural = part.startswith(PROCEDURAL_PREFIX)
        first, dash, last = part.removeprefix(PROCEDURAL_PREFIX).partition("-")
        if procedural and not all(is_procedural_seed(t) for t in ((first, last) if dash else (first,))):
            raise ConfigError(f"{part!r}: use 'procedural:<seed>' or 'procedural:<first>-<last>', "
                             "seeds integers from 0 to 18 digits")
        if procedural and dash:
            if int(last) < int(first):
                raise ConfigError(f"{part!r}: the last seed is below the first")
            if int(last) - int(first) + 1 + len(names) > MAX_WORLD_LIST:
                raise ConfigError(f"{part!r}: more than {MAX_WORLD_LIST} worlds")
            names.update(dict.fromkeys(f"{PROCEDURAL_PREFIX}{seed}" for seed in range(int(first), int(last) + 1)))
        elif procedural:  # as a range writes it: 'procedural:0201' is the world 'procedural:201'
            names[f"{PROCEDURAL_PREFIX}{int(first)}"] = None
        else:
            names[part] = None
    return tuple(names)


NEW_AREA_CAP_M2 = 4.0
"""The most newly seen floor (m^2) one step is paid for (``EnvConfig.reward_new_area_per_m2``): a
turn of 0.6 rad in one 0.5 s step opens at most a 4.8 m^2 wedge of the 4 m, 57 degree view, and
almost every step opens far less; the cap bounds what any reward may be."""


@dataclass(frozen=True)
class EnvConfig:
    """The exploration task: world, robot motion, reward and episode end."""

    world: str = "paper-indoor"
    """A built-in world ('paper-indoor', 'corridor'), 'procedural:<seed>', or an MJCF path."""
    speed_table: str = "train"
    """'train' or 'test': the paper's two speed tables (see SPEED_TABLES)."""
    control_period_s: float = 0.5
    """Seconds each moving command is held before the next depth image. 0.5 s moves the robot
    16 cm (train) / 12.5 cm (test) per step: a 200-step test episode can then cover ~25 m of
    path, enough to cross the ~12 m reference world twice, while the 0.55 m threshold still
    leaves more than two steps of travel between detection and contact."""
    physics_timestep_s: float = 0.01
    """MuJoCo integration step; the control period must be a whole multiple of it."""
    robot_radius_m: float = 0.18
    """Radius of the TurtleBot-like disc body."""
    max_episode_steps: int = 500
    """Step cap; reaching it truncates the episode (never a termination). The test protocol
    uses 200."""
    collision_distance_m: float = 0.55
    """l_s: an episode ends in collision when the minimum valid depth falls below this."""
    reward_move: float = 1.0
    """r_move: reward for a collision-free move."""
    reward_collision: float = -100.0
    """r_ter: reward on collision (terminal)."""
    reward_new_area_per_m2: float = 0.0
    """A novelty term added to r_move: this much per m^2 of free floor the depth camera sees for
    the first time in the episode at the step (the evaluation's coverage measure,
    ``shared.sim.maps.CoverageTracker``; the first image's view is not paid, and a step pays for at
    most ``NEW_AREA_CAP_M2``). Exploration is the task, and r_move alone pays a robot circling in
    one room as much as one that opens up the world. 0 (the paper's reward) in the paper preset; a
    collision pays r_ter alone."""
    reward_trap_penalty: float = 0.0
    """Foresight in the training reward: a collision-free step that takes the robot from a pose
    with a way out to one without pays r_move less this. "A way out": the privileged map expert
    finds some command sequence that stays safe for ``trap_horizon_steps`` steps at the episode's
    speeds (``CommandExpert.has_way_out``; its check reads the world's map, the policy still reads
    only the depth image). The networks fail by entering a place with no way out a median of 11
    decisions before the wall (MODEL_CARD.md, "Where the gap is"), where r_ter, discounted by
    gamma = 0.85, weighs 17%; this charges the entry itself. Costs an actor about 2 ms a step. 0
    (the paper's reward) in every preset; a collision pays r_ter alone."""
    trap_horizon_steps: int = 16
    """Steps a way out must stay safe for (``reward_trap_penalty``; unused without it): 16 is 2.6 m
    at the training speed, beyond the 1.4 m (11 decisions) by which the networks typically enter a
    place too late. Longer finds traps further ahead and costs the actors more per step; the beam
    search is a lower bound, so a longer horizon also calls more tight places traps."""
    start_index: int | None = None
    """Start pose index; None draws one of the world's starts uniformly each episode."""
    random_start_prob: float = 0.0
    """Share of episodes (when no start index is fixed) that begin at a random free pose, uniform
    over the points at least ``random_start_clearance_m`` from every obstacle, with a random
    heading, instead of at one of the world's starts. Training from 12 poses only shows the
    network the few metres an ε-greedy episode reaches from them; random poses show it the whole
    world. 0 in the paper preset. The test protocol always uses the world's starts."""
    random_start_clearance_m: float = 0.6
    """Least distance (m) from a random start to any obstacle (the collision threshold l_s is
    also checked on the first image)."""
    failure_start_prob: float = 0.0
    """Share of episodes (when no start index is fixed) that begin where an earlier episode of
    this env went wrong: at the pose one of its last ``FAILURE_STARTS_KEPT`` collisions passed 1 to
    ``failure_start_back_steps`` steps (drawn uniformly) before the collision, in that episode's
    world, moved by the config's start jitter and checked clear as any start is (none clear: a
    usual start instead). The networks fail by entering a place with no way out a median of 11
    decisions before the wall (MODEL_CARD.md, "Where the gap is"); an episode from a random pose
    meets such a decision rarely, and one from where the network last chose wrong meets it at
    once, from a pose that is never the same twice. 0 (off) in every preset; drawn before
    ``random_start_prob`` and ``extra_world_prob``."""
    failure_start_back_steps: int = 20
    """The most steps before a collision a failure start goes back (``failure_start_prob``;
    unused without it): 20 is 3.2 m at the training speed, past the 1.4 m by which the networks
    typically enter a place too late."""
    extra_worlds: str = ""
    """More training worlds, comma-separated: names as in ``world``, and
    'procedural:<first>-<last>' for a range of procedural seeds. An episode that does not fix its
    start plays one of them, drawn uniformly, with probability ``extra_world_prob``, and ``world``
    otherwise. Keep the seeds used for evaluation (procedural 101-110, validation 201-210) out of
    the list."""
    extra_world_prob: float = 0.0
    """Share of episodes played in one of ``extra_worlds`` (0: always ``world``)."""
    start_jitter_m: float = 0.0
    """Training episodes that start at a named start pose (the config's ``start_index`` or a drawn
    one; not a random free pose, not a start the caller fixes with ``reset(options={"start_index":
    ...})``) start moved by a uniform draw within ±this (m) in x and in y, redrawn while the robot
    would touch or face an obstacle (``shared.sim.env.ExploreEnv``): a real robot is never placed
    to the millimetre, and the robust test protocol does not place it so either. A start with no
    clear draw is played from its exact pose, with a warning. At most 1 m; 0: the exact pose. The
    test protocol never inherits it (it sets its own jitter)."""
    start_jitter_deg: float = 0.0
    """Half-width (degrees, at most 45) of the uniform draw added to such a start's heading."""

    def __post_init__(self) -> None:
        s = "env"
        _check(isinstance(self.world, str) and self.world != "", s, "world", self.world,
               "a world name or MJCF path")
        _check(isinstance(self.speed_table, str) and self.speed_table in SPEED_TABLES, s, "speed_table",
               self.speed_table, f"one of {sorted(SPEED_TABLES)}")
        _check(is_finite_number(self.physics_timestep_s) and 1e-4 <= self.physics_timestep_s <= 0.05, s,
               "physics_timestep_s", self.physics_timestep_s, "seconds in [1e-4, 0.05]")
        _check(is_finite_number(self.control_period_s) and 0.01 <= self.control_period_s <= 5.0, s,
               "control_period_s", self.control_period_s, "seconds in [0.01, 5]")
        if is_finite_number(self.control_period_s) and is_finite_number(self.physics_timestep_s):
            ratio = self.control_period_s / self.physics_timestep_s
            _check(abs(ratio - round(ratio)) < 1e-6, s, "control_period_s", self.control_period_s,
                   f"a whole multiple of physics_timestep_s ({self.physics_timestep_s})")
        _check(is_finite_number(self.robot_radius_m) and 0.05 <= self.robot_radius_m <= 1.0, s,
               "robot_radius_m", self.robot_radius_m, "metres in [0.05, 1]")
        _check(is_count(self.max_episode_steps, 1), s,
               "max_episode_steps", self.max_episode_steps, "an integer in [1, 2**63)")
        _check(is_finite_number(self.collision_distance_m) and 0 < self.collision_distance_m < 10, s,
               "collision_distance_m", self.collision_distance_m, "metres in (0, 10)")
        for name in ("reward_move", "reward_collision"):
            v = getattr(self, name)
            _check(is_finite_number(v) and abs(v) <= MAX_REWARD, s, name, v,
                   f"a number in [-{MAX_REWARD:g}, {MAX_REWARD:g}]")
        _check(is_finite_number(self.reward_new_area_per_m2) and 0 <= self.reward_new_area_per_m2 <= 100, s,
               "reward_new_area_per_m2", self.reward_new_area_per_m2, "a number in [0, 100]")
        _check(is_finite_number(self.reward_trap_penalty) and 0 <= self.reward_trap_penalty <= 1000, s,
               "reward_trap_penalty", self.reward_trap_penalty, "a number in [0, 1000]")
        _check(is_whole(self.trap_horizon_steps)
               and 1 <= self.trap_horizon_steps <= 100, s,
               "trap_horizon_steps", self.trap_horizon_steps, "an integer in [1, 100]")
        _check(self.start_index is None or is_count(self.start_index),
               s, "start_index", self.start_index, "none (a start drawn each episode) or an integer in [0, 2**63)")
        _check(is_finite_number(self.random_start_prob) and 0 <= self.random_start_prob <= 1, s, "random_start_prob",
               self.random_start_prob, "a probability in [0, 1]")
        _check(is_finite_number(self.random_start_clearance_m) and 0 < self.random_start_clearance_m < 5, s,
               "random_start_clearance_m", self.random_start_clearance_m, "metres in (0, 5)")
        _check(is_finite_number(self.failure_start_prob) and 0 <= self.failure_start_prob <= 1, s, "failure_start_prob",
               self.failure_start_prob, "a probability in [0, 1]")
        _check(is_whole(self.failure_start_back_steps)
               and 1 <= self.failure_start_back_steps <= FAILURE_STARTS_BACK_MAX, s, "failure_start_back_steps",
               self.failure_start_back_steps, f"an integer in [1, {FAILURE_STARTS_BACK_MAX}]")
        _check(isinstance(self.extra_worlds, str), s, "extra_worlds", self.extra_worlds,
               "a comma-separated list of world names")
        try:
            names = parse_world_list(self.extra_worlds)
        except ValueError as exc:
            raise ConfigError(f"env.extra_worlds = {self.extra_worlds!r} is invalid: {exc}") from None
        _check(is_finite_number(self.extra_world_prob) and 0 <= self.extra_world_prob <= 1, s, "extra_world_prob",
               self.extra_world_prob, "a probability in [0, 1]")
        _check(self.extra_world_prob == 0 or names, s, "extra_world_prob", self.extra_world_prob,
               "0 while env.extra_worlds is empty")
        _check(is_finite_number(self.start_jitter_m) and 0 <= self.start_jitter_m <= 1, s, "start_jitter_m",
               self.start_jitter_m, "metres in [0, 1]")
        _check(is_finite_number(self.start_jitter_deg) and 0 <= self.start_jitter_deg <= 45, s, "start_jitter_deg",
               self.start_jitter_deg, "degrees in [0, 45]")

    @property
    def max_move_reward(self) -> float:
        """The most one collision-free step pays: r_move plus the novelty term for ``NEW_AREA_CAP_M2``."""
        return self.reward_move + self.reward_new_area_per_m2 * NEW_AREA_CAP_M2

    @property
    def min_move_reward(self) -> float:
        """The least one collision-free step pays: r_move less ``reward_trap_penalty``."""
        return self.reward_move - self.reward_trap_penalty

    def pays_for_a_move(self, reward: Any) -> Any:
        """Elementwise (numpy bool): whether ``reward`` is one this task pays for a collision-free
        step, in [``min_move_reward``, ``max_move_reward``], compared in float32 as transitions
        carry it."""
        import numpy as np

        r = np.asarray(reward, dtype=np.float32)
        return (r >= np.float32(self.min_move_reward)) & (r <= np.float32(self.max_move_reward))

    def pays(self, reward: Any) -> Any:
        """Elementwise (numpy bool): whether this task pays ``reward`` for some step, a move's or r_ter.
        What a learner checks an actor's rewards against: one finite but huge reward would make every
        TD target it reaches huge."""
        import numpy as np

        r = np.asarray(reward, dtype=np.float32)
        return self.pays_for_a_move(r) | (r == np.float32(self.reward_collision))

    def describe_rewards(self) -> str:
        """What :meth:`pays` accepts, for error messages."""
        move = f"{self.min_move_reward:g}"
        if self.max_move_reward > self.min_move_reward:
            move += f" to {self.max_move_reward:g}"
        return f"{move} per move and {self.reward_collision:g} for a collision"

    @property
    def extra_world_names(self) -> tuple[str, ...]:
        """``extra_worlds`` as a tuple of world names, seed ranges expanded."""
        return parse_world_list(self.extra_worlds)

    @property
    def substeps(self) -> int:
        """Physics steps per control period."""
        return int(round(self.control_period_s / self.physics_timestep_s))


# ---------------------------------------------------------------------------
# Learning: network, replay, update rule, exploration, training loop
# (owned by the learning core; see shared/learning/model.py, replay.py, dqn.py, policy.py)
# ---------------------------------------------------------------------------


DEPTH_ENCODINGS: tuple[str, ...] = ("metric", "inverse")
"""ModelConfig.depth_encoding values (shared.learning.model.encode_depth)."""
CONV_PRECISIONS: tuple[str, ...] = ("float32", "bfloat16", "auto")
"""``dqn.conv_precision`` values (shared.learning.model.conv_autocast_dtype)."""


@dataclass(frozen=True)
class ModelConfig:
    """The Q-network (paper: 3 conv + 3 fc)."""

    fc1: int = 512
    """Units of fc1 (the paper's figure does not state them; 512 as in DQN)."""
    fc2: int = 256
    """Units of fc2."""
    dropout: float = 0.5
    """Dropout after fc1 and fc2 in training (off in evaluation), as in the paper."""
    dueling: bool = False
    """Dueling head (value + advantage) instead of a plain fc3. Off in the paper preset."""
    depth_encoding: str = "metric"
    """How depth enters the conv layers. 'metric' (the paper's): depth / 4 m, so "no return"
    (beyond range) is 0, next to a wall at the collision distance (0.14). 'inverse':
    0.5 m / depth capped at 1, so near obstacles give large values, free space beyond range
    stays 0 and the input falls monotonically with distance (see shared.learning.model.encode_depth)."""
    previous_action: bool = False
    """fc1 also reads the previous moving command (one-hot; zeros at an episode's first step).
    One depth image does not show how the robot is turning: mid U-turn, facing a wall, the image
    is nearly symmetric and a single-frame policy flips between left and right. The command
    fixes the robot's motion over the last step (every command has the same linear speed), so
    it carries what a second frame would, at no image cost. Off in the paper preset."""
    action_history: int = 1
    """How many of the latest commands fc1 reads with ``previous_action`` (1: the last one; up to
    ``MAX_ACTION_HISTORY``), each as its own one-hot, most recent first. Before a dead end a policy
    that sees one command flips between left and right (a quarter of the shipped networks' collisions
    follow two or more turn reversals in eight steps); the last few commands show that it is
    flipping, and how long it has been turning."""
    frame_stack: int = 1
    """Depth images the network reads per step, as conv1's input channels: the current one, then
    the ones before it this episode, most recent first (at an episode's start the first image
    stands in for those not yet seen; up to ``MAX_FRAME_STACK``). The camera's 57 degrees show a
    wall beside the robot only until it turns: the images before the last turn still hold it.
    Replay rebuilds each stack from the episode chain and the policies remember their episode's
    images, so transitions on the wire stay one image each. 1 (the paper's one image) in every preset."""

    quantiles: int = 0
    """Return quantiles per command (QR-DQN, Dabney et al. 2018): fc3 gives each command N values,
    the quantiles at (2i + 1) / 2N of its discounted return, trained with the quantile Huber loss
    (``dqn.quantile_kappa``) towards the N quantiles of the target command's return. A policy acts
    on their mean, the Q-value, so everything that plays a network plays this one unchanged. A
    collision one step in five is one fifth of the quantiles, not a fifth of one mean: the
    distribution keeps the rare -100 that a mean smears. 0: one Q-value per command (the paper's,
    and every preset's). Not with ``dueling``."""

    def __post_init__(self) -> None:
        s = "model"
        for name in ("fc1", "fc2"):
            v = getattr(self, name)
            _check(is_whole(v) and 1 <= v <= 8192, s, name, v,
                   "an integer in [1, 8192]")
        _check(is_finite_number(self.dropout) and 0 <= self.dropout < 1, s, "dropout", self.dropout,
               "a probability in [0, 1)")
        _check(isinstance(self.dueling, bool), s, "dueling", self.dueling, "true or false")
        _check(isinstance(self.previous_action, bool), s, "previous_action", self.previous_action,
               "true or false")
        _check(is_whole(self.action_history)
               and 1 <= self.action_history <= MAX_ACTION_HISTORY, s, "action_history", self.action_history,
               f"an integer in [1, {MAX_ACTION_HISTORY}]")
        _check(self.action_history == 1 or self.previous_action, s, "action_history", self.action_history,
               "1 unless model.previous_action is on (the history is of previous commands)")
        _check(self.depth_encoding in DEPTH_ENCODINGS, s, "depth_encoding", self.depth_encoding,
               f"one of {', '.join(DEPTH_ENCODINGS)}")
        _check(is_whole(self.quantiles) and (self.quantiles == 0 or 2 <= self.quantiles <= MAX_QUANTILES), s,
               "quantiles", self.quantiles, f"0 (one Q-value per command) or an integer in [2, {MAX_QUANTILES}]")
        _check(self.quantiles == 0 or not self.dueling, s, "quantiles", self.quantiles,
               "0 with model.dueling (a quantile head has no value/advantage split)")
        _check(is_whole(self.frame_stack)
               and 1 <= self.frame_stack <= MAX_FRAME_STACK, s, "frame_stack", self.frame_stack,
               f"an integer in [1, {MAX_FRAME_STACK}]")


@dataclass(frozen=True)
class ReplayConfig:
    """Replay memory."""

    capacity: int = 3000
    """Transitions kept (paper: 3000)."""
    prioritized: bool = False
    """Proportional prioritised replay (Schaul et al.). Off in the paper preset."""
    priority_alpha: float = 0.6
    """Priority exponent alpha (prioritised replay only)."""
    priority_beta: float = 0.4
    """Importance-sampling exponent beta (prioritised replay only)."""

    def __post_init__(self) -> None:
        s = "replay"
        _check(is_whole(self.capacity)
               and 2 <= self.capacity <= 10_000_000, s, "capacity", self.capacity,
               "an integer in [2, 10000000]")
        _check(isinstance(self.prioritized, bool), s, "prioritized", self.prioritized, "true or false")
        _check(is_finite_number(self.priority_alpha) and 0 <= self.priority_alpha <= 1, s, "priority_alpha",
               self.priority_alpha, "a number in [0, 1]")
        _check(is_finite_number(self.priority_beta) and 0 <= self.priority_beta <= 1, s, "priority_beta",
               self.priority_beta, "a number in [0, 1]")


@dataclass(frozen=True)
class DQNConfig:
    """The update rule."""

    batch_size: int = 32
    """Transitions per update (paper: 32)."""
    gamma: float = 0.85
    """Discount factor (paper: 0.85)."""
    target_sync_every: int = 500
    """Copy theta into theta^- every this many updates (C)."""
    optimizer: str = "sgd"
    """'sgd' (paper: momentum SGD) or 'adam'."""
    lr: float = 1e-4
    """Learning rate of the fully connected layers (see shared/learning/dqn.py for the Caffe mapping)."""
    conv_lr_scale: float = 0.1
    """Learning rate of the conv layers as a fraction of lr (the paper trains them slower)."""
    lr_decay_updates: int = 0
    """Updates over which both learning rates fall linearly to ``lr_final_scale`` times their
    start, then stay (0: constant, the paper's). Smaller late steps are meant to steady the greedy
    policy, which swings from checkpoint to checkpoint at a constant rate."""
    lr_final_scale: float = 0.1
    """The learning rates after ``lr_decay_updates``, as a fraction of their start."""
    momentum: float = 0.99
    """SGD momentum (paper: 0.99)."""
    double_dqn: bool = False
    """Double DQN targets (argmax by theta, value by theta^-)."""
    n_step: int = 1
    """n-step returns (the robust preset's 3; 5 scored no higher there: run M1, MODEL_CARD.md)."""
    loss: str = "mse"
    """'mse' (paper) or 'huber' (slope 1 beyond an error of 1: meant for rewards clipped to +-1; on
    the unclipped -100 collision reward it fits close to a median and under-weights rare collisions).
    A ``model.quantiles`` network is trained with the quantile Huber loss instead, whatever this says."""
    quantile_kappa: float = 1.0
    """The quantile Huber loss's threshold (QR-DQN's kappa: 1): the error beyond which a quantile's
    pull stops growing (``model.quantiles`` networks only)."""
    grad_clip_norm: float = 0.0
    """Clip the gradient's global norm to this value (0 = off)."""
    mirror_augment: bool = False
    """Mirror a random half of each batch left-right (both frames flipped, left <-> right
    commands swapped): the task is symmetric, so every transition teaches its mirror image too."""
    shift_augment_px: int = 0
    """Shift each sampled frame (both frames of a transition, each by its own draw) by up to this
    many pixels in x and y, edges repeated (DrQ's random shift, Kostrikov et al. 2021): a camera
    mounted a few degrees off in yaw or pitch (a 40 x 30 pixel spans 1.4 degrees) sees the same
    room, so the Q-values should not hang on one pixel column. 0: off (the paper's, and every
    preset's: at 2 the robust recipe did not score above its unshifted runs; run D1, MODEL_CARD.md)."""
    demo_batch: int = 0
    """Demonstration transitions (``train.demos``) added to every batch, on top of
    ``batch_size`` from the replay memory (0: none, the paper's)."""
    demo_margin: float = 0.8
    """Large-margin loss on labelled samples (DQfD): demonstrations (shared.learning.demos) and
    transitions the expert labelled (``explore.expert_label_prob``). The labelled command's Q-value
    should lead every other command's by this much (DQfD: 0.8)."""
    demo_weight: float = 1.0
    """Weight of the large-margin loss against the TD loss (DQfD: 1; 0: demonstrations only add
    TD targets and expert labels are ignored)."""
    safe_margin: float = 1.0
    """Safe-set margin loss on transitions the map expert marked with the commands that keep a way
    out (``explore.safe_label_prob``): the best such command's Q-value should lead every command
    without one by this much (one step's reward, ``env.reward_move``: 1)."""
    safe_weight: float = 1.0
    """Weight of the safe-set margin loss against the TD loss (0: the marks are ignored). The loss is
    summed over a batch's marked samples and divided by the batch's size, so a marked sample weighs
    what one TD sample does, however few the marks."""
    conv_precision: str = "float32"
    """Number format of the conv layers' arithmetic in the learner's updates (forward, backward and
    the TD targets' forwards): 'float32'; 'bfloat16' (mixed precision: weights, optimiser and the
    fc layers stay float32, the convolutions, four fifths of an update's work, run in bfloat16,
    about 1.6x faster on a CPU with AVX512-BF16 or AMX and on recent GPUs); 'auto': bfloat16
    where the device computes it natively, float32 elsewhere (an emulated bfloat16 convolution is
    slower than float32). Acting and evaluation always run float32."""

    def __post_init__(self) -> None:
        s = "dqn"
        _check(is_whole(self.batch_size) and 1 <= self.batch_size <= 4096, s, "batch_size",
               self.batch_size, "an integer in [1, 4096]")
        _check(is_finite_number(self.gamma) and 0 <= self.gamma < 1, s, "gamma", self.gamma, "a number in [0, 1)")
        _check(is_count(self.target_sync_every, 1), s,
               "target_sync_every", self.target_sync_every, "an integer in [1, 2**63)")
        _check(self.optimizer in ("sgd", "adam"), s, "optimizer", self.optimizer, "'sgd' or 'adam'")
        _check(is_finite_number(self.lr) and 0 < self.lr <= 1, s, "lr", self.lr, "a number in (0, 1]")
        _check(is_finite_number(self.conv_lr_scale) and 0 <= self.conv_lr_scale <= 10, s, "conv_lr_scale",
               self.conv_lr_scale, "a number in [0, 10] (0 freezes the conv layers)")
        _check(is_count(self.lr_decay_updates), s, "lr_decay_updates",
               self.lr_decay_updates, "an integer in [0, 2**63) (0: constant learning rate)")
        _check(is_finite_number(self.lr_final_scale) and 0 < self.lr_final_scale <= 1, s, "lr_final_scale",
               self.lr_final_scale, "a number in (0, 1]")
        _check(is_finite_number(self.momentum) and 0 <= self.momentum < 1, s, "momentum", self.momentum,
               "a number in [0, 1)")
        _check(isinstance(self.double_dqn, bool), s, "double_dqn", self.double_dqn, "true or false")
        _check(is_whole(self.n_step) and 1 <= self.n_step <= 20, s, "n_step", self.n_step,
               "an integer in [1, 20]")
        _check(self.loss in ("mse", "huber"), s, "loss", self.loss, "'mse' or 'huber'")
        _check(is_finite_number(self.quantile_kappa) and 0 < self.quantile_kappa <= 1000, s, "quantile_kappa",
               self.quantile_kappa, "a number in (0, 1000]")
        _check(is_finite_number(self.grad_clip_norm) and self.grad_clip_norm >= 0, s, "grad_clip_norm",
               self.grad_clip_norm, "a number >= 0")
        _check(isinstance(self.mirror_augment, bool), s, "mirror_augment", self.mirror_augment, "true or false")
        _check(is_whole(self.shift_augment_px) and 0 <= self.shift_augment_px <= MAX_SHIFT_AUGMENT_PX, s,
               "shift_augment_px", self.shift_augment_px, f"an integer in [0, {MAX_SHIFT_AUGMENT_PX}]")
        _check(is_whole(self.demo_batch) and 0 <= self.demo_batch <= 4096, s, "demo_batch", self.demo_batch,
               "an integer in [0, 4096]")
        _check(is_finite_number(self.demo_margin) and 0 <= self.demo_margin <= 100, s, "demo_margin", self.demo_margin,
               "a number in [0, 100]")
        _check(is_finite_number(self.demo_weight) and 0 <= self.demo_weight <= 100, s, "demo_weight", self.demo_weight,
               "a number in [0, 100]")
        _check(is_finite_number(self.safe_margin) and 0 <= self.safe_margin <= 100, s, "safe_margin", self.safe_margin,
               "a number in [0, 100]")
        _check(is_finite_number(self.safe_weight) and 0 <= self.safe_weight <= 100, s, "safe_weight", self.safe_weight,
               "a number in [0, 100]")
        _check(self.conv_precision in CONV_PRECISIONS, s, "conv_precision", self.conv_precision,
               f"one of {', '.join(CONV_PRECISIONS)}")


@dataclass(frozen=True)
class ExploreConfig:
    """epsilon-greedy exploration."""

    eps_start: float = 1.0
    """epsilon at the first environment step."""
    eps_end: float = 0.1
    """epsilon after the decay."""
    eps_decay_steps: int = 10_000
    """Environment steps over which epsilon falls linearly from eps_start to eps_end."""
    per_actor: bool = False
    """Ape-X per-actor epsilon: actor i of N uses eps_base ** (1 + apex_alpha * i / (N - 1))."""
    apex_base: float = 0.4
    """Ape-X base epsilon."""
    apex_alpha: float = 7.0
    """Ape-X alpha."""
    expert_episode_prob: float = 0.0
    """Fraction of training episodes in which the privileged map expert
    (shared.expert.expert.CommandExpert, the supervised labels' source) chooses the non-random actions
    instead of the Q-network: demonstrations that reach the parts of the world an epsilon-greedy
    episode rarely does. The network still sees only depth; 0 is the paper's plain epsilon-greedy."""
    expert_label_prob: float = 0.0
    """Fraction of the actors' steps at which the privileged map expert also names its own command
    for the state the network acted in (from the true pose, which the network never sees). The
    label travels with the transition; the learner adds DQfD's large-margin loss on labelled samples
    (``dqn.demo_margin``, ``dqn.demo_weight``): the expert as a teacher at the states the network
    itself reaches (DAgger's states, "learning by cheating"). Costs the actor the expert's plan,
    ~1.8 ms a labelled step. 0: no labels, the paper's DQN (and the shipped recipe: on the actors'
    states one depth image barely shows what this expert decides, MODEL_CARD.md run ET2)."""
    safe_label_prob: float = 0.0
    """Fraction of the actors' steps at which the privileged map expert marks, for the state the
    network acted in, which of the five commands still has a way out: a plan starting with it that
    stays safe for ``env.trap_horizon_steps`` steps (CommandExpert.safe_commands). A mark is sent
    only where some commands have one and some have not; the learner adds a margin loss putting the
    best marked command above every unmarked one (``dqn.safe_margin``, ``dqn.safe_weight``). Unlike
    ``expert_label_prob`` it names no one command to copy, only the ones that enter a place with no
    way out, for all five commands at once where the trap charge (``env.reward_trap_penalty``)
    prices only the one taken. With the trap charge on, the expert's plans at the pose are already
    computed, so the mark is nearly free; without it ~1.5 ms a marked step. 0: none (the paper's, and
    every preset's: on the charged recipe it did not lift a network, MODEL_CARD.md run SM1)."""

    def __post_init__(self) -> None:
        s = "explore"
        for name in ("eps_start", "eps_end", "apex_base", "expert_episode_prob", "expert_label_prob",
                     "safe_label_prob"):
            v = getattr(self, name)
            _check(is_finite_number(v) and 0 <= v <= 1, s, name, v, "a probability in [0, 1]")
        _check(is_count(self.eps_decay_steps), s,
               "eps_decay_steps", self.eps_decay_steps, "an integer in [0, 2**63)")
        _check(isinstance(self.per_actor, bool), s, "per_actor", self.per_actor, "true or false")
        # An epsilon that rises as training goes on is almost surely the two swapped; the schedule is
        # not run with per_actor, nor with no decay (eps_end from the first step).
        _check(self.per_actor or self.eps_decay_steps == 0 or self.eps_end <= self.eps_start, s, "eps_end",
               self.eps_end, f"at most eps_start ({self.eps_start:g}): epsilon falls from eps_start to eps_end")
        _check(is_finite_number(self.apex_alpha) and self.apex_alpha >= 0, s, "apex_alpha", self.apex_alpha,
               "a number >= 0")


@dataclass(frozen=True)
class TrainConfig:
    """The training loop (single-process trainer and learner service)."""

    total_updates: int = 40_000
    """Stop after this many gradient updates (paper's longest model: 40000)."""
    warmup_transitions: int = 500
    """Transitions collected before the first update."""
    replay_ratio: float = 1.0
    """Updates per inserted transition (the paper's Algorithm 1: 1)."""
    checkpoint_every: int = 1000
    """Updates between checkpoints."""
    keep_checkpoints: int = 3
    """How many of the newest checkpoints stay on disk (raise it to evaluate a learning curve
    afterwards: each one holds weights, target weights and optimiser state; the replay memory,
    the bulk of the bytes, stays with the newest two only)."""
    log_every: int = 50
    """Updates between log rows."""
    seed: int = 0
    """Seed of every random generator in the run."""
    device: str = "auto"
    """'auto' (CUDA when present), 'cpu', 'cuda' or 'cuda:<n>'."""
    init_conv_from: str = ""
    """A supervised model file (``cogexplore pretrain``) whose conv layers initialise the
    Q-network when a run starts fresh (the paper's transfer); 'pretrained:sl' = the shipped one
    (80 x 60 images); '' = random initialisation. A resumed run keeps its checkpoint's weights."""
    init_from: str = ""
    """Fine-tuning: a Q-network weights file (``cogexplore model export``) or 'pretrained' (the
    shipped DRL model) whose weights initialise the whole network, online and target, when a run
    starts fresh; its architecture and image must be the run's. '' = no such start. When set,
    ``init_conv_from`` is not used (these weights include the conv layers). A resumed run keeps
    its checkpoint's weights."""

    demos: str = ""
    """Planner demonstration files (``cogexplore worlds demo``, .npz), comma-separated, or
    'pretrained:demos' (the shipped ones, paper-indoor): their transitions stay in the learner
    for good and ``dqn.demo_batch`` of them join every batch (shared/learning/demos.py). '' = none. Needs
    ``dqn.demo_batch`` > 0."""

    def __post_init__(self) -> None:
        s = "train"
        for name in ("total_updates", "warmup_transitions", "checkpoint_every", "keep_checkpoints", "log_every"):
            v = getattr(self, name)
            _check(is_count(v), s, name, v, "an integer in [0, 2**63)")
        _check(self.keep_checkpoints >= 1, s, "keep_checkpoints", self.keep_checkpoints, "an integer >= 1")
        _check(self.checkpoint_every >= 1 and self.log_every >= 1, s, "checkpoint_every/log_every",
               (self.checkpoint_every, self.log_every), "integers >= 1")
        _check(is_whole(self.seed) and 0 <= self.seed <= MAX_SEED, s, "seed", self.seed,
               f"an integer in [0, {MAX_SEED}] (2**53 - 1)")
        _check(is_finite_number(self.replay_ratio) and 0 < self.replay_ratio <= 64, s, "replay_ratio",
               self.replay_ratio, "a number in (0, 64]")
        # the learner asks for total_updates / replay_ratio transitions: an infinite count is a crash
        _check(math.isfinite(self.total_updates / self.replay_ratio), s, "replay_ratio", self.replay_ratio,
               f"large enough that total_updates ({self.total_updates}) / replay_ratio is a finite number")
        cuda_index = self.device.removeprefix("cuda:") if isinstance(self.device, str) else ""
        _check(isinstance(self.device, str) and (self.device in ("auto", "cpu", "cuda") or (
               self.device.startswith("cuda:") and cuda_index.isascii() and cuda_index.isdigit())),
               s, "device", self.device, "'auto', 'cpu', 'cuda' or 'cuda:<n>'")
        _check(isinstance(self.init_conv_from, str) and (self.init_conv_from in ("", "pretrained:sl") or (
               self.init_conv_from.strip() == self.init_conv_from and self.init_conv_from.endswith(".safetensors"))),
               s, "init_conv_from", self.init_conv_from,
               "'' (random conv layers), 'pretrained:sl' or the path of a supervised model .safetensors file")
        _check(isinstance(self.init_from, str) and (self.init_from in ("", "pretrained", "pretrained:drl") or (
               self.init_from.strip() == self.init_from and self.init_from.endswith(".safetensors"))),
               s, "init_from", self.init_from,
               "'', 'pretrained' or the path of a Q-network weights .safetensors file (`cogexplore model export`)")
        _check(isinstance(self.demos, str) and all(p.endswith(".npz") or p == "pretrained:demos"
                                                   for p in self.demo_paths), s, "demos", self.demos,
               "'' or comma-separated .npz demonstration files (`cogexplore worlds demo`) or 'pretrained:demos'")

    @property
    def demo_paths(self) -> tuple[str, ...]:
        """``demos`` as a tuple of paths."""
        return tuple(p.strip() for p in self.demos.split(",") if p.strip())


# ---------------------------------------------------------------------------
# The whole run
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class RunConfig:
    """Everything a run needs; one TOML table per section."""

    sensor: SensorConfig = field(default_factory=SensorConfig)
    env: EnvConfig = field(default_factory=EnvConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    dqn: DQNConfig = field(default_factory=DQNConfig)
    explore: ExploreConfig = field(default_factory=ExploreConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        _check(bool(self.train.demo_paths) == (self.dqn.demo_batch > 0), "dqn", "demo_batch", self.dqn.demo_batch,
               "> 0 exactly when train.demos names demonstration files")

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return dataclasses.asdict(self)

    def with_overrides(self, overrides: Mapping[str, Any]) -> "RunConfig":
        """Apply ``{"section.field": value}`` overrides (e.g. from ``--set dqn.lr=1e-3``)."""
        nested: dict[str, dict[str, Any]] = {}
        for key, value in overrides.items():
            section, _, name = key.partition(".")
            if not name:
                raise ConfigError(f"override {key!r} must look like 'section.field'")
            nested.setdefault(section, {})[name] = value
        return from_dict(nested, base=self)


_SECTIONS: dict[str, type] = {f.name: f.default_factory().__class__ for f in fields(RunConfig)}  # type: ignore[misc]


def _is_utf8(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def section_from_dict(cls: type, data: Mapping[str, Any], base: Any, section: str) -> Any:
    """``base`` (a config section of type ``cls``) with the fields in ``data`` over it, as a preset's
    ``[section]`` is read: ConfigError for an unknown field or a value of the wrong type."""
    hints = get_type_hints(cls)
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ConfigError(f"[{section}] unknown field(s) {unknown}; known: {sorted(known)}")
    values = {}
    for name, value in data.items():
        hint = hints[name]
        # TOML has no None and no int/float distinction the user cares about.
        if hint in (float, "float") and is_whole(value) and is_finite_number(value):  # too large: the check says so
            value = float(value)
        if value == "none" and "None" in str(hint):
            value = None
        # a lone surrogate (an undecodable byte of argv) has no UTF-8: the run's config.toml could not be saved
        _check(not isinstance(value, str) or _is_utf8(value), section, name, value,
               "text in UTF-8 (an undecodable byte on the command line?)")
        values[name] = value
    try:
        return replace(base, **values)
    except TypeError as exc:  # pragma: no cover - replace() only fails on unknown names
        raise ConfigError(f"[{section}] {exc}") from None


def from_dict(data: Mapping[str, Any], base: RunConfig | None = None) -> RunConfig:
    """Build a RunConfig from nested mappings, validating every section."""
    base = base or RunConfig()
    if not isinstance(data, Mapping):
        raise ConfigError(f"a config must be a table of sections, got {type(data).__name__}")
    unknown = sorted(set(data) - set(_SECTIONS))
    if unknown:
        raise ConfigError(f"unknown section(s) {unknown}; known: {sorted(_SECTIONS)}")
    sections = {}
    for name in _SECTIONS:
        part = data.get(name, {})
        if not isinstance(part, Mapping):
            raise ConfigError(f"[{name}] must be a table, got {type(part).__name__}")
        sections[name] = section_from_dict(_SECTIONS[name], part, getattr(base, name), name)
    return RunConfig(**sections)


def preset_names() -> list[str]:
    return sorted(p.stem for p in PRESET_DIR.glob("*.toml"))


def load_preset(name_or_path: str | Path, *, complete: bool = False) -> RunConfig:
    """Load a preset by name (``paper``, ``fast``, ...) or from a TOML file path. ``complete`` (a
    run's saved ``config.toml``, which names every section): a missing section is an error, not its
    defaults; such a file was cut short."""
    path = Path(name_or_path)
    if not path.suffix:
        path = PRESET_DIR / f"{name_or_path}.toml"
        if not path.exists():
            raise ConfigError(f"unknown preset {str(name_or_path)!r}; known: {preset_names()}")
    try:
        data = tomllib.loads(read_regular_file(path).decode())
    except FileNotFoundError:
        raise ConfigError(f"preset file {path} does not exist") from None
    except OSError as exc:  # a folder, no permission
        raise ConfigError(f"preset file {path} cannot be read: {exc.strerror or exc}") from None
    except (ValueError, RecursionError) as exc:  # bad TOML, bad UTF-8, nesting deep enough to exhaust the parser
        reason = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise ConfigError(f"preset file {path} is not valid TOML: {reason}") from None
    missing = [name for name in _SECTIONS if name not in data] if complete else []
    if missing:
        raise ConfigError(f"{path} lacks section(s) {missing}: cut short? A run's saved config names every "
                          "section; restore it, or start the run over")
    try:
        return from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


_TOML_ESCAPES = {"\\": "\\\\", '"': '\\"', "\n": "\\n", "\r": "\\r"}


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        # TOML's basic strings hold no control character but tab: a newline written as it is would
        # make the saved config.toml unreadable
        return '"' + "".join(_TOML_ESCAPES.get(c, c if c == "\t" or (c >= " " and c != "\x7f")
                                               else f"\\u{ord(c):04x}") for c in value) + '"'
    raise ConfigError(f"cannot write {value!r} to TOML")


def to_toml(cfg: RunConfig) -> str:
    """The whole config as TOML that ``load_preset`` reads back to an equal RunConfig
    (None values are left out: they are the defaults)."""
    lines: list[str] = []
    for section, values in cfg.to_dict().items():
        lines.append(f"[{section}]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in values.items() if v is not None]
        lines.append("")
    return "\n".join(lines)


def parse_override(text: str) -> tuple[str, Any]:
    """Parse ``section.field=value`` with a TOML value (bare words are strings, without the spaces
    around them: ``dqn.optimizer = adam`` is ``"adam"``)."""
    key, sep, raw = text.partition("=")
    if not sep:
        raise ConfigError(f"override {text!r} must look like section.field=value")
    try:
        parsed = tomllib.loads(f"v = {raw}")
        value = parsed["v"] if parsed.keys() == {"v"} else raw.strip()  # 'v = 1\nx = 2' is no one value
    except (ValueError, RecursionError):  # not a TOML value (an integer of thousands of digits neither): the text
        value = raw.strip()
    return key.strip(), value


# ---------------------------------------------------------------------------
# What every process of a run must share with its learner
# ---------------------------------------------------------------------------

ROBOT_FIELDS: tuple[str, ...] = (
    "env.speed_table", "env.control_period_s", "env.physics_timestep_s", "env.robot_radius_m",
    "env.collision_distance_m",
)
"""The robot a network was trained to drive: its moves and what counts as a collision. Networks
joined into one model (an ensemble, a mean of weights) must share it; their rewards may differ."""

MUST_MATCH_FIELDS: tuple[str, ...] = (
    "sensor.width", "sensor.height", "sensor.hfov_deg", "sensor.vfov_deg", "sensor.max_range_m",
    "sensor.min_range_m", "sensor.mount_height_m", "sensor.mount_forward_m",
    "model.fc1", "model.fc2", "model.dueling", "model.depth_encoding", "model.previous_action",
    "model.action_history", "model.quantiles",
    *ROBOT_FIELDS, "env.reward_move", "env.reward_collision", "env.reward_new_area_per_m2",
    "env.reward_trap_penalty", "env.trap_horizon_steps",
)
"""The fields an actor's or the evaluator's configuration must share with its run's learner: what a
depth image is (the sensor; its backend agrees to 2 cm, and noise is an actor's to add), the network
that reads it (the architecture; dropout acts in training only) and what a transition means (the
robot's motion, the reward and the collision rule). The rest is a process's own (its worlds and
starts and the starts' jitter, step cap, exploration, seed, device) or the learner's alone (replay
and the update rule: n-step returns and the discount are applied by the learner to the raw rewards
it receives)."""


class ConfigMismatchError(ConfigError):
    """A process's configuration differs from its run's in a field the run's data depends on."""


def config_differences(mine: RunConfig, run: RunConfig) -> list[tuple[str, Any, Any]]:
    """``(field, mine, the run's)`` for each of :data:`MUST_MATCH_FIELDS` that differs, in that order."""
    differences = []
    for name in MUST_MATCH_FIELDS:
        section, _, attr = name.partition(".")
        a, b = getattr(getattr(mine, section), attr), getattr(getattr(run, section), attr)
        if a != b:
            differences.append((name, a, b))
    return differences


def require_same_run(mine: RunConfig, run: RunConfig, *, who: str = "this process", source: str = "",
                     hint: str = "") -> None:
    """Raise :class:`ConfigMismatchError` unless ``mine`` agrees with ``run`` in every field of
    :data:`MUST_MATCH_FIELDS`: one line naming the first difference (and the others' names), where
    the run's configuration came from (``source``) and what to do (``hint``)."""
    differences = config_differences(mine, run)
    if not differences:
        return
    name, a, b = differences[0]
    others = [d[0] for d in differences[1:]]
    notes = ([source] if source else []) + (
        [f"also differ: {', '.join(others[:4])}{f' and {len(others) - 4} more' if len(others) > 4 else ''}"]
        if others else [])
    raise ConfigMismatchError(f"{who}'s {name}={_shown(a)} differs from the run's {_shown(b)}"
                              + (f" ({'; '.join(notes)})" if notes else "") + (f"; {hint}" if hint else ""))


def _shown(value: Any) -> str:
    return "none" if value is None else _toml_value(value)
