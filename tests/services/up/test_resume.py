"""``cogexplore up`` on a run that exists: an unfinished one resumes and says from which update, a
finished one is refused in one line naming --resume and --fresh (never silently reused), --resume
redoes its report, --fresh keeps the old folder aside. The run folders are written by the real
checkpoint writer; one real run of ten updates (smoke preset) finishes in between."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest
from service_processes import ENV, REPO

from services.bus.security import SecurityError
from services.cli import main
from services.runs import RunPaths, save_config
from services.up.launcher import Launcher, checkpoint_updates, resume_line
from services.up.options import add_up_arguments
from shared.config import load_preset
from shared.evaluation import PROTOCOLS
from shared.learning.checkpoints import CheckpointManager
from shared.learning.learner import LearnerCore

RUN = "again"
UP = ["up", "--run", RUN, "--actors", "1", "--no-evaluator", "--no-report", "--quiet", "--no-tensorboard"]


def run_at(runs_dir: Path, updates: int, total_updates: int) -> RunPaths:
    """A run folder whose learner stopped at ``updates`` of ``total_updates`` (smoke preset)."""
    cfg = load_preset("smoke").with_overrides({"train.total_updates": total_updates})
    paths = RunPaths(runs_dir / RUN).make()
    save_config(cfg, paths)
    core = LearnerCore(cfg, device="cpu")
    core.agent.update_count = updates
    CheckpointManager(paths.checkpoints, keep=cfg.train.keep_checkpoints).save(
        core.agent, config=cfg.to_dict(), extra={"transitions_received": 0})
    return paths


def up(runs_dir: Path, *flags: str, timeout_s: float = 150.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *UP, "--runs-dir", str(runs_dir), *flags],
                          cwd=REPO, env=ENV, capture_output=True, text=True, timeout=timeout_s, check=False)


@pytest.mark.timeout(240)
def test_an_unfinished_run_resumes_and_a_finished_one_is_refused_until_resume(tmp_path: Path) -> None:
    paths = run_at(tmp_path, updates=10, total_updates=20)
    resumed = up(tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"run {RUN!r}: resuming from update 10/20" in resumed.stderr
    assert checkpoint_updates(paths) == 20

    router_log = (paths.logs / "router.log").read_bytes()
    refused = up(tmp_path, timeout_s=60)
    assert refused.returncode == 2, refused.stderr
    message = refused.stderr.strip()
    assert "\n" not in message and "has finished" in message and "20/20 updates" in message, message
    assert "--resume" in message and "--fresh" in message
    assert (paths.logs / "router.log").read_bytes() == router_log  # nothing was started

    again = up(tmp_path, "--resume", timeout_s=60)
    assert again.returncode == 0, again.stderr
    assert f"run {RUN!r} has finished training (20/20 updates)" in again.stderr
    assert checkpoint_updates(paths) == 20


def launcher_args(runs_dir: Path, *flags: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_up_arguments(parser)
    return parser.parse_args(["--run", RUN, "--runs-dir", str(runs_dir), "--quiet", *flags])


def test_fresh_keeps_the_old_run_aside_and_starts_an_empty_one(tmp_path: Path, capsys) -> None:
    run_at(tmp_path, updates=20, total_updates=20)
    with pytest.raises(SecurityError):  # a refused start: the old run stays where it was
        Launcher(launcher_args(tmp_path, "--fresh", "--listen", "tls/0.0.0.0:0"))
    assert checkpoint_updates(RunPaths(tmp_path / RUN)) == 20 and not list(tmp_path.glob(f"{RUN}.old-*"))
    launcher = Launcher(launcher_args(tmp_path, "--fresh"))
    (old,) = tmp_path.glob(f"{RUN}.old-*")
    assert checkpoint_updates(RunPaths(old)) == 20  # kept, whole
    assert checkpoint_updates(launcher.paths) is None and launcher.paths.secure.is_dir()
    assert f"is now {old}" in capsys.readouterr().err


def test_a_config_that_cannot_resume_the_run_is_refused_before_it_replaces_the_run_s(tmp_path: Path,
                                                                                       capsys) -> None:
    # The learner refused it ("cannot resume"), but up had already written it over the run's own:
    # a plain `up --run` could then not resume the run either.
    paths = run_at(tmp_path, updates=10, total_updates=20)
    recipe = paths.config.read_bytes()
    assert main(["up", "--run", RUN, "--runs-dir", str(tmp_path), "--preset", "paper", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "cannot resume run 'again' with this config" in err and err.count("\n") == 1
    assert paths.config.read_bytes() == recipe and not list(paths.logs.glob("*.log"))  # nothing started


def test_fresh_moves_nothing_while_a_learner_holds_the_run_or_an_option_is_refused(tmp_path: Path) -> None:
    from services.runs import RunInUseError, RunLock
    from shared.config import ConfigError

    paths = run_at(tmp_path, updates=20, total_updates=20)
    # A learner started outside up: moved aside, its last checkpoint went into the "fresh" run.
    held = RunLock(paths, "learner")
    try:
        with pytest.raises(RunInUseError, match="its learner is pid"):
            Launcher(launcher_args(tmp_path, "--fresh"))
    finally:
        held.release()
    # A preset that does not exist: refused with the old run where it was (it was moved, then refused).
    with pytest.raises(ConfigError):
        Launcher(launcher_args(tmp_path, "--fresh", "--preset", "no-such-preset"))
    assert checkpoint_updates(paths) == 20 and not list(tmp_path.glob(f"{RUN}.old-*"))


@pytest.mark.timeout(240)
def test_a_failed_learner_is_reported_with_its_exit_code_and_last_line(tmp_path: Path) -> None:
    paths = run_at(tmp_path, updates=10, total_updates=20)
    # a folder where its checkpoint's pointer goes: the learner fails at its first save (a learner of
    # the run running elsewhere is refused before up starts anything: test_chaos.py)
    (paths.checkpoints / "latest").unlink()
    (paths.checkpoints / "latest").mkdir()
    failed = up(tmp_path)
    assert failed.returncode == 1, failed.stderr[-3000:]
    assert f"run {RUN!r} ended: failed: learner" in failed.stderr
    said = [line for line in failed.stderr.splitlines() if line.startswith("its learner exited (2): ")]
    assert len(said) == 1 and "Is a directory" in said[0], failed.stderr[-3000:]


def test_the_processes_of_this_machine_connect_where_the_router_listens() -> None:
    from services.up.launcher import router_endpoints

    assert router_endpoints(["tls/0.0.0.0:7447"], None)[1] == "tls/localhost:7447"
    assert router_endpoints(["tls/[::]:7447"], None)[1] == "tls/localhost:7447"
    # localhost may not name ::1 (it never started), nor a name the router listens on alone
    assert router_endpoints(["tcp/[::1]:7447"], None)[1] == "tcp/[::1]:7447"
    assert router_endpoints(["tls/robot.lan:7447"], None)[1] == "tls/robot.lan:7447"
    # with TLS, the access control admits a role over TLS only: never the plain loopback beside it
    assert router_endpoints(["tls/0.0.0.0:7447", "tcp/127.0.0.1:7448"], None)[1] == "tls/localhost:7447"
    assert router_endpoints(["tcp/127.0.0.1:7448", "tls/[::1]:7447"], None)[1] == "tls/localhost:7447"


@pytest.mark.timeout(240)
def test_a_run_whose_security_folder_has_tls_trains_over_tls_on_loopback(tmp_path: Path) -> None:
    """Its access control admits every role over TLS only: on the default plain-TCP loopback router
    (resuming a run first started with --listen tls/... --tls, or a compose run, or `up --tls`) every
    session was refused its part and the run hung, silently, in "waiting for the learner"."""
    from services.bus.security import init_secure

    init_secure(tmp_path / RUN / "secure", RUN, tls=True)
    trained = up(tmp_path, "--preset", "smoke", "--updates", "5", timeout_s=120)
    assert trained.returncode == 0, trained.stderr[-3000:]
    assert f"run {RUN!r}: router tls/localhost:" in trained.stderr and f"run {RUN!r} ended: done" in trained.stderr
    assert checkpoint_updates(RunPaths(tmp_path / RUN)) == 5
    # a plain TCP router named by hand would hang it the same way: refused in one line, before anything starts
    logs = {p: p.read_bytes() for p in (tmp_path / RUN / "logs").glob("*.log")}
    refused = up(tmp_path, "--updates", "10", "--listen", "tcp/127.0.0.1:9", timeout_s=60)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert "admits every role over TLS only (--listen tls/127.0.0.1:9)" in refused.stderr
    assert {p: p.read_bytes() for p in logs} == logs
    # a new run given --tls alone: its loopback router listens with TLS too
    launcher = Launcher(launcher_args(tmp_path / "new", "--tls"))
    try:
        assert launcher.listen[0].startswith("tls/127.0.0.1:") and launcher.endpoint.startswith("tls/localhost:")
    finally:
        launcher.close()


@pytest.mark.timeout(240)
def test_only_up_s_router_listens_whatever_the_shell_s_compose_variables(tmp_path: Path) -> None:
    """The services read COGEXPLORE_ZENOH_LISTEN (compose passes it on); inherited from the shell, it
    had the learner and every actor bind that one endpoint: the second to try failed and so did the run."""
    from services.bus.session import free_tcp_port

    env = dict(ENV, COGEXPLORE_ZENOH_LISTEN=f"tcp/127.0.0.1:{free_tcp_port()}")
    result = subprocess.run([sys.executable, "-m", "services.cli", *UP, "--runs-dir", str(tmp_path), "--actors", "2",
                             "--preset", "smoke", "--updates", "5"], cwd=REPO, env=env, capture_output=True,
                            text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr[-3000:]
    assert checkpoint_updates(RunPaths(tmp_path / RUN)) == 5


def test_a_replay_memory_the_config_cannot_hold_is_refused_before_the_config_is_saved(tmp_path: Path) -> None:
    from services.up.launcher import RunStateError

    cfg = load_preset("smoke")
    paths = RunPaths(tmp_path / RUN).make()
    core = LearnerCore(cfg, device="cpu")
    CheckpointManager(paths.checkpoints).save(core.agent, replay=core.replay, config=cfg.to_dict())
    assert checkpoint_updates(paths, cfg) == 0
    with pytest.raises(RunStateError, match="does not fit this replay memory"):
        checkpoint_updates(paths, cfg.with_overrides({"replay.capacity": cfg.replay.capacity + 1000}))


def test_nohup_keeps_a_service_alive_when_its_terminal_closes() -> None:
    import signal

    from services.process import stop_event_on_signals, stop_signals

    previous = {s: signal.getsignal(s) for s in (signal.SIGHUP, signal.SIGINT, signal.SIGTERM)}
    try:
        signal.signal(signal.SIGHUP, signal.SIG_IGN)  # what nohup does
        assert signal.SIGHUP not in stop_signals()
        stop_event_on_signals()
        assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
        signal.signal(signal.SIGHUP, signal.SIG_DFL)
        assert signal.SIGHUP in stop_signals()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def test_resume_names_a_run_that_exists(tmp_path: Path, capsys) -> None:
    assert main(["up", "--run", "nothing-here", "--runs-dir", str(tmp_path), "--resume", "--quiet"]) == 2
    assert "there is no run 'nothing-here'" in capsys.readouterr().err
    assert not (tmp_path / "nothing-here").exists()


def test_a_resumed_run_expects_its_own_learners_rate(tmp_path: Path) -> None:
    paths = run_at(tmp_path, updates=100, total_updates=400)
    assert resume_line(RUN, paths, 100, 400) == f"run {RUN!r}: resuming from update 100/400"  # nothing on record
    rows = ["time_s,update,updates_per_s"] + [f"{t},{0 if t < 30 else 2 * (t - 30)},{0 if t < 30 else 2.0}"
                                              for t in range(30 + 60)]
    (paths.stats / "learner.csv").write_text("\n".join(rows) + "\n")
    assert resume_line(RUN, paths, 100, 400) == (f"run {RUN!r}: resuming from update 100/400; its learner made "
                                                 "2.0 updates/s so far: the 300 left should take ~2m30s, then "
                                                 "the final evaluation")


def test_the_final_model_is_the_mean_of_the_last_checkpoints(tmp_path: Path) -> None:
    import torch

    from shared.learning.checkpoints import load_model
    from shared.learning.model import weights_to_tensors

    cfg = load_preset("smoke").with_overrides({"train.total_updates": 30, "train.keep_checkpoints": 5})
    paths = RunPaths(tmp_path / RUN).make()
    save_config(cfg, paths)
    manager = CheckpointManager(paths.checkpoints, keep=5)
    for seed, updates in enumerate((10, 20, 30)):  # three different networks
        core = LearnerCore(cfg.with_overrides({"train.seed": seed}), device="cpu")
        core.agent.update_count = core.agent.policy_version = updates
        manager.save(core.agent, config=cfg.to_dict())

    # A run keeps at least K checkpoints: its saved config is raised to K.
    assert main(UP + ["--runs-dir", str(tmp_path), "--resume", "--final-average", "6"]) == 0
    assert load_preset(str(paths.config)).train.keep_checkpoints == 6

    out = Launcher(launcher_args(tmp_path, "--resume", "--final-average", "2")).final_model()
    assert out == paths.root / f"{RUN}-mean2.safetensors"
    mean = load_model(out)
    assert [s["policy_version"] for s in mean.averaged_from] == [20, 30] and mean.policy_version == 30
    last_two = [weights_to_tensors(load_model(paths.checkpoints / f"ckpt-{u:09d}.safetensors").net) for u in (20, 30)]
    for name, tensor in weights_to_tensors(mean.net).items():
        torch.testing.assert_close(tensor, (last_two[0][name] + last_two[1][name]) / 2)
    assert mean.weights_sha256 != load_model(paths.root).weights_sha256

    # The run's end as `up` plays it: that mean evaluated under the test protocol, then the report
    # with it beside the shipped model under both protocols.
    ending = Launcher(launcher_args(tmp_path, "--resume", "--final-average", "2", "--final-episodes", "1"))
    assert ending.final_report() == 0
    ending.close()
    final = json.loads((paths.stats / "final-eval.json").read_text())["meta"]
    assert final["weights_sha256"] == mean.weights_sha256 and final["protocol"] == PROTOCOLS["robust"].to_dict()
    assert (paths.recordings / "final-eval.rrd").is_file()
    text = (paths.report / "report.md").read_text()
    robust_at, paper_at = text.index("## Table III, robust protocol"), text.index("## Table III, paper protocol")
    for section in (text[robust_at:paper_at], text[paper_at:]):
        assert f"| Count | {RUN}-mean2@30 |" in section and "|  | drl@" in section
    assert "robust reused: [final-eval.json]" in text  # the report took the evaluation above, not another

    # More than there are: all three. One: the run folder (its latest checkpoint) as it is.
    three = Launcher(launcher_args(tmp_path, "--resume", "--final-average", "4")).final_model()
    assert three.name == f"{RUN}-mean3.safetensors" and len(load_model(three).averaged_from) == 3
    assert Launcher(launcher_args(tmp_path, "--resume", "--final-average", "1")).final_model() == paths.root
    with pytest.raises(SystemExit) as refused:  # refused when parsed
        main(UP + ["--runs-dir", str(tmp_path), "--final-average", "0"])
    assert refused.value.code == 2


def test_the_final_model_leaves_out_the_untrained_checkpoint_of_a_warm_up_stop(tmp_path: Path) -> None:
    """A learner stopped in its warm-up saves its network at update 0; resumed, the run kept that
    checkpoint among its last K and the final model was half random weights."""
    from shared.learning.checkpoints import load_model

    paths = run_at(tmp_path, updates=0, total_updates=30)  # stopped in the warm-up
    cfg = load_preset(str(paths.config))
    manager = CheckpointManager(paths.checkpoints, keep=4)
    for seed, updates in enumerate((20, 30), start=1):  # then resumed and trained to the end
        core = LearnerCore(cfg.with_overrides({"train.seed": seed}), device="cpu")
        core.agent.update_count = core.agent.policy_version = updates
        manager.save(core.agent, config=cfg.to_dict())
    assert (paths.checkpoints / "ckpt-000000000.safetensors").is_file()

    launcher = Launcher(launcher_args(tmp_path, "--resume"))
    try:
        out = launcher.final_model()
        assert [s["policy_version"] for s in load_model(out).averaged_from] == [20, 30]
        (paths.checkpoints / "ckpt-000000020.safetensors").unlink()  # one trained checkpoint: the run folder
        assert launcher.final_model() == paths.root
    finally:
        launcher.close()


def test_a_run_is_started_by_one_up_and_trained_by_one_learner_at_a_time(tmp_path: Path, capsys) -> None:
    paths = run_at(tmp_path, updates=10, total_updates=20)
    holder = Launcher(launcher_args(tmp_path))  # an `up` of the run, as long as it lives
    try:
        for flags in ([], ["--fresh"]):  # --fresh would move the folder away under the running learner
            assert main(UP + ["--runs-dir", str(tmp_path), *flags]) == 2
            err = capsys.readouterr().err
            assert f"run {RUN!r} is in use: its up is pid " in err and err.count("\n") == 1, err
        assert not list(tmp_path.glob(f"{RUN}.old-*")) and checkpoint_updates(paths) == 10
    finally:
        holder.close()
    from services.runs import RunInUseError, RunLock

    learner = RunLock(paths, "learner")  # a learner service of the run, or `cogexplore train`
    try:
        with pytest.raises(RunInUseError, match="its learner is pid"):
            RunLock(paths, "learner")
        assert main(["train", "--run", RUN, "--runs-dir", str(tmp_path), "--quiet"]) == 2
        assert "is in use" in capsys.readouterr().err and checkpoint_updates(paths) == 10
        assert main(["learner", "--run", RUN, "--runs-dir", str(tmp_path), "--connect", "tcp/127.0.0.1:9",
                     "--no-tensorboard"]) == 2  # the service refuses before it joins the bus
        assert "its learner is pid" in capsys.readouterr().err and checkpoint_updates(paths) == 10
    finally:
        learner.release()
    RunLock(paths, "learner").release()  # free again once let go


def test_a_run_whose_config_was_cut_short_or_does_not_fit_its_checkpoints_is_refused(tmp_path: Path, capsys) -> None:
    paths = run_at(tmp_path, updates=10, total_updates=20)
    whole = paths.config.read_text()
    paths.config.write_text(whole[:whole.index("[dqn]")])  # cut at a section: what remains parses
    assert main(UP + ["--runs-dir", str(tmp_path)]) == 2
    assert "lacks section(s) ['dqn', 'explore', 'train']" in capsys.readouterr().err
    assert paths.config.read_text() == whole[:whole.index("[dqn]")]  # not overwritten with defaults
    # a learner given another network does not start the run over in its checkpoints folder
    from shared.learning.checkpoints import CheckpointError
    from shared.learning.learner import resume_from

    other = LearnerCore(load_preset("smoke").with_overrides({"model.fc1": 48}), device="cpu")
    with pytest.raises(CheckpointError, match="cannot resume: .*does not fit this agent.*another network or optimiser"):
        resume_from(CheckpointManager(paths.checkpoints), other)
    assert checkpoint_updates(paths) == 10


@pytest.mark.timeout(240)
@pytest.mark.parametrize("who", ["actor", "learner"])
def test_up_ends_failed_when_its_actors_die_or_its_learner_is_stopped_early(who: str, tmp_path: Path) -> None:
    """All actors gone, the learner would wait forever; a learner stopped by someone else before its
    last update is no finished run: neither is 'done', nor goes on to a final report of it."""
    import os
    import signal
    import time

    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "up", "--run", RUN, "--actors", "1", "--preset",
                             "smoke", "--updates", "1000000", "--runs-dir", str(tmp_path), "--quiet",
                             "--no-tensorboard", "--no-evaluator"],
                            cwd=REPO, env=ENV, stderr=subprocess.PIPE, text=True)
    try:
        paths = RunPaths(tmp_path / RUN)
        deadline = time.monotonic() + 120
        while checkpoint_updates(paths) is None and time.monotonic() < deadline:  # training
            time.sleep(1.0)
        pids = [int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit()
                and f"{who}\0" in _cmdline(p) and str(tmp_path) in _cmdline(p)]
        assert pids, f"no {who} process found"
        for pid in pids:
            os.kill(pid, signal.SIGKILL if who == "actor" else signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 1, err[-2000:]
    expected = "ended: failed: actor-0" if who == "actor" else "its learner stopped at update"
    assert expected in err and "report:" not in err, err[-2000:]


@pytest.mark.timeout(240)
def test_an_actor_that_dies_while_another_trains_on_is_reported(tmp_path: Path) -> None:
    """One actor of two gone: the run goes on, but it went without a word (the evaluator's exit was
    reported, an actor's not), its progress line only showing one actor fewer."""
    import os
    import signal
    import time

    proc = subprocess.Popen([sys.executable, "-m", "services.cli", *UP, "--actors", "2", "--preset", "smoke",
                             "--updates", "20", "--runs-dir", str(tmp_path)],
                            cwd=REPO, env=ENV, stderr=subprocess.PIPE, text=True)
    try:
        deadline, pids = time.monotonic() + 60, []
        while not pids and time.monotonic() < deadline:
            time.sleep(0.5)
            pids = [int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit()
                    and "actor-1\0" in _cmdline(p) and str(tmp_path) in _cmdline(p)]
        assert pids, "no actor-1 process found"
        os.kill(pids[0], signal.SIGKILL)
        _, err = proc.communicate(timeout=180)
    finally:
        proc.kill()
    assert proc.returncode == 0 and f"run {RUN!r} ended: done" in err, err[-2000:]
    assert "its actor-1 was ended by SIGKILL: " in err and "training goes on with 1 actor(s) of this machine" in err, err[-2000:]


def _cmdline(proc_dir: Path) -> str:
    try:
        return (proc_dir / "cmdline").read_text()
    except OSError:
        return ""


def test_up_whose_router_port_is_taken_says_so_before_it_starts_anything(tmp_path: Path) -> None:
    """A taken --listen port is named at once, before any process starts: before, up's progress
    session waited 30 s on whatever held the port and said only that it could not connect."""
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = up(tmp_path, "--listen", f"tcp/127.0.0.1:{port}", "--minutes", "1", timeout_s=60)
    assert result.returncode == 2
    assert f"the router cannot listen on tcp/127.0.0.1:{port}: port {port} of 127.0.0.1 is taken" in result.stderr, \
        result.stderr[-2000:]
    assert not (tmp_path / RUN).exists()  # no run folder either (its config and security were written before)
    assert f"run {RUN!r}: router" not in result.stderr  # nor a line that says it started


def test_a_child_that_exited_says_how_from_its_log(tmp_path: Path) -> None:
    """What `up` reports when its router exits while it waits for it (Child.exited)."""
    from services.up.launcher import Child

    log = tmp_path / "router.log"
    log.write_text("error: an earlier run's router, in the same log\n")
    for code, said in (("print('starting'); sys.exit('error: no')", "error: no"), ("sys.exit(3)", "no output")):
        with open(log, "ab") as out:
            start = out.seek(0, 2)
            process = subprocess.Popen([sys.executable, "-u", "-c", f"import sys; {code}"], stdout=out,
                                       stderr=subprocess.STDOUT)
        process.wait(30)
        child = Child("router", "router", process, log, start)
        assert child.exited() == f"its router exited ({process.returncode}): {said} (see {log})"
    sleeper = Child("router", "router", subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"]), log)
    try:
        assert sleeper.exited() is None
    finally:
        sleeper.process.kill()
        sleeper.process.wait()


def test_a_transfer_or_demonstration_file_the_learner_cannot_read_is_refused_before_the_config_is_saved(
        tmp_path: Path, capsys) -> None:
    # The resume check passed a missing train.init_conv_from; the learner then failed on it at every
    # start (it transfers before it resumes), with the config already saved over the run's own.
    paths = run_at(tmp_path, updates=10, total_updates=20)
    recipe = paths.config.read_bytes()
    for override, said in (("train.init_conv_from=missing.safetensors", "init_conv_from = 'missing.safetensors'"),
                           ("train.init_from=missing.safetensors", "init_from = 'missing.safetensors'"),
                           ("train.demos=missing.npz", "missing.npz: no such demonstration file")):
        extra = ["--set", "dqn.demo_batch=2"] if override.startswith("train.demos") else []
        assert main(["up", "--run", RUN, "--runs-dir", str(tmp_path), "--set", override, *extra, "--quiet"]) == 2
        err = capsys.readouterr().err
        assert f"run {RUN!r} cannot start its learner" in err and said in err and err.count("\n") == 1, err
        assert paths.config.read_bytes() == recipe and not list(paths.logs.glob("*.log"))  # nothing started
    # a new run too: refused before anything starts
    assert main(["up", "--run", "new", "--runs-dir", str(tmp_path), "--preset", "smoke", "--set",
                 "train.init_conv_from=missing.safetensors", "--quiet"]) == 2
    assert "cannot start its learner" in capsys.readouterr().err
    assert not (tmp_path / "new" / "config.toml").exists()
    # the learner service on its own (docker compose): no config for a run that never ran
    assert main(["learner", "--run", "solo", "--runs-dir", str(tmp_path), "--preset", "smoke", "--set",
                 "train.init_conv_from=missing.safetensors"]) == 2
    assert "no such file" in capsys.readouterr().err and not (tmp_path / "solo" / "config.toml").exists()


def test_a_stop_during_the_final_report_says_so_and_takes_the_report_with_it(tmp_path: Path) -> None:
    # SIGTERM then ended `up` without a word (the handlers were restored before the report).
    import signal
    import time

    run_at(tmp_path, updates=20, total_updates=20)
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "up", "--run", RUN, "--runs-dir", str(tmp_path),
                             "--resume", "--final-episodes", "1", "--quiet"], cwd=REPO, env=ENV,
                            stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stderr.readline()  # type: ignore[union-attr]
        assert "redoing its final evaluation and report" in line, line
        time.sleep(1.0)  # into the evaluation's child process
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 128 + signal.SIGTERM
        err = proc.stderr.read()  # type: ignore[union-attr]
        assert f"run {RUN!r}: SIGTERM during the final evaluation and report" in err and "--resume" in err
    finally:
        if proc.poll() is None:
            proc.kill()
    # its child went with it: nothing of this run is still running
    time.sleep(0.5)
    running = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            running.append(cmdline.read_bytes().replace(b"\0", b" ").decode(errors="replace"))
        except OSError:
            continue
    assert not [c for c in running if str(tmp_path) in c and "services.cli" in c]


REPORT_ONLY = ["up", "--run", RUN, "--report-only", "--quiet", "--final-episodes", "1"]


def test_report_only_reports_a_run_as_far_as_it_got_and_trains_nothing(tmp_path: Path, capfd) -> None:
    """What compose's `report` service runs once its learner has stopped: the final evaluation and
    report of an unfinished run, with no router, service or training started and the run's config
    and checkpoints left as they were; refused while the run's learner holds it, for a run with no
    trained checkpoint, and with an option it would ignore."""
    from services.runs import RunLock

    args = REPORT_ONLY + ["--runs-dir", str(tmp_path)]
    assert main(args) == 2
    assert f"--report-only: there is no run {RUN!r} in {tmp_path} to report on" in capfd.readouterr().err
    paths = run_at(tmp_path, updates=0, total_updates=20)  # stopped in its warm-up: nothing to report
    assert main(args) == 2
    assert f"--report-only: run {RUN!r} has no trained checkpoint yet" in capfd.readouterr().err

    paths = run_at(tmp_path, updates=10, total_updates=20)  # stopped early (`docker compose stop learner`)
    for flags in (["--updates", "30"], ["--minutes", "1"], ["--set", "dqn.lr=1e-3"], ["--no-report"]):
        assert main(args + flags) == 2
        err = capfd.readouterr().err
        assert "--report-only trains nothing" in err and flags[0] in err and err.count("\n") == 1, err
    learner = RunLock(paths, "learner")  # its learner still training: the checkpoints are still moving
    try:
        assert main(args) == 2
        assert "its learner is pid" in capfd.readouterr().err
    finally:
        learner.release()

    config = paths.config.read_bytes()
    assert main(args) == 0
    err = capfd.readouterr().err
    assert f"run {RUN!r}: the final evaluation and report of its training so far (10 updates)" in err, err
    assert "%|" not in err, err  # --quiet reaches the evaluation and the report: no progress bar of theirs
    assert checkpoint_updates(paths) == 10 and paths.config.read_bytes() == config  # trained nothing
    assert not paths.secure.exists() and not (paths.logs / "router.log").exists()  # started nothing
    assert json.loads((paths.stats / "final-eval.json").read_text())["meta"]["protocol"] == \
        PROTOCOLS["robust"].to_dict()
    assert "| Count | again@" in (paths.report / "report.md").read_text()  # the run (its one checkpoint)
    RunLock(paths, "learner").release()  # let go once the report is made


def test_a_resumed_run_s_own_transfer_file_is_not_needed_but_one_given_anew_is(tmp_path: Path) -> None:
    # The checkpoint replaces the transferred weights: up refused to resume a run whose transfer file
    # had gone since (its learner read it at every start too).
    from services.up.launcher import RunStateError, check_learner_sources
    from shared.config import load_preset

    gone = load_preset("smoke").with_overrides({"train.init_conv_from": str(tmp_path / "gone.safetensors")})
    check_learner_sources("r", gone, resumed_from=gone)
    for resumed_from in (None, load_preset("smoke")):  # a new run; a transfer given anew on resume
        with pytest.raises(RunStateError, match="gone.safetensors"):
            check_learner_sources("r", gone, resumed_from=resumed_from)
