"""The statistics files as named records: columns from the fields, one writer, cells by format."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from shared.learning.stats import CsvLog, EpisodeRow, LearnerRow


def row(**changes) -> LearnerRow:
    values = dict(time_s=1.23456, update=50, policy_version=50, loss=0.5, mean_q=None, updates_per_s=2.0,
                  transitions=700, transitions_per_s=None, replay_size=700, rejected=0, actors_alive=1,
                  mean_weight_lag=0.0, demo_agreement=0.875)
    values.update(changes)
    return LearnerRow(**values)


def test_columns_are_the_fields_in_order_and_return_keeps_its_name():
    assert LearnerRow.columns() == ("time_s", "update", "policy_version", "loss", "mean_q", "updates_per_s",
                                    "transitions", "transitions_per_s", "replay_size", "rejected", "actors_alive",
                                    "mean_weight_lag", "demo_agreement")
    assert EpisodeRow.columns()[5] == "return" and "episode_return" not in EpisodeRow.columns()


def test_a_log_writes_its_header_once_across_reopening_and_formats_each_cell(tmp_path: Path):
    with CsvLog(tmp_path, LearnerRow) as log:
        log.write(row())
    with CsvLog(tmp_path, LearnerRow) as log:  # a resumed run appends
        log.write(row(update=100, loss=None, demo_agreement=None))
        with pytest.raises(TypeError, match="LearnerRow"):
            log.write(EpisodeRow(0, 0, 0, 0, 1, 1.0, 0.5, None, 0.0, 0.0, 0.0, 0, "box-room"))
    rows = list(csv.reader(open(tmp_path / "learner.csv", newline="")))
    assert rows[0] == list(LearnerRow.columns()) and len(rows) == 3
    first = dict(zip(rows[0], rows[1]))
    assert first["time_s"] == "1.235" and first["loss"] == "0.5" and first["mean_q"] == ""
    assert first["transitions_per_s"] == "" and first["demo_agreement"] == "0.875"
    assert dict(zip(rows[0], rows[2]))["loss"] == "" and rows[2][1] == "100"


def test_a_record_needs_every_column():
    with pytest.raises(TypeError):
        LearnerRow(time_s=0.0, update=1)  # type: ignore[call-arg]
