"""Replay memory: shared frames, wrap-around, never-stale sampling, streams, n-step, priorities."""

import numpy as np
import pytest

from shared.config import MAX_ACTION_HISTORY, ReplayConfig
from shared.depth import depth_to_mm
from shared.learning.replay import Batch, ReplayError, ReplayMemory, SumTree

SHAPE = (6, 8)


def frame(value: int) -> np.ndarray:
    """A uint16 frame whose every pixel is ``value`` (so content identifies the step)."""
    return np.full(SHAPE, value, dtype=np.uint16)


def add_episode(mem: ReplayMemory, stream, first: int, length: int, end: str = "collision",
                rewards=None) -> list[int]:
    """Steps first..first+length-1 with frames valued by step; returns transition ids."""
    tids = []
    for k in range(length):
        step = first + k
        last = k == length - 1
        terminated = last and end == "collision"
        truncated = last and end == "truncation"
        r = rewards[k] if rewards is not None else (-100.0 if terminated else 1.0)
        nxt = None if terminated else frame(step + 1)
        tids.append(mem.add(stream, frame(step), k % 5, r, nxt, terminated, truncated))
    return tids


def test_depth_to_mm_rounds_clips_and_rejects_nan():
    out = depth_to_mm(np.array([[0.0, 1.2344, 70.0]], dtype=np.float32))
    assert out.dtype == np.uint16 and out.tolist() == [[0, 1234, 65535]]
    with pytest.raises(ValueError, match="NaN"):
        depth_to_mm(np.array([[np.nan]], dtype=np.float32))
    memory = ReplayMemory(ReplayConfig(capacity=4), (1, 1))
    with pytest.raises(ReplayError, match="NaN"):
        memory.add("s", np.array([[np.nan]], np.float32), 0, 1.0, np.zeros((1, 1), np.float32), False)


def test_frames_are_stored_once_per_transition():
    mem = ReplayMemory(ReplayConfig(capacity=100), SHAPE)
    add_episode(mem, "a", 0, 10, end="collision")
    assert mem._frames_written == 10  # obs_0..obs_9, no next frame at the collision
    add_episode(mem, "a", 100, 5, end="truncation")
    assert mem._frames_written == 10 + 6  # a truncation keeps its next frame
    # paper-sized frames: about one 38.4 KB frame per transition, not two
    big = ReplayMemory(ReplayConfig(capacity=3000), (120, 160))
    frame_bytes = 120 * 160 * 2
    assert frame_bytes < big.bytes_per_transition < 1.2 * frame_bytes


def test_wrap_around_never_returns_a_stale_frame():
    mem = ReplayMemory(ReplayConfig(capacity=10), SHAPE, seed=0)
    step = 0
    for length, end in [(7, "collision"), (4, "truncation"), (9, "collision"), (3, "truncation"),
                        (12, "collision")]:
        add_episode(mem, "a", step, length, end)
        step += 1000
    assert len(mem) == 10
    for _ in range(50):
        b = mem.sample(16)
        obs_val = b.obs[:, 0, 0].astype(np.int64)
        assert np.all(b.obs == obs_val[:, None, None])  # whole frames, not mixes
        live = ~b.terminated
        # the next frame is always the step after the obs: frames belong to their transition
        assert np.all(b.next_obs[live, 0, 0] == obs_val[live] + 1)
        assert np.all(b.next_obs[b.terminated] == 0)
        # only the last 10 transitions can come back
        assert set(b.indices.tolist()) <= set(range(mem.transitions_added - 10, mem.transitions_added))


def test_frame_pressure_invalidates_transitions_exactly():
    # 1-step truncated episodes need 2 frames each: a small frame ring evicts transitions early
    mem = ReplayMemory(ReplayConfig(capacity=10), SHAPE, frame_capacity=8, seed=1)
    for ep in range(20):
        add_episode(mem, "a", 10 * ep, 1, end="truncation")
    assert len(mem) == 4  # 8 frames hold the last four 2-frame transitions
    for _ in range(30):
        b = mem.sample(8)
        assert np.all(b.next_obs[:, 0, 0] == b.obs[:, 0, 0] + 1)
        assert set(b.indices.tolist()) <= {16, 17, 18, 19}


