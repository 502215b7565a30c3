"""Live Rerun streaming against a real Rerun server: ``evaluate --rerun-connect/--rerun-serve``,
the evaluator service's ``--rerun-connect`` and the actors' sampled episodes.

The viewer stand-in is the Rerun CLI bundled with rerun-sdk, headless: ``rerun --port P --save
FILE`` is the same gRPC proxy a viewer hosts and writes everything it receives to FILE, which
is read back after a SIGINT. Reading back what a server received is the proof that streaming
works; each test also runs the case that must *not* reach it (no option, no viewer) and checks
that it did not, so a stream that silently goes nowhere fails here.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.request
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import rerun_cli
from rerun.chunk import RrdReader

from services.actor.service import run_actor
from services.bus.session import (
    ZenohSettings,
    declare_alive,
    free_tcp_port,
    open_router,
    open_session,
    subscribe_messages,
)
from services.cli import main as cli
from services.evaluator.service import EvaluatorService, recording_path
from services.viz.rerun import (
    EpisodeStream,
    RerunLogError,
    ViewerLink,
    local_viewer_url,
    parse_viewer_url,
    viewer_reachable,
)
from shared.config import load_preset
from shared.learning.model import QNetwork
from shared.learning.weights import to_message
from shared.sim.world import load_world
from shared.wire.keys import RunKeys
from shared.wire.messages import EpisodeStats, FlowControl, RejectCounter

REPO = Path(__file__).resolve().parents[3]
RERUN_BIN = Path(rerun_cli.__file__).with_name("rerun")  # the binary itself: a signal reaches it
SMALL = {"sensor.width": 64, "sensor.height": 48, "model.fc1": 32, "model.fc2": 16, "env.world": "box-room"}
SET_ARGS = [a for k, v in SMALL.items() if k.startswith("sensor.") for a in ("--set", f"{k}={v}")]
EVAL_ARGS = ["--policy", "random", "--world", "box-room", "--episodes-per-start", "1", "--max-steps", "3",
             "--starts", "1", "2", "--quiet", *SET_ARGS]
CHILD_ENV = {**os.environ, "RERUN_ANALYTICS": "0", "OMP_NUM_THREADS": "1"}


def wait_until_file_settles(path: Path, quiet_s: float = 0.5, timeout_s: float = 10.0) -> None:
    """Until ``path`` has not grown for ``quiet_s``: a Rerun process writing what it received."""
    last, since, deadline = -1, time.monotonic(), time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        size = path.stat().st_size if path.exists() else 0
        if size != last:
            last, since = size, time.monotonic()
        elif time.monotonic() - since > quiet_s:
            return
        time.sleep(0.05)


class ViewerServer:
    """A headless Rerun gRPC server on ``port`` saving what it receives to ``path``."""

    def __init__(self, path: Path, port: int | None = None):
        self.path = path
        self.port = port or free_tcp_port()
        self.url = local_viewer_url(self.port)
        self.proc: subprocess.Popen | None = None

    def start(self) -> ViewerServer:
        self.proc = subprocess.Popen([str(RERUN_BIN), "--bind", "127.0.0.1", "--port", str(self.port),
                                      "--save", str(self.path)], env=CHILD_ENV, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)
        deadline = time.monotonic() + 20
        while not viewer_reachable(self.url, 0.2):
            assert self.proc.poll() is None, self.proc.communicate()[0]
            assert time.monotonic() < deadline, "the Rerun server did not start listening"
            time.sleep(0.05)
        return self

    def stop(self) -> None:
        """SIGINT, once the file has stopped growing (what a client flushed may still be on its
        way to the file): the server closes its file; it can be read afterwards."""
        if self.proc is not None and self.proc.poll() is None:
            wait_until_file_settles(self.path)
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.communicate(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.communicate()

    def __enter__(self) -> ViewerServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def closed_port_url() -> str:
    return local_viewer_url(free_tcp_port())


def recordings(path: Path) -> dict[str, dict]:
    """Per recording id: its name and the temporal rows per entity (no leading '/')."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # files saved by `rerun --save` have no footer: streamed
        reader = RrdReader(path)
        out: dict[str, dict] = {}
        for store in reader.recordings():
            rows: Counter[str] = Counter()
            name = None
            episodes: set[int] = set()
            for chunk in reader.stream(store=store).to_chunks():
                batch = chunk.to_record_batch()
                if chunk.entity_path == "/__properties" and "RecordingInfo:name" in batch.schema.names:
                    name = batch.column("RecordingInfo:name").to_pylist()[-1][0]
                if chunk.is_static:
                    continue
                entity = chunk.entity_path.lstrip("/")
                rows[entity] += batch.num_rows
                if entity == "policy/action" and "episode" in batch.schema.names:
                    episodes.update(batch.column("episode").to_pylist())
            out[store.recording_id] = {"name": name, "rows": rows, "episodes": episodes}
        return out


