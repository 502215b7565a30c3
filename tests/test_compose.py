"""docker-compose.yml, the Dockerfile and .dockerignore, checked without a Docker engine.

The compose file is validated against the Compose schema by Debian's ``docker-compose``
(Compose v1 validates with no engine), read structurally with PyYAML, and every command a
service runs is started with ``--help`` through this venv's ``cogexplore`` (or ``rerun``),
with each option the command passes checked against that help text.
"""

from __future__ import annotations

import importlib.metadata
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from services.bus.session import ZenohSettings, parse_endpoints

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
EXTRA_ENV = ("COGEXPLORE_RERUN_URL", "COGEXPLORE_RERUN_EVERY_EPISODES")
"""Also read by the services: where the evaluator and the actors stream to the Rerun viewer,
and which share of its episodes each actor streams."""
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


def interpolate(value: object) -> object:
    """Compose's ``${NAME:-default}`` interpolation with no variables set (the defaults)."""
    if isinstance(value, str):
        return _VAR.sub(lambda m: m.group(2) or "", value)
    if isinstance(value, list):
        return [interpolate(v) for v in value]
    if isinstance(value, dict):
        return {k: interpolate(v) for k, v in value.items()}
    return value


@pytest.fixture(scope="module")
def services() -> dict[str, dict]:
    doc = yaml.safe_load(COMPOSE_FILE.read_text())  # safe_load resolves the `<<:` merge keys
    assert isinstance(doc, dict) and "services" in doc, "docker-compose.yml has no services"
    return {name: interpolate(spec) for name, spec in doc["services"].items()}


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


# -- structure ------------------------------------------------------------------------------

def test_services_are_router_learner_actor_evaluator_and_viewer(services: dict[str, dict]) -> None:
    assert set(services) == {"router", *IMAGE_SERVICES}


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
