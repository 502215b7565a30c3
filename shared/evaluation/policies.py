"""Policies the evaluator can run: the learned greedy policy and the baselines.

Every policy is a callable ``policy(depth_m) -> (action, scores or None)`` as
``results.run_protocol`` wants it, with ``depth_m`` a float32 (H, W) image in metres
(0 = no return) and ``action`` an index into ``shared.config.ACTION_NAMES``. A policy with
memory across steps also has ``reset()``, which the protocol calls at each episode's start; one
that draws random numbers has ``seed_episode(seed)``, which the protocol calls before each episode
with its reset seed.

- ``greedy``: argmax of a QNetwork's Q-values, dropout off (the paper's test protocol); a
  ``QEnsemble`` plays the same way, on the mean of its networks' Q-values.
- ``sl``: the supervised model (the authors' IROS 2016 baseline, ``shared.expert``): argmax
  of its five class scores; the softmax probabilities are returned as the scores.
- ``rl``: the authors' RCAR 2016 Q-learning baseline: greedy on a DQN checkpoint whose conv
  layers were copied from the supervised model and frozen (``train.init_conv_from`` + ``dqn.
  conv_lr_scale = 0``), only the fully connected layers trained. The same computation as
  ``greedy``; the name labels it.
- ``random``: a uniformly random command from a seeded generator, reseeded per episode.
- ``reactive``: a non-learned obstacle avoider in the spirit of vector-field histograms
  (VFH, Borenstein & Koren 1991): the image columns are split into five sectors, one per
  command (column 0 is the leftmost, like command 0 = left); each sector is scored by how
  much of it is free beyond a clearance and how deep it is, and the best sector's command
  is taken. Deterministic: the same image always gives the same command.

``make_policy(name, ...)`` builds one by name.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from shared.config import NUM_ACTIONS, EnvConfig, SensorConfig, is_whole
from shared.evaluation import POLICY_NAMES
from shared.learning.policy import PolicyError

PolicyFn = Callable[[np.ndarray], tuple[int, Sequence[float] | np.ndarray | None]]


def _check_depth(depth_m: Any, sensor_cfg: SensorConfig | None) -> np.ndarray:
    depth = np.asarray(depth_m)
    if depth.ndim != 2:
        raise PolicyError(f"depth_m must be one (H, W) image, got shape {depth.shape}")
    if sensor_cfg is not None and depth.shape != (sensor_cfg.height, sensor_cfg.width):
        raise PolicyError(f"depth_m is {depth.shape}, the sensor gives ({sensor_cfg.height}, {sensor_cfg.width})")
    return depth


class GreedyPolicy:
    """Argmax of a Q-network's values (eval mode: dropout off); returns the Q-values too.
    Remembers its last command for a ``model.previous_action`` network (a ``QEnsemble`` feeds it
    to every member)."""

    name = "greedy"

    def __init__(self, net: Any):
        from shared.learning.policy import EpsilonGreedyPolicy

        self.net = net
        self.policy = EpsilonGreedyPolicy(net)  # no schedule: greedy, with the actors' memory

    def reset(self) -> None:
        self.policy.reset()

    def __call__(self, depth_m: np.ndarray) -> tuple[int, np.ndarray]:
        # argmax takes the first maximum: ties (a fresh net rarely has any) break toward "left".
        # NonFiniteQValues: broken weights are not scored as if they had chosen command 0
        choice = self.policy.greedy(_check_depth(depth_m, self.net.sensor_cfg))
        return choice.action, choice.q_values


class RLPolicy(GreedyPolicy):
    """Greedy on a frozen-conv Q-learning checkpoint (the RL baseline): only the name differs."""

    name = "rl"


class SupervisedPolicy:
    """Argmax of the supervised model's class scores (eval mode); returns the softmax
    probabilities as the scores."""

    name = "sl"

    def __init__(self, net: Any):
        from shared.learning.model import SupervisedNet

        if not isinstance(net, SupervisedNet):
            raise PolicyError(f"the sl policy needs a SupervisedNet, got {type(net).__name__}")
        self.net = net.eval()

    def __call__(self, depth_m: np.ndarray) -> tuple[int, np.ndarray]:
        import torch

        from shared.learning.model import preprocess_depth

        depth = _check_depth(depth_m, self.net.sensor_cfg)
        with torch.inference_mode():
            logits = self.net(preprocess_depth(depth, next(self.net.parameters()).device))
            probs = torch.softmax(logits.float(), dim=1)[0].cpu().numpy()
        return int(np.argmax(probs)), probs


class RandomPolicy:
    """A uniformly random command; the generator is seeded, so a protocol run repeats. Under the
    protocol each episode draws from (``seed``, the episode's reset seed) alone
    (:meth:`seed_episode`), so an episode is the same whatever ran before it: a subset of the
    starts, another world or protocol first, a reused policy object (``cogexplore report``)."""

    name = "random"
    DRAWS = "per-episode"
    """How its commands are drawn, as results record it (``random_draws``): a results file without it
    holds episodes of the draws before, one stream for the whole run."""

    def __init__(self, seed: int = 0):
        if not is_whole(seed) or seed < 0:  # numpy's own refusal is a traceback
            raise PolicyError(f"the random policy's seed must be an integer >= 0, got {seed!r}")
        self.seed = seed
        self.rng = np.random.default_rng(seed)

    def seed_episode(self, episode_seed: int) -> None:
        """Draw the next episode's commands from (``seed``, ``episode_seed``) (the protocol calls it
        before each episode). Not ``episode_seed`` alone: that is the env's stream (start jitter)."""
        self.rng = np.random.default_rng([self.seed, int(episode_seed)])

    def __call__(self, depth_m: np.ndarray) -> tuple[int, None]:
        return int(self.rng.integers(NUM_ACTIONS)), None


