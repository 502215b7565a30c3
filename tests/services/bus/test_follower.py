"""The newest-weights follower of the actors and the evaluator: newest wins, misfits are counted, never raised."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest
import torch

from services.bus.follower import WeightFollower
from services.bus.session import (
    ZenohSettings,
    free_tcp_port,
    open_router,
    open_session,
    serve_latest,
)
from shared.config import ModelConfig, SensorConfig
from shared.learning.model import QNetwork, architecture_fingerprint
from shared.learning.weights import to_message
from shared.wire.keys import RunKeys
from shared.wire.messages import FlowControl, RejectCounter, WeightsMessage

SENSOR = SensorConfig(width=32, height=24)


def network(seed: int) -> QNetwork:
    torch.manual_seed(seed)
    return QNetwork(ModelConfig(fc1=16, fc2=8), SENSOR).eval()


def follower_for(net: QNetwork) -> WeightFollower:
    return WeightFollower(architecture_fingerprint(net), RejectCounter("weights message", logging.getLogger("test")))


def test_the_newest_fitting_weights_win_and_older_ones_never_come_back():
    net = network(0)
    follower = follower_for(net)
    assert follower.take() is None
    for version in (3, 7, 5):
        follower.offer(to_message(net, version))
    assert follower.take().policy_version == 7 and follower.take() is None
    follower.offer(to_message(net, 6))  # older than the one taken: dropped
    assert follower.take() is None
    follower.offer(to_message(net, 8))
    assert follower.take().policy_version == 8


def test_another_architecture_or_tensors_that_do_not_load_are_counted_and_leave_the_network_untouched():
    net, other = network(0), QNetwork(ModelConfig(fc1=32, fc2=8), SENSOR)
    follower = follower_for(net)
    follower.offer(to_message(other, 9))
    assert follower.take() is None and follower.rejects.counts == {"fingerprint": 1}

    source = network(1)
    message = to_message(source, 10)
    weight = next(k for k, v in message.tensors.items() if v.ndim == 2 and v.shape[0] != v.shape[1])
    tensors = dict(message.tensors, **{weight: np.ascontiguousarray(message.tensors[weight].T)})
    transposed = WeightsMessage(policy_version=10, architecture_fingerprint=message.architecture_fingerprint,
                                tensors=tensors)  # the right fingerprint, one tensor the wrong way round
    before = {k: v.clone() for k, v in net.state_dict().items()}
    follower.offer(transposed)
    taken = follower.take()
    assert taken is not None and not follower.load(net, taken)
    assert follower.rejects.counts == {"fingerprint": 1, "shape": 1}
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())
    assert follower.load(net, message) and torch.equal(net.state_dict()[weight], source.state_dict()[weight])


def test_take_waits_for_weights_that_arrive_late():
    net = network(0)
    follower = follower_for(net)
    threading.Timer(0.2, follower.offer, args=(to_message(net, 1),)).start()
    started = time.monotonic()
    assert follower.take(timeout_s=60.0).policy_version == 1
    assert time.monotonic() - started < 30.0  # woken by the offer, not by its timeout


def test_a_follower_gets_the_learners_newest_weights_through_a_real_router():
    net, keys = network(0), RunKeys("follow")
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    newest = to_message(net, 42).encode()
    with open_router([endpoint]), open_session(ZenohSettings(connect=(endpoint,)), wait_s=10) as learner, \
            open_session(ZenohSettings(connect=(endpoint,)), wait_s=10) as actor:
        queryable = serve_latest(learner, keys.weights_latest, lambda: newest)  # noqa: F841
        follower = follower_for(net)
        follower.subscribe(actor, keys, query_timeout_s=5.0)
        assert follower.take(timeout_s=10.0).policy_version == 42


def test_leaving_following_closes_the_session_and_ends_the_query_thread_even_mid_query():
    # A query thread left running past its session may free Zenoh objects while the interpreter shuts
    # down, which aborts the process on Python < 3.14; the session's own __exit__ would raise "Already
    # borrowed" while that thread is inside get. Leaving `following` closes the session and joins it.
    net, keys = network(0), RunKeys("follow-join")
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    held: list[object] = []  # queries kept unanswered: the follower's query stays open
    follower = follower_for(net)
    with open_router([endpoint]), open_session(ZenohSettings(connect=(endpoint,)), wait_s=10) as learner:
        queryable = learner.declare_queryable(keys.weights_latest, held.append)  # noqa: F841
        with open_session(ZenohSettings(connect=(endpoint,)), wait_s=10) as actor:
            with follower.following(actor, keys, query_timeout_s=60.0):
                deadline = time.monotonic() + 10
                while not held and time.monotonic() < deadline:
                    time.sleep(0.05)
                assert held, "the follower's query never reached the learner"
                assert [t for t in threading.enumerate() if t.name == "weights-query"]  # waiting for an answer
                follower.fetch_latest(actor, keys, 60.0, background=True)  # a second, as on a learner's return
                started = time.monotonic()
            assert time.monotonic() - started < 30.0  # not the 60 s query timeout
            assert actor.is_closed()
            assert not [t for t in threading.enumerate() if t.name == "weights-query"]
        held.clear()


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def clocked_follower(net: QNetwork, clock: Clock) -> WeightFollower:
    """A follower on an injected clock, with the service's 5 s quiet time."""
    return WeightFollower(architecture_fingerprint(net), RejectCounter("weights message", logging.getLogger("t")),
                          quiet_s=5.0, clock=clock)