def test_interleaved_streams_keep_their_own_chains():
    mem = ReplayMemory(ReplayConfig(capacity=100), SHAPE, seed=0)
    # actor A's steps are 0.., actor B's 500..; their transitions arrive alternately
    for k in range(6):
        for stream, base in (("A", 0), ("B", 500)):
            term = k == 5 and stream == "A"
            mem.add(stream, frame(base + k), 2, float(base + k), None if term else frame(base + k + 1), term)
    assert mem._frames_written == 2 * 7 - 1  # A ends in a collision, B stays open
    b = mem._gather(np.array([0, 1]), 3, np.ones(2, np.float32))  # first transition of A and of B
    np.testing.assert_array_equal(b.rewards, [[0, 1, 2], [500, 501, 502]])
    np.testing.assert_array_equal(b.n_steps, [3, 3])
    np.testing.assert_array_equal(b.next_obs[:, 0, 0], [3, 503])


def test_n_step_chains_stop_at_collision_truncation_and_missing_links():
    mem = ReplayMemory(ReplayConfig(capacity=100), SHAPE, seed=0)
    col = add_episode(mem, "c", 0, 3, "collision", rewards=[1.0, 2.0, -100.0])
    tru = add_episode(mem, "t", 100, 2, "truncation", rewards=[1.0, 3.0])
    opn = add_episode(mem, "o", 200, 2, "open", rewards=[1.0, 4.0])  # episode still running
    n = 4
    b = mem._gather(np.array([col[0], col[2], tru[0], opn[0], opn[1]]), n, np.ones(5, np.float32))
    np.testing.assert_array_equal(b.n_steps, [3, 1, 2, 2, 1])
    np.testing.assert_array_equal(b.terminated, [True, True, False, False, False])
    np.testing.assert_array_equal(b.rewards[0], [1.0, 2.0, -100.0, 0.0])
    np.testing.assert_array_equal(b.rewards[2], [1.0, 3.0, 0.0, 0.0])
    assert b.next_obs[2, 0, 0] == 102  # bootstrap from the truncation's next frame
    assert b.next_obs[3, 0, 0] == 202  # chain stops where the stream has not arrived yet
    assert b.next_obs[4, 0, 0] == 202
    assert np.all(b.next_obs[:2] == 0)


def test_mismatched_obs_breaks_the_chain_instead_of_linking_wrong_frames():
    mem = ReplayMemory(ReplayConfig(capacity=100), SHAPE)
    mem.add("s", frame(0), 0, 1.0, frame(1), False)
    mem.add("s", frame(7), 0, 1.0, frame(8), False)  # a lost transition: obs is not frame(1)
    assert mem._frames_written == 4
    b = mem._gather(np.array([0]), 3, np.ones(1, np.float32))
    assert b.n_steps[0] == 1 and b.next_obs[0, 0, 0] == 1
    mem.add("s", None, 1, 1.0, frame(9), False)  # obs=None continues from frame(8)
    assert mem._frames_written == 5
    with pytest.raises(ReplayError, match="open episode"):
        mem.add("new", None, 0, 1.0, frame(1), False)


def test_numbered_steps_link_only_the_step_after_even_where_the_images_match():
    mem = ReplayMemory(ReplayConfig(capacity=100), SHAPE)
    zeros = frame(0)  # an all-zero image: open space beyond the sensor's range, seen again and again
    mem.add("s", frame(5), 1, 1.0, zeros, False, step=0)
    mem.add("s", zeros, 2, 1.0, zeros, False, step=1)  # the step after: it links, its obs frame shared
    assert mem._frames_written == 3 and mem._prev_tid[1] == 0
    mem.add("s", zeros, 3, 1.0, frame(9), False, step=3)  # step 2 was lost: a new chain, its own frame
    assert mem._frames_written == 5 and mem._prev_tid[2] == -1 and mem._next_tid[1] == -1
    assert mem._previous_action[2, 0] == -1
    b = mem._gather(np.array([0, 1]), 3, np.ones(2, np.float32))
    np.testing.assert_array_equal(b.n_steps, [2, 1])
    with pytest.raises(ReplayError, match="open episode"):
        mem.add("s", None, 0, 1.0, frame(9), False, step=5)  # obs=None cannot skip step 4 either
    mem.add("s", None, 4, 1.0, frame(9), False, step=4)
    assert mem._prev_tid[3] == 2 and mem._previous_action[3, 0] == 3
    with pytest.raises(ReplayError, match="step"):
        mem.add("s", zeros, 0, 1.0, zeros, False, step=-1)

