"""Wire messages: round trips, the batch layout, and every reject cause."""

from __future__ import annotations

import dataclasses
import logging
import math
import subprocess
import sys
from typing import Any, Callable

import msgpack
import numpy as np
import pytest

from shared.config import load_preset
from shared.depth import depth_from_mm, depth_to_mm
from shared.wire import messages as m
from shared.wire.messages import (
    EpisodeStats,
    EvalResult,
    LearnerStats,
    MessageError,
    RejectCounter,
    RunConfigMessage,
    TransitionBatch,
    WeightsMessage,
    decode_message,
    shape_fingerprint,
)

H, W = 12, 16  # small frames keep the tests fast; the layout does not depend on the size


def make_batch(steps: int = 4, *, terminated: bool = False, truncated: bool = False,
               seed: int = 0) -> TransitionBatch:
    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 4000, size=(steps + 1, H, W), dtype=np.uint16)
    reward = np.ones(steps, dtype=np.float32)
    if terminated:
        reward[-1] = -100.0
    return TransitionBatch(
        actor_id="actor-0", episode=5, first_step=8, start_index=3, actor_epoch=42,
        depth_mm=frames[:steps], next_depth_mm=None if terminated else frames[steps],
        action=rng.integers(0, 5, steps).astype(np.uint8),
        reward=reward,
        policy_version=np.arange(10, 10 + steps, dtype=np.int64),
        pose=rng.normal(size=(steps, 3)).astype(np.float32),
        terminated=terminated, truncated=truncated)


def make_weights(version: int = 3) -> WeightsMessage:
    tensors = {"conv1.weight": np.linspace(-1, 1, 32 * 9, dtype=np.float32).reshape(32, 1, 3, 3),
               "fc.bias": np.zeros(5, dtype=np.float16)}
    fp = shape_fingerprint({k: v.shape for k, v in tensors.items()})
    return WeightsMessage(policy_version=version, architecture_fingerprint=fp, tensors=tensors)


def make_episode_stats(**kw: Any) -> EpisodeStats:
    values: dict[str, Any] = dict(
        actor_id="actor-0", episode=5, start_index=3, steps=42, episode_return=-59.0,
        terminated=True, truncated=False, collision_cause="depth", path_length_m=6.5,
        distance_from_start_m=2.25, epsilon=0.3, policy_version=9, duration_s=3.5,
        extra={"coverage": 0.25})
    values.update(kw)
    return EpisodeStats(**values)


def make_learner_stats() -> LearnerStats:
    return LearnerStats(learner_id="learner", updates=1000, policy_version=20, replay_size=3000,
                        transitions_received=5000, transitions_rejected=2, loss=None, mean_q=1.5,
                        updates_per_s=2.5, transitions_per_s=40.0, uptime_s=400.0,
                        rejects={"garbage": 2}, extra={"grad_norm": 0.1})


def make_eval() -> EvalResult:
    return EvalResult(evaluator_id="eval", policy_version=20, world="paper-indoor",
                      speed_table="test", max_steps=200, start_index=(0, 1, 2),
                      steps=(200, 31, 7), collided=(False, True, True),
                      path_length_m=(25.0, 3.9, 0.875))


def rewrite(data: bytes, edit: Callable[[dict[str, Any]], None]) -> bytes:
    """Unpack an encoded message, apply ``edit`` to the map, pack it again."""
    obj = msgpack.unpackb(data, raw=False)
    edit(obj)
    return msgpack.packb(obj, use_bin_type=True)


def cause_of(data: bytes, cls: type[m.Message] = TransitionBatch) -> str:
    with pytest.raises(MessageError) as info:
        cls.decode(data)
    return info.value.cause


# --- round trips -----------------------------------------------------------------------------

