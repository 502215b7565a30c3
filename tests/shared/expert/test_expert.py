"""Supervised pretraining: the expert, the dataset, SL training, the transfer into the Q-network,
and the ``sl`` / ``rl`` evaluation policies (real worlds, real env, real files; tiny sizes)."""

from __future__ import annotations

import json
import math
import os
import re

import numpy as np
import pytest
import torch

from shared.config import ACTION_NAMES, ConfigError, EnvConfig, SensorConfig, TrainConfig, load_preset
from shared.expert.dataset import (
    DriveConfig,
    SupervisedDataset,
    dataset_request,
    generate_dataset,
    open_or_generate,
)
from shared.expert.expert import (
    CommandExpert,
    ExpertConfig,
    ExpertGuide,
    SupervisedError,
)
from shared.expert.supervised import TrainSettings, train_supervised
from shared.learning.checkpoints import (
    CheckpointError,
    card_path,
    load_supervised,
    save_supervised,
)
from shared.sim.maps import clearance_map
from shared.sim.world import SceneBuilder, StartPose, load_world

SMALL_SENSOR = SensorConfig(width=40, height=30)
TEST_ENV = EnvConfig(speed_table="test")


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    # Small convolutions on a busy 2-core machine: one thread is several times faster than two.
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> SupervisedDataset:
    """800 frames in the corridor world (40 x 30 images): the structured corridors of the
    authors' supervised data."""
    return generate_dataset(tmp_path_factory.mktemp("sl") / "data", worlds=["corridor"], frames=800,
                            sensor_cfg=SMALL_SENSOR, env_cfg=TEST_ENV, drive_cfg=DriveConfig(episode_steps=60),
                            seed=0, test_fraction=0.25, progress=False)


@pytest.fixture(scope="module")
def trained(dataset, tmp_path_factory):
    net, card = train_supervised(dataset, TrainSettings(epochs=6, batch_size=32, lr=2e-3, seed=1, device="cpu"),
                                 progress=False)
    path = save_supervised(tmp_path_factory.mktemp("model") / "sl.safetensors", net, card)
    return net, card, path


# ----------------------------------------------------------------------------------- expert


@pytest.mark.parametrize("shape, share", [((23, 31), 0.05), ((6, 41), 0.0), ((41, 6), 0.0), ((50, 60), 0.002)])
def test_clearance_map_is_the_exact_distance_to_the_nearest_occupied_cell(shape, share):
    # sparse grids leave whole columns free: their nearest occupied cell lies far along the row
    rng = np.random.default_rng(3)
    occ = rng.random(shape) < share
    occ[0, 0] = True
    got = clearance_map(occ, 0.1)
    cells = np.argwhere(occ)
    iy, ix = np.mgrid[0:shape[0], 0:shape[1]]
    brute = np.sqrt(((iy[..., None] - cells[:, 0]) ** 2 + (ix[..., None] - cells[:, 1]) ** 2).min(axis=-1)) * 0.1
    np.testing.assert_allclose(got, brute, atol=1e-9)
    assert np.all(got[occ] == 0)


def _wall_scene(open_side: str):
    """A 6 x 6 m room; the robot at the origin faces +x toward a wall 1.2 m ahead that blocks
    straight ahead and one side; the other side is open."""
    b = SceneBuilder(f"wall-open-{open_side}", (-3.0, -3.0, 3.0, 3.0))
    b.boundary()
    if open_side == "left":
        b.wall(1.2, -3.0, 1.2, 0.3)
    else:
        b.wall(1.2, -0.3, 1.2, 3.0)
    return b.build(f"wall-open-{open_side}", [StartPose(0.0, 0.0, 0.0)])


@pytest.mark.parametrize("open_side, wanted", [("left", {0, 1}), ("right", {3, 4})])
def test_expert_turns_toward_the_free_side(open_side, wanted):
    expert = CommandExpert(_wall_scene(open_side), TEST_ENV)
    scores = expert.scores(0.0, 0.0, 0.0)
    assert expert.label(0.0, 0.0, 0.0) in wanted
    # the blocked side is worse than the open one, and a wall 1.2 m ahead stops "straight" early
    turn_open, turn_blocked = (scores[0], scores[4]) if open_side == "left" else (scores[4], scores[0])
    assert turn_open > turn_blocked
    assert max(scores[i] for i in wanted) > scores[2]
    # with the wall out of the way straight ahead wins
    open_room = SceneBuilder("open-room", (-3.0, -3.0, 3.0, 3.0))
    open_room.boundary()
    assert CommandExpert(open_room.build("open-room", [StartPose(0, 0, 0)]), TEST_ENV).label(-2.0, 0.0, 0.0) == 2


def test_expert_drives_box_room_without_collision():
    from shared.sim.env import ExploreEnv

    env = ExploreEnv(TEST_ENV, SMALL_SENSOR, world="box-room", max_episode_steps=60)
    expert = CommandExpert(env.world, env.env_config, SMALL_SENSOR)
    for start in range(len(env.world.starts)):
        env.reset(seed=start, options={"start_index": start})
        for _ in range(60):
            _, _, terminated, truncated, info = env.step(expert.label(*env.robot.pose()))
            assert not terminated, f"start {start}: collision ({info['collision_cause']}) at step {info['step']}"
            if truncated:
                break


