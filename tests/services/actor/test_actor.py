"""The actor's pure parts: batching transitions for the wire and the learner's flow control."""

import numpy as np
import pytest

from services.actor.batcher import TransitionBatcher
from services.actor.service import FlowGate
from services.cli import build_parser
from shared.config import MAX_ACTION_HISTORY, load_preset
from shared.learning.learner import LearnerCore
from shared.wire.messages import MAX_BATCH_STEPS, FlowControl, TransitionBatch


def _frame(value: float) -> np.ndarray:
    return np.full((30, 40), value, dtype=np.float32)


def _flow(credit: int, received_from_a: int, learner_epoch: int = 1, actor_epoch: int = 0) -> FlowControl:
    return FlowControl(learner_id="l", updates=0, transitions_received=100, transitions_wanted=100 + credit,
                       received_from={"a": received_from_a}, actor_epochs={"a": actor_epoch},
                       learner_epoch=learner_epoch)


def test_batcher_cuts_at_size_and_episode_end_and_never_spans_episodes():
    batcher = TransitionBatcher("a", batch_steps=3)
    batcher.begin_episode(_frame(1.0), start_index=2)
    out = [batcher.add(1, 1.0, _frame(1.0 + 0.1 * k), False, False, 0, (0.0, 0.0, 0.0)) for k in range(1, 4)]
    assert out[:2] == [None, None] and out[2].steps == 3 and out[2].next_depth_mm is not None
    assert out[2].first_step == 0 and out[2].start_index == 2
    last = batcher.add(2, -100.0, _frame(0.3), True, False, 5, (1.0, 1.0, 0.0))
    assert last.steps == 1 and last.terminated and last.next_depth_mm is None and last.first_step == 3
    # the next batch starts a new episode with the observation of the reset
    batcher.begin_episode(_frame(2.0), start_index=0)
    b = batcher.add(0, 1.0, _frame(2.1), False, True, 6, (0.0, 0.0, 0.0))
    assert b.episode == 1 and b.truncated and b.next_depth_mm is not None
    assert int(b.depth_mm[0, 0, 0]) == 2000


def test_batcher_flush_gives_the_steps_held_as_a_batch_cut_mid_episode():
    batcher = TransitionBatcher("a", batch_steps=4)
    assert batcher.flush() is None  # nothing begun
    batcher.begin_episode(_frame(1.0), start_index=1)
    for k in range(1, 3):
        assert batcher.add(1, 1.0, _frame(1.0 + 0.1 * k), False, False, 0, (0.0, 0.0, 0.0)) is None
    held = batcher.flush()
    assert held.steps == 2 and held.first_step == 0 and not (held.terminated or held.truncated)
    assert int(held.next_depth_mm[0, 0]) == 1200  # the last step's next image: a whole transition
    assert batcher.flush() is None and batcher.pending == 0
    after = batcher.add(2, 1.0, _frame(1.3), False, False, 0, (0.0, 0.0, 0.0))
    assert after is None and batcher.flush().first_step == 2  # the episode goes on where it was


def test_flow_gate_counts_in_flight_transitions_once():
    gate = FlowGate("a", horizon_s=10.0)
    assert not gate.open(now=0.0), "no word from the learner yet: hold, rather than send beyond what it wants"
    assert not gate.open(now=9.0) and gate.open(now=11.0), "but a learner silent for the horizon holds no one"
    gate.on_flow(_flow(credit=20, received_from_a=0))
    gate.sent(16)
    assert gate.open()  # 4 more wanted than in flight
    gate.sent(16)
    assert not gate.open()  # 32 in flight > 20 wanted
    gate.on_flow(_flow(credit=20, received_from_a=16))  # 16 arrived, 16 still in flight
    assert gate.open()
    gate.on_flow(_flow(credit=0, received_from_a=32))
    assert not gate.open()


def test_flow_gate_recovers_when_a_learner_restarts():
    gate = FlowGate("a")
    gate.on_flow(_flow(credit=10, received_from_a=500))
    gate.sent(510)
    assert not gate.open()
    gate.on_flow(_flow(credit=50, received_from_a=0))  # a fresh learner counts from 0
    assert gate.open()


def test_flow_gate_forgets_transitions_lost_in_flight():
    gate = FlowGate("a", horizon_s=10.0)
    gate.on_flow(_flow(credit=20, received_from_a=0))
    gate.sent(32, now=100.0)  # e.g. sent before the learner subscribed: never counted
    assert not gate.open(now=105.0)
    assert gate.open(now=111.0), "after the horizon, unacknowledged transitions count as lost"


def test_ingested_batches_give_each_transition_its_previous_command_across_batch_borders():
    core = LearnerCore(load_preset("smoke"), device="cpu")
    h, w = core.cfg.sensor.height, core.cfg.sensor.width
    batcher = TransitionBatcher("a", batch_steps=2)
    actions = [4, 0, 3, 1, 2]
    for episode in range(2):  # the second episode starts without a previous command again
        batcher.begin_episode(np.full((h, w), 1.0 + episode, np.float32), start_index=0)
        for k, action in enumerate(actions):
            last = k == len(actions) - 1
            depth = np.full((h, w), 1.0 + episode + 0.1 * (k + 1), np.float32)
            batch = batcher.add(action, -100.0 if last else 1.0, depth, last, False, 0, (0.0, 0.0, 0.0))
            if batch is not None:
                core.ingest(TransitionBatch.decode(batch.encode()))  # through the wire format
    got = core.replay._gather(np.arange(10), 1, np.ones(10, np.float32))
    np.testing.assert_array_equal(got.action, actions * 2)
    np.testing.assert_array_equal(got.previous_action[:, 0], [-1, 4, 0, 3, 1] * 2)
    np.testing.assert_array_equal(got.previous_action[4, :5], [1, 3, 0, 4, -1])  # the episode's commands, latest first
    np.testing.assert_array_equal(got.previous_action[5], [-1] * MAX_ACTION_HISTORY)


