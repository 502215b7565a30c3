"""``cogexplore model summary|export|select|agreement``: a Q-network's layers, a weights-only or ONNX
export, the choice of the model to ship from a run's checkpoints, and how far models agree with the
map expert's labels on the states a run's actors visited."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from shared.config import ConfigError, parse_world_list
from shared.jsontext import SMALL_JSON_BYTES, read_json_file


def run_summary(args: argparse.Namespace) -> int:
    from shared.config import load_preset
    from shared.learning.model import summary

    cfg = load_preset(args.preset)
    rows = summary(cfg.model, cfg.sensor)
    if args.json:
        _print_json(rows)
    else:
        for row in rows if isinstance(rows, list) else rows.get("layers", []):
            print(row)
    return 0


def run_export(args: argparse.Namespace) -> int:
    if not (args.out or args.onnx):
        raise ConfigError("give --out FILE.safetensors (weights for torch), --onnx FILE.onnx (runs without torch) "
                          "or both")
    if args.half and not args.out:
        raise ConfigError("--half stores the --out weights as float16; an --onnx export is float32")
    if args.out and args.onnx and _same_file(args.out, args.onnx):
        # the weights would be written over the ONNX file just written, and both reported written
        raise ConfigError(f"--out and --onnx name the same file ({args.out}): give each its own")
    from services.tools.selection import check_output
    from shared.learning.checkpoints import (average_models, ensemble_members, ensemble_models, export_weights,
                                             load_model)

    if args.ensemble and len(args.checkpoint) < 2:
        raise ConfigError("--ensemble joins several checkpoints: give at least two")
    sources = [load_model(c) for c in args.checkpoint]
    for what, out in (("--out", args.out), ("--onnx", args.onnx)):
        if out:
            check_output(Path(out), [s.path for s in sources], what)
    loaded = ensemble_models(sources) if args.ensemble else average_models(sources)
    if args.members:
        loaded = ensemble_members(loaded, [m.strip() for m in args.members.split(",")])
    card = {}
    if args.card:
        card = read_json_file(args.card, "--card", ConfigError, allow_nan=False,  # the file's metadata is JSON
                              max_bytes=SMALL_JSON_BYTES)
        if not isinstance(card, dict):
            raise ConfigError(f"--card {args.card} must hold a JSON object")
    report: dict[str, Any] = {}

    def write_weights() -> None:
        if not args.out:
            return
        extra: dict[str, Any] = {}
        if loaded.averaged_from:
            extra["averaged_from"] = list(loaded.averaged_from)
        if loaded.ensemble_of:
            extra["ensemble_of"] = list(loaded.ensemble_of)
        if card:
            extra["card"] = card
        out = export_weights(args.out, loaded.net, loaded.policy_version, half=args.half,
                             run_config=loaded.run_config, extra=extra or None)
        report.update(out=str(out), bytes=out.stat().st_size, half=args.half)

    if args.onnx:
        from shared.files import write_atomically
        from shared.learning.onnx_export import onnx_file_bytes

        # first: its check against torch may refuse it, and then nothing is written
        data = onnx_file_bytes(loaded, args.onnx, extra={"card": card} if card else None)
        onnx_path = Path(args.onnx)
        onnx_path.parent.mkdir(parents=True, exist_ok=True)
        # the weights are written while the ONNX file has its temporary name: a refused or failed --out
        # (float16 overflow, a full disk) leaves neither file, and an earlier export under the name as it was
        write_atomically(onnx_path, lambda tmp: (tmp.write_bytes(data), write_weights()))
        report["onnx"] = {"out": str(onnx_path), "bytes": onnx_path.stat().st_size}
    else:
        write_weights()
    _print_json({**report, "policy_version": loaded.policy_version, "source": str(loaded.path),
                 "averaged": max(1, len(loaded.averaged_from)), "ensemble": len(loaded.ensemble_of)})
    return 0


def _same_file(a: str, b: str) -> bool:
    """Whether two paths name one file: the same path once links and ``..`` are resolved, or one
    existing file under two names (a hard link)."""
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist yet
        return False


def run_select(args: argparse.Namespace) -> int:
    from services.options import apply_cpu_threads, protocol_from_args
    from services.tools.selection import SelectOptions, select

    apply_cpu_threads(args.threads)

    opts = SelectOptions(run=Path(args.run), out=Path(args.out), window=args.window, stride=args.stride,
                         first_end=args.first, last_end=args.last, gate_world=args.gate_world,
                         gate_min=args.gate_min, gate_start_min=args.gate_start_min,
                         validation_worlds=parse_world_list(args.validate),
                         test_worlds=parse_world_list(args.test) if args.test else (),
                         episodes_per_start=args.episodes_per_start, max_steps=args.max_steps,
                         half=args.half, device=args.device, protocol=protocol_from_args(args),
                         seed=args.seed)
    summary = select(opts, echo=lambda msg: print(msg, file=sys.stderr, flush=True))
    print(summary.pop("table"), end="", file=sys.stderr)
    _print_json(summary)
    return 0


def _greedy(net: Any, memory: Any, states: Any, safe_marks: bool = False) -> Any:
    """The network's greedy command at each of ``states`` (``memory.labelled``'s, re-read with the
    network's frame stack)."""
    import numpy as np

    from shared.learning.model import InferenceRunner

    stack = net.model_cfg.frame_stack
    seen = memory.labelled(stack, safe_marks=safe_marks) if stack > 1 else states
    runner = InferenceRunner(net)
    return np.concatenate([runner.q_values(seen.obs[i:i + 2048], seen.previous_action[i:i + 2048]).argmax(axis=1)
                           for i in range(0, len(seen.action), 2048)])


