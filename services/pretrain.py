"""``cogexplore pretrain``: the supervised model (the authors' IROS 2016 baseline and the DRL's
initial conv layers) from expert-labelled depth images.

    cogexplore pretrain [--worlds corridor,paper-indoor] [--frames N] [--epochs E] [--out PATH]
                        [--preset P] [--data DIR]

Collects (or reuses, when ``--data`` already holds a dataset made with the same settings) the
labelled images (``shared.supervised``), trains with a progress bar, writes the model to
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
    SPEED_TABLES,
    ConfigError,
    RunConfig,
    load_preset,
    parse_override,
)

log = logging.getLogger("cogexplore.pretrain")

DEFAULT_WORLDS = ("corridor", "paper-indoor")
DEFAULT_OUT = "runs/pretrain/sl.safetensors"


def parse_worlds(text: str) -> list[str]:
    """'corridor,paper-indoor' -> ['corridor', 'paper-indoor'] (empty names refused)."""
    worlds = [w.strip() for w in text.split(",")]
    if not text.strip() or any(not w for w in worlds):
        raise ConfigError(f"--worlds {text!r}: give comma-separated world names, e.g. corridor,paper-indoor")
    return worlds


def add_pretrain_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``cogexplore pretrain``."""
    parser.add_argument("--worlds", default=",".join(DEFAULT_WORLDS),
                        help=f"comma-separated worlds to collect data in (default {','.join(DEFAULT_WORLDS)})")
    parser.add_argument("--frames", type=int, default=30_000, help="labelled images in all (default 30000)")
    parser.add_argument("--epochs", type=int, default=3, help="training epochs (default 3)")
    parser.add_argument("--out", default=DEFAULT_OUT, help=f"model file (default {DEFAULT_OUT})")
    parser.add_argument("--data", default=None, metavar="DIR",
                        help="dataset folder, reused when it matches (default: <out stem>-data next to --out)")
    parser.add_argument("--preset", default="paper", help="preset for the sensor and robot (default paper)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                        help="override a sensor./env. field (repeatable)")
    parser.add_argument("--speed-table", choices=sorted(SPEED_TABLES), default="test",
                        help="speeds the data is driven at (default test)")
    parser.add_argument("--episode-steps", type=int, default=150, help="data episode cap (default 150)")
    parser.add_argument("--test-fraction", type=float, default=0.2,
                        help="share of the frames, in whole episodes, held out for testing (default 0.2)")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (default 1e-3)")
    parser.add_argument("--class-balance", type=float, default=0.5,
                        help="class weights (1/frequency)**this: 0 plain loss, 1 balanced (default 0.5)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="auto", help="torch device: auto, cpu, cuda, cuda:N")
    parser.add_argument("--json", action="store_true", help="print the model card as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


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
    """Collect or reuse the data, train, write the model; returns ``shared.supervised.PretrainResult``."""
    from shared.supervised import DriveConfig, TrainSettings, pretrain

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
              f"always-majority {data['majority_class_rate']:.3f}; the paper's SL model: 0.802 on its own data)"),
             "per class: " + ", ".join(f"{k} {'-' if v is None else f'{v:.3f}'}"
                                      for k, v in card["per_class_accuracy"].items()),
             "confusion (rows: expert label, columns: predicted):",
             "  " + " ".join(f"{n[:6]:>7}" for n in ACTION_NAMES)]
    for name, row in zip(ACTION_NAMES, card["confusion_matrix"]):
        lines.append(f"  {name[:10]:<10} " + " ".join(f"{v:>7d}" for v in row))
    return "\n".join(lines)


def run_pretrain_command(args: argparse.Namespace) -> int:
    """``cogexplore pretrain``: returns a process exit status."""
    from shared.supervised import SupervisedError

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        cfg = config_for(args.preset, args.overrides)
        result = run_pretraining(cfg, out=args.out, worlds=parse_worlds(args.worlds), frames=args.frames,
                                 epochs=args.epochs, data_dir=args.data, speed_table=args.speed_table,
                                 episode_steps=args.episode_steps, test_fraction=args.test_fraction,
                                 batch_size=args.batch_size, lr=args.lr, class_balance=args.class_balance,
                                 seed=args.seed, device=args.device, progress=not args.quiet)
    except (SupervisedError, ConfigError, ValueError) as exc:
        print(f"cogexplore pretrain: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(result.card, indent=2))
    else:
        print(("reused" if result.data_reused else "collected") + f" data in {result.dataset.root}")
        print(card_summary(result.card))
    print(f"model: {result.model_path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="cogexplore pretrain", description=__doc__.split("\n\n")[0])
    add_pretrain_arguments(parser)
    return run_pretrain_command(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
