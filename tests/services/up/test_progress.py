"""The progress line of ``cogexplore up``: what limits the run, env steps/s over the run, and the end
time once there is a minute of learning, made from plain numbers (no bus) and from real stats messages."""

from __future__ import annotations

import dataclasses
import time

from services.up.launcher import (
    ETA_AFTER_S,
    LEARNER_SILENT_S,
    Progress,
    ProgressFigures,
    limiter,
    progress_line,
)
from shared.wire.messages import EpisodeStats, LearnerStats

LEARNING = ProgressFigures(
    updates=100, total_updates=500, transitions_received=1400, warmup_transitions=1000, learning_s=90.0,
    learning_updates=100, learning_goal=500, waiting_share=0.0, held_share=0.8, env_steps=3000, env_s=100.0, episodes=20,
    mean_steps=42.0, loss=1.5, actors_alive=2, clock_s=time.mktime((2030, 1, 1, 12, 0, 0, 0, 0, -1)))


def figures(**changes) -> ProgressFigures:
    return dataclasses.replace(LEARNING, **changes)


def learner_stats(updates: int, received: int, waiting_share: float | None = None) -> LearnerStats:
    extra = {} if waiting_share is None else {LearnerStats.WAITING_SHARE: waiting_share}
    return LearnerStats(learner_id="learner", updates=updates, policy_version=updates, replay_size=received,
                        transitions_received=received, transitions_rejected=0, loss=None if not updates else 1.0,
                        mean_q=None, updates_per_s=0.0, transitions_per_s=0.0, uptime_s=1.0, extra=extra)


def episode(steps: int, duration_s: float, held_s: float = 0.0) -> EpisodeStats:
    return EpisodeStats(actor_id="actor-0", episode=0, start_index=0, steps=steps, episode_return=float(steps),
                        terminated=False, truncated=True, collision_cause=None, path_length_m=1.0,
                        distance_from_start_m=1.0, epsilon=1.0, policy_version=0, duration_s=duration_s,
                        extra={EpisodeStats.HELD_S: held_s})


def test_each_limiter_has_its_label() -> None:
    assert limiter(figures(transitions_received=None, learning_s=None)) == "starting: waiting for the learner"
    assert limiter(figures(transitions_received=400, learning_s=None)) == "warm-up: filling replay 400/1000"
    assert limiter(figures(transitions_received=1200, learning_s=None)) == "warm-up: filling replay 1000/1000"
    # a resume without its replay memory warms up again: the memory fills, the count is long past
    assert limiter(figures(transitions_received=52000, replay_size=300, learning_s=None)) == (
        "warm-up: filling replay 300/1000")
    assert limiter(figures(waiting_share=0.02)) == "learner-bound: actors held by flow control 80% of the time"
    assert limiter(figures(waiting_share=0.02, held_share=None)) == "learner-bound: the learner never waits for data"
    assert limiter(figures(waiting_share=0.02, held_share=0.05)) == ("balanced: the learner never waits, the actors "
                                                                     "are not held")
    assert limiter(figures(waiting_share=0.6, held_share=0.0)) == ("actor-bound: the learner waits for data 60% of "
                                                                   "the time")
    assert limiter(figures(actors_alive=0)) == "no actor alive: the learner waits"
    assert limiter(figures(waiting_share=None, held_share=None)) == "learning"  # older services: no claim made
    assert limiter(figures(updates=500)) == "finishing: final checkpoint"


def test_the_line_shows_env_steps_per_second_over_the_run_and_the_end_time() -> None:
    line = progress_line(LEARNING)
    # 3000 steps in 100 s; 400 updates left at 100 updates in 90 s: 360 s, from 12:00
    assert line == ("learner-bound: actors held by flow control 80% of the time | env 30 st/s avg | ep 20 | steps/ep 42.0 | "
                    "loss 1.5 | actors 2 | ends ~12:06 (6m00s left)")
    early = progress_line(figures(updates=0, learning_s=None, learning_updates=0, transitions_received=10,
                                  env_steps=0, env_s=None, episodes=0, mean_steps=None, loss=None))
    assert early == ("warm-up: filling replay 10/1000 | env - st/s avg | ep 0 | steps/ep - | loss - | actors 2 | "
                     "ETA after the first minute")
    # a run whose transitions carry the expert's labels (explore.expert_label_prob) shows the agreement
    assert "| loss 1.5 | label 0.43 | actors 2 |" in progress_line(figures(label_agreement=0.432))


