"""``cogexplore.__version__``: the installed distribution's, else the source tree's pyproject.toml."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import cogexplore

REPO = Path(__file__).resolve().parents[2]


def test_the_version_is_the_distribution_s_and_the_source_tree_s(tmp_path: Path) -> None:
    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    assert cogexplore.__version__ == metadata.version("cogexplore") == declared
    # A source tree that was never installed (a copy, run without site-packages): pyproject.toml answers.
    shutil.copytree(REPO / "cogexplore", tmp_path / "cogexplore", ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "shared").mkdir()
    for name in ("__init__.py", "errors.py"):
        shutil.copy(REPO / "shared" / name, tmp_path / "shared" / name)
    (tmp_path / "pyproject.toml").write_text('[project]\nname = "cogexplore"\nversion = "9.8.7"\n')
    script = ("import cogexplore, importlib.metadata as m, sys\n"
              "try:\n    m.version('cogexplore'); sys.exit('an installed distribution is visible')\n"
              "except m.PackageNotFoundError:\n    print(cogexplore.__version__)")
    proc = subprocess.run([sys.executable, "-S", "-c", script], cwd=tmp_path, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "9.8.7"
    (tmp_path / "pyproject.toml").unlink()
    proc = subprocess.run([sys.executable, "-S", "-c", script], cwd=tmp_path, capture_output=True, text=True,
                          timeout=60)
    assert proc.stdout.strip() == "0+unknown", proc.stderr
