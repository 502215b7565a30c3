"""``cogexplore bench env``: environment steps per second on one process and one core."""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from services.bench import print_json
from shared.config import ConfigError, SensorConfig
from shared.expert.expert import ExpertGuide
from shared.sim.env import ExploreEnv


def run(world: str = "paper-indoor", steps: int = 2000, backend: str = "raycast",
        allow_columns: bool = True, pin_cpu: int | None = 0, seed: int = 0, expert_labels: bool = False) -> dict:
    """Random-policy rollouts; times every depth capture and every physics step separately.
    ``expert_labels``: also the map expert's label at every pose of the end-to-end rollout (what an
    actor pays per step at ``explore.expert_label_prob`` = 1). ``allow_columns=False`` (``--per-pixel``)
    is for the ray caster: the gl backend has no column fast path to turn off."""
    if backend != "raycast" and not allow_columns:
        raise ConfigError(f"--per-pixel times the ray caster's per-pixel rays: the {backend} backend renders "
                          "every pixel anyway (leave out one of them)")
    if pin_cpu is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {pin_cpu})
    env = ExploreEnv(world=world, sensor=SensorConfig(backend=backend))
    if not allow_columns:
        from shared.sim.sensor import DepthCamera
        # the scene the env plays (its main world: no extra worlds here) gets the per-pixel camera
        env._scene.camera = DepthCamera(env.model, env.sensor_config, allow_columns=False)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    depth_ms, physics_ms = [], []
    episodes = 0
    start = time.perf_counter()
    for _ in range(steps):
        action = int(rng.integers(5))
        # Time the two halves of a step the way ExploreEnv.step runs them.
        t0 = time.perf_counter()
        env.robot.drive(env.linear_mps, env.angular_rps[action], env.env_config.substeps)
        t1 = time.perf_counter()
        env.camera.capture(env.data)
        t2 = time.perf_counter()
        physics_ms.append((t1 - t0) * 1e3)
        depth_ms.append((t2 - t1) * 1e3)
    raw_s = time.perf_counter() - start
    # End-to-end through the Gymnasium API (reward, collision rule, info, resets).
    guide = ExpertGuide(env, 0.0, label_prob=1.0) if expert_labels else None
    label_ms = []
    _, info = env.reset(seed=seed)
    start = time.perf_counter()
    for _ in range(steps):
        if guide is not None:
            t0 = time.perf_counter()
            guide.teacher_label(info["pose"])
            label_ms.append((time.perf_counter() - t0) * 1e3)
        _, _, term, trunc, info = env.step(int(rng.integers(5)))
        if term or trunc:
            episodes += 1
            _, info = env.reset()
    env_s = time.perf_counter() - start
    env.close()
    return {
        "world": world,
        "backend": backend,
        "camera_mode": env.camera.mode,
        "image": [env.sensor_config.height, env.sensor_config.width],
        "steps": steps,
        "steps_per_s": steps / env_s,
        "episodes": episodes,
        "depth_ms_p50": float(np.percentile(depth_ms, 50)),
        "depth_ms_p90": float(np.percentile(depth_ms, 90)),
        "physics_ms_p50": float(np.percentile(physics_ms, 50)),
        "raw_steps_per_s": steps / raw_s,
        "pinned_cpu": pin_cpu,
        **({"expert_label_ms_p50": float(np.percentile(label_ms, 50)),
            "expert_label_ms_p90": float(np.percentile(label_ms, 90))} if label_ms else {}),
    }


def run_command(args: argparse.Namespace) -> int:
    """``cogexplore bench env``."""
    result = run(world=args.world, steps=args.steps, backend=args.backend, allow_columns=not args.per_pixel,
                 pin_cpu=None if args.no_pin else 0, expert_labels=args.expert_labels)
    print_json(result, args.json)
    return 0
