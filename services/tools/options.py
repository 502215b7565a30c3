"""The options of the offline tools (``evaluate``, ``report``, ``experiment``, ``pretrain``,
``train``, ``worlds``, ``model``), apart from their code so that ``cogexplore --help`` and each
``cogexplore COMMAND --help`` import nothing heavy (no torch, MuJoCo, Zenoh or Rerun)."""

from __future__ import annotations

import argparse

from services.options import (
    add_cpu_threads_argument,
    add_protocol_arguments,
    add_runs_dir_argument,
    add_tensorboard_argument,
    count_argument,
    positive_number_argument,
)
from shared.config import SPEED_TABLES
from shared.evaluation import (
    DEFAULT_WORLD,
    PAPER_EPISODES_PER_START,
    PAPER_MAX_STEPS,
    POLICY_NAMES,
    PROTOCOLS,
    SELECTION_SEED,
    TEST_SEED,
)

PRETRAIN_WORLDS = ("corridor", "paper-indoor")
"""Worlds the supervised data is collected in by default (the paper's corridors and the test world)."""
PRETRAIN_OUT = "runs/pretrain/sl.safetensors"
EXPERIMENTS = ("paper",)
REPORT_PROTOCOLS = ("robust", "paper")
"""The protocols ``cogexplore report`` shows, in Table III's order: the robust one leads."""
UNSEEN_WORLDS = "procedural:101-103"
"""Worlds the experiment also tests every model in by default: no run or SL data plays them (the
shipped model's validation worlds are 201-210, its test worlds 301-330)."""


