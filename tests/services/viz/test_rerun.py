"""Rerun logging: write real .rrd files, check them with the bundled CLI and read them back."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from services.viz.rerun import (
    ACTION,
    DEPTH,
    ROBOT,
    DriveRecorder,
    EvalRecorder,
    RecordingFile,
    RerunLogError,
    default_blueprint,
    evaluate_recorded,
    q_entity,
    trajectory_entity,
)
from shared.config import ACTION_NAMES, SensorConfig
from shared.evaluation.protocol import run_protocol
from shared.sim.env import ExploreEnv
from shared.sim.maps import occupancy_grid
from shared.sim.world import load_world

RERUN_CLI = Path(sys.executable).with_name("rerun")


@pytest.fixture(scope="module")
def world():
    return load_world("box-room")


@pytest.fixture(scope="module")
def grid(world):
    return occupancy_grid(world)


def verify(path: Path) -> None:
    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    proc = subprocess.run([str(RERUN_CLI), "rrd", "verify", str(path)], capture_output=True, text=True,
                          env=env, timeout=60)
    assert proc.returncode == 0, proc.stderr + proc.stdout


def read_rows(path: Path) -> dict[str, list[dict]]:
    """Temporal rows per entity path (without the leading '/'), each a dict of columns."""
    rows: dict[str, list[dict]] = defaultdict(list)
    for chunk in RrdReader(path).stream().to_chunks():
        if chunk.is_static:
            rows["static:" + chunk.entity_path.lstrip("/")].append({})
            continue
        batch = chunk.to_record_batch()
        names = [n for n in batch.schema.names if n not in ("log_time", "rerun.controls.RowId")]
        columns = {n: batch.column(n).to_pylist() for n in names}
        for i in range(batch.num_rows):
            rows[chunk.entity_path.lstrip("/")].append({n: columns[n][i] for n in names})
    return rows


def frames(rows: list[dict]) -> list[int]:
    return sorted(r["eval_frame"] for r in rows)


def test_recording_holds_every_step(tmp_path, world, grid) -> None:
    sensor = SensorConfig()
    rng = np.random.default_rng(0)
    logged = []  # (frame, start, episode, step, depth, q, action, pose)
    path = tmp_path / "eval.rrd"
    with EvalRecorder(path, world, grid, sensor, recording_name="test") as rec:
        frame = 0
        for start, episode, n_steps in ((0, 0, 4), (2, 1, 3)):
            rec.begin_episode(start, episode)
            traj = []
            for step in range(n_steps):
                depth = rng.uniform(0.3, 4.0, (120, 160)).astype(np.float32)
                depth[:5] = 0.0  # no return
                q = rng.normal(size=5)
                action = int(rng.integers(5))
                pose = (0.1 * step, -0.2 * start, 0.3 * step)
                traj.append(pose[:2])
                rec.log_step(step, pose, depth, q, action)
                logged.append((frame, start, episode, step, depth, q, action, pose))
                frame += 1
            rec.end_episode({"steps": n_steps, "distance_m": 0.5, "terminated": True,
                             "collision_cause": "depth", "trajectory_xy": traj + [(9.0, 9.0)]})
            frame += 1
        rec.log_training(120, {"loss": 3.5, "mean_q": -2.0, "epsilon": 0.4, "updates_per_s": 2.5,
                               "episode_length": 31})
    verify(path)
    rows = read_rows(path)
    step_frames = [f for f, *_ in logged]

    # Depth: present at every step, in millimetres that decode to the logged metres.
    assert frames(rows[DEPTH]) == step_frames
    by_frame = {r["eval_frame"]: r for r in rows[DEPTH]}
    for f, start, episode, step, depth, *_ in logged:
        r = by_frame[f]
        assert r["episode_step"] == step
        fmt = r["DepthImage:format"][0]
        assert (fmt["width"], fmt["height"]) == (160, 120)
        assert r["DepthImage:meter"] == [1000.0]
        mm = np.frombuffer(bytes(r["DepthImage:buffer"][0]), dtype=np.uint16).reshape(120, 160)
        np.testing.assert_allclose(mm / 1000.0, depth, atol=5e-4)
        assert (mm[:5] == 0).all()

    # Q-values: one series per command, each with the logged value at every step.
    for a in range(5):
        series = {r["eval_frame"]: r["Scalars:scalars"][0] for r in rows[q_entity(a)]}
        assert sorted(series) == step_frames
        for f, *_, q, _action, _pose in logged:
            assert series[f] == pytest.approx(q[a])
    actions = {r["eval_frame"]: r["Scalars:scalars"][0] for r in rows[ACTION]}
    assert [actions[f] for f, *_ in logged] == [float(a) for *_, a, _p in logged]

    # Trajectory: the path so far at every step of the episode, then the full path at its end.
    for start, episode, n_steps in ((0, 0, 4), (2, 1, 3)):
        traj_rows = rows[trajectory_entity(start, episode)]
        mine = [f for f, s, e, *_ in logged if (s, e) == (start, episode)]
        assert frames(traj_rows)[:-1] == mine
        strips = sorted(traj_rows, key=lambda r: r["eval_frame"])
        for i, r in enumerate(strips[:-1]):
            assert len(r["LineStrips3D:strips"][0]) == i + 1
        final = strips[-1]["LineStrips3D:strips"][0]
        assert len(final) == n_steps + 1 and final[-1][:2] == [9.0, 9.0]
    assert trajectory_entity(0, 0) == "world/trajectory/start_1/episode_0"

    # Robot pose, learner metrics, static scene.
    assert frames(rows[ROBOT]) == step_frames
    assert rows["train/loss"][0]["update"] == 120 and rows["train/loss"][0]["Scalars:scalars"] == [3.5]
    assert "episode" not in rows["train/loss"][0]  # no episode timeline leaks into learner metrics
    assert {f"train/{k}" for k in ("mean_q", "epsilon", "updates_per_s", "episode_length")} <= set(rows)
    for static in ("world/map", "world/map/starts", "camera", "world"):
        assert "static:" + static in rows
    texts = [r["TextLog:text"][0] for r in rows["log/episodes"]]
    assert texts[0].startswith("start 1 episode 0: 4 steps, collision (depth)")
    # A blueprint travels with the file.
    assert RrdReader(path).blueprints()


def test_protocol_with_recorder_logs_every_step(tmp_path, world, grid) -> None:
    path = tmp_path / "protocol.rrd"

    def policy(depth_m):
        q = np.array([0.0, 0.1, 1.0 if depth_m[depth_m > 0].min() > 1.0 else -1.0, 0.1, 0.0])
        return int(np.argmax(q)), q

    with EvalRecorder(path, world, grid, SensorConfig(), image_every=2) as rec:
        results = run_protocol(policy, lambda: ExploreEnv(world="box-room", speed_table="test"),
                               starts=[0, 3], episodes_per_start=1, max_steps=12, recorder=rec, progress=False)
    verify(path)
    rows = read_rows(path)
    total = sum(e.steps for e in results.episodes)
    assert len(rows[q_entity(2)]) == total
    assert len(rows[ROBOT]) == total
    # image_every=2: depth at even steps only.
    assert sorted(r["episode_step"] for r in rows[DEPTH]) == sorted(
        s for e in results.episodes for s in range(0, e.steps, 2))
    for e in results.episodes:
        traj = rows[trajectory_entity(e.start_index, e.episode)]
        assert len(traj) == e.steps + 1
        last = max(traj, key=lambda r: r["eval_frame"])["LineStrips3D:strips"][0]
        np.testing.assert_allclose(np.array(last)[:, :2], np.array(e.trajectory_xy), atol=1e-5)
    assert len(rows["eval/episode/steps"]) == len(results.episodes)
    # every view the blueprint names shows something a recording holds: the camera view once
    # promised a receptive-field layer that nothing logged
    logged = " ".join(e for e in rows if not e.startswith("static:"))
    views = list(_views(default_blueprint(world).root_container))
    assert any(origin == "camera" for origin, _ in views)
    for origin, name in views:
        assert "receptive" not in name.lower() or "receptive" in logged, name


def _views(item):
    """(origin, name) of every view under a blueprint container."""
    for child in getattr(item, "contents", None) or []:
        if hasattr(child, "origin"):
            yield str(child.origin), str(child.name)
        else:
            yield from _views(child)


def test_depth_without_a_return_is_recorded_as_no_return(tmp_path, world, grid) -> None:
    # NaN, infinity and negative depths are "no return" (shared.depth): +inf was recorded as 65535 mm,
    # the farthest return there is, in the evaluation's recording and the drive's.
    from services.viz.rerun import DriveRecorder

    sensor = SensorConfig()
    depth = np.full((sensor.height, sensor.width), 2.0, np.float32)
    depth[0, :4] = (np.inf, -np.inf, np.nan, -1.0)
    path = tmp_path / "odd.rrd"
    with EvalRecorder(path, world, grid, sensor) as rec:
        rec.begin_episode(0, 0)
        rec.log_step(0, (0.0, 0.0, 0.0), depth, None, None)
        rec.end_episode({"steps": 1})
    drive = DriveRecorder(tmp_path / "drive.rrd", robot="bot")
    drive.log_decision(_decision(1), depth)
    drive.close()
    for rrd, entity in ((path, DEPTH), (tmp_path / "drive.rrd", "drive/depth")):
        mm = np.frombuffer(bytes(read_rows(rrd)[entity][0]["DepthImage:buffer"][0]), np.uint16)
        assert mm[:5].tolist() == [0, 0, 0, 0, 2000], rrd


def static_component(path: Path, entity: str, suffix: str):
    """The first value of the static component of ``entity`` whose column name ends in ``suffix``."""
    for chunk in RrdReader(path).stream().to_chunks():
        if chunk.is_static and chunk.entity_path == "/" + entity:
            batch = chunk.to_record_batch()
            for name in batch.schema.names:
                if name.endswith(suffix):
                    return batch.column(name).to_pylist()[0][0]
    raise AssertionError(f"{path} has no static {entity} {suffix}")


def test_the_recorded_map_lies_under_the_robot_as_the_world_does(tmp_path, world, grid) -> None:
    # A GridMap's buffer is an image whose lower-left corner lies at its translation (Rerun's GridMap
    # reference), so its top row is drawn at translation + height * cell_size: the grid's lowest-y row
    # was sent first, and the map showed mirrored in y under the robot, its path and the start arrows.
    path = tmp_path / "map.rrd"
    with EvalRecorder(path, world, grid, SensorConfig()):
        pass
    fmt = static_component(path, "world/map", ":format")
    cell = static_component(path, "world/map", ":cell_size")
    x0, y0, _ = static_component(path, "world/map", ":translation")
    image = np.frombuffer(bytes(static_component(path, "world/map", ":data")), np.uint8).reshape(
        fmt["height"], fmt["width"])
    top = y0 + fmt["height"] * cell
    iy, ix = np.nonzero(np.ones(grid.shape, bool))
    x, y = grid.cell_to_world(ix, iy)
    shown_dark = image[np.floor((top - y) / cell).astype(int), np.floor((x - x0) / cell).astype(int)] < 128
    assert np.array_equal(shown_dark, grid.occupied[iy, ix])
    assert grid.occupied.any() and not np.array_equal(grid.occupied, np.flipud(grid.occupied))  # it can tell


def test_recorder_on_callers_stream_and_misuse(tmp_path, world) -> None:
    path = tmp_path / "own.rrd"
    stream = rr.RecordingStream("cogexplore-test")
    stream.save(path)
    rec = EvalRecorder(stream, world, None, SensorConfig())  # no grid: map image left out
    rec.begin_episode(1, 0)
    with pytest.raises(RerunLogError, match="depth_m must be"):
        rec.log_step(0, (0, 0, 0), np.zeros((10, 10), np.float32), None, 2)
    with pytest.raises(RerunLogError, match="5 entries"):
        rec.log_step(0, (0, 0, 0), None, [1.0, 2.0], 2)
    with pytest.raises(RerunLogError, match="action"):
        rec.log_step(0, (0, 0, 0), None, None, 5)
    with pytest.raises(RerunLogError, match="lower_snake_case"):
        rec.log_training(1, {"Loss!": 1.0})
    with pytest.raises(RerunLogError, match="finite"):
        rec.log_training(1, {"loss": float("nan")})
    with pytest.raises(RerunLogError, match="start_index"):
        rec.begin_episode(7, 0)
    rec.log_evaluation(500, {"overall": {"mean_steps": 12.5, "collisions": {"depth": 3, "contact": 1},
                                         "episodes": 4}})
    rec.close()
    with pytest.raises(RerunLogError, match="closed"):
        rec.begin_episode(0, 0)
    stream.log("after/close", rr.Scalars(1.0))  # the caller's stream stays open
    stream.disconnect()
    verify(path)
    rows = read_rows(path)
    assert "static:world/map" not in rows
    assert rows["eval/mean_steps"][0]["update"] == 500
    assert rows["eval/collisions_depth"][0]["Scalars:scalars"] == [3.0]
    assert "after/close" in rows


def test_recorder_needs_a_sink(world) -> None:
    with pytest.raises(RerunLogError, match="nothing to log to"):
        EvalRecorder(None, world, None, SensorConfig())
    with pytest.raises(RerunLogError, match="image_every"):
        EvalRecorder(None, world, None, SensorConfig(), image_every=0)


def test_command_entities_are_named_after_commands() -> None:
    assert [q_entity(a) for a in range(5)] == [f"policy/q/{n}" for n in ACTION_NAMES]


def test_the_drive_recorder_logs_each_decision_and_reads_back(tmp_path) -> None:
    from services.viz.rerun import DriveRecorder
    from shared.wire.robot import DriveDiagnostics

    path = tmp_path / "drive.rrd"
    recorder = DriveRecorder(path, robot="bot")
    depth = np.full((30, 40), 2.0, np.float32)
    for i in range(1, 6):
        recorder.log_decision(DriveDiagnostics("bot", i, 2, 0.25, 0.0, None, 1.5, 1.0 + i,
                                               tuple(float(q) for q in range(5))), depth)
    recorder.log_decision(DriveDiagnostics("bot", 6, None, 0.0, 0.0, "watchdog", None, None), None)
    recorder.close()
    verify(path)
    rows = read_rows(path)
    assert len(rows["drive/depth"]) == 5  # the stop has no image
    assert len(rows["drive/command"]) == 6 and len(rows["drive/latency_ms"]) == 5
    assert all(len(rows[f"drive/q/{name}"]) == 5 for name in ACTION_NAMES)
    assert sorted(r["decision"] for r in rows["drive/command"]) == list(range(1, 7))


def _decision(i: int):
    from shared.wire.robot import DriveDiagnostics

    return DriveDiagnostics("bot", i, 2, 0.25, 0.0, None, 1.5, 3.0, tuple(float(q) for q in range(5)))


def test_a_folder_given_for_a_recording_is_refused_when_the_recorder_opens(tmp_path, world, grid, capsys) -> None:
    folder = tmp_path / "out.rrd"
    folder.mkdir()
    for open_one in (lambda: EvalRecorder(folder, world, grid, SensorConfig()), lambda: DriveRecorder(folder)):
        with pytest.raises(RerunLogError, match="is a folder"):
            open_one()
    # the command stops before it evaluates (it used to play every episode, then fail at the rename
    # and lose the --json results too)
    from services.cli import main

    out = tmp_path / "results.json"
    assert main(["evaluate", "--policy", "random", "--world", "box-room", "--max-steps", "400", "--quiet",
                 "--rrd", str(folder), "--json", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cogexplore evaluate: error: the recording ") and "is a folder" in err
    assert err.count("\n") == 1 and list(folder.iterdir()) == [] and sorted(tmp_path.iterdir()) == [folder]
    assert main(["drive", "--rrd", str(folder)]) == 2  # a traceback from Rerun's file sink before
    err = capsys.readouterr().err
    assert err.startswith("cogexplore drive: error: the recording ") and err.count("\n") == 1, err


def test_a_recording_that_cannot_take_its_name_leaves_no_temporary(tmp_path, world, grid) -> None:
    path = tmp_path / "eval.rrd"
    rec = EvalRecorder(path, world, grid, SensorConfig())
    path.mkdir()  # the name is taken by a folder while the recording runs
    with pytest.raises(OSError):
        rec.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval.rrd"] and list(path.iterdir()) == []


def test_the_results_survive_a_recording_that_cannot_be_finished(tmp_path, caplog) -> None:
    path = tmp_path / "eval.rrd"

    def policy(depth):
        path.mkdir(exist_ok=True)  # the recording's name is taken while the protocol plays
        return 0, None

    results = evaluate_recorded(policy, world="box-room", sensor_cfg=SensorConfig(width=64, height=48),
                                max_steps=3, rrd=path, starts=[0], episodes_per_start=1, progress=False)
    assert len(results.episodes) == 1 and results.episodes[0].steps >= 1
    assert "could not be written" in caplog.text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval.rrd"]  # no temporary left
    # the results name no recording (the evaluator's row named the path, an earlier file's maybe)
    assert "recording" not in results.meta
    written = evaluate_recorded(lambda depth: (0, None), world="box-room", sensor_cfg=SensorConfig(width=64, height=48),
                                max_steps=3, rrd=tmp_path / "ok.rrd", starts=[0], episodes_per_start=1, progress=False)
    assert written.meta["recording"] == str(tmp_path / "ok.rrd")


def test_a_temporary_left_by_a_killed_recorder_is_removed_at_the_next_open(tmp_path, world) -> None:
    import fcntl

    path = tmp_path / "eval.rrd"
    killed = tmp_path / ".eval.rrd.tmp-4194305-0a1b2c3d"  # nobody holds its lock: its process is gone
    killed.write_bytes(b"half a recording")
    writing = tmp_path / ".eval.rrd.tmp-1-feedbeef"  # another live recorder's, locked
    writing.write_bytes(b"being written")
    other = tmp_path / ".other.rrd.tmp-7-00000000"  # another recording's
    other.write_bytes(b"not ours")
    with open(writing, "rb") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        file = RecordingFile(path)
        assert not killed.exists() and writing.exists() and other.exists()
        assert file.partial is not None and file.partial.exists() and file.partial.name.startswith(".eval.rrd.tmp-")
        file.finish(keep=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([writing.name, other.name])
    # the writer let go of its lock (it ended without a rename): the next open removes that one too;
    # this process's own recorders hold theirs as well, so a second one for the same name leaves the first's
    first = EvalRecorder(path, world, None, SensorConfig())
    second = EvalRecorder(path, world, None, SensorConfig())
    assert not writing.exists() and first.file.partial.exists() and second.file.partial.exists()
    second.close()
    first.close()
    verify(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([path.name, other.name])


def test_an_earlier_releases_partial_recording_is_cleared_once_stale(tmp_path) -> None:
    # Releases before the locked temporaries wrote <name>.partial; nothing ever removed one a kill left.
    from services.viz.rerun import LEGACY_PARTIAL_STALE_S

    path = tmp_path / "eval.rrd"
    stale, fresh = tmp_path / "eval.rrd.partial", tmp_path / "other.rrd.partial"
    for legacy in (stale, fresh):
        legacy.write_bytes(b"half a recording")
    old = time.time() - LEGACY_PARTIAL_STALE_S - 5
    os.utime(stale, (old, old))
    RecordingFile(tmp_path / "other.rrd").finish(keep=False)  # fresh: maybe still written, left
    assert fresh.exists()
    RecordingFile(path).finish(keep=False)
    assert not stale.exists()
    stale.write_bytes(b"a drive's log")  # drive keeps what it finds
    os.utime(stale, (old, old))
    RecordingFile(tmp_path / "eval.rrd", orphans="keep").finish(keep=False)
    assert not stale.exists() and (tmp_path / "eval.unfinished-earlier.rrd").read_bytes() == b"a drive's log"
    stale.write_bytes(b"another")  # a second one is kept beside the first, not over it
    os.utime(stale, (old, old))
    RecordingFile(tmp_path / "eval.rrd", orphans="keep").finish(keep=False)
    assert (tmp_path / "eval.unfinished-earlier.rrd").read_bytes() == b"a drive's log"
    assert (tmp_path / "eval.unfinished-earlier-2.rrd").read_bytes() == b"another"


def test_what_a_killed_drive_recorded_is_kept_under_a_name_of_its_own(tmp_path) -> None:
    # A drive killed mid-run (SIGKILL, the OOM killer, a power cut) left its log in a hidden
    # temporary, which the next drive deleted: every step until the kill counts in a drive's log.
    path = tmp_path / "drive.rrd"
    depth = np.full((30, 40), 2.0, np.float32)
    killed = DriveRecorder(path, robot="bot")
    killed.log_decision(_decision(1), depth)
    killed.rec.flush(timeout_sec=10.0)
    orphan = killed.file.partial
    killed.file.release()  # its process is gone: nobody holds the lock
    killed.file.partial = None
    DriveRecorder(path, robot="bot").close()
    kept = tmp_path / f"drive.unfinished-{orphan.name.rsplit('-', 2)[-2]}.rrd"
    assert not orphan.exists() and kept.exists() and path.exists()
    # unfinished (no footer), but every chunk written before the kill reads back
    stats = subprocess.run([str(RERUN_CLI), "rrd", "stats", str(kept)], capture_output=True, text=True,
                           env={**os.environ, "RERUN_ANALYTICS": "0"}, timeout=60)
    assert stats.returncode == 0 and "num_chunks" in stats.stdout, stats.stderr


def test_the_drive_recording_replaces_an_earlier_one_only_when_it_is_whole(tmp_path) -> None:
    path = tmp_path / "drive.rrd"
    depth = np.full((30, 40), 2.0, np.float32)
    first = DriveRecorder(path, robot="bot")
    first.log_decision(_decision(1), depth)
    first.close()
    whole = path.read_bytes()
    second = DriveRecorder(path, robot="bot")
    for i in range(1, 4):
        second.log_decision(_decision(i), depth)
    assert path.read_bytes() == whole  # written to its temporary, not over the earlier recording
    second.close()
    verify(path)
    assert len(read_rows(path)["drive/command"]) == 3
    assert [p.name for p in tmp_path.iterdir()] == ["drive.rrd"]


def test_a_drive_without_its_viewer_says_it_will_not_look_for_one_again(tmp_path, caplog) -> None:
    # The drive checks its viewer once, when it opens; the warning said "checked again each time",
    # so a user started the viewer afterwards and waited for a stream that never came.
    import logging

    from services.bus.session import free_tcp_port
    from services.viz.rerun import local_viewer_url

    caplog.set_level(logging.WARNING, logger="cogexplore")
    recorder = DriveRecorder(tmp_path / "drive.rrd", connect_url=local_viewer_url(free_tcp_port()), robot="bot")
    recorder.log_decision(_decision(1), None)
    recorder.close()
    warned = [r.getMessage() for r in caplog.records if "no Rerun viewer" in r.getMessage()]
    assert len(warned) == 1 and "checked again" not in warned[0] and "start the viewer first" in warned[0]
    assert (tmp_path / "drive.rrd").exists()