def test_flow_gate_follows_one_learner_process_and_counts_only_its_own_actor_process():
    clock = [100.0]
    gate = FlowGate("a", actor_epoch=7, quiet_s=2.0, clock=lambda: clock[0])
    gate.on_flow(_flow(credit=10, received_from_a=0, learner_epoch=5, actor_epoch=7))
    gate.sent(16)
    assert not gate.open()
    # another learner's word while this one speaks, and one from the future, change nothing: before,
    # one message with a later epoch and a credit of 0 (forged) held the actor for good
    gate.on_flow(_flow(credit=10_000, received_from_a=16, learner_epoch=4, actor_epoch=7))
    gate.on_flow(_flow(credit=10_000, received_from_a=16, learner_epoch=6, actor_epoch=7))
    gate.on_flow(_flow(credit=10_000, received_from_a=16, learner_epoch=2**62, actor_epoch=7))
    assert not gate.open() and gate.ignored == 3
    clock[0] += 1.5
    gate.on_flow(_flow(credit=0, received_from_a=16, learner_epoch=5, actor_epoch=7))  # the learner speaks on
    clock[0] += 1.5
    gate.on_flow(_flow(credit=10_000, received_from_a=0, learner_epoch=6, actor_epoch=7))
    assert not gate.open() and gate.ignored == 4  # quiet for 1.5 s only
    # a restarted learner, once the dead one has been quiet for 2 s, counts afresh
    clock[0] += 0.5
    gate.on_flow(_flow(credit=10, received_from_a=0, learner_epoch=6, actor_epoch=7))
    assert gate.open() and gate.ignored == 4


def test_a_restarted_actor_does_not_inherit_its_predecessors_count():
    gate = FlowGate("a", actor_epoch=9)  # the same id, a new process
    gate.on_flow(_flow(credit=20, received_from_a=500, actor_epoch=8))  # the predecessor's 500
    gate.sent(32)
    assert not gate.open(), "32 of its own are in flight: more than the 20 wanted"


def test_batch_steps_beyond_the_wire_limit_is_an_option_error() -> None:
    # before, --batch-steps 65 passed the parser and raised a traceback only once the actor had built its
    # world and network, opened its session and joined the run
    parser = build_parser()
    assert parser.parse_args(["actor", "--batch-steps", str(MAX_BATCH_STEPS)]).batch_steps == MAX_BATCH_STEPS
    with pytest.raises(SystemExit) as info:
        parser.parse_args(["actor", "--batch-steps", str(MAX_BATCH_STEPS + 1)])
    assert info.value.code == 2


def test_the_same_learner_heard_again_after_a_pause_keeps_counting_what_is_in_flight():
    # a router restart: liveliness goes and comes back, the learner process and its count stay. Before, the
    # gate's reset zeroed what this actor had sent while the learner's count went on from 5000, so nothing
    # counted as in flight (and the credit was overshot) until the actor had sent 5000 more
    gate = FlowGate("a", horizon_s=10.0)
    gate.on_flow(_flow(credit=10, received_from_a=0))
    gate.sent(5032, now=0.0)
    gate.on_flow(_flow(credit=10, received_from_a=5000))
    gate.reset()  # the 32 sent as the router went down are lost: they hold nothing after the reset either
    assert not gate.open(now=1.0), "after a reset the gate waits for the learner's word"
    gate.on_flow(_flow(credit=10, received_from_a=5000))
    assert gate.open(now=1.0)
    gate.sent(16, now=1.0)
    assert not gate.open(now=1.0), "16 in flight > the 10 wanted"
    gate.on_flow(_flow(credit=10, received_from_a=5016))
    assert gate.open(now=1.5)


def test_transitions_lost_once_are_not_held_against_the_actor_afterwards():
    gate = FlowGate("a", horizon_s=10.0)
    gate.on_flow(_flow(credit=10, received_from_a=0))
    gate.sent(32, now=100.0)  # never counted: lost
    assert gate.open(now=111.0)
    gate.sent(16, now=111.0)
    gate.on_flow(_flow(credit=10, received_from_a=16))  # the 16 arrived: nothing is in flight
    # before, the learner's 16 were compared with the 32 settled: 16 in flight, held, and the loss counted
    # against the actor for as long as it sent more than 32 transitions in 10 s
    assert gate.open(now=111.5)
    gate.sent(16, now=112.0)
    assert not gate.open(now=112.0), "16 really in flight > the 10 wanted"


def test_a_batch_the_learner_counts_after_the_horizon_was_not_lost_after_all():
    gate = FlowGate("a", horizon_s=10.0)
    gate.on_flow(_flow(credit=10, received_from_a=0))
    gate.sent(32, now=100.0)
    assert gate.open(now=111.0)  # taken as lost: the learner stalled
    gate.on_flow(_flow(credit=10, received_from_a=32))  # ... and counts them now
    assert gate.open(now=111.5)
    gate.sent(16, now=112.0)
    assert not gate.open(now=112.0), "16 in flight > the 10 wanted, whatever was taken as lost before"
