"""Reading Rerun recordings back in tests (importable from any test: pytest puts tests/ on sys.path
for its conftest.py)."""

from __future__ import annotations

from pathlib import Path

from rerun.chunk import RrdReader


def recorded_protocol(path: Path) -> dict:
    """The recording's ``protocol`` property (what ``EvalRecorder.log_evaluation`` sends)."""
    for chunk in RrdReader(path).stream().to_chunks():
        if chunk.entity_path == "/__properties/protocol":
            row = chunk.to_record_batch().to_pylist()[0]
            return {k: v[0] for k, v in row.items() if k != "rerun.controls.RowId"}
    raise AssertionError(f"{path} has no protocol property")
