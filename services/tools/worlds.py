"""``cogexplore worlds list|show|starts|demo``: the worlds, their maps, their start poses' survival, and
planner demonstrations."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def run_list(args: argparse.Namespace) -> int:
    from shared.sim.world import BUILTIN_WORLDS, world_summary

    names = list(BUILTIN_WORLDS) + [f"procedural:{s}" for s in args.procedural]
    rows = [world_summary(name) for name in names]
    if args.json:
        print(json.dumps(rows, indent=2, default=float))
    else:
        for row in rows:
            w, h = row["size_m"]
            print(f"{row['name']:<18} {w:5.1f} x {h:4.1f} m  {row['num_starts']:2d} starts  "
                  f"{row['free_area_m2']:6.1f} m2 free")
    return 0


def run_show(args: argparse.Namespace) -> int:
    from shared.sim.maps import occupancy_grid, render_map_png
    from shared.sim.world import load_world

    world = load_world(args.world)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    render_map_png(world, occupancy_grid(world), out, title=world.name)
    print(out)
    return 0


def run_starts(args: argparse.Namespace) -> int:
    from shared.config import ACTION_NAMES, ConfigError, EnvConfig, SensorConfig
    from shared.expert.expert import CommandExpert, ExpertConfig
    from shared.sim.world import load_world

    world = load_world(args.world)
    if not (1 <= args.horizon <= 1000):
        raise ConfigError(f"--horizon must be in [1, 1000], got {args.horizon}")
    # Fine map cells and view-wedge samples: an escape may pass within centimetres of the thresholds.
    expert = CommandExpert(world, EnvConfig(world=args.world, speed_table=args.speed), SensorConfig(),
                           ExpertConfig(contact_margin_m=args.margin_m, depth_margin_m=args.margin_m,
                                        wedge_spacing_m=0.01, resolution_m=0.02))
    rows = []
    width = max((len(s.name or "") for s in world.starts), default=0)
    for i, start in enumerate(world.starts):
        steps = expert.survival_steps(start.x, start.y, start.yaw, horizon=args.horizon)
        rows.append({"start": i + 1, "name": start.name, "pose": [start.x, start.y, start.yaw],
                     "survival_steps": int(steps.max()), "trap": bool(steps.max() < args.horizon),
                     "per_command": dict(zip(ACTION_NAMES, (int(v) for v in steps)))})
        if not args.json:
            r = rows[-1]
            verdict = (f"ok (survives {args.horizon} steps)" if not r["trap"] else
                       f"TRAP: collides within {r['survival_steps'] + 1} steps whatever it commands")
            print(f"start {r['start']:2d} {r['name'] or '':<{width}}  {verdict}", flush=True)
    if args.json:
        print(json.dumps(rows, indent=2, default=float))
    return 0


def run_demo(args: argparse.Namespace) -> int:
    import dataclasses
    import time

    from shared.config import ConfigError, load_preset
    from shared.evaluation import PROTOCOLS
    from shared.evaluation.protocol import episode_seed, protocol_env_config
    from shared.learning.demos import (
        DemoError,
        StartDraw,
        plan_commands,
        plan_summary,
        record_demonstration,
        save_demonstrations,
    )
    from shared.sim.env import ExploreEnv

    protocol = PROTOCOLS[args.protocol]
    if args.episodes < 1:
        raise ConfigError(f"--episodes must be an integer >= 1, got {args.episodes}")
    if args.episodes > 1 and not protocol.jittered:
        raise ConfigError(f"--episodes {args.episodes}: give 1, or more with --protocol robust (the {protocol.name} "
                          "protocol's starts are exact: every episode would be the same)")
    if args.seed < 0:  # numpy's refusal, in the first draw, was a traceback
        raise ConfigError(f"--seed must be an integer >= 0, got {args.seed}")
    rc = load_preset(args.preset)
    # The protocol's env (fixed starts: no random poses or extra worlds) and sensor noise, at
    # --speed, with a step cap the horizon cannot reach.
    env_cfg = dataclasses.replace(protocol_env_config(rc.env, args.world, args.horizon + 1), speed_table=args.speed)
    env = ExploreEnv(env_cfg, protocol.sensor(rc.sensor))
    demos, plans = [], []
    try:
        n_starts = len(env.main_world.starts)
        bad = [s for s in args.start if not 1 <= s <= n_starts]
        if bad:
            raise DemoError(f"--start {bad[0]}: {args.world} has starts 1-{n_starts}")
        starts = list(dict.fromkeys(args.start))  # a start given twice would be planned and recorded twice
        if len(starts) < len(args.start):
            twice = sorted({s for s in args.start if args.start.count(s) > 1})
            print(f"cogexplore worlds demo: note: start {' '.join(map(str, twice))} given more than once; "
                  "planned once", file=sys.stderr)
        for start in starts:
            for k in range(args.episodes):
                draw = StartDraw(episode_seed(args.seed, start - 1, k), protocol.start_jitter_m,
                                 protocol.start_jitter_deg) if protocol.jittered else None
                began = time.monotonic()
                where = f"start {start}" + ("" if draw is None else f", draw {k}")

                def progress(depth: int, kept: int) -> None:
                    if not args.quiet and (depth % 10 == 0 or depth == args.horizon):
                        print(f"  {where}: depth {depth}/{args.horizon}, {kept} sequences kept, "
                              f"{time.monotonic() - began:.0f} s", file=sys.stderr, flush=True)

                plan = plan_commands(env, start - 1, horizon=args.horizon, beam=args.beam, draw=draw,
                                     progress=progress)
                if plan.survived_steps < args.horizon:
                    print(f"cogexplore worlds demo: warning: from {where} no sequence the beam kept survives "
                          f"{args.horizon} steps; the demonstration ends after {plan.survived_steps}, before a "
                          "collision no command avoids (a trap: see `cogexplore worlds starts`)",
                          file=sys.stderr)
                demos.append(record_demonstration(env, plan.start_index, plan.actions, draw))
                plans.append(dict(plan_summary(plan), start=start, episode=k,
                                  seconds=round(time.monotonic() - began, 1)))
                print(json.dumps(plans[-1]), flush=True)
    finally:
        env.close()
    print(save_demonstrations(args.out, demos, {"plans": plans, "preset": args.preset, "protocol": protocol.name}))
    return 0
