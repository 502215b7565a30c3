"""Planner demonstrations: the env snapshot, the planner, recording, files, and the DQfD update."""

import dataclasses
import io
import json
import zipfile

import numpy as np
import pytest
import torch

from shared.config import ConfigError, DQNConfig, ModelConfig, SensorConfig, load_preset
from shared.evaluation import PROTOCOLS
from shared.learning import demos as demos_module
from shared.learning.demos import (
    DemoError,
    Demonstration,
    StartDraw,
    demo_replay,
    load_demonstrations,
    plan_commands,
    record_demonstration,
    save_demonstrations,
)
from shared.learning.dqn import DQNAgent, large_margin_loss
from shared.learning.replay import concat_batches
from shared.sim.env import ExploreEnv
from shared.sim.world import SceneBuilder, StartPose

TINY = SensorConfig(width=40, height=30)
SMALL = ModelConfig(fc1=32, fc2=16, dropout=0.0, previous_action=True)


def dead_end_world():
    """A 2 m wide corridor closed 2.2 m ahead of the start and open 4 m behind it: driving
    straight collides, turning about in time survives."""
    b = SceneBuilder("dead-end", (-6.0, -3.0, 3.0, 3.0))
    b.boundary()
    b.wall(-5.0, -1.0, 2.3, -1.0)
    b.wall(-5.0, 1.0, 2.3, 1.0)
    b.wall(2.3, -1.0, 2.3, 1.0)
    return b.build("dead-end", [StartPose(0.0, 0.0, 0.0, "facing-the-end")])


@pytest.fixture(scope="module")
def env():
    e = ExploreEnv(world=dead_end_world(), sensor=TINY, speed_table="test", max_episode_steps=1000)
    yield e
    e.close()


def test_restoring_a_snapshot_replays_the_same_step_exactly(env):
    env.reset(options={"start_index": 0})
    for a in (2, 1, 1):
        env.step(a)
    snap = env.snapshot()
    first = env.step(4)
    env.step(0)  # wander off, then come back
    env.restore(snap)
    again = env.step(4)
    np.testing.assert_array_equal(first[0], again[0])
    assert first[4]["pose"] == again[4]["pose"] and first[4]["step"] == again[4]["step"] == 4
    assert first[4]["path_length_m"] == again[4]["path_length_m"]


def test_the_planner_turns_about_where_straight_collides_and_the_recording_replays(env):
    depth, _ = env.reset(options={"start_index": 0})
    straight = 0
    while not env.step(2)[2]:
        straight += 1
    horizon = 30
    assert straight < horizon  # the dead end is a real trap for "straight"
    plan = plan_commands(env, 0, horizon=horizon, beam=60)
    assert plan.survived_steps == len(plan.actions) == horizon
    assert plan.min_margin_m > 0 and plan.switches >= 1
    assert plan.distance_m > 1.0  # it left the dead end's end wall behind
    demo = record_demonstration(env, 0, plan.actions)
    assert len(demo) == horizon and not demo.terminated
    assert demo.depth_mm.shape == (horizon + 1, 30, 40) and demo.depth_mm.dtype == np.uint16
    assert (demo.rewards == 1.0).all()
    # deterministic: the same commands from the same start give the same images
    again = record_demonstration(env, 0, plan.actions)
    np.testing.assert_array_equal(demo.depth_mm, again.depth_mm)


def test_a_plan_longer_than_the_envs_step_cap_is_refused_before_it_searches():
    # The search stepped on from nodes the cap had ended (an env that now refuses a step after its episode
    # ended raised in the middle of the search); a horizon the env cannot play is said at once.
    capped = ExploreEnv(world=dead_end_world(), sensor=TINY, speed_table="test", max_episode_steps=10)
    try:
        with pytest.raises(DemoError, match=r"horizon 11 exceeds the env's step cap \(10\)"):
            plan_commands(capped, 0, horizon=11, beam=5)
        assert len(plan_commands(capped, 0, horizon=10, beam=5).actions) == 10
    finally:
        capped.close()