def test_a_restarted_learner_takes_over_once_the_dead_one_is_quiet_and_one_message_never_holds_a_follower(caplog):
    from shared.wire.messages import MessageError, new_epoch

    net = network(0)
    clock = Clock()
    follower = clocked_follower(net, clock)
    dead, restarted = new_epoch(), new_epoch() + 1
    follower.offer(to_message(net, 1450, learner_epoch=dead))
    assert follower.take().policy_version == 1450
    clock.t += 6.0  # the learner was killed; its successor loads torch and its checkpoint
    follower.offer(to_message(net, 1000, learner_epoch=restarted))  # resumed from an older checkpoint
    assert follower.take().version == (restarted, 1000)
    follower.offer(to_message(net, 1475, learner_epoch=dead))  # the dead learner's last message, late
    assert follower.take() is None
    with caplog.at_level(logging.WARNING, logger="test"):
        follower.offer(to_message(net, 5, learner_epoch=2**62))  # a learner "started" in the next century
    assert follower.take() is None and follower.rejects.counts == {"range": 1}
    # said once, naming what a real learner there would mean: the machines' clocks disagree
    assert "10 minutes ahead of this machine's clock" in caplog.text and "clocks disagree" in caplog.text
    with pytest.raises(MessageError, match="policy_version"):  # 2^62 updates: refused on decode already
        WeightsMessage(policy_version=2**62, architecture_fingerprint="x", tensors={"w": np.zeros(1, np.float32)})

    # One forged message dated now (the newest epoch there can be) among the live learner's: ignored.
    # Ranking epochs alone took it, and refused the real learner's weights from then on, for good.
    forged = new_epoch() + 10**9
    for update in (1025, 1050):
        clock.t += 1.5
        follower.offer(to_message(net, update, learner_epoch=restarted))
        follower.offer(to_message(net, 0, learner_epoch=forged))
    assert follower.take().version == (restarted, 1050) and follower.rejects.counts == {"range": 1}
    # One that arrives while the learner is quiet (warm-up, a checkpoint) is followed, but only
    # until the learner speaks again after the forger has been quiet as long.
    clock.t += 6.0
    follower.offer(to_message(net, 0, learner_epoch=forged))
    assert follower.take().version == (forged, 0)
    clock.t += 1.0
    follower.offer(to_message(net, 1075, learner_epoch=restarted))
    assert follower.take() is None  # the forger spoke 1 s ago
    clock.t += 4.0
    follower.offer(to_message(net, 1100, learner_epoch=restarted))
    assert follower.take().version == (restarted, 1100)


