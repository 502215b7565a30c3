"""The benchmarks through the real CLI, small: `bench env`, `bench learner`, `bench transport`, `bench system`."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from services.runs import RunPaths
from services.up.launcher import checkpoint_updates
from shared.config import load_preset
from shared.evaluation import PROTOCOLS
from shared.evaluation.results import load_results
from shared.learning.dqn import update_flops
from shared.learning.model import QNetwork
from shared.wire.messages import MAX_BATCH_STEPS, MAX_FRAME_PIXELS

REPO = Path(__file__).resolve().parents[3]


def _bench(*argv: str, timeout_s: float) -> dict:
    env = dict(os.environ, RERUN_ANALYTICS="0", PYTHONUNBUFFERED="1")
    result = subprocess.run([sys.executable, "-m", "services.cli", "bench", *argv, "--json"], cwd=REPO, env=env,
                            check=False, capture_output=True, text=True, timeout=timeout_s)
    assert result.returncode == 0, f"bench {argv[0]} failed ({result.returncode}):\n{result.stderr[-3000:]}"
    return json.loads(result.stdout)


def test_bench_env_json() -> None:
    out = _bench("env", "--world", "box-room", "--steps", "50", "--no-pin", timeout_s=120)
    assert out["world"] == "box-room" and out["steps"] == 50
    assert out["image"] == [120, 160]
    assert out["steps_per_s"] > 0 and out["raw_steps_per_s"] > 0
    assert 0 < out["depth_ms_p50"] <= out["depth_ms_p90"]
    assert out["physics_ms_p50"] > 0 and "expert_label_ms_p50" not in out
    taught = _bench("env", "--world", "box-room", "--steps", "20", "--no-pin", "--expert-labels", timeout_s=120)
    assert 0 < taught["expert_label_ms_p50"] <= taught["expert_label_ms_p90"]


def test_bench_learner_times_the_update_of_the_preset_it_is_given() -> None:
    smoke = load_preset("smoke")
    out = _bench("learner", "--preset", "smoke", "--repeats", "1", timeout_s=120)
    assert out["preset"] == "smoke" and out["image"] == [30, 40] and out["batch_size"] == smoke.dqn.batch_size
    # smoke's small fc layers, not the paper network's: the FLOPs say which network was timed
    net = QNetwork(smoke.model, smoke.sensor)
    assert out["flops_per_update"] == update_flops(net, smoke.dqn.batch_size, double_dqn=smoke.dqn.double_dqn)
    assert 0 < out["ms_per_update"] <= out["ms_per_update_median"] and out["achieved_gflops"] > 0
    halved = _bench("learner", "--preset", "smoke", "--set", "dqn.batch_size=4", "--repeats", "1", timeout_s=120)
    assert halved["batch_size"] == 4 and halved["flops_per_update"] == out["flops_per_update"] // 2
    refused = subprocess.run([sys.executable, "-m", "services.cli", "bench", "learner", "--preset", "smoke",
                              "--baseline"], cwd=REPO, capture_output=True, text=True, timeout=60, check=False)
    assert refused.returncode == 2 and "--baseline times the paper network" in refused.stderr


def test_bench_transport_json() -> None:
    out = _bench("transport", "--seconds", "1", timeout_s=180)
    assert out["batch_steps"] == 16 and out["frame"] == "160x120"
    # Depth dominates the wire: within 5 % of the raw uint16 frames.
    assert out["depth_bytes_per_transition"] <= out["bytes_per_transition"] < 1.05 * out["depth_bytes_per_transition"]
    assert out["codec"]["transitions_per_s"] > 0 and out["codec"]["batches"] > 0
    loop = out["loopback"]
    assert loop["transitions_per_s"] > 0 and loop["batches_sent"] > 0
    # reliable puts: everything sent arrives, unless Zenoh closed a link on a stall of 5 s (a loaded
    # machine's; the receiver's link test shows that loss), which the bench then reports
    if loop["links_closed"] == 0:
        assert loop["lost"] == 0 and loop["rejected"] == 0, loop
        assert loop["batches_received"] == loop["batches_sent"]
    else:
        assert max(loop["max_gap_s"], loop["max_put_s"]) > 1, loop


@pytest.mark.timeout(300)
def test_bench_system_json(tmp_path: Path) -> None:
    # Replay ratio 0.1: the learner's catch-up on the actors' first burst (flow-control slack)
    # is a tenth as long as at ratio 1, which keeps this quick on a busy 2-core machine.
    out = _bench("system", "--preset", "smoke", "--actors", "1", "--seconds", "5", "--warmup-s", "0",
                 "--set", "train.replay_ratio=0.1", "--learner-threads", "1", "--startup-timeout-s", "150",
                 "--runs-dir", str(tmp_path), timeout_s=280)
    expected = {"preset", "actors", "seconds", "env_steps_per_s", "env_steps_per_s_per_actor", "updates_per_s",
                "replay_ratio_target", "replay_ratio_achieved", "mean_weight_lag", "transitions", "updates",
                "cpu_percent", "time_to_steady_s"}
    assert expected <= set(out)
    assert out["preset"] == "smoke" and out["actors"] == 1 and out["frame"] == "40x30"
    assert out["seconds"] >= 4.0  # the learner's clock between its two reports
    assert out["transitions"] > 0 and out["env_steps_per_s"] > 0
    assert out["updates"] > 0 and out["updates_per_s"] > 0
    assert set(out["env_steps_per_s_per_actor"]) == {"actor-0"}
    assert out["env_steps_per_s_per_actor"]["actor-0"] == pytest.approx(out["env_steps_per_s"])
    assert out["replay_ratio_target"] == 0.1 and out["replay_ratio_achieved"] > 0
    assert out["omp_num_threads"] == 1
    assert out["mean_weight_lag"] is not None and out["mean_weight_lag"] >= 0
    assert {"router", "learner", "actor-0"} <= set(out["cpu_percent"])
    # Everything was stopped: the learner wrote its final checkpoint on SIGTERM.
    run_dir = Path(out["run_dir"])
    assert run_dir.parent == tmp_path
    assert (run_dir / "checkpoints" / "latest").exists()
    assert (run_dir / "stats" / "learner.csv").exists()


@pytest.mark.timeout(400)
def test_bench_system_compares_up_with_the_single_process_trainer(tmp_path: Path) -> None:
    out = _bench("system", "--compare-single-process", "--preset", "smoke", "--minutes", "0.4",
                 "--set", "dqn.lr_decay_updates=20", "--episodes-per-start", "1",
                 "--set", "env.extra_worlds=procedural:900-901", "--set", "env.extra_world_prob=0.5",
                 "--runs-dir", str(tmp_path), timeout_s=380)
    # each side generated the extra worlds into a cache of its own: the second did not read the first's warm
    for run_dir in ("up", "single"):
        kept = {p.name for p in (tmp_path / f"{run_dir}-world-cache").glob("worlds/*/*.json")}
        assert kept == {"procedural-900.json", "procedural-901.json"}, run_dir
    for name, run_dir in (("up", "up"), ("single_process", "single")):
        run = out[name]
        assert run["updates"] > 0 and run["transitions"] > 0
        assert 0.4 * 60 <= run["wall_s"] < 0.4 * 60 + 120  # the time limit, then its stop and checkpoint
        assert run["updates_per_s"] == pytest.approx(run["updates"] / run["wall_s"])
        assert run["env_steps_per_s"] == pytest.approx(run["transitions"] / run["wall_s"])
        for protocol in ("robust", "paper"):
            # each score is its own protocol's evaluation of this run's model, as its JSON records
            played = load_results(tmp_path / f"{run_dir}-{protocol}.json")
            assert played.meta["protocol"] == PROTOCOLS[protocol].to_dict()
            assert run[protocol]["mean_steps"] == pytest.approx(played.summary["overall"]["mean_steps"])
            assert 0 <= run[protocol]["worst_start_steps"] <= run[protocol]["mean_steps"] <= 200
    up, single, ratios = out["up"], out["single_process"], out["ratios_up_over_single"]
    pairs = {"updates_per_s": (up["updates_per_s"], single["updates_per_s"]),
             "env_steps_per_s": (up["env_steps_per_s"], single["env_steps_per_s"]),
             **{f"{p}_mean_steps": (up[p]["mean_steps"], single[p]["mean_steps"]) for p in ("robust", "paper")}}
    assert set(ratios) == set(pairs)
    for key, (a, b) in pairs.items():  # up over single, each its own quantity; None where single's is 0
        assert ratios[key] == (pytest.approx(a / b) if b else None), key
    assert (tmp_path / "up" / "checkpoints").is_dir() and (tmp_path / "single" / "checkpoints").is_dir()
    # both trainers' logs end at the update their final checkpoint holds, and log the learning
    # rate: smoke's 1e-3, falling to its tenth over 20 updates
    assert out["up"]["updates"] == checkpoint_updates(RunPaths(tmp_path / "up"))
    assert out["single_process"]["updates"] == checkpoint_updates(RunPaths(tmp_path / "single"))
    for run in ("up", "single"):
        with open(tmp_path / run / "stats" / "learner.csv", newline="") as f:
            lrs = [float(r["lr"]) for r in csv.DictReader(f) if r["lr"]]
        assert lrs == sorted(lrs, reverse=True) and lrs[0] <= 1e-3 and lrs[-1] == pytest.approx(1e-4), run


def test_a_benchmark_prints_json_without_json_too() -> None:
    # the group's help says "(print JSON)": without --json it printed a Python repr
    env = dict(os.environ, RERUN_ANALYTICS="0")
    proc = subprocess.run([sys.executable, "-m", "services.cli", "bench", "env", "--world", "box-room", "--steps", "5",
                           "--no-pin"], cwd=REPO, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.count("\n") == 1 and json.loads(proc.stdout)["steps"] == 5  # one line a script can append


@pytest.mark.parametrize("argv,said", [
    (["--height", "100000", "--width", "100000"], f"--height x --width must be 1..{MAX_FRAME_PIXELS} pixels"),
    (["--height", str(MAX_FRAME_PIXELS // 640 + 1), "--width", "640"],
     f"--height x --width must be 1..{MAX_FRAME_PIXELS} pixels"),
    (["--batch-steps", str(MAX_BATCH_STEPS + 1)], f"--batch-steps must be in 1..{MAX_BATCH_STEPS}"),
])
def test_bench_transport_refuses_a_batch_the_wire_would_not_carry(argv: list[str], said: str, capsys) -> None:
    from services.cli import main

    # 100000 x 100000 asked numpy for 317 GiB before anything was measured
    assert main(["bench", "transport", "--seconds", "0.1", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"cogexplore bench transport: error: {said}") and err.count("\n") == 1, err


def test_a_side_of_the_transport_bench_that_never_reports_is_an_error_not_a_traceback() -> None:
    import queue

    from services.bench.transport import _REPORT_SLACK_S, TransportBenchError, _report, _subscriber
    from shared.errors import CogexploreError

    with pytest.raises(TransportBenchError, match="no word from the subscriber in 0 s") as raised:
        _report(queue.Queue(), 0.01, "subscriber")
    assert isinstance(raised.value, CogexploreError)
    # the subscriber waits for the publisher's count as long as the publisher is given (it waited a
    # fixed 120 s, so `--seconds 125` lost it) and the publisher's count then arrives
    ready, control, results = queue.Queue(), queue.Queue(), queue.Queue()
    control.put(0)
    from services.bus.session import free_tcp_port, open_router

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_router([endpoint]):
        _subscriber(endpoint, 0.5, ready, control, results)
    assert ready.get_nowait() == "ready" and results.get_nowait()["received"] == 0
    assert _REPORT_SLACK_S >= 60


def test_bench_drive_refuses_an_image_no_camera_sends(capsys) -> None:
    from services.cli import main

    # 100000 x 100000 asked the resize for 37 GiB per image, 64 of them, before anything was sent
    assert main(["bench", "drive", "--images", "10", "--width", "100000", "--height", "100000"]) != 0
    err = capsys.readouterr().err
    assert err.startswith("cogexplore bench drive: error: --width x --height is 100000 x 100000: at most 2073600 "
                          "pixels") and err.count("\n") == 1, err


@pytest.mark.timeout(60)
def test_bench_drive_refuses_an_absurd_image_count(capsys) -> None:
    from services.bench.drive import run
    from services.bench.options import MAX_IMAGES
    from services.cli import main
    from shared.errors import CogexploreError

    # No bound: 10**10 grew an 80 GB list of frames before the first image was sent (out of memory
    # after 33 s under a 6 GB cap); one past the bound went on to start drive and time a million images.
    for images in (MAX_IMAGES + 1, 10**10):
        with pytest.raises(SystemExit) as stop:
            main(["bench", "drive", "--images", str(images)])
        assert stop.value.code == 2
        assert (f"--images: must be a whole number in 10..{MAX_IMAGES}, got '{images}'"
                in capsys.readouterr().err)
        with pytest.raises(CogexploreError, match=f"--images must be a whole number in 10..{MAX_IMAGES}"):
            run(images=images)  # the API as the command line