def add_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``cogexplore evaluate``."""
    parser.add_argument("--checkpoint", metavar="CKPT",
                        help="checkpoint file or directory, run folder, weights export, or `pretrained` "
                             "(the shipped DRL model; with --policy sl the shipped supervised model)")
    parser.add_argument("--ensemble", nargs="+", default=(), metavar="CKPT",
                        help="further checkpoints (as --checkpoint) whose Q-values the greedy policy averages "
                             "with --checkpoint's: a Q-value ensemble of independently trained models; the "
                             "episodes run in --checkpoint's environment (`model export A B --ensemble` makes "
                             "one file of it)")
    parser.add_argument("--policy", choices=POLICY_NAMES, default=None,
                        help="greedy (the checkpoint's; default with --checkpoint), random or reactive "
                             "(baselines, no checkpoint needed), sl (--checkpoint: a supervised model from "
                             "`cogexplore pretrain`), rl (--checkpoint: a frozen-conv Q-learning run; "
                             "greedy, labelled RL) or expert (the privileged map expert: commands from the "
                             "true pose and the world's map, never the image; a ceiling, not a baseline)")
    parser.add_argument("--world", default=None,
                        help="built-in world, procedural:<seed> or an MJCF file (default: the checkpoint's "
                             f"training world, else {DEFAULT_WORLD}); several, comma-separated or as seed "
                             "ranges (procedural:101-110), are evaluated one after the other and averaged")
    parser.add_argument("--episodes-per-start", type=int, default=PAPER_EPISODES_PER_START,
                        help=f"episodes from each start pose (default {PAPER_EPISODES_PER_START})")
    parser.add_argument("--max-steps", type=int, default=PAPER_MAX_STEPS,
                        help=f"moving steps per episode at most (default {PAPER_MAX_STEPS})")
    parser.add_argument("--starts", type=int, nargs="+", default=None, metavar="I",
                        help="only these start poses, numbered from 1 as in every table and "
                             "`worlds starts` (default: all)")
    parser.add_argument("--seed", type=int, default=TEST_SEED,
                        help=f"seed of the episodes and the random policy (default {TEST_SEED}: the test draws)")
    parser.add_argument("--foresight", action="store_true",
                        help="also ask the map expert at every decision whether some command still has a safe plan "
                             "(its 24-step horizon) and print, per world, how many decisions before each collision "
                             "the last such state was (how far ahead the policy went wrong); it only observes")
    parser.add_argument("--json", dest="json_out", metavar="PATH",
                        help="write the results JSON here (several worlds: one file each, PATH-<world>.json, written "
                             "as each world finishes, so an interrupted run keeps the worlds it finished)")
    parser.add_argument("--rrd", metavar="PATH", help="write a Rerun recording here")
    parser.add_argument("--image-every", type=int, default=1, metavar="N",
                        help="record every N-th depth image only (default 1)")
    live = parser.add_argument_group("Rerun live", "watch the evaluation while it runs (with or without --rrd)")
    live.add_argument("--rerun-connect", metavar="URL",
                      help="stream to a running Rerun viewer, e.g. rerun+http://127.0.0.1:9876/proxy (start one "
                           "with `rerun`); a viewer that does not answer is skipped with a warning")
    live.add_argument("--rerun-serve", action="store_true",
                      help="host a Rerun gRPC server and web viewer, print the address to open, and keep serving "
                           "after the evaluation until Ctrl-C")
    live.add_argument("--rerun-port", type=int, default=9876, metavar="PORT",
                      help="gRPC port of --rerun-serve (default 9876)")
    live.add_argument("--rerun-web-port", type=int, default=9090, metavar="PORT",
                      help="web viewer port of --rerun-serve (default 9090)")
    live.add_argument("--rerun-serve-seconds", type=float, default=None, metavar="S",
                      help="with --rerun-serve: stop serving S seconds after the evaluation (scripts, tests)")
    parser.add_argument("--device", default="auto", help="torch device: auto, cpu, cuda, cuda:N (default auto)")
    add_cpu_threads_argument(parser)
    parser.add_argument("--preset", default=None,
                        help="config preset for a baseline's sensor and env (default: the checkpoint's config, "
                             "else paper)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                        help="override a sensor./env. field, e.g. --set sensor.max_range_m=3.5 (repeatable; the "
                             "sensor's noise is the protocol's)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_protocol_arguments(parser)


def add_report_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``cogexplore report``."""
    parser.add_argument("run_dir", metavar="RUN_DIR", help="the run folder (runs/<run>)")
    parser.add_argument("--model", default=None, metavar="CKPT",
                        help="the model that stands for the run (default: its latest checkpoint; `cogexplore up` "
                             "gives the mean of its last checkpoints, see its --final-average)")
    parser.add_argument("--compare", nargs="+", action="extend", default=[], metavar="CKPT",
                        help="more checkpoints (files, directories, run folders or weights exports) to compare")
    parser.add_argument("--out", default=None, metavar="DIR", help="output folder (default RUN_DIR/report)")
    parser.add_argument("--episodes-per-start", type=int, default=PAPER_EPISODES_PER_START, metavar="N",
                        help=f"episodes from each start pose (default {PAPER_EPISODES_PER_START}, the paper's)")
    parser.add_argument("--max-steps", type=int, default=PAPER_MAX_STEPS, metavar="N",
                        help=f"moving steps per episode at most (default {PAPER_MAX_STEPS})")
    parser.add_argument("--world", default=None, help="world to evaluate in (default: the run's)")
    parser.add_argument("--probe", action="append", default=[], metavar="FILE",
                        help="an extra probe depth image: 16-bit PNG in millimetres or .npy in metres (repeatable)")
    parser.add_argument("--seed", type=int, default=TEST_SEED,
                        help=f"seed of the episodes and the random baseline (default {TEST_SEED}: the test draws)")
    parser.add_argument("--device", default="auto", help="torch device: auto, cpu, cuda, cuda:N (default auto)")
    add_cpu_threads_argument(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--protocol", nargs="+", choices=tuple(PROTOCOLS), default=list(REPORT_PROTOCOLS),
                        metavar="NAME", help="the test protocols of Table III, in order (default: "
                                             f"{' '.join(REPORT_PROTOCOLS)}; " + "; ".join(
                                                 p.describe() for p in PROTOCOLS.values()) + ")")