def test_a_plan_from_a_start_draw_begins_where_that_draw_puts_the_robot_and_replays_from_it(env):
    exact = plan_commands(env, 0, horizon=5, beam=20)
    assert exact.draw is None and exact.start_pose == (0.0, 0.0, 0.0)
    draw = StartDraw(seed=7, jitter_m=0.05, jitter_deg=3.0)
    plan = plan_commands(env, 0, horizon=30, beam=60, draw=draw)
    x, y, yaw = plan.start_pose
    assert plan.draw == draw and (x, y) != (0.0, 0.0)
    assert abs(x) <= 0.05 and abs(y) <= 0.05 and abs(yaw) <= np.radians(3.0) + 1e-9
    _, info = env.reset(seed=7, options={"start_index": 0, "start_jitter": (0.05, 3.0)})
    assert info["pose"] == plan.start_pose  # the protocol's own draw for that seed
    assert plan.survived_steps == 30 and plan.min_margin_m > 0
    demo = record_demonstration(env, 0, plan.actions, draw)
    assert len(demo) == 30 and not demo.terminated  # the plan survives from its draw, not only in the search
    from_exact = record_demonstration(env, 0, plan.actions[:1])
    assert not np.array_equal(demo.depth_mm[0], from_exact.depth_mm[0])


def _demo(steps=5, shape=(30, 40), seed=0):
    rng = np.random.default_rng(seed)
    return Demonstration("w", 0, "test", rng.integers(300, 4000, (steps + 1, *shape)).astype(np.uint16),
                         rng.integers(0, 5, steps).astype(np.int64), np.ones(steps, np.float32), False)


def _stripes_demo(steps, seed):
    """Images a network can tell apart: a near stripe at a different column and depth in each."""
    rng = np.random.default_rng(seed)
    frames = np.full((steps + 1, 30, 40), 3000, np.uint16)
    for t in range(steps + 1):
        c = (t * 7 + seed * 5) % 34
        frames[t, :, c:c + 6] = 600 + 40 * t
    return Demonstration("w", 0, "test", frames, rng.integers(0, 5, steps).astype(np.int64),
                         np.ones(steps, np.float32), False)


def test_files_round_trip_and_damaged_ones_are_refused_clearly(tmp_path):
    demos = [_demo(5), _demo(3, seed=1)]
    path = save_demonstrations(tmp_path / "d.npz", demos, {"plans": [{"start": 1}]})
    back = load_demonstrations(path, (30, 40))
    assert [len(d) for d in back] == [5, 3]
    np.testing.assert_array_equal(back[1].depth_mm, demos[1].depth_mm)
    np.testing.assert_array_equal(back[0].actions, demos[0].actions)

    with pytest.raises(DemoError, match="sensor gives"):
        load_demonstrations(path, (60, 80))
    with pytest.raises(DemoError, match="no such"):
        load_demonstrations(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DemoError, match="not a readable"):
        load_demonstrations(tmp_path / "junk.npz")
    # an object array needs pickle to load: refused, never unpickled
    np.savez(tmp_path / "pickled.npz", meta=np.array([{"format": "x"}], dtype=object))
    with pytest.raises(DemoError, match="not a readable"):
        load_demonstrations(tmp_path / "pickled.npz")

    def tampered(name, **arrays):
        with np.load(path) as npz:
            content = {k: npz[k] for k in npz.files}
        content.update(arrays)
        np.savez(tmp_path / name, **content)
        return tmp_path / name

    with pytest.raises(DemoError, match="outside"):
        load_demonstrations(tampered("a.npz", **{"actions.0": np.array([0, 1, 7, 1, 0], np.int64)}))
    with pytest.raises(DemoError, match="rewards"):
        load_demonstrations(tampered("r.npz", **{"rewards.0": np.array([1, np.nan, 1, 1, 1], np.float32)}))
    with pytest.raises(DemoError, match="actions are"):
        load_demonstrations(tampered("s.npz", **{"actions.0": np.zeros(9, np.int64)}))
    meta = json.dumps({"format": "other", "version": 1, "demos": []}).encode()
    with pytest.raises(DemoError, match="format"):
        load_demonstrations(tampered("f.npz", meta=np.frombuffer(meta, np.uint8)))
    with pytest.raises(DemoError, match="metadata"):
        load_demonstrations(tampered("m.npz", meta=np.frombuffer(b"{broken", np.uint8)))
    with pytest.raises(DemoError, match=r"\.npz"):
        save_demonstrations(tmp_path / "d.pkl", demos)