class ReactivePolicy:
    """Five-sector free-space avoider (see the module docstring).

    Obstacles: per image column the nearest return that is not the floor (the floor's axial
    depth on each row below the horizon is known from the camera height; a pixel at least
    ``floor_margin`` nearer than it is an obstacle, which also catches low obstacles a
    horizon scan would miss). Each column's obstacle becomes a point in the robot frame.

    Score of command ``a`` (heading change ``turn_rad[a]`` over one step):

    - *free depth*: how far a corridor of half-width ``corridor_m`` along the new heading is
      free of obstacle points (capped at ``lookahead_m``), over ``lookahead_m``. The corridor
      is wider than the robot because the task ends an episode when anything in view comes
      nearer than 0.55 m, so passing an obstacle needs about 0.3 m of lateral room;
    - *free width*: the fraction of the command's sector of columns (the image split in five,
      column 0 leftmost like command 0 = left) whose obstacle lies beyond ``clearance_m``,
      and the sector's mean obstacle depth over the maximum range, each weighted by
      ``sector_weight``;
    - a small preference for straight, then the half turns, so that an open corridor is
      followed rather than spun in.

    When none of the three middle commands has ``danger_m`` of free corridor ahead, the full
    turn toward the more open half of the image wins outright. The defaults were picked on
    paper-indoor (one episode per start, 200 steps): about 40 mean moving steps against
    about 8 for the random policy.

    The best command wins (ties to the lower index). The scores are returned with it; the
    recorder plots them where a network's Q-values would be.
    """

    name = "reactive"
    PREFERENCE: tuple[float, ...] = (0.0, 0.01, 0.02, 0.01, 0.0)
    DANGER_BONUS = 10.0  # more than any score can otherwise reach

    def __init__(self, sensor_cfg: SensorConfig | None = None, turn_rad: Sequence[float] | None = None,
                 corridor_m: float = 0.3, lookahead_m: float = 2.5, clearance_m: float = 1.0,
                 sector_weight: float = 0.25, floor_margin: float = 0.1, danger_m: float = 0.9):
        for name, v in (("corridor_m", corridor_m), ("lookahead_m", lookahead_m), ("clearance_m", clearance_m),
                        ("danger_m", danger_m)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise PolicyError(f"{name} must be a positive number of metres, got {v!r}")
        if not (isinstance(sector_weight, (int, float)) and math.isfinite(sector_weight) and sector_weight >= 0):
            raise PolicyError(f"sector_weight must be a number >= 0, got {sector_weight!r}")
        if not (isinstance(floor_margin, (int, float)) and 0 <= floor_margin < 1):
            raise PolicyError(f"floor_margin must be in [0, 1), got {floor_margin!r}")
        if turn_rad is None:
            from shared.config import SPEED_TABLES, EnvConfig

            turn_rad = [w * EnvConfig().control_period_s for w in SPEED_TABLES["test"][0]]
        if len(turn_rad) != NUM_ACTIONS or not all(math.isfinite(float(t)) for t in turn_rad):
            raise PolicyError(f"turn_rad must hold {NUM_ACTIONS} finite angles, got {turn_rad!r}")
        self.sensor_cfg = cfg = sensor_cfg or SensorConfig()
        self.corridor_m = float(corridor_m)
        self.lookahead_m = float(lookahead_m)
        self.clearance_m = float(clearance_m)
        self.sector_weight = float(sector_weight)
        self.danger_m = float(danger_m)
        fy = (cfg.height / 2) / math.tan(math.radians(cfg.vfov_deg) / 2)
        up = (cfg.height / 2 - (np.arange(cfg.height) + 0.5)) / fy
        with np.errstate(divide="ignore"):
            floor = np.where(up < 0, cfg.mount_height_m / -up, np.inf)
        # Anything nearer than this on a row is not floor (inf above the horizon: all of it).
        self._obstacle_below = ((1.0 - floor_margin) * floor)[:, None]
        fx = (cfg.width / 2) / math.tan(math.radians(cfg.hfov_deg) / 2)
        self._lateral_per_m = (cfg.width / 2 - (np.arange(cfg.width) + 0.5)) / fx  # y / x, left positive
        self._headings = np.array([[math.cos(t), math.sin(t)] for t in turn_rad])
        # Sector s covers columns bounds[s]:bounds[s + 1]; column 0 is the leftmost (left turn).
        self._bounds = np.linspace(0, cfg.width, NUM_ACTIONS + 1).round().astype(int)

    def column_depth(self, depth_m: np.ndarray) -> np.ndarray:
        """(W,) nearest non-floor depth per column, inf where there is none in range."""
        depth = _check_depth(depth_m, self.sensor_cfg).astype(np.float64)
        obstacle = (depth > 0) & (depth < self._obstacle_below)
        return np.where(obstacle, depth, np.inf).min(axis=0)

    def scores(self, depth_m: np.ndarray) -> np.ndarray:
        """(5,) command scores, left to right."""
        col = self.column_depth(depth_m)
        free = np.empty(NUM_ACTIONS)
        seen = np.isfinite(col)
        points = np.stack([col[seen], col[seen] * self._lateral_per_m[seen]], axis=1)  # (N, 2) x fwd, y left
        capped = np.minimum(col, self.sensor_cfg.max_range_m)
        out = np.empty(NUM_ACTIONS)
        for a in range(NUM_ACTIONS):
            ux, uy = self._headings[a]
            along = points[:, 0] * ux + points[:, 1] * uy
            perp = np.abs(points[:, 0] * uy - points[:, 1] * ux)
            blocking = along[(perp < self.corridor_m) & (along > 0)]
            free[a] = min(float(blocking.min()) if blocking.size else math.inf, self.lookahead_m)
            part = capped[self._bounds[a]:self._bounds[a + 1]]
            width = float(np.mean(part > self.clearance_m)) + float(part.mean()) / self.sensor_cfg.max_range_m
            out[a] = free[a] / self.lookahead_m + self.sector_weight * width + self.PREFERENCE[a]
        if free[1:4].max() < self.danger_m:
            # Boxed in ahead: creeping forward only gets nearer, so turn hard toward the
            # more open half of the view.
            half = len(capped) // 2
            left = float(capped[:half].mean()) >= float(capped[half:].mean())
            out[0 if left else NUM_ACTIONS - 1] += self.DANGER_BONUS
        return out

    def __call__(self, depth_m: np.ndarray) -> tuple[int, np.ndarray]:
        s = self.scores(depth_m)
        return int(np.argmax(s)), s


class ExpertsByWorld:
    """The privileged map expert of each world a protocol plays, built when first asked for, at the
    protocol's speeds (``env_cfg``'s robot with the test speed table)."""

    def __init__(self, sensor_cfg: SensorConfig | None = None, env_cfg: EnvConfig | None = None):
        self.sensor_cfg = sensor_cfg or SensorConfig()
        self.env_cfg = dataclasses.replace(env_cfg or EnvConfig(), speed_table="test")
        self._experts: dict[str, Any] = {}

    def __call__(self, info: Mapping[str, Any] | None, who: str) -> tuple[Any, tuple[float, float, float]]:
        """(the expert of ``info``'s world, the pose in ``info``); PolicyError naming ``who`` without them."""
        if not info or "pose" not in info or "world" not in info:
            raise PolicyError(f"{who} reads the robot's pose and world: play it through the test protocol")
        expert = self._experts.get(info["world"])
        if expert is None:
            from shared.errors import CogexploreError
            from shared.expert.expert import CommandExpert
            from shared.sim.world import load_world

            try:
                world = load_world(info["world"])
            except CogexploreError as exc:
                raise PolicyError(f"{who} needs the map of world {info['world']!r}: {exc}") from None
            expert = self._experts[info["world"]] = CommandExpert(world, self.env_cfg, self.sensor_cfg)
        x, y, yaw = (float(v) for v in info["pose"])
        return expert, (x, y, yaw)


class ExpertPolicy:
    """The privileged map expert (``shared.expert.expert.CommandExpert``, the supervised labels'
    source) driving: each command from the robot's true pose on the world's clearance map, with a
    3 m lookahead. It never reads the image, so its score is what a controller that knows the map
    reaches under the protocol: a ceiling for the depth policies, not a baseline. The protocol passes
    it the rollout's info (``reads_pose``); it builds one expert per world, at the protocol's speeds."""

    name = "expert"
    reads_pose = True

    def __init__(self, sensor_cfg: SensorConfig | None = None, env_cfg: EnvConfig | None = None):
        self.experts = ExpertsByWorld(sensor_cfg, env_cfg)

    def __call__(self, depth_m: np.ndarray, info: Mapping[str, Any] | None = None) -> tuple[int, np.ndarray]:
        expert, pose = self.experts(info, "the expert policy (cogexplore evaluate --policy expert)")
        scores = expert.scores(*pose)
        return int(np.argmax(scores)), np.asarray(scores, dtype=np.float32)


def make_policy(name: str, *, net: Any = None, sensor_cfg: SensorConfig | None = None,
                seed: int = 0, env_cfg: EnvConfig | None = None) -> PolicyFn:
    """A policy by name: ``greedy`` and ``rl`` need ``net`` (a QNetwork or QEnsemble), ``sl`` a
    SupervisedNet, ``random`` uses ``seed``, ``reactive`` the sensor geometry of ``sensor_cfg``,
    ``expert`` the robot of ``env_cfg`` (its speeds: the protocol's)."""
    if name in ("greedy", "rl", "sl") and net is None:
        raise PolicyError(f"the {name} policy needs a network: give a checkpoint")
    if name == "greedy":
        return GreedyPolicy(net)
    if name == "rl":
        return RLPolicy(net)
    if name == "sl":
        return SupervisedPolicy(net)
    if name == "random":
        return RandomPolicy(seed)
    if name == "reactive":
        return ReactivePolicy(sensor_cfg)
    if name == "expert":
        return ExpertPolicy(sensor_cfg, env_cfg)
    raise PolicyError(f"unknown policy {name!r}; known: {list(POLICY_NAMES)}")
