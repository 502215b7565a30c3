"""The evaluator service on a real loopback Zenoh router: weights in, EvalResult, eval.jsonl and
.rrd out; bad weights counted, not fatal; ``--once`` and SIGTERM as a real process."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
import zenoh

from services.bus.session import (
    LivelinessWatch,
    ZenohSettings,
    free_tcp_port,
    open_router,
    open_session,
    put_reliable,
    serve_latest,
)
from services.evaluator.service import EvaluatorService, recording_path
from shared.config import ConfigError, load_preset
from shared.errors import StopRequested
from shared.evaluation import PROTOCOLS
from shared.evaluation.results import load_results
from shared.learning.model import QNetwork
from shared.learning.policy import NonFiniteQValues
from shared.learning.weights import to_message
from shared.wire.keys import RunKeys
from shared.wire.messages import EvalResult

REPO = Path(__file__).resolve().parents[3]
RERUN_CLI = Path(sys.executable).with_name("rerun")
OVERRIDES = {"sensor.width": 64, "sensor.height": 48, "model.fc1": 32, "model.fc2": 16, "env.world": "box-room"}
SET_ARGS = [a for k, v in OVERRIDES.items() for a in ("--set", f"{k}={v}")]


@pytest.fixture(scope="module")
def router() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_router([endpoint]):
        yield endpoint


def small_net(**extra) -> QNetwork:
    cfg = load_preset("paper").with_overrides({**OVERRIDES, **extra})
    return QNetwork(cfg.model, cfg.sensor)


class Results:
    """EvalResult messages received on a run's eval key, in arrival order."""

    def __init__(self, session: zenoh.Session, keys: RunKeys):
        self.items: list[EvalResult] = []
        self._cond = threading.Condition()
        self._sub = session.declare_subscriber(keys.all_stats("eval"), self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.items.append(EvalResult.decode(sample.payload.to_bytes()))
            self._cond.notify_all()

    def wait(self, n: int, timeout_s: float = 60.0) -> list[EvalResult]:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.items) >= n, timeout_s), f"{len(self.items)} results"
            return list(self.items)