def test_the_demo_replay_keeps_each_chain_with_its_previous_commands():
    demo = _demo(6)
    memory = demo_replay([demo], (30, 40), seed=0)
    assert len(memory) == 6
    batch = memory.sample(64, n_step=3)
    for i in range(len(batch)):
        t = int(batch.indices[i])  # one chain: transition id = step
        np.testing.assert_array_equal(batch.obs[i], demo.depth_mm[t])
        assert batch.action[i] == demo.actions[t]
        assert batch.previous_action[i, 0] == (demo.actions[t - 1] if t else -1)
        assert batch.n_steps[i] == min(3, 6 - t) and not batch.terminated[i]
        np.testing.assert_array_equal(batch.next_obs[i], demo.depth_mm[t + batch.n_steps[i]])


def test_margin_loss_by_hand_and_zero_once_the_demonstrated_command_leads():
    q = torch.tensor([[1.0, 2.0, 0.0, 0.0, 0.0], [5.0, 0.0, 0.0, 0.0, 0.0]])
    action = torch.tensor([0, 0])
    loss, agreement = large_margin_loss(q, action, 0.8)
    # row 0: max(1, 2.8, 0.8, ...) - 1 = 1.8; row 1: max(5, 0.8, ...) - 5 = 0
    assert loss.item() == pytest.approx(0.9) and agreement == 0.5


def test_the_margin_loss_teaches_the_demonstrated_commands(one_torch_thread):
    torch.manual_seed(0)
    agent = DQNAgent(SMALL, TINY, DQNConfig(optimizer="adam", lr=3e-3, demo_batch=8, n_step=3), device="cpu",
                     seed=0)
    demos = [_stripes_demo(12, seed=3)]
    memory = demo_replay(demos, (30, 40), seed=0)
    replay = demo_replay([_stripes_demo(40, seed=4)], (30, 40), seed=1)  # stands in for the agent's own replay
    q = agent.q_values(demos[0].depth_mm[:-1], np.concatenate([[-1], demos[0].actions[:-1]]))
    assert (q.argmax(axis=1) == demos[0].actions).mean() < 0.5  # a fresh network does not know them
    first = agent.update(concat_batches(replay.sample(16, 3), memory.sample(8, 3)))
    assert set(first) >= {"label_margin_loss", "label_agreement"}
    for _ in range(400):
        metrics = agent.update(concat_batches(replay.sample(16, 3), memory.sample(8, 3)))
    assert metrics["label_margin_loss"] < 0.1 * first["label_margin_loss"]
    q = agent.q_values(demos[0].depth_mm[:-1], np.concatenate([[-1], demos[0].actions[:-1]]))
    assert (q.argmax(axis=1) == demos[0].actions).all()
    # without demonstration samples the update reports no demonstration metrics
    assert "label_agreement" not in agent.update(replay.sample(16, 3))


def test_the_learner_core_mixes_demonstrations_into_every_batch(tmp_path, one_torch_thread):
    from shared.learning.learner import LearnerCore

    path = save_demonstrations(tmp_path / "d.npz", [_demo(10)])
    cfg = load_preset("smoke").with_overrides({"sensor.width": 40, "sensor.height": 30, "train.demos": str(path),
                                               "dqn.demo_batch": 4, "train.warmup_transitions": 8})
    core = LearnerCore(cfg, device="cpu")
    assert len(core.demo_replay) == 10
    demo = _demo(20, seed=5)
    for t in range(20):
        core.add_transition("a", demo.depth_mm[t], int(demo.actions[t]), 1.0, demo.depth_mm[t + 1], False, t == 19)
    metrics = core.train_step()
    assert len(metrics["td_errors"]) == cfg.dqn.batch_size + 4 and "label_agreement" in metrics

    with pytest.raises(ConfigError, match="demo_batch"):
        cfg.with_overrides({"dqn.demo_batch": 0})
    with pytest.raises(ConfigError, match="demo_batch"):
        load_preset("smoke").with_overrides({"dqn.demo_batch": 4})
    with pytest.raises(ConfigError, match="demos"):
        load_preset("smoke").with_overrides({"train.demos": "d.pkl", "dqn.demo_batch": 4})
    with pytest.raises(DemoError, match="sensor gives"):
        LearnerCore(cfg.with_overrides({"sensor.width": 80, "sensor.height": 60}), device="cpu")


