"""docker-compose.yml, the Dockerfile and .dockerignore, checked without a Docker engine.

The compose file is validated against the Compose schema by Debian's ``docker-compose``
(Compose v1 validates with no engine), read structurally with PyYAML, and every command a
service runs is started with ``--help`` through this venv's ``cogexplore`` (or ``rerun``),
with each option the command passes checked against that help text. Each ``cogexplore`` command
is also parsed by the real CLI parser in its container's environment, with the defaults and with
the settings a user gives compose, and compared option by option with what ``cogexplore up``
(services.up.launcher) gives the same service: the local twin and the compose file cannot drift apart.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.metadata
import io
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from services.bus import DEFAULT_ROUTER_WAIT_S
from services.bus.session import ZenohSettings, parse_endpoints
from shared.sim.world_cache import CACHE_DIR_ENV

ROOT = Path(__file__).resolve().parents[1]
COMPOSE_FILE = ROOT / "docker-compose.yml"
DOCKERFILE = ROOT / "Dockerfile"
DOCKERIGNORE = ROOT / ".dockerignore"
VENV_BIN = Path(sys.executable).parent

PROJECT_SERVICES = ("learner", "actor", "evaluator")
"""Services that run ``cogexplore`` and join the run through the router."""
IMAGE_SERVICES = (*PROJECT_SERVICES, "rerun", "secure")
"""Services built from this repository's Dockerfile."""

SERVICE_ENV = (
    "COGEXPLORE_RUN", "COGEXPLORE_PRESET", "COGEXPLORE_RUNS_DIR", "COGEXPLORE_ZENOH_CONNECT",
    "COGEXPLORE_ZENOH_LISTEN", "COGEXPLORE_ZENOH_MODE", "COGEXPLORE_ZENOH_CONFIG", "COGEXPLORE_ZENOH_ROUTER_WAIT_S",
    "COGEXPLORE_DEVICE",
)
"""The environment variables every service reads (the CLI contract)."""
EXTRA_ENV = ("COGEXPLORE_RERUN_URL", "COGEXPLORE_RERUN_EVERY_EPISODES", CACHE_DIR_ENV)
"""Also read by the services: where the evaluator and the actors stream to the Rerun viewer,
which share of its episodes each actor streams, and where generated worlds are kept."""
RERUN_ENV_READERS = ("actor", "evaluator")
"""Services whose ``--rerun-connect`` defaults to ``COGEXPLORE_RERUN_URL``."""
ACTOR_ENV = ("COGEXPLORE_NUM_ACTORS",)
"""Read by the actors alone: the fleet's size (``--num-actors``), which a replica cannot count."""

# The flags of zenohd 1.x (zenohd/src/main.rs): the router service runs the official image,
# whose entrypoint passes the compose `command` to zenohd.
ZENOHD_FLAGS = {
    "-c", "--config", "-l", "--listen", "-e", "--connect", "-i", "--id", "-P", "--plugin",
    "--plugin-search-dir", "--no-timestamp", "--no-multicast-scouting", "--rest-http-port", "--cfg",
    "--adminspace-permissions", "-h", "--help", "-V", "--version",
}

# Each CLI subcommand of the services contract and the options it must offer.
CLI_CONTRACT = {
    "router": ("--listen",),
    "learner": ("--run", "--preset", "--connect", "--runs-dir"),
    "actor": ("--run", "--connect", "--actor-id", "--preset"),
    "evaluator": ("--run", "--connect", "--every-updates"),
}
LANDS_LATER: set[str] = set()
"""Subcommands not in services/cli.py yet: their cases xfail (non-strict) until they land."""

_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::?-([^}]*))?\}")


def interpolate(value: object, variables: dict[str, str] | None = None) -> object:
    """Compose's ``${NAME:-default}`` interpolation: ``variables`` as the user's shell or .env sets
    them (an empty one counts as unset, as ``:-`` says), the defaults for the others."""
    given = variables or {}
    if isinstance(value, str):
        return _VAR.sub(lambda m: given.get(m.group(1)) or m.group(2) or "", value)
    if isinstance(value, list):
        return [interpolate(v, variables) for v in value]
    if isinstance(value, dict):
        return {k: interpolate(v, variables) for k, v in value.items()}
    return value


def compose_services(path: Path = COMPOSE_FILE, variables: dict[str, str] | None = None) -> dict[str, dict]:
    """A compose file's services, merge keys resolved (safe_load does) and variables interpolated."""
    doc = yaml.safe_load(path.read_text())
    assert isinstance(doc, dict) and "services" in doc, f"{path.name} has no services"
    return {name: interpolate(spec, variables) for name, spec in doc["services"].items()}