@pytest.mark.parametrize("terminated, truncated", [(False, False), (True, False), (False, True)])
def test_transition_batch_round_trip(terminated: bool, truncated: bool) -> None:
    batch = make_batch(terminated=terminated, truncated=truncated)
    back = TransitionBatch.decode(batch.encode())
    assert (back.actor_id, back.episode, back.first_step, back.start_index) == ("actor-0", 5, 8, 3)
    assert (back.terminated, back.truncated) == (terminated, truncated)
    for name in ("depth_mm", "action", "reward", "policy_version", "pose"):
        got, want = getattr(back, name), getattr(batch, name)
        assert got.dtype == want.dtype and np.array_equal(got, want), name
    if terminated:
        assert back.next_depth_mm is None and back.next_depth(3) is None
    else:
        assert np.array_equal(back.next_depth_mm, batch.next_depth_mm)
    assert not back.depth_mm.flags.writeable  # zero-copy views of the message bytes
    assert back.expert_action is None and (back.expert_labels() == -1).all()


def test_expert_labels_round_trip_and_hostile_ones_are_refused() -> None:
    labels = np.array([3, m.NO_EXPERT_LABEL, 0, 4], np.uint8)
    batch = dataclasses.replace(make_batch(), expert_action=labels)
    back = TransitionBatch.decode(batch.encode())
    assert back.expert_action.tolist() == labels.tolist() and back.expert_labels().tolist() == [3, -1, 0, 4]
    good = batch.encode()
    assert cause_of(rewrite(good, _set_array("expert_action", np.array([3, 5, 0, 4], np.uint8)))) == m.RANGE
    assert cause_of(rewrite(good, _set_array("expert_action", np.array([3, 1, 0], np.uint8)))) == m.SHAPE
    assert cause_of(rewrite(good, _set_array("expert_action", np.array([3, 1, 0, 4], np.int64)))) == m.DTYPE
    assert cause_of(rewrite(good, lambda o: o.update(expert_action=[3, 1, 0, 4]))) == m.FIELD_TYPE
    # a sender of the previous schema (no labels field) is told apart, not half-read
    assert cause_of(rewrite(good, lambda o: o.pop("expert_action"))) == m.MISSING_FIELD


def test_batch_layout_carries_each_frame_once() -> None:
    batch = make_batch(steps=5)
    assert batch.steps == 5 and batch.frame_shape == (H, W)
    # the next observation of transition i is the observation of transition i + 1
    for i in range(4):
        assert np.array_equal(batch.next_depth(i), batch.depth_mm[i + 1])
    assert np.array_equal(batch.next_depth(4), batch.next_depth_mm)
    with pytest.raises(IndexError, match="transition 5 of a batch of 5"):
        batch.next_depth(5)
    ended = make_batch(steps=3, truncated=True)
    assert ended.truncated_flags().tolist() == [False, False, True]
    assert ended.terminated_flags().tolist() == [False, False, False]
    # 5 frames + 1 next frame of uint16, plus a small envelope
    raw = 6 * H * W * 2
    assert raw < len(batch.encode()) < raw + 600


def test_from_steps_converts_metres_to_millimetres() -> None:
    frames_m = [np.full((H, W), 1.2345, dtype=np.float32), np.zeros((H, W), dtype=np.float32)]
    batch = TransitionBatch.from_steps(
        actor_id="a", episode=0, first_step=0, start_index=0, depth=frames_m,
        next_depth=np.full((H, W), 0.5, dtype=np.float32), action=[2, 4], reward=[1.0, 1.0],
        policy_version=[0, 1], pose=[(0.0, 0.0, 0.0), (0.1, 0.0, 0.2)])
    assert batch.depth_mm.dtype == np.uint16
    assert batch.depth_mm[0, 0, 0] == 1234 or batch.depth_mm[0, 0, 0] == 1235
    assert batch.depth_mm[1].max() == 0 and batch.next_depth_mm[0, 0] == 500
    assert TransitionBatch.decode(batch.encode()).action.tolist() == [2, 4]
    with pytest.raises(MessageError) as info:
        TransitionBatch.from_steps(actor_id="a", episode=0, first_step=0, start_index=0,
                                   depth=frames_m, next_depth=frames_m[0], action=[2, 9],
                                   reward=[1, 1], policy_version=[0, 0], pose=np.zeros((2, 3)))
    assert info.value.cause == m.RANGE


