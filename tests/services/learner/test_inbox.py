"""The learner's inbox between the Zenoh threads and its loop: bounded by bytes, not only batches."""

from __future__ import annotations

import numpy as np

from services.learner.service import BatchInbox
from shared.wire.messages import TransitionBatch


def batch(steps: int, height: int = 120, width: int = 160) -> TransitionBatch:
    frame = np.full((height, width), 1000, np.uint16)
    return TransitionBatch.from_steps(actor_id="a", episode=0, first_step=0, start_index=0, depth=[frame] * steps,
                                      next_depth=frame, action=[0] * steps, reward=[1.0] * steps,
                                      policy_version=[0] * steps, pose=[(0, 0, 0)] * steps)


def test_the_inbox_holds_what_its_bytes_allow_and_frees_them_as_the_loop_takes_batches():
    small, big = batch(16), batch(64)
    per_small = sum(v.nbytes for v in vars(small).values() if isinstance(v, np.ndarray))
    inbox = BatchInbox(max_bytes=10 * per_small)
    # sized by what arrives: ten real 16-step batches fit where a worst-case (64-step) bound took four
    assert all(inbox.put(small) for _ in range(10)) and not inbox.put(small)
    assert inbox.get() is small and inbox.put(small) and not inbox.put(big)
    while inbox.get() is not None:
        pass
    assert inbox.put(big) and inbox.get() is big and inbox.get() is None
    counted = BatchInbox(max_batches=2)
    assert counted.put(small) and counted.put(small) and not counted.put(small)