def test_the_learner_core_refuses_demonstrations_paid_other_rewards_than_its_task(tmp_path):
    # What an actor's transitions must pass, a demonstration must: a file recorded under another
    # reward (or with a finite but huge one) would bend every TD target it reaches.
    from shared.learning.learner import LearnerCore, check_start_sources

    cfg = load_preset("smoke").with_overrides({"sensor.width": 40, "sensor.height": 30, "dqn.demo_batch": 4,
                                               "train.demos": str(tmp_path / "d.npz")})
    huge = dataclasses.replace(_demo(5), rewards=np.full(5, 3e38, np.float32))
    save_demonstrations(tmp_path / "d.npz", [_demo(3), huge])
    with pytest.raises(DemoError, match=r"demonstration 1: reward\[0\] = 3\.0+\d*e\+38"):
        LearnerCore(cfg, device="cpu")
    with pytest.raises(DemoError, match="reward"):
        check_start_sources(cfg)  # the launcher refuses it before the run starts
    # another task's move reward; a collision paid like a move
    with pytest.raises(DemoError, match="pays 0.5 per move"):
        LearnerCore(cfg.with_overrides({"env.reward_move": 0.5}), device="cpu")
    crash = dataclasses.replace(_demo(4), terminated=True)
    save_demonstrations(tmp_path / "d.npz", [crash])
    with pytest.raises(DemoError, match=r"reward\[3\] = 1\.0"):
        LearnerCore(cfg, device="cpu")
    rewards = crash.rewards.copy()
    rewards[-1] = -100.0
    save_demonstrations(tmp_path / "d.npz", [dataclasses.replace(crash, rewards=rewards)])
    core = LearnerCore(cfg, device="cpu")
    assert core.demo_replay.stored_rewards()[1].tolist() == [1.0, 1.0, 1.0, -100.0]


def test_worlds_demo_command_writes_a_loadable_file_and_refuses_bad_input(tmp_path, capsys):
    from services.cli import main

    out = tmp_path / "demo.npz"
    assert main(["worlds", "demo", "corridor", "--start", "1", "--horizon", "6", "--beam", "20",
                 "--out", str(out), "--quiet"]) == 0
    plan = json.loads(capsys.readouterr().out.splitlines()[0])
    assert plan["start"] == 1 and plan["survived_steps"] == 6
    demo, = load_demonstrations(out, (30, 40))  # fast-40x30's sensor
    assert demo.world == "corridor" and demo.speed_table == "test" and len(demo) == 6
    assert main(["worlds", "demo", "corridor", "--start", "99", "--out", str(out)]) == 2
    assert "corridor has starts 1-" in capsys.readouterr().err

    # From the robust protocol's draws: one plan per draw, each from its own pose.
    assert main(["worlds", "demo", "corridor", "--start", "1", "--horizon", "6", "--beam", "20", "--protocol",
                 "robust", "--episodes", "2", "--out", str(out), "--quiet"]) == 0
    plans = [json.loads(line) for line in capsys.readouterr().out.splitlines()[:2]]
    assert [p["episode"] for p in plans] == [0, 1] and plans[0]["start_pose"] != plans[1]["start_pose"]
    assert all(p["draw"]["jitter_m"] == PROTOCOLS["robust"].start_jitter_m for p in plans)
    assert len(load_demonstrations(out, (30, 40))) == 2
    assert main(["worlds", "demo", "corridor", "--start", "1", "--episodes", "2", "--out", str(out)]) == 2
    assert "every episode would be the same" in capsys.readouterr().err


def test_demonstrations_are_not_mirrored_so_a_symmetric_scene_keeps_its_demonstrated_turn(one_torch_thread):
    # Start 6 of paper-indoor: an exactly symmetric image, demonstrated "half-right". Mirrored,
    # the same image would also teach "half-left", and the two would tie.
    frames = np.full((9, 30, 40), 3000, np.uint16)
    for t in range(9):
        frames[t, :, 14:26] = 900 + 150 * t  # centred: each image is its own mirror image
    assert (frames == frames[:, :, ::-1]).all()
    demo = Demonstration("w", 0, "test", frames, np.full(8, 3, np.int64), np.ones(8, np.float32), False)
    memory = demo_replay([demo], (30, 40), seed=0)
    replay = demo_replay([_stripes_demo(40, seed=4)], (30, 40), seed=1)
    agent = DQNAgent(SMALL, TINY, DQNConfig(optimizer="adam", lr=3e-3, demo_batch=8, n_step=3, mirror_augment=True),
                     device="cpu", seed=0)
    for _ in range(300):
        metrics = agent.update(concat_batches(replay.sample(16, 3), memory.sample(8, 3)))
    q = agent.q_values(frames[:-1], np.concatenate([[-1], demo.actions[:-1]]))
    assert (q.argmax(axis=1) == 3).all() and metrics["label_agreement"] == 1.0
    assert (q[:, 3] - q[:, 1] > 0.4).all()  # not a tie with the mirror-image turn


