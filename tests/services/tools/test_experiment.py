"""``cogexplore experiment paper`` end to end at CI size: SL pretraining, the frozen-conv RL run,
DRL stages through the distributed system (``cogexplore up`` subprocesses) resuming one run,
evaluation of every model, the tables and figures, and resuming an interrupted experiment."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from service_processes import run_on_a_full_disk

from services.cli import main as cli
from services.tools.experiment import (
    Experiment,
    ExperimentError,
    options_from_args,
    parse_checkpoints,
)
from services.tools.options import add_experiment_arguments
from shared.evaluation import PROTOCOLS
from shared.evaluation.setup import setup_evaluation


def main(argv: list[str]) -> int:
    """``cogexplore experiment ARGV``: the exit status."""
    return cli(["experiment", *argv])

TINY = ["paper", "--preset", "smoke", "--world", "box-room", "--actors", "1", "--sl-worlds", "box-room",
        "--sl-frames", "120", "--sl-epochs", "1", "--rl-updates", "20", "--episodes-per-start", "1",
        "--max-steps", "10", "--device", "cpu", "--quiet", "--unseen-worlds", "corridor"]


def run(out: Path, checkpoints: str, *extra: str) -> Experiment:
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    args = parser.parse_args([*TINY, "--out", str(out), "--checkpoints", checkpoints, *extra])
    messages: list[str] = []
    experiment = Experiment(options_from_args(args), echo=messages.append)
    experiment.run()
    return experiment


def conv(tensors: dict[str, torch.Tensor], prefix: str = "") -> dict[str, torch.Tensor]:
    return {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix + "trunk.")}


def test_tiny_experiment_runs_end_to_end_and_resumes(tmp_path):
    from shared.learning.checkpoints import (
        CheckpointManager,
        load_exported_weights,
        load_supervised,
    )

    out = tmp_path / "exp"
    first = run(out, "20")
    labels = ["SL", "RL", "DRL-20", "reactive", "random"]
    assert first.ran == ["sl", "rl", "drl-20", *(f"eval-{m}" for m in labels), *(f"eval-{m}@corridor" for m in labels)]
    table = (out / "table.md").read_text()
    for label in ("SL", "RL", "DRL-20", "reactive", "random"):
        assert f"| {label} |" in table
    assert "| Count |" in table and "| Distance (m) |" in table
    assert (out / "heatmaps.png").stat().st_size > 1000
    wall = (out / "wallclock.md").read_text()
    assert "| drl-20 |" in wall and "| rl |" in wall
    report = (out / "report.md").read_text()
    assert "![heatmaps](heatmaps.png)" in report and "## Generalisation" in report
    # Every model on the unseen world, with its own results file and heatmaps.
    general = (out / "generalisation.md").read_text()
    assert "| Model | `corridor` | Mean |" in general
    for label in labels:
        info = json.loads((out / "state.json").read_text())["stages"][f"eval-{label}@corridor"]
        assert not Path(info["results"]).is_absolute()  # the experiment's own files: relative to it
        results = json.loads((out / info["results"]).read_text())
        assert results["meta"]["world"] == "corridor" and results["meta"]["model"] == label
        assert f"| {label} | " in general and f"{info['mean_steps']:.1f}" in general
    assert (out / "heatmaps-corridor.png").stat().st_size > 1000
    assert "![learning curve](learning_curve.png)" in report and (out / "learning_curve.png").stat().st_size > 1000
    assert "Table III, paper protocol" in report and PROTOCOLS["paper"].describe() in report
    for label in ("SL", "RL", "DRL-20"):
        results = json.loads((out / "eval" / f"{label}.json").read_text())
        assert results["meta"]["model"] == label and len(results["episodes"]) == 4  # box-room: 4 starts
        assert results["meta"]["protocol"] == PROTOCOLS["paper"].to_dict()  # the paper's comparison
        assert all(e["steps"] <= 10 for e in results["episodes"])

    # RL: conv layers are the SL model's, frozen; fc layers trained. DRL starts from the SL conv.
    sl_net, _ = load_supervised(out / "sl" / "sl.safetensors")
    sl_conv = conv(sl_net.state_dict())
    rl = CheckpointManager(out / "runs" / "rl" / "checkpoints").load()
    assert rl.update_count == 20
    for name, t in conv(rl.tensors, "online.").items():
        assert torch.equal(t, sl_conv[name]), name
    drl_net, drl_meta = load_exported_weights(out / "models" / "drl-20.safetensors")
    assert drl_meta["policy_version"] >= 20
    assert drl_net.sensor_cfg.width == 40  # the smoke preset's image

    # The next stage resumes the same DRL run; finished stages are skipped.
    second = run(out, "20,40")
    assert second.ran == ["drl-40", "eval-DRL-40", "eval-DRL-40@corridor"]
    assert set(second.skipped) >= {"sl", "rl", "drl-20", "eval-SL", "eval-RL", "eval-DRL-20"}
    learner_log = (out / "runs" / "drl" / "logs" / "learner.log").read_text()
    assert "resumed from ckpt-000000020.safetensors" in learner_log
    assert CheckpointManager(out / "runs" / "drl" / "checkpoints").load().update_count == 40
    assert "| DRL-40 |" in (out / "table.md").read_text()
    state = json.loads((out / "state.json").read_text())
    assert state["stages"]["drl-40"]["updates"] == 40

    # Nothing left to do: a third invocation only rewrites the report, from the experiment's own
    # files wherever it has moved (the state held absolute paths: a moved one failed, a copy read
    # the original's results).
    moved = tmp_path / "moved"
    out.rename(moved)
    third = run(moved, "20,40")
    assert third.ran == [] and "| DRL-40 |" in (moved / "table.md").read_text()
    moved.rename(out)
    # An unseen world added on resume is evaluated for every model; nothing else reruns.
    fourth = run(out, "20,40", "--unseen-worlds", "corridor,procedural:7")
    assert fourth.ran == [f"eval-{m}@procedural:7" for m in ("SL", "RL", "DRL-20", "DRL-40", "reactive", "random")]
    assert "| Model | `corridor` | `procedural:7` | Mean |" in (out / "generalisation.md").read_text()

    # Other options than the state's are refused, through the command too.
    with pytest.raises(ExperimentError, match="other options"):
        run(out, "20,40", "--max-steps", "20")
    assert main([*TINY, "--out", str(out), "--checkpoints", "10,20,40"]) == 2  # 10 is behind the run


def test_a_state_file_too_large_to_be_one_is_refused_unread(tmp_path):
    # A state file was read and parsed up to 256 MiB (a results file or a log moved there by mistake).
    from services.tools.experiment import ExperimentState
    from shared.jsontext import SMALL_JSON_BYTES

    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    options = options_from_args(parser.parse_args([*TINY, "--out", str(tmp_path), "--checkpoints", "20"]))
    path = tmp_path / "state.json"
    with open(path, "wb") as fh:
        fh.truncate(SMALL_JSON_BYTES + 1)
    with pytest.raises(ExperimentError, match=rf"^state file .*state.json cannot be read: too large: "
                                              rf"{SMALL_JSON_BYTES + 1:,} bytes, .*: move it away to start afresh$"):
        ExperimentState(path, options)


def test_the_protocol_is_fixed_with_the_experiment(tmp_path):
    from services.tools.experiment import ExperimentState

    def options(*extra: str):
        parser = argparse.ArgumentParser()
        add_experiment_arguments(parser)
        return options_from_args(parser.parse_args([*TINY, "--out", str(tmp_path), "--checkpoints", "20", *extra]))

    path = tmp_path / "state.json"
    ExperimentState(path, options()).save()
    state = json.loads(path.read_text())
    assert state["options"]["protocol"] == PROTOCOLS["paper"].to_dict()
    # A state file from before the protocol was an option was evaluated under the paper's: it resumes.
    del state["options"]["protocol"]
    path.write_text(json.dumps(state))
    ExperimentState(path, options())
    with pytest.raises(ExperimentError, match="other options.*'protocol'"):
        ExperimentState(path, options("--protocol", "robust"))
    assert options("--protocol", "robust", "--sensor-noise-m", "0").protocol.name == "custom"
    with pytest.raises(ExperimentError, match="--protocol: .*start_jitter_m"):
        options("--start-jitter-m", "-1")
    # Training noise is training's: it never reaches the test episodes, whose noise is the protocol's.
    noisy = Experiment.__new__(Experiment)
    noisy.o = options("--set", "sensor.noise_std_m=0.02", "--set", "sensor.width=40", "--set", "dqn.lr=1e-4")
    assert noisy._eval_overrides() == ["sensor.width=40"]
    # So are training's episode cap, speeds and start jitter, which setup_evaluation refuses after the training.
    noisy.o = options("--set", "env.max_episode_steps=300", "--set", "env.speed_table=train", "--set",
                      "env.start_jitter_m=0.1", "--set", "env.robot_radius_m=0.2")
    assert noisy._eval_overrides() == ["env.robot_radius_m=0.2"]
    setup_evaluation("random", world="box-room", overrides=noisy._eval_overrides())


def test_a_stage_that_stopped_where_the_one_before_did_is_one_row(tmp_path):
    # --minutes-per-stage can end a stage before its first new checkpoint: both stages then hold
    # the model of the same update, and the table had two "DRL-<n>" rows sharing one evaluation.
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    experiment = Experiment(options_from_args(parser.parse_args([*TINY, "--out", str(tmp_path),
                                                                 "--checkpoints", "20,40,60"])), echo=print)
    for stage, updates in (("drl-20", 20), ("drl-40", 25), ("drl-60", 25)):
        experiment.state.finish(stage, 60.0, file=f"models/{stage}.safetensors", updates=updates)
    labels = [label for label, _policy, _ckpt in experiment.models()]
    assert labels == ["SL", "RL", "DRL-20", "DRL-25", "reactive", "random"]
    assert experiment.models()[3][2] == str(tmp_path / "models" / "drl-40.safetensors")


def test_a_checkpoint_added_on_resume_keeps_the_default_rl_baseline(tmp_path):
    from services.tools.experiment import ExperimentState

    def options(checkpoints: str, *extra: str):
        parser = argparse.ArgumentParser()
        add_experiment_arguments(parser)
        argv = [a for a in TINY if a not in ("--rl-updates", "20")]  # the default: the last checkpoint's
        return options_from_args(parser.parse_args([*argv, "--out", str(tmp_path), "--checkpoints", checkpoints,
                                                    *extra]))

    path = tmp_path / "state.json"
    ExperimentState(path, options("20")).save()
    # Refused before as "other options ({'rl_updates': 20})", though --rl-updates was never given.
    resumed = options("20,40")
    ExperimentState(path, resumed)
    assert resumed.rl_updates == 20  # the RL baseline the experiment began with
    with pytest.raises(ExperimentError, match="other options.*'rl_updates'"):
        ExperimentState(path, options("20,40", "--rl-updates", "40"))  # given: it must match


def test_checkpoint_list_and_options_are_validated(tmp_path, capsys):
    assert parse_checkpoints("500,4000,7500,40000") == [500, 4000, 7500, 40000]
    for bad in ("", "500,400", "0,10", "a,b"):
        with pytest.raises(ExperimentError):
            parse_checkpoints(bad)
    assert main([*TINY, "--out", str(tmp_path / "x"), "--checkpoints", "20", "--world", "nowhere"]) == 2
    assert "nowhere" in capsys.readouterr().err
    assert main([*TINY, "--out", str(tmp_path / "x"), "--checkpoints", "20", "--actors", "0"]) == 2
    assert main([*TINY, "--out", str(tmp_path / "x"), "--checkpoints", "20", "--unseen-worlds", "procedural:x"]) == 2
    assert "procedural:x" in capsys.readouterr().err
    assert not (tmp_path / "x" / "state.json").exists()
    # A world the runs or the SL data play is not unseen.
    for seen in (["--unseen-worlds", "box-room"], ["--unseen-worlds", "corridor", "--sl-worlds", "box-room,corridor"],
                 ["--unseen-worlds", "procedural:7", "--set", "env.extra_worlds=procedural:5-9"]):
        assert main([*TINY, "--out", str(tmp_path / "y"), "--checkpoints", "20", *seen]) == 2
        assert "never trained on" in capsys.readouterr().err
    assert not (tmp_path / "y" / "state.json").exists()


STATE_HEAD = '{"format": "cogexplore-experiment", "version": 1, "options": {}, "stages": '


@pytest.mark.parametrize("state", ["[]", '{"format": "cogexplore-experiment", "version": 1}', "\xff",
                                   STATE_HEAD + "[]}",
                                   # hand-edited or damaged stages: tracebacks deep in a resumed run before
                                   STATE_HEAD + '{"rl": {"run": "runs/rl"}}}',
                                   STATE_HEAD + '{"drl-x": {"seconds": 1, "file": "m", "updates": 5}}}',
                                   STATE_HEAD + '{"drl-20": {"seconds": 1, "file": "m"}}}',
                                   STATE_HEAD + '{"eval-SL": {"seconds": 1, "results": null, "mean_steps": 3}}}',
                                   STATE_HEAD + '{"sl": {"seconds": 1, "model": "m", "accuracy": "high"}}}',
                                   STATE_HEAD + '{"what": {"seconds": 1}}}'])
def test_a_damaged_state_file_is_one_line_and_left_as_it_is(state: str, tmp_path, capsys):
    out = tmp_path / "exp"
    out.mkdir()
    (out / "state.json").write_bytes(state.encode("latin-1"))
    assert cli(["experiment", "paper", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cogexplore experiment: error: ") and "move it away to start afresh" in err
    assert err.count("\n") == 1 and (out / "state.json").read_bytes() == state.encode("latin-1")


def test_an_interrupted_stage_s_time_counts_when_it_is_resumed(tmp_path):
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    options = options_from_args(parser.parse_args([*TINY, "--out", str(tmp_path), "--checkpoints", "20"]))
    experiment = Experiment(options, echo=lambda _msg: None)

    def interrupted() -> dict:
        time.sleep(0.3)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        experiment._stage("drl-20", interrupted)
    again = Experiment(options, echo=lambda _msg: None)  # a new invocation: from the state file
    entry = again._stage("drl-20", lambda: {"file": "models/drl-20.safetensors", "updates": 20})
    assert entry["seconds"] >= 0.3 and "drl-20" not in again.state.data.get("partial_seconds", {})


@pytest.mark.parametrize("seed", ["-1", str(2**53)])
def test_a_seed_out_of_range_is_refused_before_any_stage(tmp_path, capsys, seed):
    # 2**53 was refused only by the pretrain stage, after the run folder was made
    assert main([*TINY, "--out", str(tmp_path / "x"), "--checkpoints", "20", "--seed", seed]) == 2
    assert "--seed must be in [0, 9007199254740991]" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_sl_epochs_past_the_pretrain_bound_are_refused_before_any_stage(tmp_path, capsys):
    from shared.expert.supervised import MAX_EPOCHS

    # refused only by the SL stage, after the run folder was made
    assert main([*TINY, "--out", str(tmp_path / "x"), "--checkpoints", "20", "--sl-epochs", str(MAX_EPOCHS + 1)]) == 2
    assert f"--sl-epochs must be <= {MAX_EPOCHS}" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_an_up_child_is_told_to_stop_when_only_the_experiment_got_the_signal(tmp_path):
    from services.tools.experiment import _stop_child

    mark = tmp_path / "checkpoint"
    child = subprocess.Popen([sys.executable, "-c", f"""