def test_bad_transitions_and_requests_are_rejected():
    mem = ReplayMemory(ReplayConfig(capacity=10), SHAPE)
    with pytest.raises(ReplayError, match="empty"):
        mem.sample(4)
    with pytest.raises(ReplayError, match="action"):
        mem.add("s", frame(0), 5, 1.0, frame(1), False)
    with pytest.raises(ReplayError, match="needs next_obs"):
        mem.add("s", frame(0), 1, 1.0, None, False)
    with pytest.raises(ReplayError, match="shape"):
        mem.add("s", np.zeros((3, 3), np.uint16), 1, 1.0, frame(1), False)
    with pytest.raises(ReplayError, match="both"):
        mem.add("s", frame(0), 1, 1.0, frame(1), True, True)
    with pytest.raises(ReplayError, match="finite"):
        mem.add("s", frame(0), 1, float("nan"), frame(1), False)
    with pytest.raises(ReplayError, match="ReplayConfig"):
        ReplayMemory({"capacity": 10}, SHAPE)


def test_prioritised_sampling_follows_priorities():
    cfg = ReplayConfig(capacity=8, prioritized=True, priority_alpha=1.0, priority_beta=0.5)
    mem = ReplayMemory(cfg, SHAPE, seed=3)
    tids = add_episode(mem, "a", 0, 4, "collision")
    mem.update_priorities(np.array(tids), np.array([1.0, 2.0, 3.0, 4.0]) - 1e-3)
    counts = np.zeros(4)
    for _ in range(400):
        b = mem.sample(32)
        counts += np.bincount(b.indices, minlength=4)
    freq = counts / counts.sum()
    np.testing.assert_allclose(freq, [0.1, 0.2, 0.3, 0.4], atol=0.015)
    # importance weights (N P)^-beta, normalised by the batch maximum
    b = mem.sample(32)
    p = (b.indices + 1) / 10.0
    w = (4 * p) ** -0.5
    np.testing.assert_allclose(b.weights, w / w.max(), rtol=1e-5)
    # evicted transitions get probability 0; new ones the largest priority so far
    add_episode(mem, "b", 100, 6, "collision")
    assert len(mem) == 8
    prios = mem.priorities()
    assert prios[tids[0] % 8] == pytest.approx(4.0) and prios[tids[1] % 8] == pytest.approx(4.0)
    assert set(mem.sample(64).indices.tolist()) <= set(range(2, 10))


def test_sum_tree_never_finds_a_leaf_past_its_size_at_the_top_of_the_mass():
    # 3 leaves pad to 4: rounding in the walk down took a mass just under the total to leaf 3,
    # past the replay's arrays (an IndexError in the prioritised sampler)
    tree = SumTree(3)
    tree.set(np.arange(3), np.array([0.7, 0.6, 10.0]))
    top = np.array([np.nextafter(tree.total, 0), 0.0, 0.69, 0.7, 1.3])
    assert tree.find(top).tolist() == [2, 0, 0, 1, 2]


def test_uniform_sampling_is_uniform_and_weights_are_one():
    mem = ReplayMemory(ReplayConfig(capacity=50), SHAPE, seed=5)
    add_episode(mem, "a", 0, 5, "collision")
    b = mem.sample(4000)
    assert isinstance(b, Batch) and len(b) == 4000
    assert np.all(b.weights == 1.0)
    np.testing.assert_allclose(np.bincount(b.indices) / 4000, 0.2, atol=0.03)