def test_the_shipped_demonstration_still_replays_in_todays_world():
    """pretrained:demos was recorded in paper-indoor with fast-40x30's sensor at the test speeds: the
    same commands must still give the same images (a changed world, robot or sensor needs
    `cogexplore worlds demo paper-indoor --start 6 --out shared/pretrained/paper-indoor-demos.npz`)."""
    from shared.evaluation.protocol import protocol_env_config

    rc = load_preset("fast-40x30")
    shipped = load_demonstrations("pretrained:demos", (rc.sensor.height, rc.sensor.width))
    env = ExploreEnv(protocol_env_config(rc.env, "paper-indoor", 200), rc.sensor)
    try:
        for demo in shipped:
            assert demo.world == "paper-indoor" and demo.speed_table == "test" and not demo.terminated
            again = record_demonstration(env, demo.start_index, demo.actions)
            assert len(again) == len(demo) and not again.terminated
            np.testing.assert_array_equal(again.depth_mm, demo.depth_mm)
    finally:
        env.close()


def test_a_damaged_archive_or_one_that_is_no_demonstration_file_is_refused_clearly(tmp_path):
    # a user's file: torn, bit-flipped, a lone .npy, or a zip with plain members gave tracebacks
    # (BadZipFile, zlib.error, TypeError, AttributeError) instead of a DemoError
    path = save_demonstrations(tmp_path / "d.npz", [_demo(5)])
    data = path.read_bytes()
    (tmp_path / "torn.npz").write_bytes(data[:len(data) // 2])
    np.save(tmp_path / "one.npy", np.zeros(3))
    with zipfile.ZipFile(tmp_path / "plain.npz", "w") as z:
        z.writestr("meta", json.dumps({"format": "cogexplore-demos", "version": 1, "demos": []}))
    for name in ("torn.npz", "one.npy", "plain.npz"):
        with pytest.raises(DemoError, match="not a readable demonstration file"):
            load_demonstrations(tmp_path / name)
    with np.load(path) as npz:
        content = {k: npz[k] for k in npz.files}
    meta = json.loads(content["meta"].tobytes())
    meta["demos"][0]["start_index"] = 1e999  # JSON that Python reads as infinity
    np.savez(tmp_path / "inf.npz", **{**content, "meta": np.frombuffer(json.dumps(meta).encode(), np.uint8)})
    with pytest.raises(DemoError, match="incomplete"):
        load_demonstrations(tmp_path / "inf.npz")
    for offset in range(40, len(data) - 30, 37):  # each byte flip: a clear refusal or a good file
        flipped = bytearray(data)
        flipped[offset] ^= 0xFF
        (tmp_path / "flipped.npz").write_bytes(bytes(flipped))
        try:
            load_demonstrations(tmp_path / "flipped.npz")
        except DemoError:
            pass


def test_a_demonstration_file_too_large_to_unpack_is_refused_before_it_is_read(tmp_path, monkeypatch):
    path = save_demonstrations(tmp_path / "d.npz", [_demo(20)])  # 21 images of 30x40: 50 KB unpacked
    monkeypatch.setattr(demos_module, "MAX_DEMO_FILE_BYTES", 40_000, raising=False)
    with pytest.raises(DemoError, match=r"readable demonstration file: it unpacks to 5\d{4} bytes, more than 40000$"):
        load_demonstrations(path)
    monkeypatch.undo()
    # an array header that claims far more than its member holds: refused, not a MemoryError
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<u2", "fortran_order": False, "shape": (2**40,)})
    with zipfile.ZipFile(tmp_path / "claims.npz", "w") as z:
        z.writestr("meta.npy", header.getvalue() + b"\0" * 64)
    with pytest.raises(DemoError, match="not a readable demonstration file"):
        load_demonstrations(tmp_path / "claims.npz")
