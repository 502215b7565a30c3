"""The actor process end to end: ``run_actor`` on the smoke preset against a real Zenoh router on
loopback, with this test speaking as the learner (liveliness token and flow control) and reading
what the actor publishes."""

from __future__ import annotations

import threading
import time

import pytest

from services.actor.service import run_actor
from services.bus.session import (
    ZenohSettings,
    declare_alive,
    free_tcp_port,
    open_router,
    open_session,
    subscribe_messages,
)
from shared.config import load_preset
from shared.wire.keys import RunKeys
from shared.wire.messages import EpisodeStats, FlowControl, RejectCounter, TransitionBatch


@pytest.fixture(scope="module")
def router() -> str:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_router([endpoint]):
        yield endpoint


def play(router: str, run: str, max_steps: int, *, received: int = 0, overrides: dict | None = None,
         batch_steps: int = 16, seed: int | None = 3) -> tuple[dict, list[TransitionBatch], list[EpisodeStats]]:
    """run_actor for ``max_steps`` env steps, this test being its learner: alive, with all the credit
    it wants and ``received`` transitions of the run so far; returns its counters, the batches and
    the episode stats it published (once they have all arrived). ``seed``: the actor's (None: its own
    process's, as the actor command leaves it)."""
    cfg = load_preset("smoke").with_overrides(overrides or {})
    settings = ZenohSettings(connect=(router,))
    keys = RunKeys(run)
    batches: list[TransitionBatch] = []
    episodes: list[EpisodeStats] = []
    done = threading.Event()
    with open_session(settings) as session:
        token = declare_alive(session, keys.alive("learner", "L"))
        subs = [subscribe_messages(session, keys.all_transitions, TransitionBatch,
                                   lambda m, _k: batches.append(m), RejectCounter("batch")),
                subscribe_messages(session, keys.all_stats("episode"), EpisodeStats,
                                   lambda m, _k: episodes.append(m), RejectCounter("episode stats"))]
        flow = FlowControl(learner_id="L", updates=0, transitions_received=received,
                           transitions_wanted=received + 10**9).encode()

        def speak_as_the_learner() -> None:
            while not done.wait(0.1):
                session.put(keys.flow, flow)

        speaker = threading.Thread(target=speak_as_the_learner, daemon=True)
        speaker.start()
        try:
            counters = run_actor(cfg, run, "a-1", settings, threading.Event(), max_steps=max_steps, seed=seed,
                                 batch_steps=batch_steps)
            deadline = time.monotonic() + 20
            while (sum(b.steps for b in batches) < counters["env_steps"]
                   or len(episodes) < counters["episodes"]) and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.3)  # anything more would have come by now
        finally:
            done.set()
            speaker.join()
            for held in (token, *subs):
                held.undeclare()
    return counters, batches, episodes


def test_epsilon_goes_on_from_the_runs_env_steps_not_from_this_process_start(router: str) -> None:
    """An actor that joins a run the learner has already collected 10^6 transitions for (a resumed
    run, or a restarted actor) explores at the end of the decay, as the single-process trainer does
    after a resume -- not at eps_start again for eps_decay_steps / N of its own steps."""
    overrides = {"explore.eps_start": 1.0, "explore.eps_end": 0.05, "explore.eps_decay_steps": 100_000}
    counters, _, episodes = play(router, "eps-resumed", 60, received=10**6, overrides=overrides)
    assert counters["episodes"] >= 1 and episodes, counters
    assert all(e.epsilon == pytest.approx(0.05) for e in episodes), [e.epsilon for e in episodes]
    # a fresh run (the learner has nothing yet) starts at eps_start, as before
    _, _, fresh = play(router, "eps-fresh", 60, received=0, overrides=overrides)
    assert fresh and fresh[0].epsilon > 0.99, [e.epsilon for e in fresh]


def test_a_restarted_actor_plays_new_episodes_and_a_fixed_seed_the_same_ones(router: str) -> None:
    """Two processes of one actor id (a restart by compose or up) start from other poses with other
    noise: the replay gets no duplicate episodes. A seed given repeats its episodes exactly."""
    def played(run: str, seed: int | None) -> list[tuple[int, int, list, list]]:
        """Every step's episode, start, pose and command: 40 steps, too many to match by chance (an
        episode's first start and command alone matched one time in a few dozen). Random commands
        only: a greedy one would come from the actor's network, whose weights no learner sent here."""
        random = {"explore.eps_start": 1.0, "explore.eps_end": 1.0}
        _, batches, _ = play(router, run, 40, seed=seed, overrides=random)
        return [(b.episode, b.start_index, b.pose.tolist(), b.action.tolist())
                for b in sorted(batches, key=lambda b: (b.episode, b.first_step))]

    first, restarted = played("restart-1", None), played("restart-2", None)
    assert first != restarted, first
    assert played("fixed-1", 3) == played("fixed-2", 3)


def test_every_step_reaches_the_learner_including_the_last_partial_batch(router: str) -> None:
    """Steps are sent in batches of 16 cut at episode ends; the steps of the episode still playing
    when the actor stops are sent too, not dropped with the process."""
    expert = {"explore.expert_episode_prob": 1.0, "explore.eps_start": 0.0, "explore.eps_end": 0.0}
    counters, batches, _ = play(router, "flush", 70, overrides=expert)  # 50-step episodes: 20 into the second
    assert counters["env_steps"] == 70
    by_episode: dict[int, list[TransitionBatch]] = {}
    for b in batches:
        by_episode.setdefault(b.episode, []).append(b)
    assert sorted(by_episode) == [0, 1], sorted(by_episode)
    for episode, got in by_episode.items():  # contiguous, from step 0, no gaps
        got.sort(key=lambda b: b.first_step)
        assert [b.first_step for b in got] == [sum(b.steps for b in got[:i]) for i in range(len(got))]
    assert sum(b.steps for b in by_episode[1]) == 20, [(b.first_step, b.steps) for b in by_episode[1]]
    last = by_episode[1][-1]
    assert not last.terminated and not last.truncated and last.next_depth(last.steps - 1) is not None


def test_an_actor_without_a_learner_waits_and_stops_on_request_counting_the_pause(router: str) -> None:
    """No learner on the run: the actor steps nothing and waits (no busy loop) until it is stopped,
    then ends within a second and reports the time it spent waiting."""
    stop = threading.Event()
    stopper = threading.Timer(2.0, stop.set)
    stopper.start()
    started = time.monotonic()
    cpu = time.process_time()
    counters = run_actor(load_preset("smoke"), "no-learner", "a-1", ZenohSettings(connect=(router,)), stop, seed=3)
    stopper.join()
    assert time.monotonic() - started < 2.0 + 1.5
    assert time.process_time() - cpu < 1.5  # it waited: 2 s of spinning would take about as much CPU
    assert counters["env_steps"] == 0 and counters["batches"] == 0, counters
    assert counters["paused_s"] > 1.0, counters