def test_a_restarted_learners_start_up_weights_are_kept_until_the_dead_one_is_quiet():
    # A learner publishes its weights once at start-up, then not until it trains (minutes of
    # warm-up, maybe): if they came within the quiet time of the dead one's last, dropping them
    # left every receiver on the dead learner's weights until then.
    from shared.wire.messages import new_epoch

    net = network(0)
    clock = Clock()
    follower = clocked_follower(net, clock)
    dead, restarted, forged = new_epoch(), new_epoch() + 1, new_epoch() + 2
    follower.offer(to_message(net, 1450, learner_epoch=dead))
    assert follower.take().version == (dead, 1450)
    clock.t += 2.0
    follower.offer(to_message(net, 1000, learner_epoch=restarted))  # its start-up weights, 2 s after
    assert follower.take() is None
    clock.t += 3.0  # the dead one quiet for 5 s: the kept message is followed, without another
    assert follower.take(timeout_s=0.01).version == (restarted, 1000)
    # A message kept while the followed learner spoke on is dropped after twice the quiet time:
    # a forged one is not followed the next time the learner pauses (a checkpoint, its warm-up).
    follower.offer(to_message(net, 1, learner_epoch=forged))
    for update in range(1025, 1300, 25):
        clock.t += 1.0
        follower.offer(to_message(net, update, learner_epoch=restarted))
        assert follower.take().version == (restarted, update)
    clock.t += 6.0
    assert follower.take() is None


def test_a_follower_with_the_networks_shapes_refuses_a_misshapen_message_on_arrival():
    from shared.learning.model import named_shapes

    net = network(0)
    follower = WeightFollower(architecture_fingerprint(net), RejectCounter("w", logging.getLogger("test")),
                              shapes=named_shapes(net))
    good = to_message(network(1), 4)
    weight = next(k for k, v in good.tensors.items() if v.ndim == 2 and v.shape[0] != v.shape[1])
    bad = WeightsMessage(policy_version=5, architecture_fingerprint=good.architecture_fingerprint,
                         tensors=dict(good.tensors, **{weight: np.ascontiguousarray(good.tensors[weight].T)}))
    follower.offer(good)
    follower.offer(bad)  # newer, but misshapen: never parked over the good one
    assert follower.rejects.counts == {"shape": 1} and follower.take().policy_version == 4


def flow_of(epoch: int, updates: int = 0) -> FlowControl:
    return FlowControl(learner_id="l", updates=updates, transitions_received=0, transitions_wanted=0,
                       learner_epoch=epoch)


def test_the_learners_flow_control_keeps_it_followed_through_a_long_silence_in_weights():
    # Warm-up or a slow preset leaves minutes between two weights; weights of another epoch put then
    # were followed. The learner's flow control (every 0.1 s) says it is alive: they are not now.
    from shared.wire.messages import new_epoch

    net = network(0)
    clock = Clock()
    follower = clocked_follower(net, clock)
    learner, forged = new_epoch(), new_epoch() + 1
    follower.offer(to_message(net, 0, learner_epoch=learner))  # its start-up weights
    assert follower.take().version == (learner, 0)
    for _ in range(60):  # a minute of warm-up: flow control, no weights
        clock.t += 1.0
        follower.on_flow(flow_of(learner))
        follower.on_flow(flow_of(forged))  # another epoch's flow control is no pulse of the followed one
        follower.offer(to_message(net, 0, learner_epoch=forged))
        assert follower.take() is None
    clock.t += 1.0
    follower.on_flow(flow_of(learner, updates=1000))
    follower.offer(to_message(net, 1000, learner_epoch=learner))
    assert follower.take().version == (learner, 1000)
    # A learner that stops altogether (weights and flow) is replaced after the quiet time, as before.
    clock.t += 5.0
    follower.on_flow(flow_of(forged))
    follower.offer(to_message(net, 7, learner_epoch=forged))
    assert follower.take().version == (forged, 7)