def only_recording(path: Path) -> dict:
    recs = recordings(path)
    assert len(recs) == 1, f"expected one recording, got {[r['name'] for r in recs.values()]}"
    return next(iter(recs.values()))


# -- URLs --------------------------------------------------------------------------------------


def test_viewer_urls_are_parsed_and_bad_ones_named() -> None:
    assert parse_viewer_url("rerun+http://rerun:9876/proxy") == ("rerun", 9876)
    assert parse_viewer_url("rerun+https://viewer.example/proxy") == ("viewer.example", 443)
    for bad, words in (("http://127.0.0.1:9876/proxy", "scheme"), ("rerun+http://127.0.0.1:9876/", "/proxy"),
                       ("rerun+http://:9876/proxy", "host"), ("rerun+http://h:99999/proxy", "bad Rerun")):
        with pytest.raises(RerunLogError, match=words):
            parse_viewer_url(bad)
    assert not viewer_reachable(closed_port_url(), 0.5)


@pytest.mark.parametrize("argv, message", [
    (["--rerun-connect", "http://127.0.0.1:9876/proxy"], "scheme"),
    (["--rerun-serve-seconds", "1"], "needs --rerun-serve"),
    (["--rerun-serve", "--rerun-port", "9999", "--rerun-web-port", "9999"], "both 9999"),
])
def test_evaluate_refuses_bad_live_options(argv: list[str], message: str, capsys) -> None:
    assert cli(["evaluate", *EVAL_ARGS, *argv]) == 2
    assert message in capsys.readouterr().err


# -- cogexplore evaluate -------------------------------------------------------------------------


def test_evaluate_streams_live_to_a_running_viewer(tmp_path: Path) -> None:
    server = ViewerServer(tmp_path / "server.rrd")
    with server:
        # Control: without --rerun-connect nothing may reach the viewer.
        assert cli(["evaluate", *EVAL_ARGS, "--rrd", str(tmp_path / "file-only.rrd")]) == 0
        assert cli(["evaluate", *EVAL_ARGS, "--rrd", str(tmp_path / "live.rrd"),
                                  "--rerun-connect", server.url]) == 0
    received = only_recording(server.path)
    assert received["name"] == "evaluate random on box-room"
    in_file = only_recording(tmp_path / "live.rrd")
    # Every step the file got, the viewer got: poses, depth, Q-values, commands, the summary.
    assert received["rows"] == in_file["rows"]
    assert received["rows"]["policy/action"] >= 2 and received["rows"]["camera/depth"] >= 2
    assert received["rows"]["eval/mean_steps"] == 1


def test_evaluate_without_a_viewer_warns_and_writes_the_file_without_stalling(tmp_path: Path, caplog) -> None:
    caplog.set_level(logging.WARNING)
    started = time.monotonic()
    assert cli(["evaluate", *EVAL_ARGS, "--rrd", str(tmp_path / "e.rrd"), "--rerun-connect", closed_port_url()]) == 0
    # Handing the URL to Rerun's client unchecked costs >= 10 s (5 s connect in set_sinks, 5 s in
    # disconnect); the check before it costs a refused TCP connect.
    assert time.monotonic() - started < 8.0
    assert any("no Rerun viewer answers" in r.getMessage() for r in caplog.records)
    assert only_recording(tmp_path / "e.rrd")["rows"]["policy/action"] >= 2