def test_previous_commands_follow_each_stream_chain_and_restart_with_each_episode():
    mem = ReplayMemory(ReplayConfig(capacity=100), SHAPE, seed=0)
    # interleaved streams; add_episode's actions are k % 5, so stream "a" plays 0, 1, 2, 3
    a = add_episode(mem, "a", 0, 4, "collision")
    b = [mem.add("b", frame(300), 4, 1.0, frame(301), False), mem.add("b", frame(301), 3, 1.0, frame(302), False)]
    a2 = add_episode(mem, "a", 100, 2, "open")  # the same stream's next episode
    lost = mem.add("b", frame(999), 2, 1.0, frame(1000), False)  # a lost transition breaks b's chain
    got = mem._gather(np.array(a + b + a2 + [lost]), 1, np.ones(9, np.float32))
    assert got.previous_action.shape == (9, MAX_ACTION_HISTORY)
    np.testing.assert_array_equal(got.previous_action[:, 0], [-1, 0, 1, 2, -1, 4, -1, 0, -1])
    # the history, most recent first, within the episode only
    np.testing.assert_array_equal(got.previous_action[3, :4], [2, 1, 0, -1])
    np.testing.assert_array_equal(got.previous_action[7, :2], [0, -1])  # a2's second step
    assert np.all(got.previous_action[:, 4:] == -1)
    np.testing.assert_array_equal(got.next_previous_action[:, 0], got.action)  # one step: this command
    np.testing.assert_array_equal(got.next_previous_action[:, 1:], got.previous_action[:, :-1])
    three = mem._gather(np.array([a[0], a[2]]), 3, np.ones(2, np.float32))
    np.testing.assert_array_equal(three.next_previous_action[:, :4], [[2, 1, 0, -1], [3, 2, 1, 0]])
    # a replay saved before previous commands were kept restores with "none" everywhere, one saved
    # before their history with the last command only
    arrays, meta = mem.state_dict()
    old = ReplayMemory(ReplayConfig(capacity=100), SHAPE)
    old.load_state_dict({k: v for k, v in arrays.items() if k != "previous_action"}, meta)
    assert np.all(old._gather(np.array(a), 1, np.ones(4, np.float32)).previous_action == -1)
    old.load_state_dict({**arrays, "previous_action": arrays["previous_action"][:, 0].copy()}, meta)
    restored = old._gather(np.array(a), 1, np.ones(4, np.float32)).previous_action
    np.testing.assert_array_equal(restored[:, 0], [-1, 0, 1, 2])
    assert np.all(restored[:, 1:] == -1)


def test_state_dict_round_trip_restores_contents_streams_and_rng():
    cfg = ReplayConfig(capacity=16, prioritized=True)
    mem = ReplayMemory(cfg, SHAPE, seed=9)
    add_episode(mem, "a", 0, 20, "truncation")
    add_episode(mem, ("actor", 1), 50, 3, "open")
    mem.update_priorities(np.array([10, 12]), np.array([5.0, 0.5]))
    arrays, meta = mem.state_dict()
    other = ReplayMemory(cfg, SHAPE, seed=0)
    other.load_state_dict(arrays, meta)
    b1, b2 = mem.sample(8, n_step=3), other.sample(8, n_step=3)
    for name in ("obs", "action", "rewards", "n_steps", "terminated", "next_obs", "previous_action",
                 "next_previous_action", "weights", "indices"):
        np.testing.assert_array_equal(getattr(b1, name), getattr(b2, name))
    # the open stream continues on the restored memory: its next obs reuses the stored frame
    n = other._frames_written
    other.add(("actor", 1), frame(53), 0, 1.0, frame(54), False)
    assert other._frames_written == n + 1
    # a numbered stream keeps its next step: restored, a gap still breaks its chain, the step after links
    mem.add("n", frame(1), 0, 1.0, frame(2), False, step=6)
    arrays, meta = mem.state_dict()
    for step, linked in ((8, False), (7, True)):
        other.load_state_dict(arrays, meta)
        n = other._frames_written
        other.add("n", frame(2), 0, 1.0, frame(3), False, step=step)
        assert other._frames_written == n + 2 - linked
    # saved before steps were kept: the step it continues from is unknown, so a numbered one starts anew
    other.load_state_dict(arrays, {**meta, "streams": [row[:3] for row in meta["streams"]]})
    n = other._frames_written
    other.add("n", frame(2), 0, 1.0, frame(3), False, step=7)
    assert other._frames_written == n + 2
    with pytest.raises(ReplayError, match="does not fit"):
        ReplayMemory(ReplayConfig(capacity=32, prioritized=True), SHAPE).load_state_dict(arrays, meta)


