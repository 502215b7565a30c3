"""``cogexplore pretrain``: the supervised model (the authors' IROS 2016 baseline and the DRL's
initial conv layers) from expert-labelled depth images.

    cogexplore pretrain [--worlds corridor,paper-indoor] [--frames N] [--epochs E] [--out PATH]
                        [--preset P] [--data DIR]

Collects (or reuses, when ``--data`` already holds a dataset made with the same settings) the
labelled images (``shared.expert.dataset``), trains (``shared.expert.supervised``) with a progress bar, writes the model to
``--out`` (safetensors, with the JSON model card embedded and as ``<stem>.card.json``) and prints
the test accuracy, per class, and the confusion matrix. The sensor and the robot come from the
preset; the data is collected at the TEST speed table by default (the one the SL baseline is
evaluated at).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from pathlib import Path
from typing import Any

from shared.config import (
    ACTION_NAMES,
    ConfigError,
    RunConfig,
    load_preset,
    parse_override,
)

log = logging.getLogger("cogexplore.pretrain")

def parse_worlds(text: str) -> list[str]:
    """'corridor,paper-indoor' -> ['corridor', 'paper-indoor'] (empty names refused)."""
    worlds = [w.strip() for w in text.split(",")]
    if not text.strip() or any(not w for w in worlds):
        raise ConfigError(f"--worlds {text!r}: give comma-separated world names, e.g. corridor,paper-indoor")
    return worlds


def config_for(preset: str, overrides: list[str] | tuple[str, ...] = ()) -> RunConfig:
    """The preset with sensor./env. overrides and model.depth_encoding (what pretraining reads)."""
    cfg = load_preset(preset)
    parsed = dict(parse_override(o) for o in overrides)
    bad = sorted(k for k in parsed if not k.startswith(("sensor.", "env.")) and k != "model.depth_encoding")
    if bad:
        raise ConfigError(f"pretrain only takes sensor.*, env.* and model.depth_encoding overrides, got {bad}")
    return cfg.with_overrides(parsed) if parsed else cfg


def run_pretraining(cfg: RunConfig, *, out: str | Path, worlds: list[str], frames: int, epochs: int,
                    data_dir: str | Path | None = None, speed_table: str = "test", episode_steps: int = 150,
                    test_fraction: float = 0.2, batch_size: int = 64, lr: float = 1e-3,
                    class_balance: float = 0.5, seed: int = 0, device: str = "auto",
                    progress: bool = True) -> Any:
    """Collect or reuse the data, train, write the model; returns ``shared.expert.supervised.PretrainResult``."""
    from shared.expert.dataset import DriveConfig
    from shared.expert.supervised import TrainSettings, pretrain

    env_cfg = dataclasses.replace(cfg.env, speed_table=speed_table, start_index=None)
    return pretrain(out, worlds=worlds, frames=frames, sensor_cfg=cfg.sensor, env_cfg=env_cfg, data_dir=data_dir,
                    settings=TrainSettings(epochs=epochs, batch_size=batch_size, lr=lr, class_balance=class_balance,
                                           seed=seed, device=device, depth_encoding=cfg.model.depth_encoding),
                    drive_cfg=DriveConfig(episode_steps=episode_steps), seed=seed, test_fraction=test_fraction,
                    progress=progress)


def card_summary(card: dict[str, Any]) -> str:
    """The card's accuracy, per-class accuracy and confusion matrix as plain text."""
    data = card["data"]
    lines = [(f"data: {data['frames']} frames ({data['train_frames']} train / {data['test_frames']} test, "
              f"{data['episodes']} episodes, split by episode) from {', '.join(data['worlds'])}"),
             "labels: " + ", ".join(f"{k} {v}" for k, v in data["label_counts"].items()),
             (f"test accuracy {card['accuracy']:.3f} (balanced {card['balanced_accuracy']:.3f}; "
              f"always {card['majority_command']} {card['majority_accuracy']:.3f}; "
              "the paper's SL model: 0.802 on its own data)"),
             "per class: " + ", ".join(f"{k} {'-' if v is None else f'{v:.3f}'}"
                                      for k, v in card["per_class_accuracy"].items()),
             "confusion (rows: expert label, columns: predicted):",
             "  " + " " * 10 + "".join(f"{n:>11}" for n in ACTION_NAMES)]  # over the rows' name column
    for name, row in zip(ACTION_NAMES, card["confusion_matrix"]):
        lines.append(f"  {name:<10}" + "".join(f"{v:>11d}" for v in row))
    return "\n".join(lines)


def run_pretrain_command(args: argparse.Namespace) -> int:
    """``cogexplore pretrain``: returns a process exit status."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    cfg = config_for(args.preset, args.overrides)
    result = run_pretraining(cfg, out=args.out, worlds=parse_worlds(args.worlds), frames=args.frames,
                             epochs=args.epochs, data_dir=args.data, speed_table=args.speed_table,
                             episode_steps=args.episode_steps, test_fraction=args.test_fraction,
                             batch_size=args.batch_size, lr=args.lr, class_balance=args.class_balance,
                             seed=args.seed, device=args.device, progress=not args.quiet)
    if args.json:
        print(json.dumps(result.card, indent=2))  # stdout is the JSON alone: `| jq` reads it
    else:
        print(("reused" if result.data_reused else "collected") + f" data in {result.dataset.root}")
        print(card_summary(result.card))
    print(f"model: {result.model_path}", file=sys.stderr if args.json else sys.stdout)
    return 0
