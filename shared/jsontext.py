"""JSON from a file or a file's metadata, read as untrusted input: one clear error for whatever is
malformed (bad UTF-8, bad syntax, an integer of thousands of digits, nesting deep enough to exhaust
the parser's recursion, a folder where a file should be), never a traceback."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from shared.errors import CogexploreError
from shared.files import MAX_READ_BYTES, read_regular_file

SMALL_JSON_BYTES = 4 * 2**20
"""The limit for a small JSON file (a model card, an experiment's state, a dataset's manifest): far
more than one holds, so that a big file handed in by mistake is refused before it is parsed."""


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text} is too large for a number")
    return value


def parse_json(data: str | bytes, what: str, error: type[CogexploreError] = CogexploreError, *,
               allow_nan: bool = True) -> Any:
    """``data`` decoded; ``error`` naming ``what`` when it is not JSON. ``allow_nan=False`` also
    refuses the NaN and Infinity that Python writes but JSON does not have (and 1e999, which
    Python reads as infinity)."""
    try:
        if allow_nan:
            return json.loads(data)
        return json.loads(data, parse_constant=_refuse_constant, parse_float=_finite_float)
    except RecursionError:
        raise error(f"{what} is not readable JSON: nested too deeply") from None
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, the int-digits limit, NaN refused
        raise error(f"{what} is not readable JSON: {exc}") from None


def read_json_file(path: Path | str, what: str, error: type[CogexploreError] = CogexploreError, *,
                   allow_nan: bool = True, max_bytes: int = MAX_READ_BYTES) -> Any:
    """The JSON document in ``path`` (see :func:`parse_json`); ``error`` when it cannot be read or is
    over ``max_bytes``."""
    path = Path(path)
    try:
        data = read_regular_file(path, max_bytes)
    except OSError as exc:
        raise error(f"{what} {path} cannot be read: {exc.strerror or exc}") from None
    return parse_json(data, f"{what} {path}", error, allow_nan=allow_nan)
