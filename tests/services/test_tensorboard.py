"""TensorBoard from the services: a learner, two actors and an evaluator as real processes on a
loopback router, stopped by SIGTERM, their event files read back with TensorBoard's own reader and
checked against learner.csv and eval.jsonl; `up` hands --tensorboard / --no-tensorboard on."""

from __future__ import annotations

import argparse
import csv
import json
import signal
import subprocess
import time
from pathlib import Path

import pytest
from service_processes import cogexplore

from services.bus.session import ZenohSettings, free_tcp_port, open_router, open_session, subscribe_messages
from shared.learning.stats import EpisodeRow, LearnerRow
from shared.wire.keys import RunKeys
from shared.wire.messages import EpisodeStats, RejectCounter

RUN = "tb"


def _learner_updates(path: Path) -> list[int]:
    if not path.is_file():
        return []
    with open(path, newline="") as fh:
        return [int(r["update"]) for r in csv.DictReader(fh)]


def _eval_rows(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.is_file() else []


@pytest.mark.timeout(300)
def test_services_write_scalars_that_survive_sigterm(tmp_path: Path, tensorboard_scalars):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    run = tmp_path / RUN
    common = ["--run", RUN, "--runs-dir", str(tmp_path), "--connect", endpoint, "--zenoh-mode", "client",
              "--preset", "smoke", "--set", "train.total_updates=100000", "--set", "train.checkpoint_every=100000"]
    # actor-1's folder cannot be made (a file is in the way): it must act on without TensorBoard
    (run / "tb").mkdir(parents=True)
    (run / "tb" / "actor-1").write_text("not a folder")
    procs: dict[str, subprocess.Popen] = {}
    with open_router([endpoint]):
        try:
            procs["learner"] = cogexplore(["learner", *common, "--weights-every", "5"], tmp_path / "learner.log")
            for i in (0, 1):
                procs[f"actor-{i}"] = cogexplore(["actor", *common, "--actor-id", f"actor-{i}", "--actor-index", str(i),
                                              "--num-actors", "2"], tmp_path / f"actor-{i}.log")
            procs["evaluator"] = cogexplore(["evaluator", *common, "--id", "evaluator", "--every-updates", "20",
                                         "--max-steps", "10", "--no-record"], tmp_path / "evaluator.log")
            # actor-0 must also have finished an episode acted with learned weights: on a loaded
            # machine flow control can hold it through the learner's first 40 updates
            acted_with: list[int] = [0]
            with open_session(ZenohSettings(mode="client", connect=(endpoint,)), wait_s=30) as watcher:
                watch = subscribe_messages(  # noqa: F841  (kept alive)
                    watcher, RunKeys(RUN).episode_stats("actor-0"), EpisodeStats,
                    lambda m, _k: acted_with.append(m.policy_version), RejectCounter("episode stats"))
                deadline = time.monotonic() + 240
                while not (len(_eval_rows(run / "stats" / "eval.jsonl")) >= 2
                           and len(set(updates := _learner_updates(run / "stats" / "learner.csv"))) >= 3
                           and max(updates) >= 40 and max(acted_with) > 0):
                    assert time.monotonic() < deadline, \
                        "no 2 evaluations, 3 learner rows to 40 updates and an episode of actor-0 with weights in time"
                    assert all(p.poll() is None for p in procs.values()), {n: p.poll() for n, p in procs.items()}
                    time.sleep(0.5)
            for p in procs.values():
                p.send_signal(signal.SIGTERM)
            codes = {name: p.wait(60) for name, p in procs.items()}
        finally:
            for p in procs.values():
                if p.poll() is None:
                    p.kill()
                    p.wait()
    logs = {name: (tmp_path / f"{name}.log").read_text() for name in procs}
    assert codes == dict.fromkeys(procs, 0), {n: logs[n][-2000:] for n in procs}

    # The learner: every row of learner.csv, to its last (written within the flush period before
    # SIGTERM: the close wrote it), is a point at its update.
    learner = tensorboard_scalars(run / "tb" / "learner")
    learner.assert_steps_increase()
    assert learner.assert_match_csv(run / "stats" / "learner.csv", LearnerRow) >= 3
    assert learner.tags["learner/loss"][-1][0] == max(_learner_updates(run / "stats" / "learner.csv"))

    # The evaluator: each evaluation's summary at its policy version.
    evaluator = tensorboard_scalars(run / "tb" / "evaluator")
    evaluator.assert_steps_increase()
    rows = _eval_rows(run / "stats" / "eval.jsonl")
    for tag, key in (("eval/mean_steps", "mean_steps"), ("eval/mean_coverage_pct", "mean_coverage_pct")):
        assert evaluator.tags[tag] == [(r["policy_version"], pytest.approx(r["summary"][key], rel=1e-6))
                                       for r in rows]
    assert [v for _, v in evaluator.tags["eval/duration_s"]] == pytest.approx([r["duration_s"] for r in rows],
                                                                              rel=1e-6)

    # actor-0: one point per episode at its own env step, which is the sum of its episodes' steps;
    # the policy version it acted with rises as weights arrive.
    actor = tensorboard_scalars(run / "tb" / "actor-0")
    actor.assert_steps_increase()
    steps = actor.tags["episodes/steps"]
    assert len(steps) >= 3 and {f"episodes/{c}" for c in ("return", "epsilon", "update", "distance_m")} <= set(actor.tags)
    assert [s for s, _ in steps] == [sum(v for _, v in steps[:i + 1]) for i in range(len(steps))]
    assert set(actor.tags) <= {f"episodes/{c}" for c in EpisodeRow.columns()}
    assert actor.tags["episodes/update"][-1][1] > 0

    # actor-1: TensorBoard off with one warning, its transitions went out all the same.
    assert logs["actor-1"].count("TensorBoard off") == 1
    done = json.loads(logs["actor-1"].split("actor actor-1 done: ", 1)[1].splitlines()[0])
    assert done["env_steps"] > 0 and done["batches"] > 0


def test_up_passes_tensorboard_on_to_every_service(tmp_path: Path):
    from services.actor.options import add_actor_arguments
    from services.up.launcher import Launcher
    from services.up.options import add_up_arguments

    up, actor = argparse.ArgumentParser(), argparse.ArgumentParser()
    add_up_arguments(up)
    add_actor_arguments(actor)
    for flag, expected in (([], True), (["--no-tensorboard"], False), (["--tensorboard"], True)):
        args = up.parse_args(["--run", "r", "--runs-dir", str(tmp_path), *flag])
        assert args.tensorboard is expected
        common = Launcher(args)._common("actor")
        assert actor.parse_args(common).tensorboard is expected
