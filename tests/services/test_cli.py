"""The one command line: every user-facing error is a CogexploreError, printed once, in one line."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

from services.cli import main
from shared.errors import CogexploreError

REPO = Path(__file__).resolve().parents[2]
NOT_USER_ERRORS = {"EvaluationCancelled"}  # control flow: a stop event set during an evaluation


def test_every_error_class_of_the_project_derives_from_the_one_base():
    classes = {}
    for path in [*(REPO / "shared").rglob("*.py"), *(REPO / "services").rglob("*.py")]:
        module = ".".join(path.relative_to(REPO).with_suffix("").parts)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and node.name.endswith(("Error", "Cancelled")):
                classes[f"{module}.{node.name}"] = node.name
    assert len(classes) >= 20
    import importlib

    outside = []
    for qualified, name in classes.items():
        cls = getattr(importlib.import_module(qualified.rsplit(".", 1)[0]), name)
        if name not in NOT_USER_ERRORS and not issubclass(cls, CogexploreError):
            outside.append(qualified)
    assert not outside, outside
    names = list(classes.values())
    assert len(names) == len(set(names)), "two error classes share a name"


@pytest.mark.parametrize("argv,message", [
    (["actor", "--run", "bad name"], "cogexplore actor: error: run name 'bad name' contains whitespace"),
    (["learner", "--run", "a/b"], "cogexplore learner: error: run name 'a/b' contains a slash"),
    (["evaluate", "--policy", "random", "--world", "nowhere", "--quiet"], "cogexplore evaluate: error: "),
    (["model", "export", "no-such-checkpoint", "--out", "x.safetensors"], "cogexplore model export: error: "),
    (["evaluate", "--policy", "random", "--world", "box-room", "--image-every", "0", "--rrd", "never.rrd", "--quiet"],
     "cogexplore evaluate: error: --image-every must be a whole number >= 1, got 0"),
    (["bench", "env", "--world", "nowhere", "--steps", "1", "--no-pin"], "cogexplore bench env: error: "),
    (["bench", "env", "--backend", "gl", "--per-pixel", "--no-pin"], "cogexplore bench env: error: --per-pixel "),
    # --set values beyond a float and beyond Python's int-digits limit: were an OverflowError and a ValueError
    (["train", "--preset", "tiny", "--runs-dir", "/nonexistent/runs", "--set", "dqn.lr=" + "1" * 400],
     "cogexplore train: error: [dqn] lr = 1111"),
    (["train", "--preset", "tiny", "--runs-dir", "/nonexistent/runs", "--set", "train.seed=" + "9" * 5000],
     "cogexplore train: error: [train] seed = '99"),
])
def test_a_bad_input_is_one_line_and_exit_status_2(argv: list[str], message: str, tmp_path: Path, capsys) -> None:
    assert main([*argv, *(["--runs-dir", str(tmp_path)] if argv[0] in ("actor", "learner") else [])]) == 2
    err = capsys.readouterr().err
    assert err.startswith(message) and err.count("\n") == 1 and "Traceback" not in err


def test_evaluate_report_and_model_select_play_on_one_cpu_thread_unless_told(capsys) -> None:
    """A policy steps one image at a time: two evaluations that each take every core (or one beside
    a learner) wait on one another, so these commands default to one torch thread; 0 keeps torch's."""
    import torch

    from services.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["model", "select", "runs/r", "--out", "x.safetensors"]).threads == 1
    assert parser.parse_args(["report", "runs/r"]).threads == 1
    before = torch.get_num_threads()
    try:
        for argv, threads in (([], 1), (["--threads", "0"], 2)):
            torch.set_num_threads(2)
            assert main(["evaluate", "--policy", "reactive", "--episodes-per-start", "1", "--max-steps", "3",
                         "--protocol", "paper", "--quiet", *argv]) == 0
            assert torch.get_num_threads() == threads, argv
        assert '"episodes": 12' in capsys.readouterr().out
    finally:
        torch.set_num_threads(before)
    with pytest.raises(SystemExit) as stop:
        main(["evaluate", "--threads", "two"])
    assert stop.value.code == 2
    assert "--threads: must be a whole number in 0..1024, got 'two'" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["up", "--minutes", "nan"], ["up", "--minutes", "0"], ["up", "--eval-every", "0"], ["up", "--final-episodes", "0"],
    ["train", "--minutes", "-1"], ["evaluator", "--wait-weights", "nan"], ["evaluator", "--episodes-per-start", "0"],
    ["evaluator", "--query-timeout", "0"], ["actor", "--batch-steps", "0"], ["actor", "--config-wait", "nan"],
    ["drive", "--control-period", "-1"], ["drive", "--watchdog", "nan"], ["sim-robot", "--cmd-timeout", "inf"],
    ["bench", "system", "--seconds", "nan"], ["bench", "transport", "--seconds", "nan"],
    # these gave tracebacks (a zero division, torch's thread check, a negative array size)
    ["bench", "env", "--steps", "0"], ["bench", "learner", "--repeats", "0"], ["bench", "learner", "--threads", "0"],
    ["bench", "transport", "--batch-steps", "-2"], ["bench", "transport", "--height", "-1"],
    ["bench", "transport", "--width", "0"], ["bench", "drive", "--images", "9"], ["bench", "drive", "--width", "0"],
    ["bench", "system", "--learner-threads", "0"], ["bench", "system", "--actors", "0"],
    ["up", "--port", "70000"], ["up", "--port", "-1"], ["up", "--port", "0"],
])
def test_a_count_or_time_that_cannot_be_one_is_refused_before_anything_starts(argv: list[str], capsys) -> None:
    # a NaN deadline never passes (`up --minutes nan` trained on, `--config-wait nan` waited forever),
    # and `--eval-every 0` left the run without its evaluator
    with pytest.raises(SystemExit) as stop:
        main(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2 and f"argument {argv[-2]}: must be " in err and repr(argv[-1]) in err, err


def test_a_bad_environment_value_is_an_option_error_of_its_command_not_of_every_command(monkeypatch, capsys) -> None:
    import importlib.metadata

    monkeypatch.setenv("COGEXPLORE_NUM_ACTORS", "two")
    monkeypatch.setenv("ROS_DOMAIN_ID", "abc")
    with pytest.raises(SystemExit) as stop:  # the parser of every command is built: none may fail then
        main(["--version"])
    assert stop.value.code == 0 and importlib.metadata.version("cogexplore") in capsys.readouterr().out
    for argv, option in ((["actor"], "--num-actors"), (["drive"], "--domain-id")):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        err = capsys.readouterr().err
        assert stop.value.code == 2 and f"argument {option}: " in err and "Traceback" not in err, err


def test_an_empty_environment_variable_counts_as_unset(monkeypatch) -> None:
    from services.cli import build_parser

    for name in ("COGEXPLORE_RUN", "COGEXPLORE_RUNS_DIR", "COGEXPLORE_DEVICE", "COGEXPLORE_NUM_ACTORS"):
        monkeypatch.setenv(name, "")  # what docker compose passes for `${VAR:-}`
    args = build_parser().parse_args(["actor"])
    assert (args.run, args.runs_dir, args.device, args.num_actors) == ("default", "runs", None, 1)


def test_the_installed_command_prints_its_tree_quickly_and_names_every_command():
    proc = subprocess.run([sys.executable, "-m", "services.cli", "--help"], cwd=REPO, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0
    for command in ("up", "train", "router", "learner", "actor", "evaluator", "evaluate", "report", "pretrain",
                    "experiment", "worlds", "model", "bench"):
        assert f"    {command}" in proc.stdout, command


def test_version_is_the_installed_one(capsys) -> None:
    import importlib.metadata

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.strip() == f"cogexplore {importlib.metadata.version('cogexplore')}"


def _parsers(parser, path=()):
    """Every (command path, parser) of the tree."""
    import argparse

    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _parsers(child, (*path, name))


def test_every_option_of_every_command_says_what_it_does() -> None:
    from services.cli import build_parser

    parsers = list(_parsers(build_parser()))
    options = [(path, action) for path, parser in parsers for action in parser._actions if action.option_strings]
    # every command was walked, its subcommands too: the check below is not over an empty list
    commands = {" ".join(path) for path, _ in parsers}
    assert {"up", "actor", "learner", "evaluator", "evaluate", "train", "worlds demo", "model export"} <= commands
    assert len(options) >= 200, len(options)
    silent = [f"cogexplore {' '.join(path)} {action.option_strings[0]}" for path, action in options if not action.help]
    assert not silent, silent


def test_every_command_that_plays_test_episodes_draws_them_from_the_test_seed() -> None:
    """One seed for every reported figure (evaluate, report, experiment, the evaluator, the
    demonstration check), another for choosing a model: changing one never moves the other."""
    from services.cli import build_parser
    from shared.evaluation import SELECTION_SEED, TEST_SEED

    seeds = {path: action.default for path, parser in _parsers(build_parser()) for action in parser._actions
             if "--seed" in action.option_strings}
    for path in [("evaluate",), ("report",), ("experiment",), ("evaluator",), ("worlds", "demo")]:
        assert seeds.pop(path) == TEST_SEED, path
    assert seeds.pop(("model", "select")) == SELECTION_SEED != TEST_SEED
    assert set(seeds) == {("pretrain",), ("bench", "fuzz")}  # their seeds draw training data and payloads


@pytest.mark.parametrize("argv,message", [
    (["actor", "--connect", "not-an-endpoint"], "--connect endpoint 'not-an-endpoint' is invalid"),
    (["learner", "--zenoh-config", "/no/such/zenoh.json5"], "Zenoh config file /no/such/zenoh.json5 does not exist"),
    # no router there: the service retries --router-wait seconds (30 by default), then says so
    (["actor", "--connect", "tcp/127.0.0.1:9", "--router-wait", "1"], "cannot open a Zenoh session"),
])
def test_a_service_that_cannot_join_says_why_in_one_line(argv: list[str], message: str, tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "services.cli", *argv, "--runs-dir", str(tmp_path)], cwd=REPO,
                          capture_output=True, text=True, timeout=120, env={**os.environ, "RERUN_ANALYTICS": "0"})
    last = proc.stderr.strip().splitlines()[-1]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert last.startswith(f"cogexplore {argv[0]}: error: ") and message in last, last


def test_a_world_file_mujoco_cannot_compile_is_one_line_naming_the_element(tmp_path: Path, capsys) -> None:
    world = tmp_path / "broken.xml"
    world.write_text('<mujoco><worldbody><geom name="wall" type="box" size="1 -1 1"/></worldbody></mujoco>')
    assert main(["evaluate", "--policy", "random", "--world", str(world), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cogexplore evaluate: error: ") and err.count("\n") == 1 and "wall" in err, err


def test_a_router_config_that_cannot_be_used_is_one_line_naming_the_file(tmp_path: Path, capsys) -> None:
    # `up` shows the last line of its router's log: Zenoh's parser message had six, and the folder
    # given as --config was said "not to exist"
    bad = tmp_path / "bad.json5"
    bad.write_text("{ not json\n")
    for config, said in ((bad, f"Zenoh config file {bad} is invalid: "),
                         (tmp_path, f"--config {tmp_path} is not a file"),
                         (tmp_path / "missing.json5", f"Zenoh config file {tmp_path / 'missing.json5'} does not exist")):
        assert main(["router", "--config", str(config), "--listen", "tcp/127.0.0.1:0"]) == 2
        captured = capsys.readouterr()
        assert captured.err.startswith(f"cogexplore router: error: {said}") and captured.err.count("\n") == 1, \
            captured.err
        assert "cogexplore router ready" not in captured.out
    assert main(["router", "--listen", "nowhere"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cogexplore router: error: --listen ") and err.count("\n") == 1, err


def test_a_reader_that_stops_reading_ends_the_command_quietly(tmp_path: Path) -> None:
    """`cogexplore bench env --json | head -1` said "error: [Errno 32] Broken pipe" with status 2."""
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "worlds", "list"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "RERUN_ANALYTICS": "0"})
    proc.stdout.close()  # the reader is gone before the command writes its first line
    err = proc.stderr.read().decode()
    assert proc.wait(120) == 141 and err == "", err
    # an error that is not stdout's still says what it is
    done = subprocess.run([sys.executable, "-m", "services.cli", "worlds", "list"], cwd=REPO, capture_output=True,
                          text=True, timeout=120, env={**os.environ, "RERUN_ANALYTICS": "0"})
    assert done.returncode == 0 and "box-room" in done.stdout


def test_text_the_run_folder_cannot_hold_is_refused_before_the_run_starts(tmp_path: Path, capsys) -> None:
    # an undecodable byte of argv (a lone surrogate) passed the config; saving config.toml was a traceback
    argv = ["train", "--preset", "tiny", "--runs-dir", str(tmp_path), "--run", "r", "--updates", "1", "--quiet",
            "--no-tensorboard", "--set", "env.extra_worlds=\udcff"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("cogexplore train: error: [env] extra_worlds = '\\udcff' is invalid: text in UTF-8")
    assert err.count("\n") == 1


@pytest.mark.skipif(Path("/proc/sys/vm/overcommit_memory").exists()
                    and Path("/proc/sys/vm/overcommit_memory").read_text().strip() == "1",
                    reason="this kernel promises any allocation: the memory would be asked for page by page")
def test_a_replay_memory_larger_than_the_machine_is_one_line(tmp_path: Path, capsys) -> None:
    # 10 million 1024 x 1024 frames: 21.5 TiB; was a numpy MemoryError traceback
    argv = ["train", "--preset", "tiny", "--runs-dir", str(tmp_path), "--run", "r", "--updates", "1", "--quiet",
            "--no-tensorboard", "--set", "replay.capacity=10000000", "--set", "sensor.width=1024",
            "--set", "sensor.height=1024"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("cogexplore train: error: replay.capacity = 10000000 of 1024x1024 images needs more "
                          "memory than this machine has (") and "TiB" in err and err.count("\n") == 1


def test_every_option_of_the_tools_names_its_default() -> None:
    import argparse

    from services.cli import COMMANDS, Command, build_parser

    tools = {name for name, c in COMMANDS.items() if isinstance(c, Command) and c.options.startswith("services.tools.")}
    tools |= {f"{name} {action}" for name, g in COMMANDS.items() if not isinstance(g, Command)
              for action, c in g.actions.items() if c.options.startswith("services.tools.")}
    assert {"train", "evaluate", "pretrain", "experiment", "worlds demo", "model select"} <= tools
    quiet = []
    for path, parser in _parsers(build_parser()):
        if " ".join(path) not in tools:
            continue
        for action in parser._actions:
            if not action.option_strings or action.help in (None, argparse.SUPPRESS):
                continue
            has_value = action.default not in (None, False, True, [], (), argparse.SUPPRESS)
            # a device left unset is still some device: the help says which
            if (has_value or "--device" in action.option_strings) and "default" not in action.help:
                quiet.append(f"cogexplore {' '.join(path)} {action.option_strings[0]}")
    assert not quiet, quiet
