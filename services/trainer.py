"""``cogexplore train --single-process``: the paper's Algorithm 1 in one process.

    for each episode: reset at a random start
        while no collision: act epsilon-greedily, step, store the transition,
                            run the updates due at the replay ratio (1 per step in the paper)

It is the reference the distributed system is checked against, and its baseline: the same
LearnerCore (replay + agent + ratio rule) that the learner service drives, fed directly by
one environment instead of by actors over Zenoh. Writes runs/<run>/ like the distributed
system: config, checkpoints, stats/learner.csv (loss, mean Q) and stats/episodes.csv
(length, return, epsilon).
"""

from __future__ import annotations

import argparse
import csv
import logging
import threading
import time

from tqdm import tqdm

from services.common import RunPaths, resolve_config, save_config, setup_logging, stop_event_on_signals
from services.learner.core import LearnerCore, RateMeter
from services.learner.service import STATS_COLUMNS, format_agreement, resume_from
from shared.checkpoint import CheckpointManager
from shared.config import RunConfig
from shared.env import ExploreEnv
from shared.policy import EpsilonGreedyPolicy, EpsilonSchedule
from shared.supervised import ExpertGuide

log = logging.getLogger("cogexplore.train")

EPISODE_COLUMNS = ("episode", "env_step", "update", "start_index", "steps", "return", "epsilon",
                   "collision_cause", "distance_m", "path_length_m", "time_s", "expert_guided", "world")


def train_single_process(cfg: RunConfig, paths: RunPaths, stop: threading.Event | None = None, *,
                         progress: bool = True, max_minutes: float | None = None) -> dict:
    """Train until ``total_updates`` (or ``max_minutes``, or ``stop``); returns a summary."""
    stop = stop or threading.Event()
    paths.make()
    save_config(cfg, paths)
    core = LearnerCore(cfg, device=cfg.train.device)
    checkpoints = CheckpointManager(paths.checkpoints, keep=cfg.train.keep_checkpoints)
    resumed = resume_from(checkpoints, core)
    env = ExploreEnv(cfg.env, cfg.sensor)
    policy = EpsilonGreedyPolicy(core.agent.online, EpsilonSchedule(cfg.explore), seed=cfg.train.seed + 1)
    guide = ExpertGuide(env, cfg.explore.expert_episode_prob, seed=cfg.train.seed + 2)
    config_dict = cfg.to_dict()
    deadline = time.monotonic() + max_minutes * 60 if max_minutes else None
    started = time.monotonic()
    update_rate = RateMeter()

    stats_new = not (paths.stats / "learner.csv").exists()
    episodes_new = not (paths.stats / "episodes.csv").exists()
    with open(paths.stats / "learner.csv", "a", newline="") as lf, \
            open(paths.stats / "episodes.csv", "a", newline="") as ef:
        learner_log, episode_log = csv.writer(lf), csv.writer(ef)
        if stats_new:
            learner_log.writerow(STATS_COLUMNS)
        if episodes_new:
            episode_log.writerow(EPISODE_COLUMNS)
        bar = tqdm(total=cfg.train.total_updates, initial=core.updates, desc="train", unit="upd",
                   dynamic_ncols=True, disable=not progress)
        env_step = core.received
        episode = 0
        recent_lengths: list[int] = []
        obs, info = env.reset(seed=cfg.train.seed + (core.received if resumed else 0))
        guide.begin_episode()
        policy.reset()
        episode_return = 0.0
        while not core.done and not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            choice = policy.act(obs, step=env_step, guide_action=guide.action(info["pose"]))
            next_obs, reward, terminated, truncated, info = env.step(choice.action)
            core.add_transition("env", obs, choice.action, reward, None if terminated else next_obs,
                                terminated, truncated)
            env_step += 1
            episode_return += reward
            for _ in range(core.updates_due()):
                core.train_step()
                update_rate.add(1)
                bar.update(1)
                if core.updates % cfg.train.log_every == 0:
                    loss, mean_q = core.recent(cfg.train.log_every)
                    learner_log.writerow([round(time.monotonic() - started, 3), core.updates,
                                          core.agent.policy_version, f"{loss:.6g}", f"{mean_q:.6g}",
                                          f"{update_rate.rate():.3f}", core.received, "", len(core.replay),
                                          0, 1, 0, format_agreement(core.recent_demo_agreement(cfg.train.log_every))])
                    lf.flush()
                if core.updates % cfg.train.checkpoint_every == 0:
                    checkpoints.save(core.agent, replay=core.replay, config=config_dict,
                                     extra={"transitions_received": core.received})
            obs = next_obs
            if terminated or truncated:
                if not guide.active:  # the bar shows the network's episodes, not the expert's
                    recent_lengths = (recent_lengths + [info["step"]])[-20:]
                episode_log.writerow([episode, env_step, core.updates, info["start_index"], info["step"],
                                      episode_return, f"{choice.epsilon:.4f}", info["collision_cause"] or "",
                                      f"{info['distance_from_start_m']:.3f}", f"{info['path_length_m']:.3f}",
                                      round(time.monotonic() - started, 3), int(guide.active), info["world"]])
                ef.flush()
                episode += 1
                loss, mean_q = core.recent()
                mean_steps = sum(recent_lengths) / max(len(recent_lengths), 1)
                agreement = core.recent_demo_agreement()
                bar.set_postfix_str(f"eps {choice.epsilon:.2f} | steps/ep {mean_steps:5.1f}"
                                    f" | loss {loss if loss is not None else float('nan'):.3g}"
                                    + ("" if agreement is None else f" | demo {agreement:.2f}"), refresh=False)
                obs, info = env.reset()
                guide.begin_episode()
                policy.reset()
                episode_return = 0.0
        bar.close()
    final = checkpoints.save(core.agent, replay=core.replay, config=config_dict,
                             extra={"transitions_received": core.received})
    env.close()
    return {"updates": core.updates, "env_steps": env_step, "episodes": episode,
            "checkpoint": str(final), "seconds": time.monotonic() - started}


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--single-process", action="store_true",
                        help="run Algorithm 1 in this one process (the reference; the distributed "
                             "system is `cogexplore up`)")
    parser.add_argument("--preset", default="paper", help="preset name or TOML path (default: paper)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                        help="override one config field (repeatable)")
    parser.add_argument("--run", default=None, help="run name (default: train-<date>-<time>)")
    parser.add_argument("--runs-dir", default="runs")
    parser.add_argument("--device", default=None, help="auto, cpu, cuda, cuda:N")
    parser.add_argument("--updates", type=int, default=None, help="override train.total_updates")
    parser.add_argument("--minutes", type=float, default=None, help="stop after this many minutes")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run_train_command(args: argparse.Namespace) -> int:
    from pathlib import Path

    from shared.keys import validate_name

    if not args.single_process:
        print("cogexplore train needs --single-process; the distributed trainer is `cogexplore up`")
        return 2
    run = args.run or time.strftime("train-%Y%m%d-%H%M%S")
    validate_name(run, "run name")
    paths = RunPaths(Path(args.runs_dir) / run).make()
    setup_logging("INFO", paths.logs / "train.log")
    cfg = resolve_config(args, paths)
    if args.updates is not None:
        cfg = cfg.with_overrides({"train.total_updates": args.updates})
    result = train_single_process(cfg, paths, stop_event_on_signals(), progress=not args.quiet,
                                  max_minutes=args.minutes)
    print(result)
    return 0
