"""``cogexplore``: the one command-line entry to every service and tool.

Subcommands live with their code (``add_*_arguments`` + ``run_*`` in each module) and are
collected here; a service never pays for another's dependencies at run time.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any, Callable

os.environ.setdefault("RERUN_ANALYTICS", "0")  # offline machines: no telemetry attempts


def _print_json(obj: Any) -> None:
    print(json.dumps(obj, indent=2, default=float))


# -- worlds ------------------------------------------------------------------------------

def _worlds_demo(args: argparse.Namespace) -> int:
    import dataclasses
    import time

    from services.evaluator.evaluate import protocol_env_config
    from shared.config import load_preset
    from shared.demos import DemoError, plan_commands, plan_summary, record_demonstration, save_demonstrations
    from shared.env import ExploreEnv

    rc = load_preset(args.preset)
    # The protocol's env (fixed starts: no random poses or extra worlds), at --speed, with a step
    # cap the horizon cannot reach.
    env_cfg = dataclasses.replace(protocol_env_config(rc.env, args.world, args.horizon + 1), speed_table=args.speed)
    env = ExploreEnv(env_cfg, rc.sensor)
    demos, plans = [], []
    try:
        n_starts = len(env.main_world.starts)
        bad = [s for s in args.start if not 1 <= s <= n_starts]
        if bad:
            raise DemoError(f"--start {bad[0]}: {args.world} has starts 1-{n_starts}")
        for start in args.start:
            began = time.monotonic()

            def progress(depth: int, kept: int) -> None:
                if not args.quiet and (depth % 10 == 0 or depth == args.horizon):
                    print(f"  start {start}: depth {depth}/{args.horizon}, {kept} sequences kept, "
                          f"{time.monotonic() - began:.0f} s", file=sys.stderr, flush=True)

            plan = plan_commands(env, start - 1, horizon=args.horizon, beam=args.beam, progress=progress)
            if plan.survived_steps < args.horizon:
                print(f"cogexplore worlds demo: warning: from start {start} no sequence the beam kept survives "
                      f"{args.horizon} steps; the demonstration ends after {plan.survived_steps}, before a "
                      "collision no command avoids (a trap: see `cogexplore worlds starts`)",
                      file=sys.stderr)
            demos.append(record_demonstration(env, plan.start_index, plan.actions))
            plans.append(dict(plan_summary(plan), start=start, seconds=round(time.monotonic() - began, 1)))
            print(json.dumps(plans[-1]), flush=True)
    finally:
        env.close()
    print(save_demonstrations(args.out, demos, {"plans": plans, "preset": args.preset}))
    return 0


def _worlds_list(args: argparse.Namespace) -> int:
    from shared.world import BUILTIN_WORLDS, world_summary

    names = list(BUILTIN_WORLDS) + [f"procedural:{s}" for s in args.procedural]
    rows = [world_summary(name) for name in names]
    if args.json:
        _print_json(rows)
    else:
        for row in rows:
            w, h = row["size_m"]
            print(f"{row['name']:<18} {w:5.1f} x {h:4.1f} m  {row['num_starts']:2d} starts  "
                  f"{row['free_area_m2']:6.1f} m2 free")
    return 0


def _worlds_show(args: argparse.Namespace) -> int:
    from shared.maps import occupancy_grid, render_map_png
    from shared.world import load_world

    world = load_world(args.world)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    render_map_png(world, occupancy_grid(world), out, title=world.name)
    print(out)
    return 0


def _worlds_starts(args: argparse.Namespace) -> int:
    from shared.config import ACTION_NAMES, ConfigError, EnvConfig, SensorConfig
    from shared.supervised import CommandExpert, ExpertConfig, SupervisedError
    from shared.world import load_world

    try:
        world = load_world(args.world)
        if not (1 <= args.horizon <= 1000):
            raise ConfigError(f"--horizon must be in [1, 1000], got {args.horizon}")
        # Fine map cells and view-wedge samples: an escape may pass within centimetres of the thresholds.
        expert = CommandExpert(world, EnvConfig(world=args.world, speed_table=args.speed), SensorConfig(),
                               ExpertConfig(contact_margin_m=args.margin_m, depth_margin_m=args.margin_m,
                                            wedge_spacing_m=0.01, resolution_m=0.02))
    except (ValueError, SupervisedError) as exc:
        print(f"cogexplore worlds starts: error: {exc}", file=sys.stderr)
        return 2
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
        _print_json(rows)
    return 0


# -- model -------------------------------------------------------------------------------

def _model_summary(args: argparse.Namespace) -> int:
    from shared.config import load_preset
    from shared.model import summary

    cfg = load_preset(args.preset)
    rows = summary(cfg.model, cfg.sensor)
    if args.json:
        _print_json(rows)
    else:
        for row in rows if isinstance(rows, list) else rows.get("layers", []):
            print(row)
    return 0


def _model_export(args: argparse.Namespace) -> int:
    from services.evaluator.evaluate import EvaluateError, average_models, load_model
    from shared.checkpoint import export_weights

    try:
        loaded = average_models([load_model(c) for c in args.checkpoint])
    except EvaluateError as exc:
        print(f"cogexplore: error: {exc}", file=sys.stderr)
        return 2
    extra: dict[str, Any] = {}
    if loaded.averaged_from:
        extra["averaged_from"] = list(loaded.averaged_from)
    card = {}
    if args.card:
        try:
            card = json.loads(Path(args.card).read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            print(f"cogexplore: error: --card {args.card}: {exc}", file=sys.stderr)
            return 2
        if not isinstance(card, dict):
            print(f"cogexplore: error: --card {args.card} must hold a JSON object", file=sys.stderr)
            return 2
    if card:
        extra["card"] = card
    out = export_weights(args.out, loaded.net, loaded.policy_version, half=args.half, extra=extra or None)
    _print_json({"out": str(out), "bytes": out.stat().st_size, "policy_version": loaded.policy_version,
                 "source": str(loaded.path), "averaged": max(1, len(loaded.averaged_from)), "half": args.half})
    return 0


def _model_select(args: argparse.Namespace) -> int:
    from services.evaluator.selection import SelectOptions, select
    from shared.config import parse_world_list

    try:
        opts = SelectOptions(run=Path(args.run), out=Path(args.out), window=args.window, stride=args.stride,
                             first_end=args.first, last_end=args.last, gate_world=args.gate_world,
                             gate_min=args.gate_min, gate_start_min=args.gate_start_min,
                             validation_worlds=parse_world_list(args.validate),
                             test_worlds=parse_world_list(args.test) if args.test else (),
                             episodes_per_start=args.episodes_per_start, max_steps=args.max_steps,
                             half=args.half, device=args.device)
        summary = select(opts, echo=lambda msg: print(msg, file=sys.stderr, flush=True))
    except ValueError as exc:  # bad worlds, windows, checkpoints (SelectionError, EvaluateError)
        print(f"cogexplore: error: {exc}", file=sys.stderr)
        return 2
    print(summary.pop("table"), end="", file=sys.stderr)
    _print_json(summary)
    return 0


# -- bench -------------------------------------------------------------------------------

def _bench_env(args: argparse.Namespace) -> int:
    from services.benchmarks.env import run

    result = run(world=args.world, steps=args.steps, backend=args.backend,
                 allow_columns=not args.per_pixel, pin_cpu=None if args.no_pin else 0)
    _print_json(result) if args.json else print(result)
    return 0


def _bench_learner(args: argparse.Namespace) -> int:
    from services.benchmarks.learner import run

    result = run(device=args.device)
    _print_json(result) if args.json else print(result)
    return 0


def _bench_transport(args: argparse.Namespace) -> int:
    from services.benchmarks.transport import run

    result = run(seconds=args.seconds)
    _print_json(result) if args.json else print(result)
    return 0


# -- services and tools defined elsewhere: (module, add-arguments function, run function) ---

def _lazy(module: str, run: str) -> Callable[[argparse.Namespace], int]:
    def handler(args: argparse.Namespace) -> int:
        import importlib

        return getattr(importlib.import_module(module), run)(args)

    return handler


def _add_lazy(sub: Any, name: str, help_: str, module: str, add: str, run: str) -> None:
    """A subcommand whose options and code live in ``module`` (imported only when used)."""
    import importlib

    p = sub.add_parser(name, help=help_, description=help_)
    getattr(importlib.import_module(module), add)(p)
    p.set_defaults(handler=_lazy(module, run))


# -- parser -------------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cogexplore",
        description="Distributed deep RL for depth-only robot exploration (after Tai & Liu, 2016).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def add(name: str, help_: str, handler: Callable[[argparse.Namespace], int] | None = None,
            parent: Any = sub) -> argparse.ArgumentParser:
        p = parent.add_parser(name, help=help_, description=help_)
        if handler is not None:
            p.set_defaults(handler=handler)
        return p

    worlds = add("worlds", "list and draw the worlds")
    wsub = worlds.add_subparsers(dest="worlds_command", metavar="ACTION", required=True)
    p = add("list", "list built-in worlds (name, size, starts)", _worlds_list, wsub)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--procedural", type=int, nargs="*", default=[0],
                   help="also list these procedural seeds (default: 0)")
    p = add("show", "draw a top-down map with start poses and headings", _worlds_show, wsub)
    p.add_argument("world", help="built-in name, procedural:<seed> or an MJCF path")
    p.add_argument("--out", default="map.png", help="PNG path (default: map.png)")

    p = add("starts", "check that every start pose can survive: a beam search over command sequences on the "
            "map (exact kinematics, the depth-collision rule) for the longest survival from each start", _worlds_starts,
            wsub)
    p.add_argument("world", help="built-in name, procedural:<seed> or an MJCF path")
    p.add_argument("--speed", choices=("test", "train"), default="test",
                   help="speed table (default test: the protocol's)")
    p.add_argument("--horizon", type=int, default=60, help="steps a start must survive (default 60)")
    p.add_argument("--margin-m", type=float, default=0.0,
                   help="extra clearance and depth every step must keep (default 0: the task's exact thresholds)")
    p.add_argument("--json", action="store_true", help="print JSON")

    p = add("demo", "plan demonstrations for training (train.demos): a beam search in the environment itself "
            "from each --start for the smoothest command sequence that survives --horizon steps and ends "
            "farthest away, recorded as images, commands and rewards (shared/demos.py)", _worlds_demo, wsub)
    p.add_argument("world", help="built-in name, procedural:<seed> or an MJCF path")
    p.add_argument("--start", type=int, action="append", required=True,
                   help="start number, 1-based as in the tables (repeat for several)")
    p.add_argument("--out", required=True, help="demonstration file to write (.npz)")
    p.add_argument("--preset", default="fast-40x30",
                   help="preset whose sensor and robot the demonstrations use (default fast-40x30)")
    p.add_argument("--speed", choices=("test", "train"), default="test",
                   help="speed table (default test: the protocol's; some escapes exist only there)")
    p.add_argument("--horizon", type=int, default=80, help="steps to plan (default 80)")
    p.add_argument("--beam", type=int, default=2000, help="command sequences kept per step (default 2000)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")

    model = add("model", "inspect the Q-network")
    msub = model.add_subparsers(dest="model_command", metavar="ACTION", required=True)
    p = add("summary", "each layer's output shape and parameter count", _model_summary, msub)
    p.add_argument("--preset", default="paper", help="preset name or TOML path (default: paper)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p = add("export", "write a checkpoint's online weights as a weights-only file (deployment, "
            "`evaluate --checkpoint FILE`); several checkpoints are averaged", _model_export, msub)
    p.add_argument("checkpoint", nargs="+",
                   help="checkpoint file or directory, or run folder; with several (one run's later "
                        "checkpoints), their weights' mean, labelled with the last one's update")
    p.add_argument("--out", required=True, help="output .safetensors path")
    p.add_argument("--half", action="store_true", help="store float16 (half the size)")
    p.add_argument("--card", metavar="JSON", help="a JSON object stored in the file's metadata (model card)")
    p = add("select", "choose the model to ship from a run: the mean of N consecutive checkpoints' weights "
            "that reaches --gate-min on --gate-world and, among those, scores best on the --validate worlds "
            "(writes the weights, <out>-windows.png and a resumable <out>-windows.jsonl)", _model_select, msub)
    p.add_argument("run", help="run folder or its checkpoints directory (train with train.keep_checkpoints "
                               "large enough to keep the windows)")
    p.add_argument("--out", required=True, help="output .safetensors path of the chosen window")
    p.add_argument("--window", type=int, default=4, help="consecutive checkpoints averaged (default 4)")
    p.add_argument("--stride", type=int, default=1, help="score every N-th window, counted back from the "
                                                         "newest (default 1)")
    p.add_argument("--first", type=int, default=0, metavar="UPDATES",
                   help="only windows ending at or after this update")
    p.add_argument("--last", type=int, default=None, metavar="UPDATES",
                   help="only windows ending at or before this update")
    p.add_argument("--gate-world", default="paper-indoor", help="the world a window must pass (default paper-indoor)")
    p.add_argument("--gate-min", type=float, default=150.0,
                   help="mean steps a window needs on the gate world (default 150: the goal)")
    p.add_argument("--gate-start-min", type=float, default=0.0,
                   help="mean steps every start of the gate world needs too (the goal: 60; default 0: none)")
    p.add_argument("--validate", default="procedural:201-210",
                   help="validation worlds, never trained on and never test worlds (default procedural:201-210)")
    p.add_argument("--test", default=None, metavar="WORLDS",
                   help="test worlds the chosen window alone plays after the choice, reported apart "
                        "(e.g. procedural:301-330)")
    p.add_argument("--episodes-per-start", type=int, default=1,
                   help="episodes per start (default 1: the protocol is deterministic without sensor noise)")
    p.add_argument("--max-steps", type=int, default=200, help="moving steps per episode at most (default 200)")
    p.add_argument("--half", action="store_true", help="store float16")
    p.add_argument("--device", default="auto", help="torch device: auto, cpu, cuda, cuda:N (default auto)")

    bench = add("bench", "benchmarks (print JSON)")
    bsub = bench.add_subparsers(dest="bench_command", metavar="TARGET", required=True)
    p = add("env", "environment steps/s and depth-frame time on one core", _bench_env, bsub)
    p.add_argument("--world", default="paper-indoor")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--backend", choices=["raycast", "gl"], default="raycast")
    p.add_argument("--per-pixel", action="store_true",
                   help="cast every pixel's ray (disable the exact column fast path)")
    p.add_argument("--no-pin", action="store_true", help="do not pin the process to CPU 0")
    p.add_argument("--json", action="store_true", help="print JSON")
    p = add("learner", "DQN update time, forward time and FLOP utilisation", _bench_learner, bsub)
    p.add_argument("--device", default="auto")
    p.add_argument("--json", action="store_true", help="print JSON")
    p = add("transport", "transitions/s through a loopback Zenoh router", _bench_transport, bsub)
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--json", action="store_true", help="print JSON")
    _add_lazy(bsub, "system", "env steps/s, updates/s, weight lag and replay ratio of router + learner + N "
              "actors as real processes", "services.benchmarks.system", "add_arguments", "run_command")

    _add_lazy(sub, "up", "run router, learner, actors and evaluator locally (the embedded default)",
              "services.launcher", "add_up_arguments", "run_up_command")
    _add_lazy(sub, "train", "train in one process (the paper's Algorithm 1; reference and baseline)",
              "services.trainer", "add_train_arguments", "run_train_command")
    _add_lazy(sub, "router", "run a Zenoh router (default tcp/0.0.0.0:7447)",
              "services.router", "add_arguments", "run")
    _add_lazy(sub, "learner", "run the learner service", "services.learner.service",
              "add_learner_arguments", "run_learner_command")
    _add_lazy(sub, "actor", "run one actor service (joins a run through its router)",
              "services.actor.service", "add_actor_arguments", "run_actor_command")
    _add_lazy(sub, "evaluator", "run the evaluator service (tests the newest weights every K updates)",
              "services.evaluator.service", "add_evaluator_arguments", "run_evaluator")
    _add_lazy(sub, "evaluate", "run the paper's test protocol on a checkpoint or a baseline policy",
              "services.evaluator.evaluate", "add_evaluate_arguments", "run_evaluate")
    _add_lazy(sub, "report", "the paper's tables and figures (PNG + Markdown) for a run",
              "services.evaluator.report", "add_report_arguments", "run_report")
    _add_lazy(sub, "pretrain", "the supervised model (SL baseline, DRL conv init) from expert-labelled depth images",
              "services.pretrain", "add_pretrain_arguments", "run_pretrain_command")
    _add_lazy(sub, "experiment", "the paper's SL / RL / DRL comparison end to end (resumable)",
              "services.experiment", "add_experiment_arguments", "run_experiment_command")

    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from shared.config import ConfigError
    from shared.world import WorldError

    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt:
        return 130
    except Exception as exc:
        if not isinstance(exc, (ConfigError, WorldError, *_loaded_user_errors())):
            raise
        print(f"cogexplore: error: {exc}", file=sys.stderr)
        return 2


_USER_ERRORS = (("shared.checkpoint", "CheckpointError"), ("shared.supervised", "SupervisedError"),
                ("shared.demos", "DemoError"))
"""Errors that name a bad file or setting (train.init_from, init_conv_from, train.demos): a message, not a
traceback."""


def _loaded_user_errors() -> tuple[type[BaseException], ...]:
    # only modules already imported can have raised; importing them here would pull in torch
    return tuple(getattr(sys.modules[m], name) for m, name in _USER_ERRORS if m in sys.modules)


if __name__ == "__main__":
    sys.exit(main())