def test_the_pulse_travels_with_the_followers_own_subscription_through_a_real_router():
    from services.bus.session import declare_reliable_publisher
    from shared.wire.messages import new_epoch

    net, keys = network(0), RunKeys("pulse")
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    learner_epoch, forged = new_epoch(), new_epoch() + 1
    follower = WeightFollower(architecture_fingerprint(net), RejectCounter("weights message", logging.getLogger("t")),
                              quiet_s=1.0)
    gate_saw: list[int] = []
    with open_router([endpoint]), open_session(ZenohSettings(connect=(endpoint,)), wait_s=10) as learner, \
            open_session(ZenohSettings(connect=(endpoint,)), wait_s=10) as actor:
        weights = declare_reliable_publisher(learner, keys.weights)
        with follower.following(actor, keys, query_timeout_s=1.0, on_flow=lambda m, k: gate_saw.append(m.learner_epoch)):
            deadline = time.monotonic() + 30
            while (first := follower.take()) is None and time.monotonic() < deadline:  # until the route is up
                weights.put(to_message(net, 1, learner_epoch=learner_epoch).encode())
                time.sleep(0.1)
            assert first is not None and first.version == (learner_epoch, 1), "no route to the follower"
            for _ in range(20):  # 2 s of flow control only: twice the quiet time without weights
                learner.put(keys.flow, flow_of(learner_epoch).encode())
                time.sleep(0.1)
            learner.put(keys.flow, flow_of(learner_epoch).encode())
            weights.put(to_message(net, 0, learner_epoch=forged).encode())
            # the learner's next weights, on the same publisher: they arrive after the forged ones, which
            # by then have been offered and, the learner alive by its pulse alone, ignored
            weights.put(to_message(net, 3, learner_epoch=learner_epoch).encode())
            assert follower.take(timeout_s=30.0).version == (learner_epoch, 3)
            assert gate_saw and set(gate_saw) == {learner_epoch}
            time.sleep(1.2)  # the learner quiet on both streams now: another epoch is followed
            weights.put(to_message(net, 2, learner_epoch=forged).encode())
            assert follower.take(timeout_s=30.0).learner_epoch == forged


def test_weights_numbered_ahead_of_their_learners_pulse_never_hold_its_real_weights_off():
    # One forged message in the learner's own epoch, numbered 2^40 - 1, made every later real
    # weights message "older": followers stayed on it for the rest of the learner's life.
    from shared.wire.messages import MAX_POLICY_VERSION, new_epoch

    net = network(0)
    learner = new_epoch()
    follower = follower_for(net)  # a receiver that has not heard the learner's pulse yet
    follower.offer(to_message(net, 50, learner_epoch=learner))
    assert follower.take().version == (learner, 50)
    follower.offer(to_message(net, MAX_POLICY_VERSION - 1, learner_epoch=learner))
    assert follower.take().policy_version == MAX_POLICY_VERSION - 1  # taken: nothing to tell it by yet
    follower.on_flow(flow_of(learner, updates=60))
    follower.offer(to_message(net, 75, learner_epoch=learner))
    assert follower.take().version == (learner, 75)  # the learner's own again
    # after a pulse, weights ahead of it are refused on arrival: never taken, not even once
    follower.offer(to_message(net, MAX_POLICY_VERSION - 1, learner_epoch=learner))
    assert follower.take() is None and follower.rejects.counts == {"range": 1}
    # a real message overtaking its flow control (updates 80 -> weights 100) is within the slack
    follower.on_flow(flow_of(learner, updates=80))
    follower.offer(to_message(net, 100, learner_epoch=learner))
    assert follower.take().version == (learner, 100) and follower.rejects.counts == {"range": 1}
    follower.on_flow(flow_of(2**62))  # a learner "started" in the next century: counted
    assert follower.rejects.counts == {"range": 2}

    # parked before the first pulse, not yet taken: dropped and counted when it comes
    fresh = follower_for(net)
    fresh.offer(to_message(net, 10**6, learner_epoch=learner))
    fresh.on_flow(flow_of(learner, updates=100))
    assert fresh.take() is None and fresh.rejects.counts == {"range": 1}
    fresh.offer(to_message(net, 125, learner_epoch=learner))
    assert fresh.take().version == (learner, 125)