def test_depth_conversion() -> None:
    depth_m = np.array([[0.0, 0.5504, 3.9996, 70.0]], dtype=np.float32)
    mm = depth_to_mm(depth_m)
    assert mm.dtype == np.uint16 and mm.tolist() == [[0, 550, 4000, 65535]]
    assert np.allclose(depth_from_mm(mm)[0, :3], [0.0, 0.55, 4.0])
    assert depth_from_mm(mm).dtype == np.float32
    with pytest.raises(ValueError, match="finite"):
        depth_to_mm(np.array([np.nan], dtype=np.float32))
    with pytest.raises(ValueError, match="float"):
        depth_to_mm(np.array([1], dtype=np.int32))


def test_weights_round_trip_and_fingerprint() -> None:
    weights = make_weights()
    back = decode_message(weights.encode())
    assert isinstance(back, WeightsMessage) and back.policy_version == 3
    assert back.architecture_fingerprint == weights.architecture_fingerprint
    assert list(back.tensors) == ["conv1.weight", "fc.bias"]  # order kept
    for name, arr in weights.tensors.items():
        assert back.tensors[name].dtype == arr.dtype and np.array_equal(back.tensors[name], arr)
    assert back.named_shapes() == {"conv1.weight": (32, 1, 3, 3), "fc.bias": (5,)}
    back.check_fingerprint(weights.architecture_fingerprint)
    with pytest.raises(MessageError) as info:
        back.check_fingerprint(shape_fingerprint({"other": (1,)}))
    assert info.value.cause == m.FINGERPRINT


def test_shape_fingerprint_is_stable_and_sensitive() -> None:
    shapes = {"a.weight": (4, 3), "a.bias": (4,)}
    fp = shape_fingerprint(shapes)
    assert fp == shape_fingerprint(dict(reversed(list(shapes.items()))))
    assert fp == shape_fingerprint({k: list(v) for k, v in shapes.items()})
    assert fp != shape_fingerprint({"a.weight": (4, 2), "a.bias": (4,)})
    assert fp != shape_fingerprint({"b.weight": (4, 3), "a.bias": (4,)})
    assert fp != shape_fingerprint(shapes, {"fc1": 512})
    assert shape_fingerprint(shapes, {"fc1": 512}) == shape_fingerprint(shapes, {"fc1": 512})
    with pytest.raises(ValueError, match="non-empty mapping"):
        shape_fingerprint({})