def test_survival_search_agrees_with_the_env_and_finds_the_dead_end_trap(capsys):
    from services.cli import main
    from shared.sim.env import ExploreEnv

    exact = ExpertConfig(contact_margin_m=0.0, depth_margin_m=0.0, wedge_spacing_m=0.01, resolution_m=0.02)
    train = EnvConfig(speed_table="train")
    env = ExploreEnv(train, SMALL_SENSOR, world="box-room")
    box = CommandExpert(env.world, train, SMALL_SENSOR, exact)
    # 0.8 m from a wall, facing it: the env's first step ends in a collision for the same commands.
    steps = box.survival_steps(1.2, 0.0, 0.0, horizon=5)
    for a in range(5):
        env.reset(seed=0)
        env.robot.set_pose(1.2, 0.0, 0.0)
        terminated = env.step(a)[2]
        assert terminated == (steps[a] == 0), (a, steps)
    assert steps.max() >= 1  # straight is the one command still safe there

    # paper-indoor's start 6 (a 1.4 m dead end) is a trap at the training speeds; start 1 is not.
    world = load_world("paper-indoor")
    paper = CommandExpert(world, train, SMALL_SENSOR, exact)
    open_start, dead_end = world.starts[0], world.starts[5]
    assert dead_end.name == "dead-end"
    assert paper.survival_steps(open_start.x, open_start.y, open_start.yaw, horizon=40).max() == 40
    assert 15 < paper.survival_steps(dead_end.x, dead_end.y, dead_end.yaw, horizon=40).max() < 40

    assert main(["worlds", "starts", "box-room", "--horizon", "8", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert len(rows) == 4 and all(r["survival_steps"] == 8 and not r["trap"] for r in rows)
    for bad in (["nowhere"], ["box-room", "--horizon", "0"], ["box-room", "--margin-m", "-1"]):
        assert main(["worlds", "starts", *bad]) == 2
        assert "error" in capsys.readouterr().err


def test_a_way_out_is_found_by_the_beam_where_no_plan_shape_reaches_and_not_in_the_dead_end():
    train = EnvConfig(speed_table="train")
    H = train.trap_horizon_steps
    world = load_world("paper-indoor")
    expert = CommandExpert(world, train, SMALL_SENSOR)
    open_start, dead_end = world.starts[0], world.starts[5]
    # Start 1: no plan (one command, a turn, straight) stays safe for H steps, a sequence does.
    safe, _ = expert.plan_scores(open_start.x, open_start.y, open_start.yaw)
    assert safe.max() < H
    assert expert.has_way_out(open_start.x, open_start.y, open_start.yaw, H)
    assert expert.survival_steps(open_start.x, open_start.y, open_start.yaw, horizon=H).max() == H
    # Into start 6's dead end, straight ahead: a way out, then none, never again (no flicker).
    x, y, yaw = dead_end.x, dead_end.y, dead_end.yaw
    found = [expert.has_way_out(x + k * 0.1 * math.cos(yaw), y + k * 0.1 * math.sin(yaw), yaw, H)
             for k in range(14)]
    first_none = found.index(False)
    assert 0 < first_none and not any(found[first_none:])
    assert expert.has_way_out(x, y, yaw, H) == expert.has_way_out(x, y, yaw, H)  # deterministic


def _far_pillar_world(tmp_path, distance_m: float):
    """A 4 m room (start inside at (-1, 0) facing +x) and a pillar ``distance_m`` east of it."""
    path = tmp_path / f"far-{distance_m:g}.xml"
    walls = "".join(f'<geom type="box" pos="{x} {y} 1" size="{hx} {hy} 1"/>'
                    for x, y, hx, hy in ((2, 0, 0.05, 2), (-2, 0, 0.05, 2), (0, 2, 2, 0.05), (0, -2, 2, 0.05)))
    path.write_text(f'<mujoco><worldbody><geom name="floor" type="plane" size="0 0 1"/>{walls}'
                    f'<geom type="cylinder" pos="{distance_m} 0 1" size="0.2 1"/>'
                    '<site name="start_a" pos="-1 0 0"/></worldbody></mujoco>')
    return load_world(str(path))


def _uncapped(expert: CommandExpert) -> CommandExpert:
    """The expert on the exact clearance map (no cap), swapped in before its first question."""
    expert.clearance = clearance_map(expert.grid.occupied, expert.grid.resolution_m)
    expert._prepare_lookup()
    return expert


def _answers(expert: CommandExpert, poses, horizon: int) -> list:
    return [(expert.scores(*p).tolist(), expert.label(*p), expert.safe_commands(*p, horizon).tolist(),
             expert.has_way_out(*p, horizon), expert.survival_steps(*p, horizon=8).tolist()) for p in poses]


@pytest.mark.timeout(60)
def test_the_expert_of_a_world_with_an_obstacle_kilometres_away_is_built_at_once(tmp_path):
    # A pillar 2 km east of the room: the uncapped clearance map's row pass swept once per cell of
    # its largest distance (40,000 sweeps: minutes to hours) before the first label.
    expert = CommandExpert(_far_pillar_world(tmp_path, 2000.0), TEST_ENV, SMALL_SENSOR)
    assert expert.clearance_cap_m == 8.0
    assert expert.label(-1.0, 0.0, 0.0) == 2 and expert.safe_commands(-1.0, 0.0, 0.0, 4)[2]
    assert expert.clearance_at(np.array([1000.0]), np.array([0.0]))[0] >= expert.clearance_cap_m


def test_the_capped_clearance_map_changes_no_answer_of_the_expert(tmp_path):
    # A pillar 60 m away: open floor up to 28 m from any obstacle, beyond the cap, where the capped
    # map reads "at least the cap"; every answer is still the exact map's.
    world = _far_pillar_world(tmp_path, 60.0)
    capped, exact = CommandExpert(world, TEST_ENV, SMALL_SENSOR), _uncapped(CommandExpert(world, TEST_ENV, SMALL_SENSOR))
    cap = capped.clearance_cap_m
    assert exact.clearance.max() > 3 * cap
    below = exact.clearance < cap
    assert np.array_equal(capped.clearance[below], exact.clearance[below]) and np.all(capped.clearance[~below] >= cap)
    rng = np.random.default_rng(0)
    poses = [(-1.0, 0.0, 0.0), (1.7, 0.0, 0.0), (-1.8, -1.8, math.pi)]  # the start, a wall ahead, a corner
    poses += [(float(x), float(y), float(t)) for x, y, t in zip(rng.uniform(-1.9, 1.9, 12), rng.uniform(-1.9, 1.9, 12),
                                                                rng.uniform(-math.pi, math.pi, 12))]
    poses += [(30.0, 0.0, 0.0), (55.0, 1.0, 2.0), (59.0, 0.0, 0.0)]  # open floor, and facing the pillar
    assert _answers(capped, poses, 12) == _answers(exact, poses, 12)
    # and on a shipped world the capped map is the exact one, bit for bit, and so is every answer
    world = load_world("paper-indoor")
    train = EnvConfig(speed_table="train")
    capped, exact = CommandExpert(world, train, SMALL_SENSOR), _uncapped(CommandExpert(world, train, SMALL_SENSOR))
    assert np.array_equal(capped.clearance, exact.clearance)
    starts = [(s.x, s.y, s.yaw) for s in world.starts]
    assert _answers(capped, starts, train.trap_horizon_steps) == _answers(exact, starts, train.trap_horizon_steps)


def test_expert_guide_drives_the_drawn_share_of_episodes_with_the_experts_commands():
    from shared.config import ExploreConfig
    from shared.sim.env import ExploreEnv

    env = ExploreEnv(TEST_ENV, SMALL_SENSOR, world="box-room", max_episode_steps=40)
    off = ExpertGuide(env, 0.0, seed=0)
    assert not off.begin_episode() and off.action((0.0, 0.0, 0.0)) is None
    share = ExpertGuide(env, 0.3, seed=0)
    drawn = [share.begin_episode() for _ in range(2000)]
    assert 0.27 < np.mean(drawn) < 0.33
    # in a run with extra worlds the guide follows the expert of the world the episode plays
    env = ExploreEnv(TEST_ENV, SMALL_SENSOR, world="box-room", max_episode_steps=40, extra_worlds="corridor",
                     extra_world_prob=1.0)
    always = ExpertGuide(env, 1.0, seed=0)
    _, info = env.reset(seed=0)
    assert info["world"] == "corridor" and always.begin_episode()
    corridor_expert = CommandExpert(env.world, env.env_config, env.sensor_config)
    for _ in range(40):  # the guide's commands are the expert's, and they keep the robot clear
        action = always.action(info["pose"])
        assert action == corridor_expert.label(*info["pose"])
        _, _, terminated, truncated, info = env.step(action)
        assert not terminated, info["collision_cause"]
    with pytest.raises(SupervisedError, match="probability"):
        ExpertGuide(env, 1.5)
    with pytest.raises(ConfigError, match="expert_episode_prob"):
        ExploreConfig(expert_episode_prob=-0.1)


def test_expert_guide_labels_the_drawn_share_of_steps_as_a_teacher_without_touching_the_episode_draws():
    from shared.config import ExploreConfig
    from shared.sim.env import ExploreEnv

    env = ExploreEnv(TEST_ENV, SMALL_SENSOR, world="box-room", max_episode_steps=40)
    _, info = env.reset(seed=0)
    assert ExpertGuide(env, 0.5, seed=0).teacher_label(info["pose"]) is None  # labelling off
    half = ExpertGuide(env, 0.5, seed=0, label_prob=0.4)
    plain = ExpertGuide(env, 0.5, seed=0)
    expert = CommandExpert(env.world, env.env_config, env.sensor_config)
    labels = []
    for _ in range(200):
        assert half.begin_episode() == plain.begin_episode()  # the episodes' draws are the same
        labels.append(half.teacher_label(info["pose"]))
    given = [a for a in labels if a is not None]
    assert 0.3 < len(given) / len(labels) < 0.5
    assert set(given) == {expert.label(*info["pose"])}
    with pytest.raises(SupervisedError, match="label probability"):
        ExpertGuide(env, 0.0, label_prob=-0.5)
    with pytest.raises(ConfigError, match="expert_label_prob"):
        ExploreConfig(expert_label_prob=1.5)


def test_expert_config_is_validated():
    with pytest.raises(SupervisedError, match="turn_steps"):
        ExpertConfig(horizon_steps=4, turn_steps=4)
    with pytest.raises(SupervisedError, match="noise_prob"):
        DriveConfig(noise_prob=1.5)


# ---------------------------------------------------------------------------------- dataset


def test_dataset_has_declared_sizes_labels_and_an_episode_split(dataset):
    m = dataset.manifest
    n = 800
    assert len(dataset) == n == m["frames"]
    assert dataset.depth_mm.shape == (n, 30, 40) and dataset.depth_mm.dtype == np.uint16
    assert dataset.labels.dtype == np.uint8 and dataset.labels.max() <= 4
    assert sum(m["label_counts"].values()) == n
    assert len(set(np.asarray(dataset.labels).tolist())) >= 3  # not a constant label
    depth = np.asarray(dataset.depth_mm[:50])
    assert depth.max() <= 4000 and (depth > 0).mean() > 0.5  # millimetres within the 4 m range
    train, test = dataset.split()
    assert len(train) + len(test) == n and len(test) > 0 and len(train) > len(test)
    assert not set(dataset.episodes[train].tolist()) & set(dataset.episodes[test].tolist())  # by episode
    assert 0.15 < len(test) / n < 0.5
    # every file is a plain .npy (no pickle) and the manifest is JSON
    for name in ("depth_mm", "labels", "episodes", "worlds", "poses"):
        np.load(dataset.root / f"{name}.npy", allow_pickle=False, mmap_mode="r")
    assert json.loads((dataset.root / "manifest.json").read_text())["format"] == "cogexplore-sl-data"


def test_dataset_labels_are_the_experts_at_the_stored_poses(dataset):
    expert = CommandExpert(load_world("corridor"), TEST_ENV, SMALL_SENSOR)
    for i in np.random.default_rng(0).choice(len(dataset), 20, replace=False):
        assert expert.label(*dataset.poses[i]) == dataset.labels[i]


def test_dataset_is_reused_only_when_its_request_matches(tmp_path):
    args = (["box-room", "corridor"], 60, SMALL_SENSOR, TEST_ENV, ExpertConfig(), DriveConfig(episode_steps=10), 0, 0.3)
    ds, reused = open_or_generate(tmp_path / "d", dataset_request(*args), progress=False)
    assert not reused and len(ds) == 60
    assert ds.manifest["frames_per_world"] == {"box-room": 30, "corridor": 30}
    assert set(np.asarray(ds.worlds).tolist()) == {0, 1}
    again, reused = open_or_generate(tmp_path / "d", dataset_request(*args), progress=False)
    assert reused and again.manifest["created_unix"] == ds.manifest["created_unix"]
    other = list(args)
    other[1] = 70
    bigger, reused = open_or_generate(tmp_path / "d", dataset_request(*other), progress=False)
    assert not reused and len(bigger) == 70
    (tmp_path / "d" / "labels.npy").write_bytes(b"garbage")
    with pytest.raises(SupervisedError):
        SupervisedDataset.open(tmp_path / "d")
    # A folder that holds anything else is no dataset to replace: `pretrain --data ~/thesis` used
    # to delete it whole.
    precious = tmp_path / "thesis"
    (precious / "chapter").mkdir(parents=True)
    (precious / "notes.txt").write_text("months of work")
    for folder in (precious, precious / "notes.txt"):
        with pytest.raises(SupervisedError, match="not a dataset's|is a file"):
            open_or_generate(folder, dataset_request(*args), progress=False)
    assert (precious / "notes.txt").read_text() == "months of work" and (precious / "chapter").is_dir()
    # nor does a name that merely looks like a writer's temporary file pass, or a folder named like one
    for name in ("thesis.tmp-final.docx", "labels.npy.tmp-1"):
        beside = tmp_path / "beside"
        beside.mkdir(exist_ok=True)
        (beside / name).mkdir() if name.endswith("-1") else (beside / name).write_text("keep")
        with pytest.raises(SupervisedError, match="not a dataset's"):
            open_or_generate(beside, dataset_request(*args), progress=False)
        assert (beside / name).exists()


def test_dataset_refuses_bad_requests(tmp_path):
    with pytest.raises(SupervisedError, match="frames"):
        generate_dataset(tmp_path / "x", worlds=["box-room"], frames=1, progress=False)
    with pytest.raises(ValueError, match="unknown world"):
        generate_dataset(tmp_path / "x", worlds=["no-such-world"], frames=10, progress=False)


def _float_labels(manifest: dict, root) -> None:
    # labels stored as float32 (2.5 passes a "< 5" check) and declared so in the manifest
    manifest["files"]["labels"]["dtype"] = "float32"
    np.save(root / "labels.npy", np.load(root / "labels.npy").astype(np.float32) + 0.5)


@pytest.mark.parametrize("change", [
    lambda m, _root: m.pop("files"),
    lambda m, _root: m.__setitem__("files", []),
    lambda m, _root: m["files"].pop("labels"),
    lambda m, _root: m.pop("test_episodes"),
    lambda m, _root: m.__setitem__("test_episodes", ["a"]),
    lambda m, _root: m.pop("sensor"),
    lambda m, _root: m["sensor"].__setitem__("width", -3),
    lambda m, _root: m["sensor"].update(width=80, height=60),  # another image size than the arrays'
    _float_labels,
    lambda m, _root: m.__setitem__("test_episodes", []),  # training refused it, in every run, with the same folder
    lambda m, _root: m.__setitem__("test_episodes", list(range(m["episodes"]))),
    lambda m, _root: m.__setitem__("test_episodes", [m["episodes"] + 5]),
], ids=["no-files", "files-list", "no-labels-entry", "no-test-episodes", "test-episodes-text", "no-sensor",
        "bad-sensor", "sensor-size", "float-labels", "no-test-split", "no-train-split", "unknown-test-episode"])
def test_a_damaged_manifest_is_refused_clearly_and_regenerated(tmp_path, change):
    # An edited or foreign manifest used to crash with a KeyError or TypeError (or later, in the
    # split or the network) instead of being refused, so `pretrain --data` gave a traceback.
    root = tmp_path / "d"
    args = (["box-room"], 24, SMALL_SENSOR, TEST_ENV, ExpertConfig(), DriveConfig(episode_steps=6), 0, 0.3)
    ds, _ = open_or_generate(root, dataset_request(*args), progress=False)
    created = ds.manifest["created_unix"]
    manifest = json.loads((root / "manifest.json").read_text())
    change(manifest, root)
    (root / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(SupervisedError, match="manifest.json"):
        SupervisedDataset.open(root)
    again, reused = open_or_generate(root, dataset_request(*args), progress=False)
    assert not reused and len(again) == 24 and again.manifest["created_unix"] != created
    assert again.split()[1].size > 0


def _tiny_dataset(root, seed: int = 0) -> SupervisedDataset:
    return generate_dataset(root, worlds=["box-room"], frames=24, sensor_cfg=SMALL_SENSOR, env_cfg=TEST_ENV,
                            drive_cfg=DriveConfig(episode_steps=6), seed=seed, test_fraction=0.3, progress=False)


@pytest.mark.timeout(30)
def test_an_array_that_is_a_fifo_a_device_or_empty_is_refused_not_waited_on(tmp_path):
    # np.load waited for ever for a FIFO's writer, and an empty file (what a power cut leaves of
    # an unsynced write) escaped as an EOFError traceback instead of a regenerated dataset.
    root = tmp_path / "d"
    _tiny_dataset(root)
    (root / "labels.npy").unlink()
    os.mkfifo(root / "labels.npy")
    with pytest.raises(SupervisedError, match="labels.npy is missing or not a regular file"):
        SupervisedDataset.open(root)
    (root / "labels.npy").unlink()
    os.symlink("/dev/zero", root / "labels.npy")
    with pytest.raises(SupervisedError, match="labels.npy is missing or not a regular file"):
        SupervisedDataset.open(root)
    (root / "labels.npy").unlink()
    (root / "labels.npy").write_bytes(b"")
    with pytest.raises(SupervisedError, match="labels.npy cannot be read"):
        SupervisedDataset.open(root)
    request = dataset_request(["box-room"], 24, SMALL_SENSOR, TEST_ENV, ExpertConfig(), DriveConfig(episode_steps=6),
                              0, 0.3)
    again, reused = open_or_generate(root, request, progress=False)
    assert not reused and len(again) == 24


def test_a_dataset_too_big_for_the_disk_is_refused_before_anything_is_written(tmp_path):
    # The depth file is a sparse memmap: a disk that filled during the collection killed the process
    # with SIGBUS, and a size past the file system's limit gave "[Errno 22] Invalid argument".
    with pytest.raises(SupervisedError, match=r"10+ frames of 40 x 30 need .* MB free: collect fewer frames"):
        generate_dataset(tmp_path / "d", worlds=["box-room"], frames=10**12, sensor_cfg=SMALL_SENSOR,
                         env_cfg=TEST_ENV, progress=False)
    assert not (tmp_path / "d").exists()
    # Nor is a dataset already there deleted (it was, before the request was refused).
    old = _tiny_dataset(tmp_path / "old")
    with pytest.raises(SupervisedError, match="collect fewer frames"):
        generate_dataset(old.root, worlds=["box-room"], frames=10**12, sensor_cfg=SMALL_SENSOR, env_cfg=TEST_ENV,
                         progress=False)
    assert SupervisedDataset.open(old.root).manifest["created_unix"] == old.manifest["created_unix"]


def test_the_arrays_are_on_disk_before_the_manifest_and_the_old_manifest_goes_first(tmp_path, monkeypatch):
    # After a power cut, a manifest on disk must not stand beside arrays that are not (unsynced
    # np.save files), nor an old manifest beside a new dataset's arrays.
    root = tmp_path / "d"
    _tiny_dataset(root)
    synced: list[str] = []
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        synced.append(os.path.basename(os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    (root / ".labels.npy.tmp-99999").write_bytes(b"\x93NUMPY")  # what a writer killed mid-array leaves
    ds = _tiny_dataset(root, seed=1)
    manifest_at = next(i for i, name in enumerate(synced) if name.startswith(".manifest.json.tmp-"))
    for name in ("labels", "episodes", "worlds", "poses"):
        assert any(n.startswith(f".{name}.npy.tmp-") for n in synced[:manifest_at]), (name, synced)
    assert synced[0] == "d", synced  # the old manifest's removal, before any new file
    assert ds.manifest["request"]["seed"] == 1 and sorted(p.name for p in root.iterdir()) == sorted(
        ["manifest.json", "depth_mm.npy", "labels.npy", "episodes.npy", "worlds.npy", "poses.npy"])


# --------------------------------------------------------------------------------- training


def test_sl_training_is_clearly_above_chance(trained, dataset):
    _net, card, _path = trained
    assert card["data"]["test_frames"] == len(dataset.split()[1])
    # chance: 0.2 balanced accuracy whatever the label distribution
    assert card["balanced_accuracy"] >= 0.35, card
    assert card["accuracy"] >= 0.5, card
    cm = np.asarray(card["confusion_matrix"])
    assert cm.shape == (5, 5) and cm.sum() == card["data"]["test_frames"]
    assert math.isclose(card["accuracy"], np.trace(cm) / cm.sum())


def test_the_majority_baseline_is_the_training_majority_answered_on_the_test_split(trained, dataset):
    # It was the whole dataset's majority share (0.680 here) beside the test accuracy; the test split's
    # share of the training split's majority label is 0.659.
    from services.tools.pretrain import card_summary

    _net, card, _path = trained
    train, test = dataset.split()
    labels = np.asarray(dataset.labels)
    majority = int(np.bincount(labels[train], minlength=5).argmax())
    assert card["majority_command"] == ACTION_NAMES[majority] == "straight"
    assert card["majority_accuracy"] == pytest.approx(np.mean(labels[test] == majority))
    assert card["majority_accuracy"] != pytest.approx(np.bincount(labels).max() / len(labels))
    assert f"always straight {card['majority_accuracy']:.3f};" in card_summary(card)
    # the confusion matrix's column names stand over their columns
    lines = card_summary(card).splitlines()
    header, rows = lines[-6], lines[-5:]
    def column_ends(line: str) -> list[int]:
        return [m.end() for m in re.finditer(r"\S+", line)]

    assert all(column_ends(row)[1:] == column_ends(header) for row in rows), "\n".join(lines[-6:])


def test_model_file_round_trips_with_its_card(trained, tmp_path):
    net, card, path = trained
    loaded, meta = load_supervised(path)
    assert meta["card"]["accuracy"] == card["accuracy"]
    assert json.loads(card_path(path).read_text())["confusion_matrix"] == card["confusion_matrix"]
    for (name, a), b in zip(net.state_dict().items(), loaded.state_dict().values()):
        assert torch.equal(a.cpu(), b), name
    broken = tmp_path / "broken.safetensors"
    data = bytearray(path.read_bytes())
    data[-10] ^= 0xFF
    broken.write_bytes(bytes(data))
    with pytest.raises(CheckpointError):
        load_supervised(broken)
    with pytest.raises(CheckpointError, match="safetensors"):
        save_supervised(tmp_path / "model.pt", net)


def test_a_model_write_that_fails_leaves_no_card_of_another_model_beside_it(trained, tmp_path):
    # The card file was written after the model: a failed (or killed) model write left the old model's
    # card beside whatever model file there was.
    from service_processes import run_on_a_full_disk

    _net, card, path = trained
    out = tmp_path / "sl.safetensors"
    out.write_bytes(path.read_bytes())
    card_path(out).write_text(json.dumps({"accuracy": 0.25}))  # the card of the model there before
    done = run_on_a_full_disk("from shared.learning.checkpoints import load_supervised, save_supervised; "
                              f"net, meta = load_supervised({str(path)!r}); "
                              f"save_supervised({str(out)!r}, net, {{'accuracy': 0.9}})", 1000)
    assert done.returncode != 0 and "File too large" in done.stderr, done.stderr[-2000:]
    assert out.read_bytes() == path.read_bytes() and not card_path(out).exists()
    save_supervised(out, load_supervised(path)[0], card)  # written whole: both again
    assert json.loads(card_path(out).read_text())["accuracy"] == card["accuracy"]


# --------------------------------------------------------------------------------- transfer


def test_transfer_copies_exactly_the_conv_weights_and_a_resume_wins(trained, tmp_path):
    from shared.learning.checkpoints import CheckpointManager
    from shared.learning.learner import LearnerCore, resume_from

    sl_net, _card, path = trained
    base = load_preset("smoke").with_overrides({"sensor.width": 40, "sensor.height": 30})
    plain = LearnerCore(base, device="cpu")
    core = LearnerCore(base.with_overrides({"train.init_conv_from": str(path)}), device="cpu")
    sl = {k: v for k, v in sl_net.state_dict().items() if k.startswith("trunk.")}
    for net in (core.agent.online, core.agent.target):
        for name, t in net.state_dict().items():
            if name.startswith("trunk."):
                assert torch.equal(t.cpu(), sl[name].cpu()), name
            else:  # fully connected layers stay at their (seeded) initialisation
                assert torch.equal(t.cpu(), plain.agent.online.state_dict()[name].cpu()), name
    assert not torch.equal(plain.agent.online.trunk.conv1.weight, core.agent.online.trunk.conv1.weight)

    # a run that resumes keeps its checkpoint's weights, not the supervised ones
    CheckpointManager(tmp_path / "ckpt").save(plain.agent)
    resumed = LearnerCore(base.with_overrides({"train.init_conv_from": str(path)}), device="cpu")
    assert resume_from(CheckpointManager(tmp_path / "ckpt"), resumed)
    for name, t in resumed.agent.online.state_dict().items():
        assert torch.equal(t, plain.agent.online.state_dict()[name]), name


def test_transfer_needs_the_same_depth_encoding(trained, tmp_path):
    from shared.learning.learner import LearnerCore
    from shared.learning.model import SupervisedNet

    _net, _card, metric_path = trained
    base = load_preset("smoke").with_overrides({"sensor.width": 40, "sensor.height": 30,
                                                "model.depth_encoding": "inverse"})
    with pytest.raises(CheckpointError, match="trained on 'metric' depth input"):
        LearnerCore(base.with_overrides({"train.init_conv_from": str(metric_path)}), device="cpu")
    inverse_path = save_supervised(tmp_path / "inv.safetensors", SupervisedNet(SMALL_SENSOR, "inverse"))
    loaded, meta = load_supervised(inverse_path)
    assert loaded.trunk.depth_encoding == meta["depth_encoding"] == "inverse"
    core = LearnerCore(base.with_overrides({"train.init_conv_from": str(inverse_path)}), device="cpu")
    assert torch.equal(core.agent.online.trunk.conv1.weight, loaded.trunk.conv1.weight)
    with pytest.raises(SupervisedError, match="depth_encoding"):
        TrainSettings(depth_encoding="disparity")


def test_init_conv_from_is_validated(tmp_path):
    assert TrainConfig().init_conv_from == ""
    with pytest.raises(ConfigError, match="init_conv_from"):
        TrainConfig(init_conv_from="model.pt")
    with pytest.raises(ConfigError, match="init_conv_from"):
        load_preset("smoke").with_overrides({"train.init_conv_from": 3})
    from shared.learning.learner import LearnerCore

    with pytest.raises(CheckpointError, match="no such file"):
        LearnerCore(load_preset("smoke").with_overrides({"train.init_conv_from": str(tmp_path / "x.safetensors")}),
                    device="cpu")


# ------------------------------------------------------------------------------- evaluation


def _evaluate(argv: list[str]) -> int:
    from services.cli import main

    return main(["evaluate", *argv])


def test_evaluate_policy_sl_and_rl(trained, tmp_path, capsys):
    from shared.evaluation.results import load_results
    from shared.learning.checkpoints import CheckpointManager
    from shared.learning.dqn import DQNAgent

    _net, _card, path = trained
    common = ["--world", "box-room", "--episodes-per-start", "1", "--max-steps", "5", "--quiet", "--device", "cpu"]
    out = tmp_path / "sl.json"
    assert _evaluate(["--policy", "sl", "--checkpoint", str(path), "--json", str(out), *common]) == 0
    results = load_results(out)
    assert results.meta["model"] == "SL" and results.meta["policy"] == "sl"
    assert results.meta["checkpoint_kind"] == "supervised"
    assert len(results.episodes) == 4 and results.meta["sensor"]["width"] == 40
    assert "| SL |" in capsys.readouterr().out

    # rl: greedy on a frozen-conv Q-learning run, labelled RL
    cfg = load_preset("smoke").with_overrides({"sensor.width": 40, "sensor.height": 30, "dqn.conv_lr_scale": 0.0,
                                               "train.init_conv_from": str(path)})
    agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu", seed=0)
    CheckpointManager(tmp_path / "rl" / "checkpoints").save(agent, config=cfg.to_dict())
    out = tmp_path / "rl.json"
    assert _evaluate(["--policy", "rl", "--checkpoint", str(tmp_path / "rl"), "--json", str(out), *common]) == 0
    assert load_results(out).meta["model"] == "RL"

    # the wrong kind of file for each, and no file at all
    assert _evaluate(["--policy", "sl", "--checkpoint", str(tmp_path / "rl"), *common]) == 2
    assert _evaluate(["--policy", "rl", "--checkpoint", str(path), *common]) == 2
    assert _evaluate(["--policy", "sl", *common]) == 2
    assert "needs --checkpoint" in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "message"), [
    (["--out", "sl.pt"], "must end in .safetensors"),
    (["--out", "sl.safetensors", "--seed", "-1"], "seed must be an integer in [0, "),
    (["--out", "sl.safetensors", "--seed", str(2**64)], "seed must be an integer in [0, "),  # failed after collecting
    (["--out", "sl.safetensors", "--device", "gpu"], "unknown device 'gpu'"),  # failed after collecting
    (["--out", "sl.safetensors", "--data", "sl.safetensors"], "is the dataset folder (--data)"),  # after training
    (["--out", "sl.safetensors", "--data", "sl.card.json"], "is the dataset folder (--data)"),
    (["--out", "sl.safetensors", "--data", "x/../sl.safetensors"], "is the dataset folder (--data)"),  # after training
])
def test_pretrain_refuses_an_output_or_seed_it_cannot_use_before_collecting(argv, message, tmp_path, capsys,
                                                                         monkeypatch):
    from services.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["pretrain", "--preset", "smoke", "--worlds", "box-room", "--frames", "60", "--epochs", "1",
                 *argv]) == 2
    assert message in capsys.readouterr().err and list(tmp_path.iterdir()) == []  # no data collected


@pytest.mark.parametrize("folder", ["sl.safetensors", "sl.card.json"])
def test_pretrain_refuses_a_model_path_that_is_a_folder_before_collecting(folder, tmp_path, capsys, monkeypatch):
    # Refused by the last write, after the data was collected and the model trained.
    from services.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / folder).mkdir()
    assert main(["pretrain", "--preset", "smoke", "--worlds", "box-room", "--frames", "60", "--epochs", "1",
                 "--out", "sl.safetensors"]) == 2
    assert f"{folder} is a folder" in capsys.readouterr().err and [p.name for p in tmp_path.iterdir()] == [folder]


def test_pretrain_refuses_a_model_folder_it_cannot_write_before_collecting(tmp_path, capsys):
    # Found by the last write, after the data and the training, as a SafetensorError traceback.
    from services.cli import main

    out = "/proc/cogexplore-sl/sl.safetensors"  # a folder no one (root included) can make a file in
    assert main(["pretrain", "--preset", "smoke", "--worlds", "box-room", "--frames", "24", "--epochs", "1",
                 "--out", out, "--data", str(tmp_path / "data"), "--quiet", "--device", "cpu"]) == 2
    assert "the model cannot be written there" in capsys.readouterr().err
    assert not (tmp_path / "data").exists()  # no data collected


def test_pretrain_json_prints_the_card_alone_on_stdout(tmp_path, capsys):
    # The "model: PATH" line followed the JSON on stdout, so `pretrain --json | jq` failed.
    from services.cli import main

    out = tmp_path / "sl.safetensors"
    assert main(["pretrain", "--preset", "smoke", "--worlds", "box-room", "--frames", "24", "--epochs", "1",
                 "--out", str(out), "--quiet", "--device", "cpu", "--json"]) == 0
    printed = capsys.readouterr()
    assert json.loads(printed.out) == load_supervised(out)[1]["card"]
    assert f"model: {out}" in printed.err


def test_a_diverging_training_stops_at_the_first_non_finite_loss_and_writes_no_model(tmp_path, monkeypatch):
    """No setting reaches a non-finite loss for real (Adam's steps are bounded by lr and the input is clamped
    to [0, 1]: lr 1 with balanced classes peaks near 1e8), so one training forward is patched to return NaN
    logits: pretrain stops at that batch, names it, and writes neither the model nor its card."""
    from shared.expert.supervised import pretrain
    from shared.learning.model import SupervisedNet

    dataset = _tiny_dataset(tmp_path / "data")  # what pretrain's request below reuses
    steps_per_epoch = math.ceil(len(dataset.split()[0]) / 4)
    forward, calls = SupervisedNet.forward, []

    def diverging(net, x):
        logits = forward(net, x)
        if net.training:
            calls.append(x.shape[0])
            if len(calls) == steps_per_epoch + 2:  # epoch 2, batch 2
                return logits * float("nan")
        return logits

    monkeypatch.setattr(SupervisedNet, "forward", diverging)
    out = tmp_path / "sl.safetensors"
    with pytest.raises(SupervisedError, match=r"loss is nan at epoch 2, batch 2: .* at lr 0.5; try a lower --lr$"):
        pretrain(out, worlds=["box-room"], frames=24, sensor_cfg=SMALL_SENSOR, env_cfg=TEST_ENV,
                 data_dir=tmp_path / "data", drive_cfg=DriveConfig(episode_steps=6), test_fraction=0.3,
                 settings=TrainSettings(epochs=3, batch_size=4, lr=0.5, device="cpu"), progress=False)
    assert len(calls) == steps_per_epoch + 2  # not one step after
    assert not out.exists() and not card_path(out).exists()