def run_agreement(args: argparse.Namespace) -> int:
    """How often each model's command is the map expert's, on the labelled states kept in a run's
    replay memory (a run trained with explore.expert_label_prob > 0), and how often it is one with a
    way out on the states the expert marked (explore.safe_label_prob > 0)."""
    import numpy as np

    from shared.config import ACTION_NAMES, mask_commands
    from shared.expert.supervised import classification_metrics, predict
    from shared.learning.checkpoints import load_model, load_replay, load_supervised_model
    from shared.learning.replay import ReplayError

    memory = load_replay(args.run)
    sources = args.model or ["pretrained"]
    nets = {source: load_model(source).net for source in sources}
    report: dict[str, Any] = {"run": str(args.run)}
    try:
        marked = memory.labelled(safe_marks=True)
    except ReplayError:
        marked = None
    if marked is not None:
        safe = mask_commands(marked.safe_commands)  # (N, 5)
        rows = np.arange(len(safe))
        share = {n: float(v) for n, v in zip(ACTION_NAMES, safe.mean(axis=0))}  # also "always <command>"'s score
        report["safe_marks"] = {
            "marked_states": int(len(safe)),
            "safe_share": share,
            "baselines": {"the actors' own commands": float(safe[rows, marked.action].mean()),
                          **{f"always {n}": v for n, v in share.items()}},
            "models": {source: float(safe[rows, _greedy(net, memory, marked, True)].mean())
                       for source, net in nets.items()}}
        for source, share in report["safe_marks"]["models"].items():
            print(f"{source}: keeps a way out on {share:.1%} of the marked states", file=sys.stderr)
    try:
        states = memory.labelled()
    except ReplayError:
        if marked is None:
            raise ReplayError("no stored transition carries an expert label or a safe-set mark (the run trained "
                              "with explore.expert_label_prob = explore.safe_label_prob = 0?)") from None
        _print_json(report)
        return 0
    label = states.expert_action
    counts = np.bincount(label, minlength=len(ACTION_NAMES))
    majority = int(counts.argmax())
    report.update({
        "labelled_states": int(len(label)),
        "label_share": {n: float(c / len(label)) for n, c in zip(ACTION_NAMES, counts)},
        "baselines": {f"always {ACTION_NAMES[majority]}": float((label == majority).mean()),
                      "the actors' own commands": float((states.action == label).mean())},
        "models": {}})
    for source, net in nets.items():
        report["models"][source] = classification_metrics(label, _greedy(net, memory, states))
    for source in args.supervised:
        report["models"][f"{source} (supervised)"] = classification_metrics(
            label, predict(load_supervised_model(source).net, states.obs))
    for name, metrics in report["models"].items():
        print(f"{name}: agrees on {metrics['accuracy']:.1%} (balanced {metrics['balanced_accuracy']:.1%})",
              file=sys.stderr)
    _print_json(report)
    return 0


def _print_json(obj: Any) -> None:
    print(json.dumps(obj, indent=2, default=float))
