"""LearnerCore without Zenoh: the replay-ratio rule and what it ingests."""

import numpy as np
import pytest

from shared.config import load_preset
from shared.learning.learner import LearnerCore
from shared.wire.messages import MessageError, TransitionBatch


def _frame(value: float) -> np.ndarray:
    return np.full((30, 40), value, dtype=np.float32)


def test_replay_ratio_rule_and_wanted_transitions():
    cfg = load_preset("smoke").with_overrides({"train.replay_ratio": 0.5, "train.warmup_transitions": 10,
                                               "train.total_updates": 6, "dqn.batch_size": 4})
    core = LearnerCore(cfg, device="cpu")
    assert core.updates_due() == 0
    for i in range(10):
        core.add_transition("s", _frame(1.0), 1, 1.0, _frame(1.0), False, False)
    assert core.updates_due() == 1  # warm-up reached: the first update
    core.train_step()
    assert core.updates_due() == 0
    for i in range(4):
        core.add_transition("s", None, 1, 1.0, _frame(1.0), False, False)
    assert core.updates_due() == 2  # 0.5 updates per transition
    assert core.transitions_wanted(slack=3) == 10 + 2 + 3
    assert core.transitions_wanted(slack=1000) == 10 + 12  # never beyond what total_updates needs


def test_ingest_rejects_frames_of_another_sensor_and_stores_nothing():
    core = LearnerCore(load_preset("smoke"), device="cpu")
    batch = TransitionBatch.from_steps(actor_id="a", episode=0, first_step=0, start_index=0,
                                       depth=[_frame(1.0)[:20]], next_depth=_frame(1.0)[:20], action=[0],
                                       reward=[1.0], policy_version=[0], pose=[(0, 0, 0)])
    with pytest.raises(MessageError):
        core.ingest(batch)
    assert core.received == 0 and len(core.replay) == 0
