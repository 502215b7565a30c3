"""The package's version, readable without importing torch, MuJoCo or numpy."""

from __future__ import annotations

import re
from importlib import metadata
from pathlib import Path

DISTRIBUTION = "cogexplore"
PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


def package_version() -> str:
    """The installed distribution's version; from a source tree that was never installed, the
    version in ``pyproject.toml``; ``0+unknown`` when neither can be read."""
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        pass
    try:
        # A regex, not tomllib: the [project] table's version line is all that is needed.
        found = re.search(r'^version\s*=\s*"([^"]+)"', PYPROJECT.read_text(), re.MULTILINE)
    except OSError:
        found = None
    return found.group(1) if found else "0+unknown"


__version__ = package_version()