def test_the_end_time_waits_for_a_minute_or_five_percent_of_the_updates() -> None:
    assert "ETA after the first minute" in progress_line(figures(learning_s=ETA_AFTER_S - 1, learning_updates=20))
    assert "ends ~" in progress_line(figures(learning_s=ETA_AFTER_S, learning_updates=20))
    assert "ends ~" in progress_line(figures(learning_s=10.0, learning_updates=25))  # 5% of 500
    assert "ETA after the first minute" in progress_line(figures(learning_s=120.0, learning_updates=0))


def test_a_time_limit_that_comes_first_is_the_end_time() -> None:
    # 400 updates left take 360 s; --minutes stops the run in 120 s, even before the first minute
    assert progress_line(figures(time_left_s=120.0)).endswith("ends ~12:02 (2m00s left, --minutes)")
    assert progress_line(figures(time_left_s=90.0, learning_s=None, learning_updates=0)).endswith(
        "ends ~12:01 (1m30s left, --minutes)")
    assert progress_line(figures(time_left_s=900.0)).endswith("ends ~12:06 (6m00s left)")  # the updates end first


def test_progress_averages_over_the_run_and_leaves_the_warm_up_out_of_the_rate() -> None:
    progress = Progress(total_updates=500, warmup_transitions=1000)
    progress.on_learner(learner_stats(0, 200, waiting_share=1.0), now=0.0)
    progress.on_episode(episode(50, duration_s=10.0), now=10.0)  # began at 0 s
    progress.on_learner(learner_stats(0, 1000, waiting_share=1.0), now=30.0)
    assert limiter(progress.figures(2, now=30.0)) == "warm-up: filling replay 1000/1000"
    progress.on_episode(episode(150, duration_s=30.0), now=39.0)  # ended in the warm-up: not the learner's pace
    progress.on_learner(learner_stats(10, 1040, waiting_share=0.0), now=40.0)  # learning began
    for t in range(41, 101):
        progress.on_learner(learner_stats(10 + (t - 40) * 2, 1040 + (t - 40) * 8, waiting_share=0.0), now=float(t))
    progress.on_episode(episode(0, duration_s=30.0, held_s=27.0), now=100.0)
    progress.on_episode(episode(0, duration_s=10.0, held_s=9.0), now=100.0)
    f = progress.figures(2, now=100.0, clock_s=LEARNING.clock_s)
    assert (f.env_steps, f.env_s) == (200, 100.0)  # 2 st/s over the run, not the last second's 0
    assert (f.learning_s, f.learning_updates) == (60.0, 120)  # 2 updates/s, the warm-up's 40 s left out
    assert f.waiting_share == 0.0  # the last 10 reports, averaged
    assert f.held_share == 0.9  # 36 s of 40
    assert limiter(f) == "learner-bound: actors held by flow control 90% of the time"
    assert progress.figures(2, now=200.0).held_share is None  # a minute on, nothing new: no claim
    assert progress_line(f).endswith("ends ~12:03 (3m05s left)")  # 370 updates left at 2/s


def test_a_learner_that_goes_silent_is_said_and_one_that_speaks_again_is_not() -> None:
    # A learner stopped (SIGSTOP, a laptop asleep) or stuck froze the progress line on its last figures, which
    # went on reading "learner-bound" with an end time: nothing said the run had stopped moving.
    progress = Progress(total_updates=500, warmup_transitions=100)
    assert progress.figures(2, now=0.0).learner_silent_s is None
    progress.on_learner(learner_stats(200, 2000, waiting_share=0.0), now=5.0)
    progress.on_learner(learner_stats(201, 2004, waiting_share=0.0), now=10.0)  # learning
    assert limiter(progress.figures(2, now=10.0 + LEARNER_SILENT_S - 1)).startswith("learner-bound")
    quiet = progress.figures(2, now=10.0 + LEARNER_SILENT_S + 65)
    assert quiet.learner_silent_s == LEARNER_SILENT_S + 65
    assert limiter(quiet) == "learner silent for 1m20s: stopped or stuck?"  # 15 + 65 s
    assert progress_line(quiet).startswith("learner silent for")
    progress.on_learner(learner_stats(202, 2008, waiting_share=0.0), now=100.0)
    assert limiter(progress.figures(2, now=101.0)).startswith("learner-bound")
    # a learner not heard from yet is starting, not silent
    assert limiter(figures(transitions_received=None, learner_silent_s=None)) == "starting: waiting for the learner"