def test_a_paused_stream_never_reuses_a_frame_about_to_be_overwritten():
    mem = ReplayMemory(ReplayConfig(capacity=10), SHAPE, frame_capacity=6, seed=0)
    mem.add("A", frame(0), 0, 1.0, frame(1), False)
    for k in range(5):  # another actor writes 5 frames: A's frame(1) becomes the oldest
        mem.add("B", frame(100 + k), 0, -100.0, None, True)
    mem.add("A", frame(1), 0, 1.0, frame(2), False)  # must not link to the frame it evicts
    b = mem.sample(64)
    np.testing.assert_array_equal(b.next_obs[~b.terminated, 0, 0], b.obs[~b.terminated, 0, 0] + 1)
    assert mem._gather(np.array([6]), 2, np.ones(1, np.float32)).obs[0, 0, 0] == 1


def values(stacks: np.ndarray) -> list[list[int]]:
    """The step each image of (B, K, H, W) stacks shows (frames are valued by step)."""
    return stacks[:, :, 0, 0].astype(int).tolist()


def test_image_stacks_follow_the_episode_chain_and_repeat_its_first_image():
    mem = ReplayMemory(ReplayConfig(capacity=100), SHAPE, seed=0)
    a = add_episode(mem, "a", 0, 5, "collision")  # frames 0..4
    b = add_episode(mem, "b", 200, 3, "truncation")  # frames 200..202, then 203
    lost = mem.add("b", frame(900), 1, 1.0, frame(901), False)  # not b's last frame: a new chain
    got = mem._gather(np.array([a[0], a[1], a[4], b[2], lost]), 1, np.ones(5, np.float32), frames=3)
    assert got.obs.shape == (5, 3, *SHAPE) and got.next_obs.shape == (5, 3, *SHAPE)
    assert values(got.obs) == [[0, 0, 0], [1, 0, 0], [4, 3, 2], [202, 201, 200], [900, 900, 900]]
    # next_obs: the image after the chain, then the chain's last obs and the ones before it
    assert values(got.next_obs)[1] == [2, 1, 0]
    assert values(got.next_obs)[3] == [203, 202, 201]
    assert np.all(got.next_obs[2] == 0)  # a collision has no next images
    three = mem._gather(np.array([a[0], b[0]]), 3, np.ones(2, np.float32), frames=2)
    assert values(three.next_obs) == [[3, 2], [203, 202]]
    # frames=1 keeps the one-image layout
    assert mem.sample(4, 2).obs.shape == (4, *SHAPE)
    with pytest.raises(ReplayError, match="frames"):
        mem.sample(4, 1, frames=9)


def test_image_stacks_stop_at_overwritten_frames_and_survive_a_save():
    # one long episode over small rings: the frame ring (6) overwrites before the transition ring (8)
    mem = ReplayMemory(ReplayConfig(capacity=8), SHAPE, frame_capacity=6, seed=0)
    tids = add_episode(mem, "a", 0, 14, "truncation")
    valid = [t for t in tids if mem._tid[t % mem.capacity] == t and mem._valid[t % mem.capacity]]
    oldest_frame = mem._frames_written - mem.frame_capacity
    assert mem._tid[(valid[0] - 1) % mem.capacity] == valid[0] - 1 and valid[0] - 1 < oldest_frame
    got = mem._gather(np.array([t % mem.capacity for t in valid]), 1, np.ones(len(valid), np.float32), frames=4)
    for row, tid in zip(values(got.obs), valid):
        stored = [s for s in range(tid, tid - 4, -1) if s >= oldest_frame]
        # the images still stored, then the oldest of them repeated: never an overwritten frame's content
        assert row == stored + [stored[-1]] * (4 - len(stored))
    arrays, meta = mem.state_dict()
    other = ReplayMemory(ReplayConfig(capacity=8), SHAPE, frame_capacity=6)
    other.load_state_dict(arrays, meta)
    again = other._gather(np.array([t % mem.capacity for t in valid]), 1, np.ones(len(valid), np.float32), frames=4)
    np.testing.assert_array_equal(again.obs, got.obs)
    # a replay saved before predecessors were kept: each stack is its own image repeated
    other.load_state_dict({k: v for k, v in arrays.items() if k != "prev_tid"}, meta)
    old = other._gather(np.array([valid[-1] % mem.capacity]), 1, np.ones(1, np.float32), frames=2)
    assert values(old.obs) == [[valid[-1], valid[-1]]]
