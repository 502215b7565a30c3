"""``runs/<run>/stats/eval.jsonl``: the evaluator service's periodic evaluations, one JSON line each.

The evaluator writes it (``services.evaluator.service``) and reads it back at start-up to skip
weights it has evaluated already; the report draws its evaluation curve from it. A line may be
damaged (a killed evaluator cuts its last row short) or hand-edited: readers skip such rows.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from shared.config import ConfigError, is_finite_number, is_whole
from shared.errors import CogexploreError
from shared.evaluation import ProtocolConfig
from shared.evaluation.protocol import WORLD_META
from shared.jsontext import parse_json

EVAL_LOG = "eval.jsonl"
"""The file's name in a run's ``stats/`` folder."""

EVALUATION_KEY_FIELDS: tuple[str, ...] = ("policy_version", "weights_sha256", "world", "protocol",
                                          "protocol_config", "episodes_per_start", "max_steps", "seed")
"""What makes two rows the same evaluation: the same weights at the same version, played under the
same protocol, episodes and seed (the protocol's draws come from the seed, so it repeats exactly).
``protocol_config`` is the protocol's every field: its name alone is ``custom`` for any overridden set.
A row of an MJCF file world holds its content's digest too (:data:`WORLD_META`, from
``shared.evaluation.protocol.file_world_sha256``), and its key ends with it: a file edited since is
another world under the same name."""

log = logging.getLogger("cogexplore.eval_log")


def eval_log_row(line: str) -> dict[str, Any] | None:
    """One row of ``eval.jsonl`` if it is one the evaluator could have written, else None."""
    try:
        row = parse_json(line, "an eval.jsonl row", allow_nan=False)
    except CogexploreError:
        return None

    def count(value: Any, least: int) -> bool:
        return is_whole(value) and value >= least

    if not (isinstance(row, dict) and count(row.get("policy_version"), 0) and row["policy_version"] < 2**63
            and isinstance(row.get("summary"), dict)):
        return None
    mean_steps = row["summary"].get("mean_steps")
    if not (is_finite_number(mean_steps) and mean_steps >= 0):
        return None
    if not all(row.get(k) is None or count(row[k], 1) for k in ("episodes_per_start", "max_steps")):
        return None
    return row if isinstance(row.get("protocol", "paper"), str) else None


def row_protocol(row: Mapping[str, Any]) -> ProtocolConfig | None:
    """The protocol a row recorded every field of (``protocol_config``, under its ``protocol`` name);
    None for a row from before the evaluator recorded them, or one whose fields are not this
    version's protocol fields (the row is still read: only its protocol's settings are unknown)."""
    try:
        config = ProtocolConfig.from_dict(row["protocol_config"])
    except (KeyError, ConfigError):
        return None
    return config if config.name == row.get("protocol", "paper") else None


def load_eval_log(path: Path) -> list[dict[str, Any]]:
    """The evaluator service's ``eval.jsonl`` rows, sorted by version; a damaged or forged row (not
    JSON, NaN, a negative version, a count that is not one) is skipped with a warning."""
    rows, skipped = [], 0
    for line in path.read_text(errors="replace").splitlines():
        if line.strip():
            row = eval_log_row(line)
            rows += [row] if row is not None else []
            skipped += row is None
    if skipped:
        log.warning("%s: %d row(s) skipped: not an evaluation the evaluator writes", path, skipped)
    return sorted(rows, key=lambda r: r["policy_version"])


def evaluation_key(row: dict[str, Any]) -> tuple[Any, ...] | None:
    """The row's :data:`EVALUATION_KEY_FIELDS` (and its world's digest, where it has one), or None for a
    row that does not name its weights (written before the evaluator recorded their digest): such a row
    never stands for another."""
    # only where recorded: a built-in world's key, and so its files' names, are what they were before it
    fields = EVALUATION_KEY_FIELDS + ((WORLD_META,) if row.get(WORLD_META) is not None else ())
    # an object as canonical text: hashable, and equal whatever order its fields were written in
    key = tuple(json.dumps(v, sort_keys=True) if isinstance(v, Mapping) else v for v in (row.get(k) for k in fields))
    if not isinstance(row.get("weights_sha256"), str) or not all(v is None or isinstance(v, (str, int)) for v in key):
        return None
    return key


def evaluation_digest(key: tuple[Any, ...]) -> str:
    """The SHA-256 (hex) of an :func:`evaluation_key`: one evaluation's name, whatever its version shares."""
    return hashlib.sha256(json.dumps(key).encode()).hexdigest()
