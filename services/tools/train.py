"""``cogexplore train``: the paper's Algorithm 1 in one process.

    for each episode: reset at a random start
        while no collision: act epsilon-greedily, step, store the transition,
                            run the updates due at the replay ratio (1 per step in the paper)

It is the reference the distributed system is checked against, and its baseline: the same
LearnerCore (replay + agent + ratio rule) that the learner service drives, fed directly by
one environment through the rollout loop (``shared.rollout``) instead of by actors over Zenoh.
Writes runs/<run>/ like the distributed system: config, checkpoints, stats/learner.csv (loss,
mean Q) and stats/episodes.csv (length, return, epsilon), both also as TensorBoard events in tb/train/.
Weights that have diverged (NaN or infinite) are never saved: the trainer stops with one error line
naming the run's last good checkpoint, and its next start resumes there at half the learning rate
(``shared.learning.divergence``).
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import time
from pathlib import Path
from typing import Any

from tqdm import tqdm

from services.process import setup_logging, stop_event_on_signals
from services.runs import RunLock, RunPaths, resolve_config, save_config, saved_config
from shared.config import RunConfig
from shared.expert.expert import ExpertGuide
from shared.learning.checkpoints import CheckpointManager, NonFiniteWeights
from shared.learning.divergence import RunDivergences, sets_lr
from shared.learning.learner import (
    Diverged,
    LearnerCore,
    RateMeter,
    check_start_sources,
    diverged_error,
    resume_from,
)
from shared.learning.model import resolve_device
from shared.learning.policy import EpsilonGreedyPolicy, EpsilonSchedule
from shared.learning.stats import (
    CsvLog,
    EpisodeRow,
    LearnerRow,
    TensorBoardLog,
    episode_row,
    read_csv_records,
    rewind,
)
from shared.rollout import Episode, Rollout, Step
from shared.sim.env import ExploreEnv
from shared.wire.keys import validate_name
from shared.wire.messages import new_epoch

log = logging.getLogger("cogexplore.train")

NON_TERMINAL_REDRAW_S = 60.0
"""Seconds between redraws of the progress bar where stderr is no terminal (a log file, a pipe): each
redraw there is one more carriage return and bar in one endless line."""


class _Training:
    """Rollout observer: every transition into the learner, the updates it makes due, their log rows
    and checkpoints; every finished episode to ``episodes.csv`` and the progress bar. Both kinds of
    row also go to TensorBoard."""

    def __init__(self, cfg: RunConfig, core: LearnerCore, checkpoints: CheckpointManager,
                 divergences: RunDivergences, guide: ExpertGuide, learner_log: CsvLog, episode_log: CsvLog,
                 bar: Any, board: TensorBoardLog):
        self.cfg, self.core, self.checkpoints, self.divergences, self.guide = cfg, core, checkpoints, divergences, guide
        self.learner_log, self.episode_log, self.bar, self.board = learner_log, episode_log, bar, board
        self.started = time.monotonic()
        self.session = new_epoch()  # learner.csv's mark of this session: a resume's time_s starts again
        self.update_rate = RateMeter()
        self.config_dict = cfg.to_dict()
        self.episodes = 0
        self.recent_lengths: list[int] = []
        self.logged_update = core.updates

    def save(self, final: bool = False) -> Path | None:
        """A checkpoint (None: its write failed, said in one line; training goes on). CheckpointError when
        the ``final`` one fails (:meth:`LearnerCore.checkpoint`)."""
        path = self.core.checkpoint(self.checkpoints, self.config_dict, final=final)
        if path is not None:
            self.divergences.saved(self.core.updates, self.cfg.dqn.lr)
        return path

    def on_step(self, step: Step) -> None:
        core, train = self.core, self.cfg.train
        core.add_transition("env", step.obs, step.action, step.reward, None if step.terminated else step.next_obs,
                            step.terminated, step.truncated, self.guide.teacher_label(step.info["pose"]),
                            self.guide.safe_label(step.info["pose"]))
        for _ in range(core.updates_due()):
            if core.train_step() is None:  # skipped (a non-finite loss): no update to count, log or save
                continue
            self.update_rate.add(1)
            self.bar.update(1)
            if core.updates % train.log_every == 0:
                self.log_row()
            if core.updates % train.checkpoint_every == 0 and not core.done:  # the last one is the final save's
                self.save()

    def log_row(self) -> None:
        """One ``learner.csv`` row (and TensorBoard's) over the last ``train.log_every`` updates."""
        core, every = self.core, self.cfg.train.log_every
        loss, mean_q = core.recent(every)
        row = LearnerRow(
            time_s=time.monotonic() - self.started, update=core.updates,
            policy_version=core.agent.policy_version, loss=loss, mean_q=mean_q,
            updates_per_s=self.update_rate.rate(), transitions=core.received, transitions_per_s=None,
            replay_size=len(core.replay), rejected=0, actors_alive=1, mean_weight_lag=0.0,
            label_agreement=core.recent_label_agreement(every), safe_agreement=core.recent_safe_agreement(every),
            lr=core.agent.lr, session=self.session)
        self.learner_log.write(row)
        self.board.write_row(row)
        self.logged_update = core.updates

    def end_episode(self, episode: Episode) -> None:
        info, epsilon = episode.info, episode.last_step.choice.epsilon
        if not self.guide.active:  # the bar shows the network's episodes, not the expert's
            self.recent_lengths = (self.recent_lengths + [info["step"]])[-20:]
        row = episode_row(episode, env_step=self.core.received, update=self.core.updates,
                          time_s=time.monotonic() - self.started, expert_guided=self.guide.active)
        self.episode_log.write(row)
        self.board.write_row(row)
        self.episodes += 1
        loss, _ = self.core.recent()
        mean_steps = sum(self.recent_lengths) / max(len(self.recent_lengths), 1)
        agreement = self.core.recent_label_agreement()
        self.bar.set_postfix_str(f"eps {epsilon:.2f} | steps/ep {mean_steps:5.1f}"
                                 f" | loss {loss if loss is not None else float('nan'):.3g}"
                                 + ("" if agreement is None else f" | label {agreement:.2f}"), refresh=False)


def train_single_process(cfg: RunConfig, paths: RunPaths, stop: threading.Event | None = None, *,
                         progress: bool = True, max_minutes: float | None = None, tensorboard: bool = True,
                         lr_given: bool = False) -> dict:
    """Train until ``total_updates`` (or ``max_minutes``, or ``stop``); returns a summary. ``tensorboard``:
    the rows also as TensorBoard events in ``tb/train``; ``lr_given``: ``cfg``'s ``dqn.lr`` is the user's
    choice for this start, kept after a divergence (``shared.learning.divergence``). Diverged when the
    agent's weights have diverged: they are not saved, and the run's checkpoints stay as they were."""
    with RunLock(paths, "learner"):  # one learner writes a run
        return _train_locked(cfg, paths, stop or threading.Event(), progress=progress, max_minutes=max_minutes,
                             tensorboard=tensorboard, lr_given=lr_given)


def _train_locked(cfg: RunConfig, paths: RunPaths, stop: threading.Event, *, progress: bool,
                  max_minutes: float | None, tensorboard: bool, lr_given: bool) -> dict:
    paths.make()
    checkpoints = CheckpointManager(paths.checkpoints, keep=cfg.train.keep_checkpoints)
    divergences = RunDivergences(paths.root)
    cfg = divergences.resume_config(cfg, lr_given=lr_given)  # after a divergence: at half the rate it diverged at
    core = LearnerCore(cfg, device=cfg.train.device, transfer=not checkpoints.checkpoints())
    resumed = resume_from(checkpoints, core)
    save_config(cfg, paths)  # only now: a config that cannot resume the run (or run here) must not replace its own
    # its updates after the checkpoint come again; with none (a trainer killed before its first), all do
    rewind(paths.stats, LearnerRow, core.updates)
    # by env step: the episodes that ended after the checkpoint at its update (the warm-up's, or at a
    # replay ratio under 1) come again too
    rewind(paths.stats, EpisodeRow, core.received, column=EpisodeRow.STEP)
    logged_episodes = sum(1 for _ in read_csv_records(paths.stats / EpisodeRow.FILE)) \
        if (paths.stats / EpisodeRow.FILE).is_file() else 0
    env = ExploreEnv(cfg.env, cfg.sensor)
    guide = ExpertGuide(env, cfg.explore.expert_episode_prob, seed=cfg.train.seed + 2,
                        label_prob=cfg.explore.expert_label_prob, safe_prob=cfg.explore.safe_label_prob)
    policy = EpsilonGreedyPolicy(core.agent.online, EpsilonSchedule(cfg.explore), seed=cfg.train.seed + 1,
                                 guide=guide)
    deadline = time.monotonic() + max_minutes * 60 if max_minutes else None
    with CsvLog(paths.stats, LearnerRow) as learner_log, CsvLog(paths.stats, EpisodeRow) as episode_log, \
            TensorBoardLog(paths.tensorboard_folder("train") if tensorboard else None) as board, \
            tqdm(total=cfg.train.total_updates, initial=core.updates, desc="train", unit="upd",
                 dynamic_ncols=True, disable=not progress, mininterval=NON_TERMINAL_REDRAW_S
                 if not sys.stderr.isatty() else 0.1) as bar:
        training = _Training(cfg, core, checkpoints, divergences, guide, learner_log, episode_log, bar, board)
        loop = Rollout(env, policy, [guide, training], env_steps=core.received)  # epsilon goes on after a resume
        loop.episodes = logged_episodes  # episodes.csv numbers them on too
        loop.begin_episode(seed=cfg.train.seed + (core.received if resumed else 0))
        diverged: Diverged | NonFiniteWeights | None = None
        try:
            while not core.done and not stop.is_set() and (deadline is None or time.monotonic() < deadline):
                if loop.step().last:
                    loop.begin_episode()
            if core.updates != training.logged_update:  # the log ends at the last update, as the checkpoint does
                training.log_row()
            final = training.save(final=True)
        except (Diverged, NonFiniteWeights) as exc:  # it can no longer learn: its last good checkpoint stays
            diverged = exc
    env.close()
    if diverged is not None:
        raise diverged_error(diverged, checkpoints, core, divergences)
    return {"updates": core.updates, "env_steps": core.received, "episodes": training.episodes,
            "checkpoint": str(final), "seconds": time.monotonic() - training.started}


def train_config(args: argparse.Namespace, paths: RunPaths) -> RunConfig:
    """``--preset``, else the run's saved config.toml (a run trains on with its own recipe), else the
    paper's preset; then ``--set``, ``--device`` and ``--updates``."""
    cfg = resolve_config(args, paths, default_preset="paper")
    return cfg.with_overrides({"train.total_updates": args.updates}) if args.updates is not None else cfg


def run_train_command(args: argparse.Namespace) -> int:
    run = args.run or time.strftime("train-%Y%m%d-%H%M%S")
    validate_name(run, "run name")
    paths = RunPaths(Path(args.runs_dir) / run)
    cfg = train_config(args, paths)  # a bad preset or --set fails here, before the run folder exists
    # and so do a device this machine lacks and a missing or unfit transfer or demonstration file
    resolve_device(cfg.train.device)
    resumable = CheckpointManager(paths.checkpoints).checkpoints()
    check_start_sources(cfg, resumed_from=saved_config(paths) if resumable else None)
    setup_logging("INFO", paths.make().logs / "train.log")
    result = train_single_process(cfg, paths, stop_event_on_signals(), progress=not args.quiet,
                                  max_minutes=args.minutes, tensorboard=args.tensorboard,
                                  lr_given=sets_lr(args.overrides))
    print(result)
    return 0