@pytest.fixture(scope="module")
def services() -> dict[str, dict]:
    return compose_services()


def service_env(spec: dict) -> dict[str, str]:
    env = spec.get("environment") or {}
    if isinstance(env, list):  # the list form: ["KEY=value", ...]
        env = dict(item.split("=", 1) for item in env)
    return {k: "" if v is None else str(v) for k, v in env.items()}


def cogexplore_argv(args: list[str]) -> list[str]:
    exe = VENV_BIN / "cogexplore"
    return [str(exe), *args] if exe.exists() else [sys.executable, "-m", "services.cli", *args]


def run_help(argv: list[str], env_extra: dict[str, str] | None = None) -> str:
    """Run ``argv --help``; return its stdout after asserting that it started and exited 0."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("COGEXPLORE_")}
    env.update(env_extra or {}, RERUN_ANALYTICS="0")
    proc = subprocess.run([*argv, "--help"], capture_output=True, text=True, env=env, timeout=120, cwd=ROOT)
    assert proc.returncode == 0, f"{argv} --help exited {proc.returncode}: {proc.stderr[-2000:]}"
    return proc.stdout


def options_in(argv: list[str]) -> list[str]:
    return [a.split("=", 1)[0] for a in argv if a.startswith("-")]


def parse_command(argv: list[str], env: dict[str, str], monkeypatch: pytest.MonkeyPatch) -> argparse.Namespace:
    """``cogexplore ARGV`` through the real CLI parser, in a container's environment ``env``: the
    parser reads its ``COGEXPLORE_*`` defaults when it is built and converts them when it parses, so a
    stray value, a flag given a value or a variable the option's type refuses all fail here (``--help``
    exits before any of those is looked at)."""
    from services.cli import build_parser

    assert argv[0] == "cogexplore", argv
    for key in [k for k in os.environ if k.startswith("COGEXPLORE_")]:
        monkeypatch.delenv(key)  # the shell running the tests is not the container
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    said = io.StringIO()
    try:
        with contextlib.redirect_stderr(said):
            return build_parser().parse_args(argv[1:])
    except SystemExit as exc:
        pytest.fail(f"`{' '.join(argv)}` with {env}: the CLI refuses it (exit {exc.code}): {said.getvalue()}")


# -- schema ---------------------------------------------------------------------------------

def compose_binary() -> str:
    exe = shutil.which("docker-compose")
    if exe is None:
        reason = ("docker-compose (Debian's Compose v1) is not installed, so the compose file is not "
                  "schema-validated; `apt-get install docker-compose` (.ci/run does it)")
        print(reason)
        pytest.skip(reason)
    return exe


def test_compose_file_is_valid_against_the_compose_schema(services: dict[str, dict], tmp_path: Path) -> None:
    exe = compose_binary()
    env = {k: v for k, v in os.environ.items() if not k.startswith("COGEXPLORE_")}
    proc = subprocess.run([exe, "-f", str(COMPOSE_FILE), "config"], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=120)
    assert proc.returncode == 0, f"docker-compose config rejected the file:\n{proc.stderr}"
    # Compose's own interpolation agrees with the one these tests read the file through.
    resolved = yaml.safe_load(proc.stdout)["services"]
    assert set(resolved) == set(services)
    for name, spec in services.items():
        assert resolved[name].get("command") == spec.get("command"), name
        assert service_env(resolved[name]) == service_env(spec), name

    # The validator really rejects a bad file (so the check above can fail).
    bad = tmp_path / "docker-compose.yml"
    bad.write_text("services:\n  actor:\n    image: x\n    no_such_key: 1\n")
    proc = subprocess.run([exe, "-f", str(bad), "config", "-q"], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=120)
    assert proc.returncode != 0 and "no_such_key" in proc.stderr


GPU_FILE = ROOT / "docker-compose.gpu.yml"


def test_the_gpu_override_puts_the_learner_alone_on_a_cuda_build(services: dict[str, dict],
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """docker-compose.gpu.yml over docker-compose.yml, merged by Compose itself: every service built
    from the project's image gets one image with the CUDA build of torch (a tag of its own), the
    learner alone reserves a GPU and trains on `cuda`; nothing else of the base file changes."""
    import scripts.install_torch as install_torch

    exe = compose_binary()
    env = {k: v for k, v in os.environ.items() if not k.startswith("COGEXPLORE_")}
    proc = subprocess.run([exe, "-f", str(COMPOSE_FILE), "-f", str(GPU_FILE), "config"], capture_output=True,
                          text=True, env=env, cwd=ROOT, timeout=120)
    assert proc.returncode == 0, f"docker-compose config rejected the override:\n{proc.stderr}"
    merged = yaml.safe_load(proc.stdout)["services"]
    assert set(merged) == set(services)
    built = {name for name, spec in services.items() if "build" in spec}
    assert built == {*IMAGE_SERVICES, "report"}
    for name, spec in merged.items():
        gpus = spec.get("deploy", {}).get("resources", {}).get("reservations", {}).get("devices", [])
        assert bool(gpus) == (name == "learner"), name
        assert spec.get("command") == services[name].get("command"), name
        expected_env = dict(service_env(services[name]), **({"COGEXPLORE_DEVICE": "cuda"} if name == "learner" else {}))
        assert service_env(spec) == expected_env, name
        if name in built:
            assert spec["image"] == "cogexplore:cuda" and spec["build"]["args"] == {"TORCH_VARIANT": "cuda"}, name
    assert merged["learner"]["deploy"]["resources"]["reservations"]["devices"] == [
        {"driver": "nvidia", "count": 1, "capabilities": ["gpu"]}]
    assert "cuda" in install_torch.VARIANTS  # what the Dockerfile's TORCH_VARIANT hands the script
    args = parse_command(merged["learner"]["command"], service_env(merged["learner"]), monkeypatch)
    assert args._command == "learner" and args.device == "cuda"


# -- structure ------------------------------------------------------------------------------

def test_services_are_router_learner_actor_evaluator_and_viewer(services: dict[str, dict]) -> None:
    assert set(services) == {"router", "report", *IMAGE_SERVICES}
    # `docker compose up` starts all but the final report, which runs on demand once training has stopped
    assert [name for name, spec in services.items() if spec.get("profiles")] == ["report"]


def test_router_is_the_official_image_at_the_python_package_version(services: dict[str, dict]) -> None:
    router = services["router"]
    assert router["image"] == f"eclipse/zenoh:{importlib.metadata.version('eclipse-zenoh')}"
    assert "build" not in router
    command = router["command"]
    unknown = set(options_in(command)) - ZENOHD_FLAGS
    assert not unknown, f"zenohd has no option(s) {sorted(unknown)}"
    listen = parse_endpoints(command[command.index("--listen") + 1])
    assert listen == ("tls/0.0.0.0:7447",), "a published router listens with TLS only"
    assert command[command.index("--config") + 1] == "/secure/router-zenohd.json5"
    assert router["depends_on"]["secure"]["condition"] == "service_completed_successfully"
    assert "--no-multicast-scouting" in command
    # The listening port is published, so actors on other machines can connect.
    published = {str(p).rsplit(":", 1)[-1] for p in router["ports"]}
    assert "7447" in published


def test_project_services_connect_to_the_router_as_clients(services: dict[str, dict]) -> None:
    router_port = services["router"]["command"][services["router"]["command"].index("--listen") + 1]
    router_port = router_port.rsplit(":", 1)[1]
    for name in PROJECT_SERVICES:
        env = service_env(services[name])
        settings = ZenohSettings.from_env(env)  # the project's own parser validates the values
        assert settings.effective_mode == "client", name
        assert settings.effective_connect == (f"tls/router:{router_port}",), name
        command = services[name]["command"]
        assert command[command.index("--zenoh-config") + 1] == f"/secure/{name}.json5", name
        assert "router" in services[name].get("depends_on", []), name


def test_every_service_environment_variable_is_set(services: dict[str, dict]) -> None:
    for name in PROJECT_SERVICES:
        env = service_env(services[name])
        missing = [v for v in SERVICE_ENV if v not in env]
        assert not missing, f"{name} lacks {missing}"
        known = SERVICE_ENV + EXTRA_ENV + (ACTOR_ENV if name == "actor" else ())
        unknown = [v for v in env if v.startswith("COGEXPLORE_") and v not in known]
        assert not unknown, f"{name} sets unknown variables {unknown} (a typo?)"
        assert env["RERUN_ANALYTICS"] == "0" and env["MUJOCO_GL"] == "egl", name
        assert env["COGEXPLORE_RUN"], name
        # no preset named twice: the learner's default, and the actors and the evaluator take the learner's
        assert env["COGEXPLORE_PRESET"] == "", name
    runs = {service_env(services[n])["COGEXPLORE_RUN"] for n in PROJECT_SERVICES}
    assert len(runs) == 1, f"services disagree on the run name: {runs}"


def test_actor_scales(services: dict[str, dict]) -> None:
    actor = services["actor"]
    # `--scale actor=N` fails on a fixed container name or host port; a fixed hostname would give
    # every replica the same default actor id (hostname + pid, and pids repeat across containers).
    for key in ("container_name", "ports", "hostname"):
        assert key not in actor, f"actor sets {key}: it cannot scale"
    assert "--actor-id" not in actor["command"]


def test_scaled_actors_are_told_the_fleet_size(services: dict[str, dict], monkeypatch) -> None:
    """`up --actors N` passes --num-actors N; compose cannot, so every replica reads the size from
    COGEXPLORE_NUM_ACTORS, which the user sets beside --scale (its epsilon decays over the fleet's
    steps, an Ape-X schedule spreads over N, each builds 1/N of the extra worlds)."""
    from services.cli import build_parser

    raw = yaml.safe_load(COMPOSE_FILE.read_text())["services"]["actor"]["environment"]
    assert raw["COGEXPLORE_NUM_ACTORS"] == "${COGEXPLORE_NUM_ACTORS:-1}"  # what the user sets reaches the actors
    actor = services["actor"]
    assert "--num-actors" not in actor["command"]  # an option would win over the variable
    for name in ("learner", "evaluator"):
        assert "COGEXPLORE_NUM_ACTORS" not in service_env(services[name]), name
    env = service_env(actor)
    # the merge left the shared environment whole
    assert {k: v for k, v in env.items() if k != "COGEXPLORE_NUM_ACTORS"} == service_env(services["learner"])
    for key, value in env.items():  # the container's environment, with compose's default
        monkeypatch.setenv(key, value)
    assert build_parser().parse_args(actor["command"][1:]).num_actors == 1
    monkeypatch.setenv("COGEXPLORE_NUM_ACTORS", "4")  # COGEXPLORE_NUM_ACTORS=4 docker compose up --scale actor=4
    args = build_parser().parse_args(actor["command"][1:])
    assert args.num_actors == 4 and args.actor_index is None
    # wherever the project shows how to scale the actors, it sets the size to the same N
    shown = 0
    for doc in (COMPOSE_FILE, ROOT / "README.md", ROOT / "docs" / "distributed.md"):
        for line in doc.read_text().splitlines():
            for n in re.findall(r"--scale actor=(\d+)", line):
                if "docker compose" in line:
                    shown += 1
                    assert f"COGEXPLORE_NUM_ACTORS={n} " in line, f"{doc.name}: {line.strip()}"
    assert shown >= 3


def test_image_services_share_one_image_and_build(services: dict[str, dict]) -> None:
    images = {services[n].get("image") for n in IMAGE_SERVICES}
    builds = {repr(services[n].get("build")) for n in IMAGE_SERVICES}
    assert len(images) == 1 and None not in images, images
    assert len(builds) == 1, builds
    build = services["learner"]["build"]
    context = build if isinstance(build, str) else build["context"]
    assert (ROOT / context).resolve() == ROOT
    assert (ROOT / (build.get("dockerfile", "Dockerfile") if isinstance(build, dict) else "Dockerfile")).is_file()


def test_runs_directory_is_on_a_volume(services: dict[str, dict]) -> None:
    for name in PROJECT_SERVICES:
        runs_dir = service_env(services[name])["COGEXPLORE_RUNS_DIR"]
        targets = []
        for volume in services[name].get("volumes", []):
            if isinstance(volume, dict):
                targets.append(volume["target"])
            else:
                targets.append(volume.split(":")[1])
        assert runs_dir in targets, f"{name}: {runs_dir} (COGEXPLORE_RUNS_DIR) is not mounted"


# -- commands start -------------------------------------------------------------------------

def _contract_case(sub: str) -> object:
    marks = [pytest.mark.xfail(strict=False, reason="lands with the services")] if sub in LANDS_LATER else []
    return pytest.param(sub, marks=marks, id=sub)


@pytest.mark.parametrize("subcommand", [_contract_case(s) for s in CLI_CONTRACT])
def test_cli_subcommand_offers_the_contract_options(subcommand: str) -> None:
    text = run_help(cogexplore_argv([subcommand]))
    missing = [o for o in CLI_CONTRACT[subcommand] if o not in text]
    assert not missing, f"`cogexplore {subcommand} --help` lacks {missing}"


@pytest.mark.parametrize("service", [_contract_case(s) for s in PROJECT_SERVICES])
def test_service_command_starts(services: dict[str, dict], service: str) -> None:
    spec = services[service]
    command = spec["command"]
    assert isinstance(command, list) and command[0] == "cogexplore", command
    # Started with the service's own environment, so env-var defaults are parsed as in the container.
    text = run_help(cogexplore_argv(command[1:]), service_env(spec))
    missing = [o for o in options_in(command) if o not in text]
    assert not missing, f"`{' '.join(command)}`: options {missing} are not in its --help"
    if service in RERUN_ENV_READERS:  # the variable the compose file sets is one the service reads
        assert "--rerun-connect" in text and "COGEXPLORE_RERUN_URL" in text, service


def test_rerun_viewer_command_starts(services: dict[str, dict]) -> None:
    command = services["rerun"]["command"]
    assert command[0] == "rerun" and "--serve-web" in command
    text = run_help([str(VENV_BIN / "rerun"), *command[1:]])
    missing = [o for o in options_in(command) if o not in text]
    assert not missing, f"rerun {importlib.metadata.version('rerun-sdk')} has no option(s) {missing}"
    for flag in ("--port", "--web-viewer-port"):
        assert command[command.index(flag) + 1] in {str(p).rsplit(":", 1)[-1] for p in services["rerun"]["ports"]}
    # The evaluator streams to the viewer's gRPC port.
    url = service_env(services["evaluator"])["COGEXPLORE_RERUN_URL"]
    assert url == f"rerun+http://rerun:{command[command.index('--port') + 1]}/proxy"


USER_SETTINGS = {
    "COGEXPLORE_RUN": "exp1",
    "COGEXPLORE_PRESET": "paper",
    "COGEXPLORE_DEVICE": "auto",
    "COGEXPLORE_EVAL_EVERY_UPDATES": "250",
    "COGEXPLORE_NUM_ACTORS": "3",
    "COGEXPLORE_RERUN_EVERY_EPISODES": "50",
    "COGEXPLORE_ZENOH_ROUTER_WAIT_S": "45",
}
"""Settings a user gives compose (shell or .env; docs/distributed.md's table), none at its default."""


@pytest.mark.parametrize("variables", [{}, USER_SETTINGS], ids=["defaults", "user-settings"])
def test_service_commands_parse_and_take_the_user_s_settings(variables: dict[str, str],
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """Each `cogexplore` command of the compose file, in its container's environment, through the
    real parser: every argument is one the CLI takes, every variable converts, and each setting the
    user gives compose reaches the option it stands for."""
    services = compose_services(variables=variables)
    run = variables.get("COGEXPLORE_RUN", "compose")
    secure = parse_command(services["secure"]["command"], service_env(services["secure"]), monkeypatch)
    assert secure._command == "secure init" and secure.run == run and secure.dir == "/secure"
    parsed = {}
    for name in PROJECT_SERVICES:
        env = service_env(services[name])
        args = parsed[name] = parse_command(services[name]["command"], env, monkeypatch)
        assert args._command == name
        assert (args.run, args.runs_dir) == (run, "/app/runs"), name
        assert args.preset == variables.get("COGEXPLORE_PRESET"), name
        assert args.device == variables.get("COGEXPLORE_DEVICE", "cpu"), name
        assert args.tensorboard, name
        wait = ZenohSettings.from_env(env).router_wait_s
        assert wait == float(variables.get("COGEXPLORE_ZENOH_ROUTER_WAIT_S", DEFAULT_ROUTER_WAIT_S)), name
    assert parsed["evaluator"].every_updates == int(variables.get("COGEXPLORE_EVAL_EVERY_UPDATES", 1000))
    assert parsed["actor"].num_actors == int(variables.get("COGEXPLORE_NUM_ACTORS", 1))
    assert parsed["actor"].rerun_every_episodes == int(variables.get("COGEXPLORE_RERUN_EVERY_EPISODES", 20))
    for name in RERUN_ENV_READERS:
        assert parsed[name].rerun_connect == "rerun+http://rerun:9876/proxy", name


def test_a_command_the_cli_refuses_fails_the_parse(monkeypatch: pytest.MonkeyPatch) -> None:
    """What the `--help` check lets through (it exits before leftovers and env defaults are looked at)."""
    for argv, env in ((["cogexplore", "learner", "--tensorboard", "yes"], {}),
                      (["cogexplore", "actor"], {"COGEXPLORE_NUM_ACTORS": "four"})):
        with pytest.raises(pytest.fail.Exception, match="the CLI refuses it"):
            parse_command(argv, env, monkeypatch)


SAME_BY_DESIGN = {
    "runs_dir": "the container's mount of the host's runs folder (test_runs_directory_is_on_a_volume)",
    "preset": "up names the config.toml it saved in the run; compose's learner reads that file itself (else the "
              "default preset, which up saves too) and the actors and the evaluator ask the learner for it",
    "connect": "the router's address from each side: up's loopback port, compose's router service "
               "(test_project_services_connect_to_the_router_as_clients)",
    "actor_id": "replicas cannot be named: the id defaults to the container's hostname + pid (test_actor_scales)",
    "actor_index": "replicas cannot be numbered: the index defaults to a hash of the id (test_actor_scales)",
}
"""Options in which `up`'s services and compose's differ on purpose, and why."""
ZENOH_OPTIONS = ("zenoh_mode", "zenoh_config", "listen", "router_wait")
"""Compared as the session each ends up with: compose sets them by variable, up by option."""


def test_up_starts_the_services_of_the_compose_file_with_the_same_options(
        services: dict[str, dict], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The local twin: every option `cogexplore up` gives a service (services.up.launcher.Launcher.service_argvs),
    parsed by the real CLI, equals what compose's service parses to in its container, but for
    SAME_BY_DESIGN; an option added to one side and not the other fails here."""
    from services.bus import ENV_LISTEN, ENV_ROUTER_WAIT
    from services.cli import build_parser
    from services.up.launcher import Launcher

    for key in [k for k in os.environ if k.startswith("COGEXPLORE_")]:
        monkeypatch.delenv(key)
    rerun_url = service_env(services["evaluator"])["COGEXPLORE_RERUN_URL"]
    # up as compose runs by default: its run name, CPU, 2 actors (COGEXPLORE_NUM_ACTORS=2 --scale actor=2), a viewer
    launcher = Launcher(build_parser().parse_args(["up", "--run", "compose", "--runs-dir", str(tmp_path), "--actors",
                                                   "2", "--device", "cpu", "--rerun-connect", rerun_url]))
    try:
        started = launcher.service_argvs()
        up_env = launcher.service_environment()
    finally:
        launcher.close()
    compose = compose_services(variables={"COGEXPLORE_NUM_ACTORS": "2"})
    assert [role for role, _, _ in started] == ["router", "learner", "actor", "actor", "evaluator"]
    assert {role for role, _, _ in started} == {"router", *PROJECT_SERVICES}
    for role, name, argv in started[1:]:
        ours = vars(parse_command(["cogexplore", *argv], up_env, monkeypatch))
        if role != "learner" and ours["device"] is None:
            ours["device"] = "cpu"  # without --device an actor or the evaluator reads auto: the CPU (resolve_config)
        env = service_env(compose[role])
        theirs = vars(parse_command(compose[role]["command"], env, monkeypatch))
        differ = {k: (ours.get(k), theirs.get(k)) for k in ours.keys() | theirs.keys()
                  if ours.get(k) != theirs.get(k) and k not in SAME_BY_DESIGN and k not in ZENOH_OPTIONS}
        assert not differ, f"{name}: (up, compose) differ in {differ}: make them alike, or say why in SAME_BY_DESIGN"
        # the same session: a client with its role's credentials of the run's folder, no listener, the same wait
        assert ours["zenoh_mode"] == env["COGEXPLORE_ZENOH_MODE"] == "client", name
        assert Path(ours["zenoh_config"]).name == Path(theirs["zenoh_config"]).name == f"{role}.json5", name
        assert ours["listen"] is theirs["listen"] is None and not up_env.get(ENV_LISTEN) and not env[ENV_LISTEN]
        up_wait = ours["router_wait"] or float(up_env.get(ENV_ROUTER_WAIT) or DEFAULT_ROUTER_WAIT_S)
        assert up_wait == float(theirs["router_wait"] or env[ENV_ROUTER_WAIT]), name
    # what up adds to its services' environment, the containers have too (the compose file or the image)
    image_env = {}
    for word, rest in dockerfile_instructions():
        if word == "ENV":
            image_env.update(item.split("=", 1) for item in rest.split())
    added = {k: v for k, v in up_env.items() if os.environ.get(k) != v}
    for name in PROJECT_SERVICES:
        container = {**image_env, **service_env(compose[name])}
        missing = {k: v for k, v in added.items() if container.get(k) != v}
        assert not missing, f"{name}: up's services get {missing}, the container not"


FINAL_REPORT = re.compile(r"`(docker compose run [^`]*)`")


def test_the_final_report_of_a_compose_run_is_up_s_without_training(services: dict[str, dict], tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    """Compose's final evaluation and report is its `report` service, which the README shows how to run:
    `up --report-only` on the compose run's folder, as the `secure` service leaves it (TLS,
    certificates for the router service). It parses there, with the image's offline environment,
    and reaches the run folder (with no trained checkpoint yet: refused in one line)."""
    from services.cli import main
    from tests.services.up.test_resume import run_at

    shown = FINAL_REPORT.findall((ROOT / "README.md").read_text())
    assert shown == ["docker compose run --rm report"], shown
    spec = services["report"]
    env = service_env(spec)
    assert env["RERUN_ANALYTICS"] == "0" and env["COGEXPLORE_RUNS_DIR"] == "/app/runs"
    # the worlds the services generated, not each again at every report
    assert env[CACHE_DIR_ENV] == service_env(services["actor"])[CACHE_DIR_ENV]
    assert {"router", "learner"}.isdisjoint(spec.get("depends_on", [])), "it trains nothing and needs no router"
    assert [v for v in spec["volumes"] if v.endswith(":/app/runs")], "the runs folder the learner writes"
    args = parse_command(spec["command"], env, monkeypatch)
    assert args._command == "up" and args.report_only and args.runs_dir == "/app/runs"
    assert args.run == service_env(services["learner"])["COGEXPLORE_RUN"], "the compose run's name"
    assert args.final_episodes == 10 and args.final_average == 4, "the paper's ten episodes, up's final model"

    run_at(tmp_path / "made", updates=0, total_updates=20)  # a learner stopped in its warm-up
    (tmp_path / "made" / "again").rename(tmp_path / args.run)
    secure = [str(tmp_path / args.run / "secure") if a == "/secure" else a for a in services["secure"]["command"]]
    assert main(secure[1:]) == 0
    assert main([*spec["command"][1:], "--runs-dir", str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"--report-only: run {args.run!r} has no trained checkpoint yet" in err, err


# -- Dockerfile and build context --------------------------------------------------------------

def dockerfile_instructions() -> list[tuple[str, str]]:
    text = DOCKERFILE.read_text().replace("\\\n", " ")
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def test_dockerfile_builds_the_cpu_image() -> None:
    steps = dockerfile_instructions()
    assert steps[0] == ("FROM", "python:3.11-slim")
    runs = " ".join(rest for word, rest in steps if word == "RUN")
    # torch comes from scripts/install_torch.py (tests/scripts), the CPU variant unless asked
    assert ("ARG", "TORCH_VARIANT=cpu") in steps
    assert 'install_torch.py --variant "$TORCH_VARIANT"' in runs
    torch_pin = importlib.metadata.version("torch").split("+")[0]
    script = (ROOT / "scripts" / "install_torch.py").read_text()
    assert f'TORCH_PIN = "torch=={torch_pin}"' in script
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert f'"torch=={torch_pin}"' in pyproject, "the install script's torch differs from pyproject's pin"
    assert "pip install ." in runs
    assert runs.index("install_torch.py") < runs.index("pip install ."), "torch must be installed first"
    env = " ".join(rest for word, rest in steps if word == "ENV")
    assert "RERUN_ANALYTICS=0" in env.split() and "MUJOCO_GL=egl" in env.split()


def test_the_dependency_layer_copies_every_file_the_project_metadata_names() -> None:
    """The first `pip install .` builds the project's metadata from what was copied before it: the
    readme and the license files pyproject names. A license pattern that matches nothing warns today
    and is a setuptools error from 2027-02-18 (the image would no longer build)."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    steps = dockerfile_instructions()
    first_install = next(i for i, (word, rest) in enumerate(steps) if word == "RUN" and "pip install ." in rest)
    copied = {src for word, rest in steps[:first_install] if word == "COPY" for src in rest.split()[:-1]}
    named = {project["readme"], *project.get("license-files", [])}
    assert named <= copied, f"copied before `pip install .`: {sorted(copied)}; the metadata names {sorted(named)}"


def test_build_context_excludes_host_state_and_keeps_sources() -> None:
    ignored = {line.strip().rstrip("/") for line in DOCKERIGNORE.read_text().splitlines()
               if line.strip() and not line.startswith("#")}
    for heavy in (".git", ".venv", "runs"):
        assert heavy in ignored, f".dockerignore must exclude {heavy}"
    for word, rest in dockerfile_instructions():
        if word == "COPY" and not rest.startswith("--from"):
            for src in rest.split()[:-1]:
                if src != ".":
                    assert (ROOT / src).exists() and src not in ignored, f"COPY {src}: not in the context"
    for package in ("shared", "services"):
        assert package not in ignored


def test_the_secure_service_writes_what_the_router_and_every_service_read(services: dict[str, dict],
                                                                           tmp_path: Path) -> None:
    """The one-shot `secure` command, run for real into a folder standing for /secure: the router's
    zenohd config names files under /secure that it wrote, every service's --zenoh-config is one of
    its files, and a second start keeps them (--keep)."""
    import json

    command = services["secure"]["command"]
    assert command[:4] == ["cogexplore", "secure", "init", "/secure"] and "--tls" in command and "--keep" in command
    argv = [tmp_path / "secure" if a == "/secure" else a for a in command[1:]]
    for attempt in range(2):
        proc = subprocess.run(cogexplore_argv([str(a) for a in argv]), capture_output=True, text=True, timeout=120,
                              cwd=ROOT, env=dict(os.environ, RERUN_ANALYTICS="0"))
        assert proc.returncode == 0, proc.stderr
        if attempt == 0:
            first = (tmp_path / "secure" / "credentials.json").read_text()
    assert (tmp_path / "secure" / "credentials.json").read_text() == first, "--keep kept the credentials"
    zenohd = json.loads((tmp_path / "secure" / "router-zenohd.json5").read_text())
    named = [zenohd["transport"]["auth"]["usrpwd"]["dictionary_file"],
             *(v for k, v in zenohd["transport"]["link"]["tls"].items() if isinstance(v, str))]
    assert all(n.startswith("/secure/") and (tmp_path / "secure" / n.removeprefix("/secure/")).is_file()
               for n in named), named
    assert zenohd["access_control"]["default_permission"] == "deny"
    for name in PROJECT_SERVICES:
        role_config = services[name]["command"][services[name]["command"].index("--zenoh-config") + 1]
        assert (tmp_path / "secure" / role_config.removeprefix("/secure/")).is_file(), name
        mounts = [v.split(":")[1] for v in services[name]["volumes"] if isinstance(v, str)]
        assert "/secure" in mounts, name


# -- the robot example ----------------------------------------------------------------------

ROBOT_COMPOSE_FILE = ROOT / "docker-compose.robot.yml"


def test_the_robot_compose_file_is_valid_and_its_commands_start(tmp_path: Path) -> None:
    exe = compose_binary()
    env = {k: v for k, v in os.environ.items() if k not in ("ROBOT_ROUTER", "ROS2_FORMAT", "DEPTH_TOPIC")}
    proc = subprocess.run([exe, "-f", str(ROBOT_COMPOSE_FILE), "--profile", "sim", "config"], capture_output=True,
                          text=True, env=env, cwd=ROOT, timeout=120)
    if proc.returncode != 0 and "profile" in proc.stderr and "no such option" in proc.stderr.lower():
        pytest.skip(f"this docker-compose has no --profile: {proc.stderr.strip()}")
    assert proc.returncode == 0, f"docker-compose config rejected the file:\n{proc.stderr}"
    services = yaml.safe_load(proc.stdout)["services"]
    assert {"drive", "sim-robot", "robot-router"} <= set(services)
    for name in ("drive", "sim-robot"):
        command = services[name]["command"]
        assert command[0] == "cogexplore"
        text = run_help(cogexplore_argv(command[1:]))
        missing = [o for o in options_in(command) if o not in text]
        assert not missing, f"`{' '.join(command)}`: options {missing} are not in its --help"
        # both sides of the example meet at one router, in one wire format
        assert command[command.index("--connect") + 1] == "tcp/robot-router:7447"
        assert command[command.index("--ros2-format") + 1] == "rmw_zenoh"
    assert services["robot-router"]["image"] == yaml.safe_load(COMPOSE_FILE.read_text())["services"]["router"]["image"]


ROBOT_SETTINGS = {"ROBOT_ROUTER": "tcp/192.168.1.42:7447", "ROS2_FORMAT": "ros2dds", "ROS_DOMAIN_ID": "7",
                  "ROBOT_NAMESPACE": "/tb4", "DEPTH_TOPIC": "oakd/stereo/image_raw",
                  "COGEXPLORE_CHECKPOINT": "pretrained:sl"}
"""The robot example's settings (its header), none at its default."""


@pytest.mark.parametrize("variables", [{}, ROBOT_SETTINGS], ids=["defaults", "user-settings"])
def test_the_robot_compose_commands_parse_and_take_the_user_s_settings(variables: dict[str, str],
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    services = compose_services(ROBOT_COMPOSE_FILE, variables)
    for name in ("drive", "sim-robot"):
        env = service_env(services[name])
        assert env["RERUN_ANALYTICS"] == "0", name
        args = parse_command(services[name]["command"], env, monkeypatch)
        assert args._command == name
        assert args.ros2_format == variables.get("ROS2_FORMAT", "rmw_zenoh"), name
        assert args.domain_id == int(variables.get("ROS_DOMAIN_ID", 0)), name
        assert args.namespace == variables.get("ROBOT_NAMESPACE", "/"), name
        assert args.image_topic == variables.get("DEPTH_TOPIC", "camera/depth/image_raw"), name
    drive = parse_command(services["drive"]["command"], service_env(services["drive"]), monkeypatch)
    assert drive.connect == [variables.get("ROBOT_ROUTER", "tcp/robot-router:7447")]
    assert drive.checkpoint == variables.get("COGEXPLORE_CHECKPOINT", "pretrained")