def test_rerun_serve_serves_the_recording_and_exits_after_serve_seconds(tmp_path: Path) -> None:
    grpc_port, web_port = free_tcp_port(), free_tcp_port()
    cmd = [sys.executable, "-m", "services.cli", "evaluate", *EVAL_ARGS, "--rrd", str(tmp_path / "s.rrd"),
           "--rerun-serve", "--rerun-port", str(grpc_port), "--rerun-web-port", str(web_port),
           "--rerun-serve-seconds", "2"]
    proc = subprocess.Popen(cmd, cwd=REPO, env=CHILD_ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    puller = None
    try:
        first = proc.stdout.readline()  # printed (flushed) as soon as the server is up
        assert first.startswith("rerun: open http://localhost:"), first + proc.stderr.read()
        web_url = first.split()[2]
        assert f":{web_port}/?url=" in web_url
        # A client of the served stream: the CLI pulls a gRPC URL and saves what it gets.
        pulled = tmp_path / "pulled.rrd"
        puller = subprocess.Popen([str(RERUN_BIN), local_viewer_url(grpc_port), "--save", str(pulled),
                                   "--port", str(free_tcp_port())], env=CHILD_ENV,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        with urllib.request.urlopen(web_url, timeout=10) as page:  # the web viewer is served too
            assert page.status == 200
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
        if puller is not None:
            wait_until_file_settles(tmp_path / "pulled.rrd")
            puller.send_signal(signal.SIGINT)
            try:
                puller.wait(15)
            except subprocess.TimeoutExpired:
                puller.kill()
    assert proc.returncode == 0, err
    assert "rerun: serving at" in out and "for 2 s" in out
    assert only_recording(pulled)["rows"] == only_recording(tmp_path / "s.rrd")["rows"]


# -- the evaluator service --------------------------------------------------------------------------


def test_evaluator_service_skips_a_missing_viewer_once_and_streams_when_it_is_up(tmp_path: Path,
                                                                                 caplog) -> None:
    caplog.set_level(logging.INFO, logger="cogexplore")
    cfg = load_preset("paper").with_overrides(SMALL)
    server = ViewerServer(tmp_path / "server.rrd")  # its port is closed until started
    service = EvaluatorService(cfg, "svc", tmp_path / "svc", ZenohSettings(), "ev-1", every_updates=1,
                               episodes_per_start=1, max_steps=3, image_every=2, rerun_url=server.url)
    net = QNetwork(cfg.model, cfg.sensor)
    rows = [service.evaluate(to_message(net, 1)), service.evaluate(to_message(net, 2))]
    with server:
        rows.append(service.evaluate(to_message(net, 3)))
    assert [r["streamed_to"] for r in rows] == [None, None, server.url]
    warned = [r for r in caplog.records if r.levelno == logging.WARNING and "no Rerun viewer" in r.getMessage()]
    assert len(warned) == 1, [r.getMessage() for r in warned]  # once, not per evaluation
    assert any("answers again" in r.getMessage() for r in caplog.records)
    for version in (1, 2, 3):  # the .rrd files go on whatever the viewer does
        assert only_recording(recording_path(tmp_path / "svc" / "recordings", version))["rows"]["policy/action"] > 0
    received = only_recording(server.path)
    assert received["name"] == "eval svc v3"
    assert received["rows"] == only_recording(recording_path(tmp_path / "svc" / "recordings", 3))["rows"]


def test_evaluator_rejects_a_malformed_viewer_url(tmp_path: Path) -> None:
    with pytest.raises(RerunLogError, match="scheme"):
        EvaluatorService(load_preset("paper").with_overrides(SMALL), "svc", tmp_path, ZenohSettings(), "ev-1",
                         rerun_url="tcp/127.0.0.1:9876")


# -- actors ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def router() -> str:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_router([endpoint]):
        yield endpoint


def run_small_actor(router: str, rerun_url: str | None, max_steps: int, every: int = 1,
                    overrides: dict | None = None, on_episode=None) -> dict:
    """run_actor on the smoke preset (box-room, 40 x 30, 50-step episodes) with a learner's
    liveliness token present, so it steps instead of pausing; ``on_episode`` gets its
    EpisodeStats messages."""
    cfg = load_preset("smoke").with_overrides(overrides or {})
    settings = ZenohSettings(connect=(router,))
    done = threading.Event()
    with open_session(settings) as session:
        token = declare_alive(session, RunKeys("live").alive("learner", "L"))  # noqa: F841
        sub = (subscribe_messages(session, RunKeys("live").all_stats("episode"), EpisodeStats, on_episode,  # noqa: F841
                                  RejectCounter("episode stats")) if on_episode else None)
        credit = FlowControl(learner_id="L", updates=0, transitions_received=0, transitions_wanted=10**9).encode()

        def speak_as_the_learner() -> None:  # an actor holds until the learner's flow control says go
            while not done.wait(0.1):
                session.put(RunKeys("live").flow, credit)

        speaker = threading.Thread(target=speak_as_the_learner, daemon=True)
        speaker.start()
        try:
            return run_actor(cfg, "live", "a-1", settings, threading.Event(), max_steps=max_steps, seed=3,
                             rerun_url=rerun_url, rerun_every_episodes=every, rerun_image_every=2)
        finally:
            done.set()
            speaker.join()  # before the session closes: a put on a closing session raises in the thread


def test_actor_lets_the_expert_drive_the_drawn_episodes(router: str) -> None:
    """explore.expert_episode_prob = 1 with epsilon 0: every episode is the expert's, runs to
    the 50-step cap without a collision, and its stats say it was guided -- in the main world
    and in the extra one (env.extra_worlds), which the stats mark."""
    episodes: list[EpisodeStats] = []
    counters = run_small_actor(router, None, max_steps=300, on_episode=lambda m, _k: episodes.append(m),
                               overrides={"explore.expert_episode_prob": 1.0, "explore.eps_start": 0.0,
                                          "explore.eps_end": 0.0, "env.extra_worlds": "corridor",
                                          "env.extra_world_prob": 0.5})
    assert counters["episodes"] == 6, counters
    deadline = time.monotonic() + 60
    while len(episodes) < 6 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert len(episodes) == 6
    for e in episodes:
        assert e.extra["expert_guided"] == 1.0 and e.truncated and not e.terminated and e.steps == 50, e
    assert {e.extra["extra_world"] for e in episodes} == {0.0, 1.0}


def test_actor_streams_every_nth_episode_as_one_recording(router: str, tmp_path: Path) -> None:
    with ViewerServer(tmp_path / "server.rrd") as server:
        counters = run_small_actor(router, server.url, max_steps=120, every=2)
    assert counters["env_steps"] == 120 and counters["episodes"] >= 2, counters
    assert counters["rerun_episodes_streamed"] >= 1 and counters["rerun_dropped"] == 0, counters
    received = only_recording(server.path)
    assert received["name"] == "actor a-1 (live)"
    # Every step the stream took reached the viewer, each with its Q-values; the depth of every
    # 2nd step; only even episodes (every=2), on the actor's own episode numbers.
    rows = received["rows"]
    assert rows["policy/action"] == counters["rerun_steps_streamed"] > 0, (rows, counters)
    assert rows["policy/q/straight"] == rows["policy/action"] == rows["world/robot"]
    assert 0 < rows["camera/depth"] < rows["policy/action"], rows
    assert rows["log/episodes"] == counters["rerun_episodes_streamed"], (rows, counters)
    assert received["episodes"] and all(e % 2 == 0 for e in received["episodes"]), received["episodes"]
    assert 0 in received["episodes"]


def test_actor_goes_on_without_a_viewer(router: str, caplog) -> None:
    caplog.set_level(logging.WARNING, logger="cogexplore")
    started = time.monotonic()
    counters = run_small_actor(router, closed_port_url(), max_steps=60, every=1)
    assert counters["env_steps"] == 60 and counters["rerun_episodes_streamed"] == 0
    assert counters["rerun_episodes_skipped"] >= 1
    assert time.monotonic() - started < 30
    assert sum("no Rerun viewer" in r.getMessage() for r in caplog.records) == 1


def test_episode_stream_calls_never_wait_on_the_worker(tmp_path: Path) -> None:
    """A full queue drops (and counts) instead of blocking the caller."""
    world = load_world("box-room")
    cfg = load_preset("smoke")
    with ViewerServer(tmp_path / "server.rrd") as server:
        stream = EpisodeStream(server.url, world, cfg.sensor, recording_name="burst", every_episodes=1,
                               image_every=1, queue_size=8)
        depth = np.ones((cfg.sensor.height, cfg.sensor.width), "float32")
        assert stream.begin_episode(0, 0)
        for step in range(2000):
            stream.log_step(step, (0.0, 0.0, 0.0), depth, [0.0] * 5, 2)
        stream.end_episode({"steps": 2000, "truncated": True})
        stream.close()
        assert not stream.begin_episode(1, 0)  # closed: nothing more is queued
    # the caller outran the worker and its puts were dropped and counted, not waited on (how fast the
    # caller is belongs to a benchmark: a bound on wall time here only measured the machine's load)
    assert stream.dropped > 0 and stream.steps_logged + stream.dropped >= 2000
    link = ViewerLink(server.url)
    assert not link.up()  # the server is gone


def temporal_rows(path: Path, entity: str) -> list[dict]:
    """The temporal rows of ``entity`` (no leading '/') in a file ``rerun --save`` wrote, each a dict of
    its columns."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # streamed: no footer
        out = []
        for chunk in RrdReader(path).stream().to_chunks():
            if chunk.entity_path.lstrip("/") != entity or chunk.is_static:
                continue
            batch = chunk.to_record_batch()
            columns = {n: batch.column(n).to_pylist() for n in batch.schema.names
                       if n not in ("log_time", "rerun.controls.RowId")}
            out += [{n: columns[n][i] for n in columns} for i in range(batch.num_rows)]
        return out


def test_an_actors_episodes_in_other_worlds_are_each_seen_over_their_own_world(tmp_path: Path) -> None:
    # The actors play extra worlds (the 40x30 presets: 200 procedural ones). The map was static, so
    # each streamed episode replaced it for the whole recording: every path, scrubbed to any time,
    # drawn over the last world's map, and the paths of every world drawn over each other.
    worlds = [load_world("box-room"), load_world("procedural:1")]
    cfg = load_preset("smoke")
    with ViewerServer(tmp_path / "server.rrd") as server:
        stream = EpisodeStream(server.url, worlds[0], cfg.sensor, recording_name="worlds", every_episodes=1)
        for episode, world in enumerate(worlds):
            assert stream.begin_episode(episode, 0, world)
            for step in range(3):
                stream.log_step(step, (0.1 * step, 0.0, 0.0), None, [0.0] * 5, 2)
            stream.end_episode({"steps": 3, "truncated": True}, final_pose=(0.3, 0.0, 0.0))
        stream.close()
    assert stream.episodes_streamed == 2
    first_frame = {}  # episode -> its first eval_frame
    for r in temporal_rows(server.path, "policy/action"):
        first_frame[r["episode"]] = min(r["eval_frame"], first_frame.get(r["episode"], r["eval_frame"]))
    extents = {r["eval_frame"]: r["LineStrips3D:strips"][0] for r in temporal_rows(server.path, "world/map/extent")}
    assert sorted(extents) == sorted(first_frame.values())
    for episode, world in enumerate(worlds):
        xmin, ymin, xmax, ymax = world.extent
        assert extents[first_frame[episode]][2][:2] == pytest.approx([xmax, ymax])
    assert len([r for r in temporal_rows(server.path, "world/map") if r.get("GridMap:data")]) == 2
    clears = sorted(r["eval_frame"] for r in temporal_rows(server.path, "world/trajectory"))
    assert clears == [first_frame[0], first_frame[1]]  # the earlier episode's path is gone with its world


class GatedLink(ViewerLink):
    """A real viewer check that first waits for the test's go: the stream's worker is held at an
    episode's begin while the env loop fills the queue."""

    def __init__(self, url: str):
        super().__init__(url)
        self.entered = threading.Event()
        self.go = threading.Event()

    def up(self) -> bool:
        self.entered.set()
        self.go.wait(30)
        return super().up()


def test_an_episode_whose_begin_was_dropped_logs_nothing_into_the_episode_before(tmp_path: Path) -> None:
    # A full queue dropped episode 0's end and episode 1's begin; episode 1's steps were then queued
    # and the worker logged them as episode 0's: one path jumping from one start to another.
    world = load_world("box-room")
    cfg = load_preset("smoke")
    with ViewerServer(tmp_path / "server.rrd") as server:
        stream = EpisodeStream(server.url, world, cfg.sensor, recording_name="drops", every_episodes=1,
                               queue_size=4)
        stream.link = link = GatedLink(server.url)
        assert stream.begin_episode(0, 0)
        assert link.entered.wait(10)  # the worker has taken episode 0's begin
        for step in range(10):  # four queued, the other steps and the end dropped
            stream.log_step(step, (0.0, 0.0, 0.0), None, [0.0] * 5, 2)
        stream.end_episode({"steps": 10, "truncated": True})
        streamed = stream.begin_episode(1, 3)
        link.go.set()
        for step in range(10):
            stream.log_step(step, (1.0, 1.0, 0.0), None, [0.0] * 5, 0)
            time.sleep(0.02)  # the worker drains the queue meanwhile
        stream.end_episode({"steps": 10, "truncated": True})
        stream.close()
    assert stream.dropped >= 7
    actions = [r["Scalars:scalars"][0] for r in temporal_rows(server.path, "policy/action")]
    assert actions == [2.0] * 4, actions  # episode 0's four steps, none of episode 1's
    assert not streamed
