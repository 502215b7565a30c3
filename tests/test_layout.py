"""The tree keeps its architecture: read from the source (``ast``), not from a running import.

- ``shared/`` is the pure layer: no module there imports Zenoh, Rerun, ``services`` or ``cogexplore``.
- ``cogexplore/`` (the public Python API) is as pure and sits on ``shared`` alone; importing it
  (and reading ``cogexplore.__version__``) loads none of numpy, torch, MuJoCo, Zenoh or Rerun.
- ``services/`` is made of rooms (the process shells ``actor``, ``learner``, ``evaluator``,
  ``router``, ``up`` and the offline ``tools`` and ``bench``) and homes every room may use: the bus
  (``services.bus``), the pictures (``services.viz``) and the top-level helpers (``options``,
  ``runs``, ``process``). A room imports no other room.
- There is no import cycle, counting imports inside functions and under ``TYPE_CHECKING``.
- Building the command line imports none of torch, MuJoCo, Zenoh or Rerun (a real interpreter).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "mujoco", "zenoh", "rerun")
ROOMS = ("actor", "learner", "evaluator", "router", "up", "tools", "bench", "drive", "sim_robot")
HOMES = ("bus", "viz")


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """Every module ``path`` imports anywhere in its body (``from a.b import c`` gives ``a.b`` and, when
    ``a.b.c`` is a module of ours, that too)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    modules = {_module_name(p): p for top in ("shared", "services", "cogexplore") for p in (REPO / top).rglob("*.py")}
    return {name: {m for m in _imports(path) if m in modules or m.split(".")[0] in HEAVY}
            for name, path in modules.items()}


def test_the_graph_sees_the_tree(graph: dict[str, set[str]]) -> None:
    # The checks below mean something only if the walk finds the modules and their imports.
    assert {"shared.config", "shared.rollout", "services.cli", "services.actor.service"} <= set(graph)
    assert "shared.sim.env" in graph["services.actor.service"]
    assert "zenoh" in graph["services.bus.session"] and "rerun" in graph["services.viz.rerun"]
    assert "shared.evaluation.setup" in graph["cogexplore.policy"]


def test_shared_is_the_pure_layer(graph: dict[str, set[str]]) -> None:
    bad = {m: sorted(i for i in imports if i.split(".")[0] in ("zenoh", "rerun", "services"))
           for m, imports in graph.items() if m.startswith("shared")}
    assert not {m: i for m, i in bad.items() if i}, "shared/ must not import Zenoh, Rerun or services/"
    upward = {m: sorted(i for i in imports if i.split(".")[0] == "cogexplore")
              for m, imports in graph.items() if m.startswith("shared")}
    assert not {m: i for m, i in upward.items() if i}, "shared/ must not import the API above it (cogexplore/)"


def test_the_python_api_sits_on_shared_alone(graph: dict[str, set[str]]) -> None:
    api = {m: imports for m, imports in graph.items() if m.split(".")[0] == "cogexplore"}
    assert {"cogexplore", "cogexplore.policy", "cogexplore.evaluation", "cogexplore.version"} <= set(api)
    bad = {m: sorted(i for i in imports if i.split(".")[0] not in ("shared", "cogexplore", "torch", "mujoco"))
           for m, imports in api.items()}
    assert not {m: i for m, i in bad.items() if i}, "cogexplore/ imports only shared/ (no Zenoh, Rerun, services/)"


def test_importing_the_python_api_loads_no_heavy_library() -> None:
    """The CLI reads ``cogexplore.__version__``: that must stay as cheap as ``cogexplore --help``."""
    script = f"""
import json, sys
import cogexplore
from cogexplore.version import package_version
assert cogexplore.__version__ == package_version() and "load_policy" in dir(cogexplore)
print(json.dumps(sorted(m for m in sys.modules if m.split(".")[0] in {HEAVY + ("numpy",)!r})))
"""
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == []


def _room(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "services" and len(parts) > 2 and parts[1] in ROOMS else None


def test_no_room_imports_another(graph: dict[str, set[str]]) -> None:
    crossings = []
    for module, imports in graph.items():
        room = _room(module)
        if not module.startswith("services.") or module == "services.cli":
            continue  # the CLI names every room's entry points as strings, importing none of them
        for target in imports:
            other = _room(target)
            if other is not None and other != room:
                crossings.append(f"{module} -> {target}")
            if room is None and other is not None:  # a home (bus, viz, helpers) serves the rooms, never the reverse
                crossings.append(f"{module} -> {target}")
    assert not crossings, "\n".join(sorted(crossings))


def test_there_is_no_import_cycle(graph: dict[str, set[str]]) -> None:
    nodes = {m: {i for i in imports if i in graph and i != m} for m, imports in graph.items()}
    # a package's __init__ is imported by each of its modules: an edge from a module to its own
    # package is how Python works, not a cycle of ours
    for m in nodes:
        nodes[m] = {i for i in nodes[m] if not m.startswith(i + ".")}
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in nodes[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(nodes):
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test_the_command_line_imports_no_heavy_library() -> None:
    """Every ``cogexplore ... --help`` in one fresh interpreter: none of torch, MuJoCo, Zenoh, Rerun loads."""
    script = f"""
import json, sys
from services.cli import COMMANDS, Command, build_parser
parser = build_parser()
paths = [[]] + [[n] for n in COMMANDS] + [[n, a] for n, e in COMMANDS.items() if not isinstance(e, Command)
                                          for a in e.actions]
for path in paths:
    try:
        parser.parse_args([*path, "--help"])
    except SystemExit:
        pass
print(json.dumps({{"helps": len(paths), "heavy": sorted(m for m in sys.modules if m.split(".")[0] in {HEAVY!r})}}))
"""
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["helps"] > 20 and result["heavy"] == []


def test_the_license_is_an_spdx_expression_with_its_file() -> None:
    """PEP 639: no deprecated license table (setuptools warns on every install), and the file ships."""
    import tomllib

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT" and project["license-files"] == ["LICENSE"]
    assert (REPO / "LICENSE").read_text().startswith("MIT License")


def test_a_bare_pytest_imports_the_project_not_the_tests_folders() -> None:
    """``pytest`` as a user types it (not ``python -m pytest``, which puts the repository first on the
    path): tests/shared/ once shadowed the project's ``shared`` and every test under it failed to import."""
    pytest_script = Path(sys.executable).with_name("pytest")
    if not pytest_script.is_file():
        pytest.skip(f"no pytest script beside {sys.executable}")
    test = "tests/shared/sim/test_train_jitter.py"
    run = subprocess.run([str(pytest_script), "-q", "-p", "no:cacheprovider", "--collect-only", test],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]  # 2: a collection error