def wait_until(predicate, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def verify_rrd(path: Path) -> None:
    proc = subprocess.run([str(RERUN_CLI), "rrd", "verify", str(path)], capture_output=True, text=True,
                          env={**os.environ, "RERUN_ANALYTICS": "0"}, timeout=60)
    assert proc.returncode == 0, proc.stderr + proc.stdout


def test_service_evaluates_due_weights_and_counts_bad_ones(router: str, tmp_path: Path) -> None:
    keys = RunKeys("svc")
    cfg = load_preset("paper").with_overrides(OVERRIDES)
    service = EvaluatorService(cfg, "svc", tmp_path / "svc", ZenohSettings(connect=(router,)), "ev-1",
                               every_updates=10, episodes_per_start=1, max_steps=5, image_every=2)
    stop = threading.Event()
    status: list[int] = []
    worker = threading.Thread(target=lambda: status.append(service.run(stop)), daemon=True)
    net = small_net()
    with open_session(ZenohSettings(connect=(router,))) as session:
        results = Results(session, keys)
        with LivelinessWatch(session, keys.all_alive("evaluator")) as alive:
            worker.start()
            assert alive.wait(lambda keys_: keys.alive("evaluator", "ev-1") in keys_, 30.0)
            # Garbage until the first is counted (subscriptions propagate through the router).
            for _ in range(20):
                put_reliable(session, keys.weights, b"\x00not msgpack")
                if wait_until(lambda: service.rejects.total > 0, 0.5):
                    break
            assert service.rejects.counts.get("garbage", 0) >= 1
            put_reliable(session, keys.weights, to_message(small_net(**{"model.fc1": 48}), 3).encode())
            assert wait_until(lambda: service.rejects.counts.get("fingerprint") == 1)

            put_reliable(session, keys.weights, to_message(net, 5).encode())
            first = results.wait(1)[0]
            put_reliable(session, keys.weights, to_message(net, 7).encode())   # same bucket of 10: skipped
            put_reliable(session, keys.weights, to_message(net, 12).encode())  # a new multiple of 10: due
            second = results.wait(2)[1]
            # A restarted learner (a new epoch) publishes the checkpoint it resumed from first: the
            # same weights at the same version played the same draws already, so only 25 runs.
            put_reliable(session, keys.weights, to_message(net, 12, learner_epoch=1).encode())
            put_reliable(session, keys.weights, to_message(net, 25, learner_epoch=1).encode())
            assert results.wait(3)[2].policy_version == 25
            stop.set()
            worker.join(timeout=30)
            assert not worker.is_alive() and status == [0]
            # Closing the session took the liveliness token with it.
            assert alive.wait(lambda keys_: not keys_, 10.0)

    assert [first.policy_version, second.policy_version] == [5, 12]
    for r in (first, second):
        assert r.evaluator_id == "ev-1" and r.world == "box-room" and r.speed_table == "test"
        assert sorted(r.start_index) == [0, 1, 2, 3] and all(1 <= s <= 5 for s in r.steps)
        assert r.extra["mean_steps"] == pytest.approx(sum(r.steps) / 4)
    assert [e["policy_version"] for e in service.evaluations] == [5, 12, 25]

    rows = [json.loads(line) for line in (tmp_path / "svc" / "stats" / "eval.jsonl").read_text().splitlines()]
    assert [r["policy_version"] for r in rows] == [5, 12, 25]
    assert rows[1]["summary"]["episodes"] == 4 and rows[1]["max_steps"] == 5
    assert rows[1]["rejected_weights"]["fingerprint"] == 1 and rows[1]["rejected_weights"]["garbage"] >= 1
    assert rows[1]["summary"]["mean_steps"] == pytest.approx(second.extra["mean_steps"])
    assert rows[1]["protocol"] == "robust"  # the default: jittered starts and sensor noise
    for version in (5, 12):
        rrd = recording_path(tmp_path / "svc" / "recordings", version)
        assert rrd.name == f"eval-{version:06d}.rrd"
        verify_rrd(rrd)
        saved = load_results(tmp_path / "svc" / "stats" / "eval" / f"eval-{version:06d}.json")
        assert saved.protocol == PROTOCOLS["robust"] and saved.meta["policy_version"] == version
    assert not recording_path(tmp_path / "svc" / "recordings", 7).exists()


def service_process(router: str, runs: Path, *extra: str) -> subprocess.Popen:
    env = {**os.environ, "RERUN_ANALYTICS": "0", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "services.evaluator", "--run", "proc", "--runs-dir", str(runs),
           "--connect", router, "--id", "ev-proc", "--max-steps", "4", "--no-record", "--preset", "paper", *SET_ARGS,
           *extra]  # a preset: no learner here to take the run's configuration from
    return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_more_episodes_than_a_result_message_carries_are_refused_at_start_up(tmp_path: Path) -> None:
    # box-room has 4 starts: 1024 per start is the message's 4096 episodes, 1025 is not, and was
    # found only after the first evaluation (its files written), which then stopped the service.
    cfg = load_preset("paper").with_overrides(OVERRIDES)
    settings = ZenohSettings(connect=("tcp/127.0.0.1:9",))
    assert EvaluatorService(cfg, "cap", tmp_path, settings, "ev-1", episodes_per_start=1024).episodes_per_start == 1024
    with pytest.raises(ConfigError, match="4100 episodes; an evaluation result carries at most 4096"):
        EvaluatorService(cfg, "cap", tmp_path, settings, "ev-1", episodes_per_start=1025)


def test_once_queries_the_latest_weights_and_exits(router: str, tmp_path: Path) -> None:
    keys = RunKeys("proc")
    payload = to_message(small_net(), 42).encode()
    with open_session(ZenohSettings(connect=(router,))) as session:
        results = Results(session, keys)
        queryable = serve_latest(session, keys.weights_latest, lambda: payload)  # noqa: F841
        proc = service_process(router, tmp_path, "--once", "--protocol", "paper")
        out, _ = proc.communicate(timeout=120)
        assert proc.returncode == 0, out
        assert results.wait(1, 10.0)[0].policy_version == 42
    row = json.loads((tmp_path / "proc" / "stats" / "eval.jsonl").read_text())
    assert row["policy_version"] == 42 and row["recording"] is None and row["protocol"] == "paper"
    assert load_results(tmp_path / "proc" / "stats" / "eval" / "eval-000042.json").protocol == PROTOCOLS["paper"]


def test_sigterm_stops_the_service_cleanly(router: str, tmp_path: Path) -> None:
    keys = RunKeys("proc")
    with open_session(ZenohSettings(connect=(router,))) as session:
        with LivelinessWatch(session, keys.all_alive("evaluator")) as alive:
            proc = service_process(router, tmp_path)
            try:
                assert alive.wait(lambda k: keys.alive("evaluator", "ev-proc") in k, 60.0)
                proc.send_signal(signal.SIGTERM)
                out, _ = proc.communicate(timeout=30)
            finally:
                if proc.poll() is None:
                    proc.kill()
            assert proc.returncode == 0, out
            assert "signal SIGTERM: stopping" in out
            assert alive.wait(lambda k: not k, 10.0)


def test_a_preset_the_runs_weights_do_not_fit_stops_the_evaluator_in_one_line(router: str, tmp_path: Path) -> None:
    from shared.wire.messages import RunConfigMessage

    keys = RunKeys("proc")
    payload = RunConfigMessage(learner_id="learner", config=load_preset("smoke")).encode()
    with open_session(ZenohSettings(connect=(router,))) as session:
        queryable = serve_latest(session, keys.config, lambda: payload)  # noqa: F841
        proc = service_process(router, tmp_path)  # paper with a 64 x 48 image, against the learner's 40 x 30
        out, _ = proc.communicate(timeout=120)
    last = out.strip().splitlines()[-1]
    assert proc.returncode == 2 and "Traceback" not in out, out
    assert last.startswith("cogexplore evaluator: error: this evaluator's sensor.width=64 differs from the run's 40 "
                           "(learner 'learner' of run 'proc'"), last


def test_a_protocol_that_cannot_run_here_stops_the_evaluator_in_one_line(router: str, tmp_path: Path) -> None:
    # A collision distance no jittered view of box-room's starts keeps: every evaluation would fail the
    # same way. It was a traceback (status 1) when the first weights came; a negative --seed was too.
    payload = to_message(small_net(), 42).encode()
    with open_session(ZenohSettings(connect=(router,))) as session:
        queryable = serve_latest(session, RunKeys("proc").weights_latest, lambda: payload)
        proc = service_process(router, tmp_path, "--once", "--set", "env.collision_distance_m=0.85")
        out, _ = proc.communicate(timeout=120)
        queryable.undeclare()
    assert proc.returncode == 2 and "Traceback" not in out, out
    assert out.strip().splitlines()[-1].startswith("cogexplore evaluator: error: start 1 of world 'box-room': "
                                                   "none of 100 poses drawn"), out
    assert not (tmp_path / "proc" / "stats" / "eval.jsonl").exists()
    with pytest.raises(ConfigError, match="seed must be an integer >= 0, got -1"):
        EvaluatorService(load_preset("paper").with_overrides(OVERRIDES), "proc", tmp_path, ZenohSettings(), "ev-1",
                         seed=-1)


def test_no_router_leaves_no_tensorboard_writer_behind(tmp_path: Path) -> None:
    service = EvaluatorService(load_preset("paper").with_overrides(OVERRIDES), "svc", tmp_path / "svc",
                               ZenohSettings(connect=("tcp/127.0.0.1:9",), router_wait_s=0.0), "ev-1", record=False,
                               tensorboard=tmp_path / "tb")
    assert service.board.enabled
    stop = threading.Event()
    stop.set()
    with pytest.raises(StopRequested):
        service.run(stop)
    assert not service.board.enabled  # closed, its writer thread ended


def test_weights_numbered_below_the_last_evaluated_are_due_a_forged_version_holds_nothing_off(tmp_path: Path) -> None:
    # A learner's versions only rise: one forged message numbered 2^40 - 1, once evaluated, made
    # every real version "not due" for the rest of the learner's life.
    cfg = load_preset("paper").with_overrides(OVERRIDES)
    service = EvaluatorService(cfg, "svc", tmp_path / "svc", ZenohSettings(), "ev-1", every_updates=10,
                               episodes_per_start=1, max_steps=5)
    net = small_net()
    service.last_version = (1, 2**40 - 1)
    assert service.due(to_message(net, 25, learner_epoch=1))
    service.last_version = (1, 25)
    assert not service.due(to_message(net, 27, learner_epoch=1)) and service.due(to_message(net, 30, learner_epoch=1))
    assert not service.due(to_message(net, 25, learner_epoch=1))  # the same version again: not twice


def test_a_restarted_evaluator_skips_the_weights_its_run_evaluated_unless_asked_once(tmp_path: Path) -> None:
    # `up --resume` restarts the evaluator beside a learner that first publishes the checkpoint it
    # resumed from: its evaluation was in eval.jsonl already, and a second row drew the curve twice.
    cfg = load_preset("paper").with_overrides(OVERRIDES)

    def evaluator() -> EvaluatorService:
        return EvaluatorService(cfg, "svc", tmp_path / "svc", ZenohSettings(), "ev-1", every_updates=10,
                                episodes_per_start=1, max_steps=3, record=False)

    net, other = small_net(), small_net()
    assert evaluator().evaluate(to_message(net, 5), repeat=False)["weights_sha256"]
    restarted = evaluator()
    assert restarted.evaluate(to_message(net, 5, learner_epoch=1), repeat=False) is None
    assert restarted.last_version == (1, 5)  # due() counts from it all the same
    assert restarted.evaluate(to_message(other, 5), repeat=False) is not None  # other weights: evaluated
    assert restarted.evaluate(to_message(net, 5)) is not None  # --once evaluates what it is asked
    rows = (tmp_path / "svc" / "stats" / "eval.jsonl").read_text().splitlines()
    assert len(rows) == 3
    # Another protocol, seed or episode count is another evaluation.
    assert EvaluatorService(cfg, "svc", tmp_path / "svc", ZenohSettings(), "ev-1", episodes_per_start=1,
                            max_steps=3, record=False, seed=7).evaluate(to_message(net, 5), repeat=False)


def test_weights_whose_q_values_overflow_are_skipped_and_the_next_version_evaluated(tmp_path: Path, caplog) -> None:
    # Each weight finite, so they load; their Q-values are not, and argmax played NaN as command 0: the
    # evaluation scored a network that chose nothing.
    cfg = load_preset("paper").with_overrides(OVERRIDES)
    service = EvaluatorService(cfg, "svc", tmp_path / "svc", ZenohSettings(), "ev-1", every_updates=10,
                               episodes_per_start=1, max_steps=3, record=False)
    huge = small_net()
    with torch.no_grad():
        huge.fc1.weight.fill_(1e38)
    with caplog.at_level(logging.ERROR, logger="cogexplore.evaluator"):
        assert service.evaluate_in_service(to_message(huge, 5)) is None
    assert "policy version 5 not evaluated: the network gave Q-values that are not finite" in caplog.text
    assert not (tmp_path / "svc" / "stats" / "eval.jsonl").exists()
    assert service.evaluate_in_service(to_message(small_net(), 12)) is not None
    with pytest.raises(NonFiniteQValues):  # --once and the tools say it as their error
        service.evaluate(to_message(huge, 25))


def test_a_restarted_evaluator_evaluates_again_on_a_world_file_edited_since(tmp_path: Path) -> None:
    # Keyed by the file's path alone, the evaluations of the old file stood for the edited one: skipped.
    from tests.shared.evaluation.test_eval_log import write_room

    world = write_room(tmp_path / "room.xml")
    cfg = load_preset("paper").with_overrides(OVERRIDES)

    def evaluate(learner_epoch: int) -> dict | None:
        service = EvaluatorService(cfg, "svc", tmp_path / "svc", ZenohSettings(), "ev-1", episodes_per_start=1,
                                   max_steps=3, record=False, world=str(world))
        return service.evaluate(to_message(net, 5, learner_epoch=learner_epoch), repeat=False)

    net = small_net()
    first = evaluate(0)
    assert first is not None and Path(first["results"]).name == "eval-000005.json"
    assert evaluate(1) is None  # the same file: evaluated already
    write_room(world, pillar_x=-0.6)
    again = evaluate(2)
    assert again is not None and again["world_sha256"] != first["world_sha256"]
    assert Path(again["results"]).name.startswith("eval-000005-")  # the old file's results keep their name
    assert evaluate(3) is None
    # a built-in world's row records no digest: its key, and its files' names, are as before
    builtin = EvaluatorService(cfg, "svc", tmp_path / "builtin", ZenohSettings(), "ev-1", episodes_per_start=1,
                               max_steps=3, record=False).evaluate(to_message(net, 5))
    assert "world_sha256" not in builtin


def test_two_overridden_protocols_are_two_evaluations_not_one(tmp_path: Path) -> None:
    # Every overridden set is named "custom": keyed by the name, an evaluator restarted with another
    # --start-jitter-m skipped the weights as evaluated already, and its run had no row of its protocol.
    cfg = load_preset("paper").with_overrides(OVERRIDES)

    def evaluator(protocol) -> EvaluatorService:
        return EvaluatorService(cfg, "svc", tmp_path / "svc", ZenohSettings(), "ev-1", episodes_per_start=1,
                                max_steps=3, record=False, protocol=protocol)

    narrow, wide = (PROTOCOLS["robust"].overridden(start_jitter_m=m) for m in (0.02, 0.04))
    assert narrow.name == wide.name == "custom"
    net = small_net()
    assert evaluator(narrow).evaluate(to_message(net, 5), repeat=False) is not None
    row = evaluator(wide).evaluate(to_message(net, 5), repeat=False)
    assert row is not None and row["protocol_config"] == wide.to_dict()
    assert evaluator(narrow).evaluate(to_message(net, 5, learner_epoch=1), repeat=False) is None  # this one ran


def test_a_row_cut_short_before_costs_only_itself_not_the_next_evaluation(tmp_path: Path) -> None:
    # An evaluator killed mid-write (or a full disk) leaves a last line without its newline; the next
    # evaluation's row was glued to it, and the report skipped both as one damaged line.
    from shared.evaluation.eval_log import load_eval_log

    cfg = load_preset("paper").with_overrides(OVERRIDES)
    service = EvaluatorService(cfg, "svc", tmp_path / "svc", ZenohSettings(), "ev-1", every_updates=10,
                               episodes_per_start=1, max_steps=3, record=False)
    log = tmp_path / "svc" / "stats" / "eval.jsonl"
    log.parent.mkdir(parents=True)
    log.write_text('{"policy_version": 3, "summ')
    service.evaluate(to_message(small_net(), 5))
    service.evaluate(to_message(small_net(), 15))
    lines = log.read_text().splitlines()
    assert lines[0] == '{"policy_version": 3, "summ' and log.read_text().endswith("\n")
    assert [json.loads(line)["policy_version"] for line in lines[1:]] == [5, 15]
    assert [r["policy_version"] for r in load_eval_log(log)] == [5, 15]


def test_each_evaluation_of_one_version_keeps_its_own_files(tmp_path: Path) -> None:
    # Another protocol (an evaluator restarted with --start-jitter-m) or other weights at the same
    # version (a restarted learner) once overwrote the first evaluation's files, and its row then
    # pointed at the other evaluation's recording and results.
    cfg = load_preset("paper").with_overrides(OVERRIDES)
    settings = ZenohSettings(connect=("tcp/127.0.0.1:9",))  # evaluate() itself needs no router
    custom = PROTOCOLS["robust"].overridden(start_jitter_m=0.04)

    def evaluate(net: QNetwork, protocol=PROTOCOLS["robust"], learner_epoch: int = 0) -> dict:
        service = EvaluatorService(cfg, "same", tmp_path, settings, "ev-1", episodes_per_start=1, max_steps=3,
                                   image_every=3, protocol=protocol)
        row = service.evaluate(to_message(net, 12, learner_epoch=learner_epoch), repeat=True)
        assert row is not None
        return row

    net, other_net = small_net(), small_net()
    first = evaluate(net)
    rows = [first, evaluate(net, custom), evaluate(other_net, learner_epoch=1), evaluate(net)]
    # The common case keeps its plain name, and the same evaluation again (--once) its own files.
    assert [Path(r["recording"]).name for r in rows].count("eval-000012.rrd") == 2
    assert rows[3]["recording"] == first["recording"] and len({r["recording"] for r in rows}) == 3
    assert Path(first["results"]).name == "eval-000012.json" and len({r["results"] for r in rows}) == 3
    for row in rows:
        saved = load_results(row["results"])
        assert Path(row["recording"]).stem == Path(row["results"]).stem
        assert saved.meta["recording"] == row["recording"] and saved.meta["weights_sha256"] == row["weights_sha256"]
        assert saved.protocol.to_dict() == row["protocol_config"]
        assert saved.summary["overall"]["mean_steps"] == pytest.approx(row["summary"]["mean_steps"])
        verify_rrd(Path(row["recording"]))


def test_evaluators_of_one_version_at_one_moment_keep_their_own_files(tmp_path: Path) -> None:
    # Each evaluator chose its files' name when it began and wrote them minutes later: two of one
    # version at one moment (the service and `cogexplore evaluator --once`) took the plain name, and
    # the last to finish replaced the other's results and recording under the other's row.
    from shared.evaluation.protocol import EvaluationCancelled

    cfg = load_preset("paper").with_overrides(OVERRIDES)
    settings = ZenohSettings(connect=("tcp/127.0.0.1:9",))  # evaluate() itself needs no router
    runs = [("ev-a", PROTOCOLS["robust"]), ("ev-b", PROTOCOLS["paper"]), ("ev-c", PROTOCOLS["robust"])]
    all_begun = threading.Barrier(len(runs))
    rows: dict[str, dict] = {}
    waited: set[str] = set()

    def evaluator(evaluator_id: str, protocol) -> EvaluatorService:
        return EvaluatorService(cfg, "same", tmp_path, settings, evaluator_id, episodes_per_start=1, max_steps=3,
                                image_every=3, protocol=protocol)

    def evaluate(evaluator_id: str, protocol) -> None:
        service = evaluator(evaluator_id, protocol)
        greedy = service.policy

        def held(depth):  # the first step waits until every evaluation has begun
            if evaluator_id not in waited:
                waited.add(evaluator_id)
                all_begun.wait(30)
            return greedy(depth)

        service.policy = held
        rows[evaluator_id] = service.evaluate(to_message(small_net(), 12), repeat=True)

    threads = [threading.Thread(target=evaluate, args=run) for run in runs]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert len({rows[i]["results"] for i, _ in runs}) == len({rows[i]["recording"] for i, _ in runs}) == 3
    assert "eval-000012.json" in {Path(rows[i]["results"]).name for i, _ in runs}  # one keeps the plain name
    for evaluator_id, _ in runs:
        saved = load_results(rows[evaluator_id]["results"])
        assert saved.meta["evaluator_id"] == evaluator_id and saved.meta["recording"] == rows[evaluator_id]["recording"]
        assert Path(rows[evaluator_id]["recording"]).stem == Path(rows[evaluator_id]["results"]).stem
    stop = threading.Event()
    stop.set()
    with pytest.raises(EvaluationCancelled):  # the name a cancelled evaluation claimed is free again
        evaluator("ev-d", PROTOCOLS["robust"].overridden(start_jitter_m=0.04)).evaluate(to_message(small_net(), 12),
                                                                                       stop)
    assert all(f.stat().st_size > 0 for f in (tmp_path / "stats" / "eval").iterdir())