def add_experiment_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``cogexplore experiment``."""
    parser.add_argument("experiment", choices=EXPERIMENTS, help="which experiment (paper: Table III and Fig. 6)")
    parser.add_argument("--world", default="paper-indoor", help="world of training and test (default paper-indoor)")
    parser.add_argument("--checkpoints", default="500,4000,7500,40000",
                        help="DRL update counts to evaluate (default 500,4000,7500,40000, the paper's)")
    parser.add_argument("--actors", type=int, default=2, help="actor processes of the DRL run (default 2)")
    parser.add_argument("--preset", default="fast-40x30",
                        help="preset name or TOML path (default fast-40x30, our recipe on 2 CPU cores; `paper` "
                             "trains with the paper's Table I exactly, whose learning rate needs far more updates)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                        help="override a config field for every run and evaluation (repeatable)")
    parser.add_argument("--minutes-per-stage", type=float, default=None, metavar="M",
                        help="stop each training stage after M minutes (default: no limit)")
    parser.add_argument("--out", default="runs/experiment-paper", help="output folder (default runs/experiment-paper)")
    sl = parser.add_argument_group("SL model")
    sl.add_argument("--sl-model", default=None, metavar="PATH", help="use this supervised model instead of pretraining")
    sl.add_argument("--sl-worlds", default=",".join(PRETRAIN_WORLDS),
                    help=f"worlds of the SL data (default {','.join(PRETRAIN_WORLDS)})")
    sl.add_argument("--sl-frames", type=int, default=30_000, help="SL data size (default 30000)")
    sl.add_argument("--sl-epochs", type=int, default=3, help="SL training epochs (default 3)")
    parser.add_argument("--rl-updates", type=int, default=None,
                        help="updates of the RL baseline (default: the last DRL checkpoint's)")
    parser.add_argument("--unseen-worlds", default=UNSEEN_WORLDS, metavar="WORLDS",
                        help="worlds no run or SL data plays, where every model is tested too (generalisation): "
                             f"comma list, seed ranges like procedural:101-110; '' = none (default "
                             f"{UNSEEN_WORLDS})")
    parser.add_argument("--episodes-per-start", type=int, default=10, help="test episodes per start (default 10)")
    parser.add_argument("--max-steps", type=int, default=200, help="steps per test episode at most (default 200)")
    parser.add_argument("--seed", type=int, default=TEST_SEED,
                        help=f"seed of the supervised model's training and of the test episodes (default {TEST_SEED})")
    parser.add_argument("--device", default=None,
                        help="torch device for training: auto, cpu, cuda, cuda:N (default: the preset's train.device; "
                             "auto for the supervised model)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    add_protocol_arguments(parser, default="paper")


def add_pretrain_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``cogexplore pretrain``."""
    parser.add_argument("--worlds", default=",".join(PRETRAIN_WORLDS),
                        help=f"comma-separated worlds to collect data in (default {','.join(PRETRAIN_WORLDS)})")
    parser.add_argument("--frames", type=int, default=30_000, help="labelled images in all (default 30000)")
    parser.add_argument("--epochs", type=int, default=3, help="training epochs (default 3)")
    parser.add_argument("--out", default=PRETRAIN_OUT, help=f"model file (default {PRETRAIN_OUT})")
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
    parser.add_argument("--batch-size", type=int, default=64, help="images per SGD step (default 64)")
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (default 1e-3)")
    parser.add_argument("--class-balance", type=float, default=0.5,
                        help="class weights (1/frequency)**this: 0 plain loss, 1 balanced (default 0.5)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the data episodes and the training (default 0)")
    parser.add_argument("--device", default="auto", help="torch device: auto, cpu, cuda, cuda:N (default auto)")
    parser.add_argument("--json", action="store_true", help="print the model card as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    # train has one mode, one process; the flag stays so that older scripts keep working
    parser.add_argument("--single-process", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--preset", default=None,
                        help="preset name or TOML path (default: the run's config.toml where --run names one that "
                             "exists, so that it trains on with its own recipe; else paper)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                        help="override one config field (repeatable)")
    parser.add_argument("--run", default=None, help="run name (default: train-<date>-<time>)")
    add_runs_dir_argument(parser)
    parser.add_argument("--device", default=None,
                        help="torch device: auto, cpu, cuda, cuda:N (default: the config's train.device)")
    parser.add_argument("--updates", type=count_argument, default=None, help="override train.total_updates")
    parser.add_argument("--minutes", type=positive_number_argument, default=None, help="stop after this many minutes")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_tensorboard_argument(parser)


# -- worlds -------------------------------------------------------------------------------

def add_worlds_list_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--procedural", type=int, nargs="*", default=[0],
                   help="also list these procedural seeds (default: 0)")


def add_worlds_show_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("world", help="built-in name, procedural:<seed> or an MJCF path")
    p.add_argument("--out", default="map.png", help="PNG path (default: map.png)")


def add_worlds_starts_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("world", help="built-in name, procedural:<seed> or an MJCF path")
    p.add_argument("--speed", choices=("test", "train"), default="test",
                   help="speed table (default test: the protocol's)")
    p.add_argument("--horizon", type=int, default=60, help="steps a start must survive (default 60)")
    p.add_argument("--margin-m", type=float, default=0.0,
                   help="extra clearance and depth every step must keep (default 0: the task's exact thresholds)")
    p.add_argument("--json", action="store_true", help="print JSON")


def add_worlds_demo_arguments(p: argparse.ArgumentParser) -> None:
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
    p.add_argument("--protocol", choices=tuple(PROTOCOLS), default="paper",
                   help="where the plans begin: paper (default), each start's exact pose; robust, --episodes "
                        "draws around each start with the robust protocol's jitter and sensor noise")
    p.add_argument("--episodes", type=int, default=1, metavar="N",
                   help="with --protocol robust: draws per start, episode k's draw that of an evaluation with "
                        "--seed (default 1)")
    p.add_argument("--seed", type=int, default=TEST_SEED,
                   help=f"with --protocol robust: the draws' seed (default {TEST_SEED}: the very draws "
                        "`cogexplore evaluate` meets, a check that they can be survived; give another for "
                        "training demonstrations)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


# -- model --------------------------------------------------------------------------------

def add_model_summary_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default="paper", help="preset name or TOML path (default: paper)")
    p.add_argument("--json", action="store_true", help="print JSON")


def add_model_export_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoint", nargs="+",
                   help="checkpoint file or directory, run folder, weights export or `pretrained` (the shipped "
                        "model); with several (one run's later checkpoints), their weights' mean, labelled with "
                        "the last one's update")
    p.add_argument("--ensemble", action="store_true",
                   help="several checkpoints (independently trained runs) become one Q-value ensemble instead "
                        "of a weights' mean: the greedy command is the argmax of their mean Q-values (as "
                        "`evaluate --ensemble`), labelled with the first one's update")
    p.add_argument("--members", default=None, metavar="A,B,...",
                   help="keep only these networks of the ensemble (the shipped one, an ensemble's file, or what "
                        "--ensemble joined), in this order: each a member's label as the ensemble records it "
                        "(R3@104000), that label without its update (R3) or its index (one: that network alone; "
                        "`cogexplore model export pretrained --members R3 --out R3.safetensors`)")
    p.add_argument("--out", default=None, help="output .safetensors path (weights only, for torch)")
    p.add_argument("--onnx", default=None, metavar="F.onnx",
                   help="output ONNX path, instead of --out or beside it: the network for a robot computer "
                        "without torch (onnxruntime; `drive --onnx`), checked against torch before it is written")
    p.add_argument("--half", action="store_true", help="store the --out weights as float16 (half the size)")
    p.add_argument("--card", metavar="FILE.json",
                   help="a JSON file holding one object, stored in the exported file's metadata (model card)")