def test_wire_modules_do_not_import_torch_or_mujoco() -> None:
    code = ("import sys, shared.wire.messages, shared.wire.keys, services.bus.session; "
            "bad = [m for m in ('torch', 'mujoco') if m in sys.modules]; "
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


@pytest.mark.parametrize("make", [make_episode_stats, make_learner_stats, make_eval])
def test_stats_round_trip(make: Callable[[], m.Message]) -> None:
    msg = make()
    back = decode_message(msg.encode())
    assert type(back) is type(msg) and back == msg


def test_eval_result_summary() -> None:
    result = make_eval()
    assert result.episodes == 3 and math.isclose(result.mean_steps, 238 / 3)


def test_numpy_scalars_are_normalised() -> None:
    stats = make_episode_stats(episode=np.int64(5), episode_return=np.float32(-59.0))
    assert type(stats.episode) is int and type(stats.episode_return) is float
    assert decode_message(stats.encode()) == stats


# --- rejects, one per cause ------------------------------------------------------------------

def _set_array(name: str, arr: np.ndarray) -> Callable[[dict[str, Any]], None]:
    def edit(obj: dict[str, Any]) -> None:
        obj[name] = {"dtype": {np.dtype(np.float32): "float32", np.dtype(np.uint16): "uint16",
                               np.dtype(np.uint8): "uint8", np.dtype(np.int64): "int64"}[arr.dtype],
                     "shape": list(arr.shape), "data": arr.tobytes()}
    return edit


def test_wrong_dtype_is_rejected() -> None:
    good = make_batch().encode()
    depth_f32 = np.ones((4, H, W), dtype=np.float32)
    assert cause_of(rewrite(good, _set_array("depth_mm", depth_f32))) == m.DTYPE
    assert cause_of(rewrite(good, lambda o: o["depth_mm"].update(dtype="float64"))) == m.DTYPE
    weights = make_weights().encode()

    def to_uint8(obj: dict[str, Any]) -> None:
        obj["tensors"]["fc.bias"] = {"dtype": "uint8", "shape": [5], "data": bytes(5)}
    assert cause_of(rewrite(weights, to_uint8), WeightsMessage) == m.DTYPE


def test_wrong_shape_is_rejected() -> None:
    good = make_batch().encode()
    # reward of the wrong length
    assert cause_of(rewrite(good, _set_array("reward", np.ones(3, np.float32)))) == m.SHAPE
    # declared shape does not match the bytes
    assert cause_of(rewrite(good, lambda o: o["depth_mm"].update(shape=[4, H, W + 1]))) == m.SHAPE
    # bytes cut short inside an array
    assert cause_of(rewrite(good, lambda o: o["pose"].update(data=o["pose"]["data"][:-1]))) == m.SHAPE
    # a next frame of another size
    assert cause_of(rewrite(good, _set_array("next_depth_mm", np.zeros((H, W + 2), np.uint16)))) == m.SHAPE
    # hostile shapes do not overflow
    assert cause_of(rewrite(good, lambda o: o["depth_mm"].update(shape=[2**40, 2**40, 2**40]))) == m.SHAPE
    # nor do empty arrays of absurd dimensions (numpy refused them with a ValueError, uncounted)
    for shape in ([2**63, 0], [0, 2**40, 2**40], [2**31, 2**31, 0]):
        empty = lambda o, shape=shape: o["depth_mm"].update(shape=shape, data=b"")  # noqa: E731
        assert cause_of(rewrite(good, empty)) == m.SHAPE
        weights = rewrite(make_weights().encode(), lambda o, shape=shape: o["tensors"]["fc.bias"].update(
            shape=shape, data=b""))
        assert cause_of(weights, WeightsMessage) == m.SHAPE
    # the receiver's own sensor shape
    with pytest.raises(MessageError) as info:
        make_batch().require_frame_shape(120, 160)
    assert info.value.cause == m.SHAPE


def test_non_finite_values_are_rejected() -> None:
    good = make_batch().encode()
    reward = np.array([1.0, np.nan, 1.0, 1.0], dtype=np.float32)
    assert cause_of(rewrite(good, _set_array("reward", reward))) == m.NON_FINITE
    pose = np.zeros((4, 3), dtype=np.float32)
    pose[2, 1] = np.inf
    assert cause_of(rewrite(good, _set_array("pose", pose))) == m.NON_FINITE
    weights = make_weights()
    bad = dict(weights.tensors)
    bad["fc.bias"] = np.array([0, 0, np.inf, 0, 0], dtype=np.float16)
    with pytest.raises(MessageError) as info:
        WeightsMessage(policy_version=1, architecture_fingerprint="x", tensors=bad)
    assert info.value.cause == m.NON_FINITE

    def nan_weight(obj: dict[str, Any]) -> None:
        arr = np.frombuffer(obj["tensors"]["conv1.weight"]["data"], dtype=np.float32).copy()
        arr[7] = np.nan
        obj["tensors"]["conv1.weight"]["data"] = arr.tobytes()
    assert cause_of(rewrite(weights.encode(), nan_weight), WeightsMessage) == m.NON_FINITE
    stats = make_learner_stats().encode()
    assert cause_of(rewrite(stats, lambda o: o.update(loss=float("nan"))), LearnerStats) == m.NON_FINITE


def test_out_of_range_values_are_rejected() -> None:
    good = make_batch().encode()
    assert cause_of(rewrite(good, _set_array("action", np.array([0, 1, 5, 2], np.uint8)))) == m.RANGE
    assert cause_of(rewrite(good, lambda o: o.update(episode=-1))) == m.RANGE
    assert cause_of(rewrite(good, lambda o: o.update(actor_id="a/b"))) == m.RANGE
    assert cause_of(rewrite(good, _set_array("policy_version", np.array([1, -1, 2, 3], np.int64)))) == m.RANGE
    stats = make_episode_stats().encode()
    assert cause_of(rewrite(stats, lambda o: o.update(epsilon=1.5)), EpisodeStats) == m.RANGE
    assert cause_of(rewrite(stats, lambda o: o.update(collision_cause="bump")), EpisodeStats) == m.RANGE
    ev = make_eval().encode()
    assert cause_of(rewrite(ev, lambda o: o.update(steps=[201, 3, 4])), EvalResult) == m.RANGE


def test_truncated_and_garbage_bytes_are_rejected() -> None:
    good = make_batch().encode()
    for cut in (0, 1, 10, len(good) // 2, len(good) - 1):
        assert cause_of(good[:cut]) == m.TRUNCATED, cut
    rng = np.random.default_rng(1)
    assert cause_of(b"\xc1" + good) == m.GARBAGE  # 0xc1 is never used by msgpack
    assert cause_of(good + b"\x00") == m.GARBAGE  # trailing bytes
    assert cause_of(msgpack.packb([1, 2, 3])) == m.GARBAGE  # not a map
    assert cause_of(b"hello world, not msgpack") == m.GARBAGE
    for _ in range(50):  # random bytes never decode, and never raise anything but MessageError
        with pytest.raises(MessageError):
            decode_message(rng.bytes(int(rng.integers(1, 200))))


def test_schema_version_and_type_are_checked() -> None:
    good = make_batch().encode()
    assert cause_of(rewrite(good, lambda o: o.update(schema=m.SCHEMA_VERSION + 1))) == m.SCHEMA_VERSION_MISMATCH
    assert cause_of(rewrite(good, lambda o: o.pop("schema"))) == m.SCHEMA_VERSION_MISMATCH
    assert cause_of(rewrite(good, lambda o: o.update(schema=True))) == m.SCHEMA_VERSION_MISMATCH
    assert cause_of(rewrite(good, lambda o: o.update(type="telegram"))) == m.MESSAGE_TYPE
    assert cause_of(make_weights().encode(), TransitionBatch) == m.MESSAGE_TYPE


def test_fields_are_checked() -> None:
    good = make_batch().encode()
    assert cause_of(rewrite(good, lambda o: o.pop("reward"))) == m.MISSING_FIELD
    assert cause_of(rewrite(good, lambda o: o.update(mood="happy"))) == m.UNKNOWN_FIELD
    assert cause_of(rewrite(good, lambda o: o.update(episode="five"))) == m.FIELD_TYPE
    assert cause_of(rewrite(good, lambda o: o.update(terminated=1))) == m.FIELD_TYPE
    assert cause_of(rewrite(good, lambda o: o.update(reward=[1.0, 1.0, 1.0, 1.0]))) == m.FIELD_TYPE
    # a terminal batch must not carry a next frame, a non-terminal one must
    assert cause_of(rewrite(good, lambda o: o.update(terminated=True))) == m.INCONSISTENT
    terminal = make_batch(terminated=True).encode()
    assert cause_of(rewrite(terminal, lambda o: o.update(terminated=False))) == m.INCONSISTENT
    # both episode-end flags: the learner stored all but the last transition, then failed on that one
    assert cause_of(rewrite(terminal, lambda o: o.update(truncated=True))) == m.INCONSISTENT
    stats = make_episode_stats().encode()
    assert cause_of(rewrite(stats, lambda o: o.update(collision_cause=None)), EpisodeStats) == m.INCONSISTENT
    ev = make_eval().encode()
    assert cause_of(rewrite(ev, lambda o: o.update(collided=[True])), EvalResult) == m.INCONSISTENT


def test_unknown_fields_named_by_bytes_and_text_are_rejected_not_raised() -> None:
    # msgpack map keys may be str or bytes; sorting both for the error raised TypeError, which crashed
    # a caller that catches MessageError (an actor reading the answers on the run's config queryable)
    for cls, good in ((TransitionBatch, make_batch().encode()),
                      (RunConfigMessage, RunConfigMessage(learner_id="l", config=load_preset("smoke")).encode())):
        assert cause_of(rewrite(good, lambda o: o.update({"mood": 1, b"mood": 2})), cls) == m.UNKNOWN_FIELD


def test_oversize_is_rejected() -> None:
    # more frames than a batch may hold
    with pytest.raises(MessageError) as info:
        make_batch(steps=m.MAX_BATCH_STEPS + 1)
    assert info.value.cause == m.OVERSIZE
    too_many = np.zeros((m.MAX_BATCH_STEPS + 1, H, W), dtype=np.uint16)
    assert cause_of(rewrite(make_batch().encode(), _set_array("depth_mm", too_many))) == m.OVERSIZE
    # a frame larger than 640x480
    with pytest.raises(MessageError) as info:
        TransitionBatch(actor_id="a", episode=0, first_step=0, start_index=0, actor_epoch=0,
                        depth_mm=np.zeros((1, 481, 640), np.uint16), next_depth_mm=None,
                        action=np.zeros(1, np.uint8), reward=np.zeros(1, np.float32),
                        policy_version=np.zeros(1, np.int64), pose=np.zeros((1, 3), np.float32),
                        terminated=True)
    assert info.value.cause == m.OVERSIZE
    # a message longer than its type allows is refused before it is unpacked
    assert cause_of(bytes(EpisodeStats.MAX_BYTES + 1), EpisodeStats) == m.OVERSIZE
    # weights beyond 256 MB (np.zeros is lazily allocated; the size check runs before reading)
    huge = np.zeros(m.MAX_WEIGHTS_BYTES // 4 + 1, dtype=np.float32)
    with pytest.raises(MessageError) as info:
        WeightsMessage(policy_version=0, architecture_fingerprint="x", tensors={"w": huge})
    assert info.value.cause == m.OVERSIZE


def test_construction_validates_too() -> None:
    with pytest.raises(MessageError) as info:
        make_episode_stats(terminated=False)
    assert info.value.cause == m.INCONSISTENT
    with pytest.raises(MessageError) as info:
        WeightsMessage(policy_version=0, architecture_fingerprint="x",
                       tensors={"w": np.zeros(3, dtype=np.float64)})
    assert info.value.cause == m.DTYPE
    with pytest.raises(ValueError, match="unknown MessageError cause"):
        MessageError("oops")


def test_run_config_round_trip_and_validation() -> None:
    cfg = load_preset("fast-40x30").with_overrides({"env.start_index": None, "train.seed": 3})
    msg = RunConfigMessage(learner_id="learner", config=cfg)
    data = msg.encode()
    assert len(data) < RunConfigMessage.MAX_BYTES // 8
    back = decode_message(data)
    assert isinstance(back, RunConfigMessage) and back.learner_id == "learner" and back.run_config == cfg
    # every field is validated as a preset's: a value out of range, of the wrong type, unknown, or unhashable
    assert cause_of(rewrite(data, lambda o: o["config"]["sensor"].update(width=4)), RunConfigMessage) == m.RANGE
    assert cause_of(rewrite(data, lambda o: o["config"]["sensor"].update(width="40")), RunConfigMessage) == m.RANGE
    assert cause_of(rewrite(data, lambda o: o["config"]["dqn"].update(magic=1)), RunConfigMessage) == m.RANGE
    assert cause_of(rewrite(data, lambda o: o["config"]["env"].update(speed_table=[1])), RunConfigMessage) == m.RANGE
    assert cause_of(rewrite(data, lambda o: o.update(config=[1, 2])), RunConfigMessage) == m.RANGE
    bytes_names = msgpack.packb({**msgpack.unpackb(data), "config": {"sensor": {b"width": 40, "bogus": 30}}})
    assert cause_of(bytes_names, RunConfigMessage) == m.FIELD_TYPE
    assert cause_of(rewrite(data, lambda o: o.update(learner_id="a/b")), RunConfigMessage) == m.RANGE
    assert cause_of(bytes(RunConfigMessage.MAX_BYTES + 1), RunConfigMessage) == m.OVERSIZE


# --- counting rejects ------------------------------------------------------------------------

def test_reject_counter_counts_by_cause_and_logs_each_cause_once(caplog: pytest.LogCaptureFixture) -> None:
    counter = RejectCounter("transition batch", logging.getLogger("test.rejects"))
    good = make_batch().encode()
    with caplog.at_level(logging.WARNING, logger="test.rejects"):
        assert counter.decode(b"\xc1", TransitionBatch, source="k/1") is None
        assert counter.decode(b"\xc1\xc1", TransitionBatch, source="k/1") is None
        assert counter.decode(good[:5], TransitionBatch, source="k/2") is None
        assert counter.decode(make_weights().encode(), TransitionBatch) is None
        decoded = counter.decode(good, TransitionBatch)
    assert isinstance(decoded, TransitionBatch)
    assert counter.counts == {m.GARBAGE: 2, m.TRUNCATED: 1, m.MESSAGE_TYPE: 1}
    assert counter.total == 4
    records = [r for r in caplog.records if r.name == "test.rejects"]
    assert len(records) == 3  # one per cause
    assert "k/1" in records[0].getMessage() and "garbage" in records[0].getMessage()
    assert isinstance(counter.decode(make_weights().encode()), WeightsMessage)  # any type


def test_a_reject_log_line_is_one_line_whatever_the_sender_put_in_its_key(caplog: pytest.LogCaptureFixture) -> None:
    # Zenoh keys may hold line breaks and escape codes: raw, a key wrote a log line of its sender's making
    forged = "x\n2026-12-08 01:00:00,000 CRITICAL cogexplore.learner: run ABORTED\x1b[2J"
    counter = RejectCounter("transition batch", logging.getLogger("test.rejects"))
    with caplog.at_level(logging.WARNING, logger="test.rejects"):
        counter.reject(MessageError(m.RANGE, f"actor sent on {forged}"), source=f"run/transitions/{forged}")
    line = caplog.records[-1].getMessage()
    assert line.isprintable() and "\\n2026-12-08" in line and "\\x1b[2J" in line
    assert m.printable("é 1 m") == "é 1 m" and m.printable("x" * 600) == "x" * m.MAX_LOGGED_CHARS + "..."


def test_reject_counter_counts_a_decoder_bug_as_garbage_and_never_raises() -> None:
    # Bytes from the network that reach a bug in a decoder must not raise into a Zenoh thread,
    # which logs a traceback for every such message and counts nothing.
    class Buggy(TransitionBatch):
        @classmethod
        def decode(cls, data: bytes) -> TransitionBatch:
            raise ValueError("numpy: array is too big")

    counter = RejectCounter("transition batch", logging.getLogger("test.rejects"))
    assert counter.decode(make_batch().encode(), Buggy, source="k/1") is None
    assert counter.counts == {m.GARBAGE: 1}