import pathlib, signal, sys, time
def stop(*_):
    pathlib.Path({str(mark)!r}).write_text("final checkpoint")
    sys.exit(0)
signal.signal(signal.SIGINT, stop)
print("ready", flush=True)
time.sleep(60)
"""], stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "ready"
    started = time.monotonic()
    _stop_child(child, signal_it=True)
    assert child.returncode == 0 and mark.read_text() == "final checkpoint" and time.monotonic() - started < 30


@pytest.mark.parametrize("card", [{"accuracy": "0.9 (held out)"}, {"accuracy": {"held out": 0.9}}, {"accuracy": float("nan")},
                                  {"accuracy": 0.75}])
def test_a_given_sl_model_s_card_is_read_as_untrusted(card, tmp_path):
    # The card is the file's word: a text accuracy was stored, then crashed every report (":.3f").
    from shared.config import load_preset
    from shared.learning.checkpoints import save_supervised
    from shared.learning.model import SupervisedNet

    cfg = load_preset("smoke")
    model = save_supervised(tmp_path / "sl.safetensors", SupervisedNet(cfg.sensor), card=card)
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    options = options_from_args(parser.parse_args([*TINY, "--out", str(tmp_path / "exp"), "--checkpoints", "20",
                                                   "--sl-model", str(model)]))
    accuracy = Experiment(options, echo=lambda _msg: None)._pretrain()["accuracy"]
    assert accuracy == (0.75 if card == {"accuracy": 0.75} else None)


@pytest.mark.parametrize("seen", [["--world", "procedural:07", "--unseen-worlds", "procedural:7"],
                                  ["--sl-worlds", "box-room,procedural:0101", "--unseen-worlds", "procedural:101"]])
def test_a_trained_world_written_another_way_is_not_unseen(seen, tmp_path):
    # procedural:07 is the world procedural:7: it was tested as a world no run had played
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    args = parser.parse_args([*TINY, "--out", str(tmp_path / "x"), "--checkpoints", "20", *seen])
    with pytest.raises(ExperimentError, match="never trained on"):
        Experiment(options_from_args(args))
    assert not (tmp_path / "x").exists()


def test_a_report_rewrite_cut_short_by_a_full_disk_leaves_the_last_one_whole(tmp_path):
    # the report's files were written in place: a rerun that failed mid-file left half a table
    argv = [*TINY, "--out", str(tmp_path), "--checkpoints", "20", "--unseen-worlds", ""]
    parser = argparse.ArgumentParser()
    add_experiment_arguments(parser)
    experiment = Experiment(options_from_args(parser.parse_args(argv)), echo=lambda _msg: None)
    for label, policy, checkpoint in experiment.models()[-2:]:  # reactive and random: no training
        experiment._stage(experiment.eval_stage(label), lambda a=(label, policy, checkpoint): experiment._evaluate(
            *a, world="box-room"))
    experiment.write_report()
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    assert {"table.md", "report.md", "wallclock.md"} <= set(before)
    done = run_on_a_full_disk("import argparse; "
                              "from services.tools.experiment import Experiment, options_from_args; "
                              "from services.tools.options import add_experiment_arguments; "
                              "p = argparse.ArgumentParser(); add_experiment_arguments(p); "
                              f"Experiment(options_from_args(p.parse_args({argv!r}))).write_report()", 100)
    assert done.returncode != 0 and "File too large" in done.stderr, done.stderr[-2000:]
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before


def test_runs_left_without_their_state_are_not_resumed_as_this_experiment_s(tmp_path, capsys):
    # a state file moved away "to start afresh" left runs/rl: the RL stage resumed that run (trained in
    # another world, on another preset) and reported it as this experiment's baseline
    (tmp_path / "runs" / "rl" / "checkpoints").mkdir(parents=True)
    assert main([*TINY, "--out", str(tmp_path), "--checkpoints", "20"]) == 2
    err = capsys.readouterr().err
    assert "holds the runs of an experiment without its state.json" in err and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"]  # nothing written, nothing trained


def test_an_evaluation_on_a_world_file_edited_since_is_played_again(tmp_path):
    # Keyed by the world's name, a resumed experiment skipped the evaluations of the file before the
    # user edited it: its tables mixed them with any evaluated after the edit, under one name.
    from shared.config import load_preset
    from shared.evaluation.protocol import file_world_sha256
    from shared.learning.checkpoints import CheckpointManager, export_weights, save_supervised
    from shared.learning.dqn import DQNAgent
    from shared.learning.model import SupervisedNet
    from tests.services.tools.test_report import _drop_world_digest
    from tests.shared.evaluation.test_eval_log import write_room

    # Trained as the training stages leave it: an SL model, the RL run and one DRL model.
    out, cfg = tmp_path / "exp", load_preset("smoke")
    sl = save_supervised(tmp_path / "sl.safetensors", SupervisedNet(cfg.sensor))
    agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu", seed=0)
    agent.update_count = agent.policy_version = 20
    CheckpointManager(out / "runs" / "rl" / "checkpoints").save(agent, config=cfg.to_dict())
    export_weights(out / "models" / "drl-20.safetensors", agent.online, 20, run_config=cfg)
    world = write_room(tmp_path / "room.xml")
    messages: list[str] = []

    def experiment() -> Experiment:
        parser = argparse.ArgumentParser()
        add_experiment_arguments(parser)
        args = parser.parse_args([*TINY, "--out", str(out), "--checkpoints", "20", "--sl-model", str(sl),
                                  "--unseen-worlds", str(world)])
        return Experiment(options_from_args(args), echo=messages.append)

    first = experiment()
    first.state.finish("rl", 1.0, run="runs/rl", updates=20, env_steps=100)
    first.state.finish("drl-20", 1.0, file="models/drl-20.safetensors", updates=20)
    first.run()
    labels = ["SL", "RL", "DRL-20", "reactive", "random"]
    assert first.ran == ["sl", *(f"eval-{m}" for m in labels), *(f"eval-{m}@{world}" for m in labels)]
    unchanged = experiment()
    unchanged.run()
    assert unchanged.ran == []  # the same file: nothing again
    # A built-in world's results from before they recorded the world's content stand for it.
    _drop_world_digest(out / "eval" / "reactive.json")
    write_room(world, pillar_x=-0.6)  # the pillar moved into the robot's way
    again = experiment()
    again.run()
    assert again.ran == [f"eval-{m}@{world}" for m in labels]  # the file's, only
    assert f"5 evaluation(s) on {world} played the file as it was before an edit" in "\n".join(messages)
    for label in labels:
        info = again.state.done(again.eval_stage(label, str(world)))
        assert json.loads((out / info["results"]).read_text())["meta"]["world_sha256"] == file_world_sha256(str(world))


def test_a_training_world_or_preset_file_edited_after_training_stops_the_experiment(tmp_path, capsys):
    # The models of the finished training stages stood for the edited file under its name, and the
    # stages still to run trained on it: a DRL run resumed in another world, or on another recipe.
    import shutil

    from shared.config import PRESET_DIR
    from tests.shared.evaluation.test_eval_log import write_room

    out, world = tmp_path / "exp", write_room(tmp_path / "room.xml")
    preset = shutil.copy(PRESET_DIR / "smoke.toml", tmp_path / "mine.toml")
    argv = [*TINY, "--out", str(out), "--checkpoints", "20", "--world", str(world), "--sl-worlds", str(world),
            "--preset", str(preset)]

    def experiment() -> Experiment:
        parser = argparse.ArgumentParser()
        add_experiment_arguments(parser)
        return Experiment(options_from_args(parser.parse_args(argv)), echo=lambda _: None)

    first = experiment()
    first.state.save()
    first.check_training_inputs()  # as run() does before the first stage
    recorded = first.state.data["training_inputs"]
    assert sorted(recorded) == [f"preset {preset}", f"world {world}"]
    first.state.finish("rl", 1.0, run="runs/rl", updates=20, env_steps=100)
    experiment().check_training_inputs()  # the same files: it resumes

    write_room(world, pillar_x=-0.6)  # the pillar moved into the robot's way
    state = (out / "state.json").read_bytes()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"world {world} changed since stage(s) rl trained on it" in err and err.count("\n") == 1, err
    assert (out / "state.json").read_bytes() == state and not (out / "runs" / "drl").exists()  # nothing ran
    write_room(world)  # put back as it was
    Path(preset).write_text(Path(preset).read_text() + "# a comment changes no recipe\n")
    experiment().check_training_inputs()
    Path(preset).write_text(Path(preset).read_text().replace("lr = 1e-3", "lr = 1e-2"))
    with pytest.raises(ExperimentError, match=f"preset {preset} changed since stage"):
        experiment().check_training_inputs()

    # A state from before the record: the files as they are now are recorded, nothing refused.
    data = json.loads((out / "state.json").read_text())
    del data["training_inputs"]
    (out / "state.json").write_text(json.dumps(data))
    again = experiment()
    again.check_training_inputs()
    assert again.state.data["training_inputs"][f"world {world}"] == recorded[f"world {world}"]