def add_model_agreement_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="run folder, its checkpoints directory or a checkpoint file whose replay memory was "
                               "kept, from a run with explore.expert_label_prob or explore.safe_label_prob > 0")
    p.add_argument("--model", action="append", default=None, metavar="SOURCE",
                   help="a Q-network: checkpoint, run folder, weights export or `pretrained` (repeatable; "
                        "default: pretrained)")
    p.add_argument("--supervised", action="append", default=[], metavar="SOURCE",
                   help="a supervised model (`cogexplore pretrain`; `pretrained` = the shipped one), repeatable")


def add_model_select_arguments(p: argparse.ArgumentParser) -> None:
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
                   help="episodes per start (default 1: one draw per start under the robust protocol; the "
                        "paper's repeats one episode exactly)")
    p.add_argument("--max-steps", type=int, default=PAPER_MAX_STEPS,
                   help=f"moving steps per episode at most (default {PAPER_MAX_STEPS})")
    p.add_argument("--half", action="store_true", help="store float16")
    p.add_argument("--device", default="auto", help="torch device: auto, cpu, cuda, cuda:N (default auto)")
    add_cpu_threads_argument(p)
    p.add_argument("--seed", type=int, default=SELECTION_SEED,
                   help=f"seed of the gate and validation episodes' start draws and sensor noise (default "
                        f"{SELECTION_SEED}: not the test's {TEST_SEED}, so no window is chosen on the draws `evaluate` "
                        f"and `report` then measure it on; --test worlds are played with {TEST_SEED})")
    add_protocol_arguments(p)
