"""The test protocol (the paper's Section V-A): greedy episodes from every start pose.

From every start pose of a world, N episodes at the TEST speed table, each stopped at a collision
or after at most 200 moving steps, under the conditions of a :class:`ProtocolConfig` (exact or
jittered starts, the sensor's noise: ``shared.evaluation.PROTOCOLS``), which the results record
(``meta.protocol``), and the world's content (``meta.world_sha256``: :func:`world_sha256`);
:mod:`shared.evaluation.results` holds what comes out. The
episodes run through the one rollout loop (``shared.rollout``) with two observers of their own,
the trajectory and the coverage (``shared.sim.maps.CoverageTracker``), and, optionally, a
recorder (``services.viz.rerun.EvalRecorder``, or anything with its ``begin_episode`` /
``log_step`` / ``end_episode`` / ``log_evaluation``), which this module calls but never opens.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict
from typing import Any

import numpy as np
from tqdm import tqdm

from shared.config import ACTION_NAMES, EnvConfig, SensorConfig, is_whole
from shared.evaluation import (
    PAPER_EPISODES_PER_START,
    PAPER_MAX_STEPS,
    PROTOCOL_SENSOR_FIELDS,
    PROTOCOLS,
    TEST_SEED,
    ProtocolConfig,
)
from shared.evaluation.results import EpisodeResult, EvalResults, ResultsError
from shared.rollout import Episode, Rollout, Step
from shared.sim.world import World, canonical_world_name, load_world

WORLD_META = "world_sha256"
"""The results meta field holding :func:`world_sha256` of the world the episodes were played in."""

PolicyFn = Callable[[np.ndarray], tuple[int, Sequence[float] | np.ndarray | None]]
"""``policy_fn(depth_m) -> (action, q_values or None)``; with ``reset()`` when it keeps memory."""


class EvaluationCancelled(RuntimeError):
    """The ``stop`` event was set while an evaluation ran."""


def world_sha256(world: World) -> str:
    """The SHA-256 (hex) of what a world is played as: its MJCF scene, starts, extent and the content of
    the files the scene names (meshes, height fields, skins, textures: ``World.asset_sha256``). Its name
    is not enough to stand for it: an MJCF file, or a mesh beside it, edited since is another world
    under the same path."""
    content: dict[str, Any] = {"mjcf": world.mjcf, "starts": [asdict(s) for s in world.starts],
                               "extent": list(world.extent)}
    if world.asset_sha256:  # only then: a world naming no file keeps the digest it had before files counted
        content["files"] = [list(f) for f in world.asset_sha256]
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()


def file_world_sha256(world: str) -> str | None:
    """:func:`world_sha256` of the world ``world`` names when it is an MJCF file, else None: a built-in
    or procedural world is fixed by its name, so keys written before the digest still stand for it."""
    loaded = load_world(world)
    return world_sha256(loaded) if loaded.kind == "file" else None


def played_as_now(meta: Mapping[str, Any], digest_now: str | None) -> bool:
    """Whether results or an evaluation row with ``meta`` were played on their world as it is now:
    ``digest_now`` is :func:`file_world_sha256` of that world (None for a built-in or procedural world,
    fixed by its name: all its results stand; an MJCF file's stand only with its digest now)."""
    return digest_now is None or meta.get(WORLD_META) == digest_now


def episode_seed(seed: int, start_index: int, episode: int) -> int:
    """The reset seed of one episode: a function of (seed, start, episode) only, so any
    subset of the protocol reproduces the same episodes (and, under a jittered protocol, the
    same start draws and sensor noise for every policy)."""
    return int(np.random.SeedSequence([seed, start_index, episode]).generate_state(1, dtype=np.uint32)[0])


PROTOCOL_ENV_FIELDS: dict[str, str] = {
    "world": "the world is --world's",
    "speed_table": "the test protocol drives at the test speeds",
    "max_episode_steps": "the test protocol's cap is --max-steps",
    "start_index": "the test protocol plays every start, or --starts",
    "start_jitter_m": "the test protocol sets the start jitter; use --protocol or --start-jitter-m",
    "start_jitter_deg": "the test protocol sets the start jitter; use --protocol or --start-jitter-deg",
    "reward_trap_penalty": "the test protocol counts steps, not rewards",
    "extra_worlds": "the test protocol plays --world alone",
    "extra_world_prob": "the test protocol plays --world alone",
    "random_start_prob": "the test protocol plays the named starts, or --starts",
    "failure_start_prob": "the test protocol plays the named starts, or --starts",
}
"""The env fields :func:`protocol_env_config` sets whatever the base config says, and what sets
each instead: an override of one would do nothing, so ``evaluate`` refuses it."""


def protocol_env_config(base: EnvConfig | None, world: str, max_steps: int) -> EnvConfig:
    """The protocol's environment: ``base``'s robot and task, the given world, the TEST speed
    table, every start (none fixed), no training start jitter (the protocol's own is a reset
    option), no trap reward (the protocol counts steps; the trap's map checks would only cost time),
    a step cap no shorter than the protocol's, and none of training's other worlds, random or
    failure starts (the protocol names each episode's start: they were never played, but a
    training world file the env loads at construction, moved or broken since, failed the test).
    The world by its canonical name (``procedural:007`` is ``procedural:7``), as results record it."""
    return dataclasses.replace(base or EnvConfig(), world=canonical_world_name(world), speed_table="test",
                               max_episode_steps=max_steps, start_index=None,
                               start_jitter_m=0.0, start_jitter_deg=0.0, reward_trap_penalty=0.0,
                               extra_worlds="", extra_world_prob=0.0, random_start_prob=0.0,
                               failure_start_prob=0.0)


def _check_action(action: Any) -> int:
    if not (is_whole(action) and 0 <= int(action) < len(ACTION_NAMES)):
        raise ResultsError(f"policy_fn returned action {action!r}; expected an index in 0..{len(ACTION_NAMES) - 1}")
    return int(action)


class _ProtocolPolicy:
    """``policy_fn`` as the rollout calls it; raises EvaluationCancelled once ``stop`` is set."""

    def __init__(self, policy_fn: PolicyFn, stop: threading.Event | None):
        self.policy_fn = policy_fn
        self.stop = stop
        self.reset = getattr(policy_fn, "reset", None)

    def __call__(self, depth_m: np.ndarray, info: Any, _env_steps: int) -> Any:
        if self.stop is not None and self.stop.is_set():
            raise EvaluationCancelled("evaluation cancelled")
        if getattr(self.policy_fn, "reads_pose", False):  # a privileged policy: the robot's pose and world
            return self.policy_fn(depth_m, info)
        return self.policy_fn(depth_m)


class _Trace:
    """Observer: the start position and every step's, and the free area the camera has seen."""

    def __init__(self, env: Any):
        from shared.sim.maps import CoverageTracker, occupancy_grid

        self.tracker = CoverageTracker(occupancy_grid(env.world), env.sensor_config)
        self.trajectory: list[tuple[float, float]] = []

    def _observe(self, pose: Sequence[float], depth_m: np.ndarray) -> None:
        x, y, yaw = pose
        self.tracker.observe(x, y, yaw, depth_m)
        self.trajectory.append((x, y))

    def begin_episode(self, episode: Episode) -> None:
        self.tracker.reset()
        self.trajectory = []
        self._observe(episode.first_info["pose"], episode.first_obs)

    def on_step(self, step: Step) -> None:
        self._observe(step.next_info["pose"], step.next_obs)

    def coverage(self) -> tuple[float, float]:
        return self.tracker.seen_area_m2, min(1.0, self.tracker.seen_fraction)


class _RecorderSteps:
    """Observer: each step to the recorder (``log_step(step, pose, depth, q_values, action)``)."""

    def __init__(self, recorder: Any):
        self.recorder = recorder

    def on_step(self, step: Step) -> None:
        self.recorder.log_step(step.index, step.info["pose"], step.obs, step.q_values, step.action)


def run_protocol(policy_fn: PolicyFn, make_env: Callable[[], Any], starts: Sequence[int] | None = None,
                 episodes_per_start: int = PAPER_EPISODES_PER_START, max_steps: int = PAPER_MAX_STEPS,
                 seed: int = TEST_SEED, recorder: Any = None, progress: bool = True,
                 keep_trajectories: bool = True, meta: Mapping[str, Any] | None = None,
                 stop: threading.Event | None = None, protocol: ProtocolConfig = PROTOCOLS["paper"]) -> EvalResults:
    """Run exactly ``len(starts) * episodes_per_start`` episodes and return their results.

    ``policy_fn(depth_m) -> (action, q_values or None)`` picks each command (greedy for the
    paper's protocol); ``make_env()`` returns an ``ExploreEnv`` (test speeds for the paper) whose
    sensor has ``protocol``'s noise (``protocol.sensor(cfg)``; ResultsError otherwise), built once
    and reset per episode with ``episode_seed(seed, start, episode)`` and, under a jittered
    ``protocol``, its start drawn around the named one by the env (never the env config's own
    training jitter). ``starts``
    are start indices (None: all of the world's). Each episode stops at a collision or after
    ``max_steps`` steps, whichever comes first; a ``policy_fn`` with a ``reset()`` method (one that
    remembers its last command) is reset before each episode, and one with a ``seed_episode(seed)``
    method (one that draws random numbers) is given the episode's reset seed. ``recorder`` (an
    ``EvalRecorder``) gets ``begin_episode`` / ``log_step`` / ``end_episode``. Deterministic for a deterministic policy.
    ``stop``: when set, the run ends within one step with :class:`EvaluationCancelled`.
    """
    if not (is_whole(episodes_per_start) and episodes_per_start >= 1):
        raise ResultsError(f"episodes_per_start must be an integer >= 1, got {episodes_per_start!r}")
    if not (is_whole(max_steps) and max_steps >= 1):
        raise ResultsError(f"max_steps must be an integer >= 1, got {max_steps!r}")
    if not (is_whole(seed) and seed >= 0):
        raise ResultsError(f"seed must be an integer >= 0, got {seed!r}")
    if starts is not None and (isinstance(starts, (str, bytes)) or not isinstance(starts, (Sequence, np.ndarray))
                               or not all(is_whole(s) for s in starts)):
        raise ResultsError(f"starts must be a list of start indices (whole numbers), got {starts!r}")
    if not isinstance(protocol, ProtocolConfig):
        raise ResultsError(f"protocol must be a ProtocolConfig, got {type(protocol).__name__}")
    env = make_env()
    try:
        n_starts = len(env.world.starts)
        start_list = list(range(n_starts)) if starts is None else [int(s) for s in starts]
        bad = [s for s in start_list if not 0 <= s < n_starts]
        if bad or not start_list:
            raise ResultsError(f"starts {bad or start_list} invalid: world {env.world.name!r} has "
                               f"{n_starts} starts (indices 0..{n_starts - 1})")
        if len(set(start_list)) < len(start_list):  # refused now, not by the results after every episode
            raise ResultsError(f"starts {start_list} name a start more than once")
        if env.env_config.max_episode_steps < max_steps:
            raise ResultsError(f"the env truncates at {env.env_config.max_episode_steps} steps, before the "
                               f"protocol's max_steps={max_steps}: build it with max_episode_steps >= {max_steps}")
        differ = [f for f in PROTOCOL_SENSOR_FIELDS
                  if getattr(env.sensor_config, f) != getattr(protocol, f"sensor_{f}")]
        if differ:
            raise ResultsError(f"the env's sensor has {', '.join(f'{f}={getattr(env.sensor_config, f)!r}' for f in differ)}"
                               f", not the {protocol.name} protocol's: build it with protocol.sensor(sensor_cfg)")
        # Always explicit, None included: an env built with a training jitter must not move the
        # starts of an exact protocol.
        reset_options: dict[str, Any] = {
            "start_jitter": (protocol.start_jitter_m, protocol.start_jitter_deg) if protocol.jittered else None}
        trace = _Trace(env)
        seed_policy = getattr(policy_fn, "seed_episode", None)
        loop = Rollout(env, _ProtocolPolicy(policy_fn, stop),
                       [trace] + ([_RecorderSteps(recorder)] if recorder is not None else []),
                       max_steps=max_steps, check_action=_check_action)
        episodes: list[EpisodeResult] = []
        total = len(start_list) * episodes_per_start
        with tqdm(total=total, desc="evaluate", unit="ep", disable=not progress) as bar:
            for start_index in start_list:
                for k in range(episodes_per_start):
                    if recorder is not None:
                        recorder.begin_episode(start_index, k)
                    reset_seed = episode_seed(seed, start_index, k)
                    if seed_policy is not None:  # its draws: this episode's, whatever ran before it
                        seed_policy(reset_seed)
                    episode = loop.run_episode(seed=reset_seed,
                                               options={"start_index": start_index, **reset_options})
                    info = episode.info
                    area, fraction = trace.coverage()
                    result = EpisodeResult(
                        start_index=start_index, episode=k, steps=episode.steps, terminated=episode.terminated,
                        truncated=episode.truncated,
                        collision_cause=info["collision_cause"] if episode.terminated else None,
                        distance_m=float(info["distance_from_start_m"]), path_length_m=float(info["path_length_m"]),
                        coverage_m2=float(area), coverage_fraction=float(fraction),
                        trajectory_xy=tuple(trace.trajectory) if keep_trajectories else ())
                    if recorder is not None:
                        recorder.end_episode(result)
                    episodes.append(result)
                    bar.update(1)
                    bar.set_postfix(mean_steps=f"{np.mean([e.steps for e in episodes]):.1f}")
        # the conditions played win over a caller's meta: results that misstate them would be reused
        # by report and selection for another world or protocol
        run_meta = {**(meta or {}), "world": env.world.name, WORLD_META: world_sha256(env.world),
                    "speed_table": env.env_config.speed_table,
                    "starts": start_list, "episodes_per_start": episodes_per_start,
                    "max_steps": max_steps, "seed": seed, "protocol": protocol.to_dict()}
        return EvalResults(tuple(episodes), run_meta)
    finally:
        env.close()


def evaluate_policy(policy_fn: PolicyFn, *, world: str, sensor_cfg: SensorConfig, env_cfg: EnvConfig | None = None,
                    episodes_per_start: int = PAPER_EPISODES_PER_START, max_steps: int = PAPER_MAX_STEPS,
                    seed: int = TEST_SEED, starts: Sequence[int] | None = None, policy_version: int = 0,
                    progress: bool = True, meta: Mapping[str, Any] | None = None,
                    stop: threading.Event | None = None, recorder: Any = None,
                    protocol: ProtocolConfig = PROTOCOLS["paper"]) -> EvalResults:
    """Run the protocol with ``policy_fn`` in ``world`` and return its results.

    ``protocol`` (default the paper's: exact starts, no noise) sets the starts and the sensor's
    noise (``sensor_cfg``'s own noise fields are replaced: the test's noise is the protocol's).
    The results' meta holds the protocol, the sensor and the env configs beside ``meta``.
    ``recorder`` (opened and closed by the caller, e.g. ``services.viz.rerun.evaluate_recorded``)
    gets every episode and step, then the summary at update ``policy_version`` and the protocol.
    ``stop``: when set, the run ends within one step with :class:`EvaluationCancelled`.
    """
    from shared.sim.env import ExploreEnv

    cfg = protocol_env_config(env_cfg, world, max_steps)
    sensor_cfg = protocol.sensor(sensor_cfg)
    world_obj = load_world(world)  # fail early, with the world's own error, before any env is built

    def make_env() -> ExploreEnv:
        return ExploreEnv(cfg, sensor_cfg, world=world_obj)

    full_meta = {**(meta or {}), "sensor": asdict(sensor_cfg),
                 "env": {k: v for k, v in asdict(cfg).items() if k != "start_index"}}
    results = run_protocol(policy_fn, make_env, starts=starts, episodes_per_start=episodes_per_start,
                           max_steps=max_steps, seed=seed, recorder=recorder, progress=progress,
                           meta=full_meta, stop=stop, protocol=protocol)
    if recorder is not None:
        recorder.log_evaluation(policy_version, results.summary, protocol=protocol.to_dict())
    return results
