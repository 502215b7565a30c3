"""The statistics files as named records: columns from the fields, one writer, cells by format; the
same rows as TensorBoard scalars, read back with TensorBoard's own reader."""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import pytest

from shared.learning.stats import (
    CsvLog,
    EpisodeRow,
    LearnerRow,
    TensorBoardLog,
    read_csv,
    read_csv_records,
    rewind,
    scalars,
    summarize_learner_log,
)


def row(**changes) -> LearnerRow:
    values = dict(time_s=1.23456, update=50, policy_version=50, loss=0.5, mean_q=None, updates_per_s=2.0,
                  transitions=700, transitions_per_s=None, replay_size=700, rejected=0, actors_alive=1,
                  mean_weight_lag=0.0, label_agreement=0.875, lr=5e-4, safe_agreement=0.75, session=7)
    values.update(changes)
    return LearnerRow(**values)


def test_columns_are_the_fields_in_order_and_return_keeps_its_name():
    assert LearnerRow.columns() == ("time_s", "update", "policy_version", "loss", "mean_q", "updates_per_s",
                                    "transitions", "transitions_per_s", "replay_size", "rejected", "actors_alive",
                                    "mean_weight_lag", "label_agreement", "lr", "safe_agreement", "session")
    assert EpisodeRow.columns()[5] == "return" and "episode_return" not in EpisodeRow.columns()


def test_a_log_writes_its_header_once_across_reopening_and_formats_each_cell(tmp_path: Path):
    with CsvLog(tmp_path, LearnerRow) as log:
        log.write(row())
    with CsvLog(tmp_path, LearnerRow) as log:  # a resumed run appends
        log.write(row(update=100, loss=None, label_agreement=None))
        with pytest.raises(TypeError, match="LearnerRow"):
            log.write(EpisodeRow(0, 0, 0, 0, 1, 1.0, 0.5, None, 0.0, 0.0, 0.0, 0, "box-room"))
    rows = list(csv.reader(open(tmp_path / "learner.csv", newline="")))
    assert rows[0] == list(LearnerRow.columns()) and len(rows) == 3
    first = dict(zip(rows[0], rows[1]))
    assert first["time_s"] == "1.235" and first["loss"] == "0.5" and first["mean_q"] == ""
    assert first["transitions_per_s"] == "" and first["label_agreement"] == "0.875"
    assert dict(zip(rows[0], rows[2]))["loss"] == "" and rows[2][1] == "100"


def test_a_learner_log_sums_its_sessions_and_skips_what_does_not_parse(tmp_path: Path):
    with CsvLog(tmp_path, LearnerRow) as log:  # a first session, 60 s to update 100
        log.write(row(time_s=0.5, update=0, lr=None))
        log.write(row(time_s=60.0, update=100, transitions=400, lr=5e-4))
    with CsvLog(tmp_path, LearnerRow) as log:  # resumed: the clock restarts, 40 s more to update 180
        log.write(row(time_s=40.0, update=180, transitions=720, lr=2e-4, session=8))
    with open(tmp_path / "learner.csv", "a") as fh:
        fh.write("41.0,19")  # a torn last line of a killed learner
    t = summarize_learner_log(tmp_path / "learner.csv")
    assert (t.updates, t.transitions, t.learner_s, t.lr_first, t.lr_last) == (180, 720, 100.0, 5e-4, 2e-4)
    assert t.updates_per_s == pytest.approx(1.8)
    # an older run's log: no time, no transitions, no learning rate
    (tmp_path / "old.csv").write_text("update,loss\n0,\n50,2.5\n")
    old = summarize_learner_log(tmp_path / "old.csv")
    assert (old.updates, old.transitions, old.learner_s, old.lr_first, old.updates_per_s) == (50, None, None, None, None)
    (tmp_path / "empty.csv").write_text("update,loss\n")
    assert summarize_learner_log(tmp_path / "empty.csv") is None
    # a damaged cell reads as none: the report printed "learning rate nan" and "nan min"
    (tmp_path / "nan.csv").write_text("time_s,update,lr\n10.0,50,0.001\nnan,60,inf\n")
    damaged = summarize_learner_log(tmp_path / "nan.csv")
    assert (damaged.updates, damaged.learner_s, damaged.lr_first, damaged.lr_last) == (60, 10.0, 0.001, 0.001)


def test_a_learner_log_tells_its_sessions_apart_by_their_mark_not_only_by_the_clock_going_back(tmp_path: Path):
    # A reviewer's three sessions of the trainer to updates 25, 30 and 40: the second's one row
    # (0.051 s) came before the third's (0.094 s), so the clock did not go back between them and
    # the second session's time was lost (9.176 s).
    path = tmp_path / "learner.csv"
    for session, (time_s, update) in enumerate([(9.082, 25), (0.051, 30), (0.094, 40)]):
        with CsvLog(tmp_path, LearnerRow) as log:
            log.write(row(time_s=time_s, update=update, session=session + 1))
    assert summarize_learner_log(path).learner_s == pytest.approx(9.227)
    # a session logs many rows; rows without a mark (a log from before it) go by the clock going back;
    # a killed writer's torn last row, its mark cut short or gone, is its session's, not a new one
    path.write_text("time_s,update,session\n5,10,\n2,20,\n3,30,\n0.5,40,91\n1.0,50,91\n1.5,55,9\n"
                    "0.75,60,10\n0.8,61,\n0.25,70,11\n")
    assert summarize_learner_log(path).learner_s == pytest.approx(5 + 3 + 1.5 + 0.8 + 0.25)


def test_an_older_log_resumed_takes_the_new_header_and_its_rows_still_read(tmp_path: Path):
    # Its header named no session: a resumed learner's marks were cells past it, dropped by every
    # reader, and its sessions were told apart by the clock alone (9.176 s here, not 9.227).
    path = tmp_path / "learner.csv"
    old = LearnerRow.columns()[:-2]  # before safe_agreement and session
    path.write_text(",".join(old) + "\n" + ",".join(row(time_s=1.0, update=20).cells()[:-2]) + "\n"
                    # appended under the old header by a writer that had safe_agreement: a cell past it
                    + ",".join(row(time_s=9.082, update=25).cells()[:-1]) + "\n9.5,2")
    for session, (time_s, update) in enumerate([(0.051, 30), (0.094, 40)]):
        with CsvLog(tmp_path, LearnerRow) as log:
            log.write(row(time_s=time_s, update=update, safe_agreement=None, session=session + 1))
    rows = list(read_csv(path))
    assert rows[0] == list(LearnerRow.columns()) and all(len(r) == len(rows[0]) for r in rows if r != ["9.5", "2"])
    assert rows[1][-2:] == ["", ""] and rows[2][-2:] == ["0.750", ""] and ["9.5", "2"] in rows  # torn: still short
    records = list(read_csv_records(path))
    assert [(r["update"], r["session"]) for r in records if None not in r.values()] == [
        ("20", ""), ("25", ""), ("30", "1"), ("40", "2")]
    t = summarize_learner_log(path)
    assert (t.updates, t.learner_s, t.lr_first) == (40, pytest.approx(9.227), 5e-4)
    before = path.read_bytes()
    CsvLog(tmp_path, LearnerRow).close()  # a log of today's columns is left as it is
    assert path.read_bytes() == before


def test_a_power_loss_tail_or_foreign_bytes_are_skipped_by_every_reader_and_resume_rewinds_past_them(
        tmp_path: Path):
    # A power loss can leave a file's tail as NUL bytes: one csv field past the csv module's
    # 128 KiB limit, which raised csv.Error out of the learner's resume (rewind) and the report.
    with CsvLog(tmp_path, LearnerRow) as log:
        for update in (50, 100, 150):
            log.write(row(time_s=update / 10, update=update))
    path = tmp_path / "learner.csv"
    clean = path.read_bytes()
    path.write_bytes(clean + b"\0" * 200_000 + b"\n" + b"\xff\xfe,\x80\n")
    rows = list(read_csv(path))
    assert rows[0] == list(LearnerRow.columns()) and [r[1] for r in rows[1:4]] == ["50", "100", "150"]
    assert len(rows) == 5 and "\ufffd" in rows[4][0]  # the NUL line skipped, foreign bytes replaced
    t = summarize_learner_log(path)
    assert (t.updates, t.learner_s) == (150, 15.0)
    # Resumed from the checkpoint at update 100: the rows after it go, and so does the damage.
    assert rewind(tmp_path, LearnerRow, 100) == 2  # update 150 and the foreign line (the NUL one was no row)
    assert path.read_bytes() == b"\n".join(clean.split(b"\n")[:3]) + b"\n"
    assert summarize_learner_log(path).updates == 100

    # The usual power loss: the checkpoint (fsynced) at the last readable row, the rows after it
    # NULs, with no newline. No row goes, but the damage must: the resumed learner's rows are
    # appended after it, and were read as part of it (lost) before.
    path.write_bytes(clean + b"\0" * 200_000)
    assert rewind(tmp_path, LearnerRow, 150) == 0 and path.read_bytes() == clean
    path.write_bytes(clean + b"\0" * 200_000)
    for update, torn in ((200, b""), (250, b"16.0,2")):  # NULs left alone; a killed learner's torn line
        path.write_bytes(path.read_bytes() + torn)
        with CsvLog(tmp_path, LearnerRow) as log:  # a resumed learner appends
            log.write(row(time_s=update / 10, update=update))
        assert summarize_learner_log(path).updates == update


def test_a_record_needs_every_column():
    with pytest.raises(TypeError):
        LearnerRow(time_s=0.0, update=1)  # type: ignore[call-arg]


def test_rows_become_scalars_tagged_by_file_and_column_at_their_step_column(tmp_path: Path, tensorboard_scalars):
    with TensorBoardLog(tmp_path / "tb" / "learner") as board:
        assert board.enabled
        board.write_row(row(update=10, mean_q=2.5))
        board.write_row(row(update=10, loss=9.0))  # the same update again: one point per step
        board.write_row(row(update=20, loss=0.25, label_agreement=None))
        board.write("eval", {"mean_steps": 12.5, "collisions": {"depth": 3}, "world": "box-room", "none": None}, 20)
    got = tensorboard_scalars(tmp_path / "tb" / "learner").tags
    numeric = {"time_s", "policy_version", "loss", "mean_q", "updates_per_s", "transitions", "replay_size",
               "rejected", "actors_alive", "mean_weight_lag", "label_agreement", "safe_agreement", "lr"}
    assert set(got) == {f"learner/{c}" for c in numeric} | {"eval/mean_steps", "eval/collisions/depth"}
    assert got["learner/loss"] == [(10, 0.5), (20, 0.25)]
    assert got["learner/mean_q"] == [(10, 2.5)]  # None at update 20: no point
    assert got["learner/label_agreement"] == [(10, 0.875)]
    assert got["learner/time_s"] == [(10, pytest.approx(1.23456)), (20, pytest.approx(1.23456))]
    assert got["eval/collisions/depth"] == [(20, 3.0)]


def test_scalars_flatten_mappings_and_keep_only_numbers():
    assert dict(scalars({"a": 1, "b": {"c": 2.5, "d": {"e": True}}, "f": "text", "g": None, "h": [1]})) == \
        {"a": 1.0, "b/c": 2.5, "b/d/e": 1.0}


def test_a_folder_that_cannot_be_made_turns_tensorboard_off_with_one_warning(tmp_path: Path, caplog):
    (tmp_path / "tb").write_text("a file where the folder should be")
    with caplog.at_level(logging.WARNING, logger="cogexplore.stats"), \
            TensorBoardLog(tmp_path / "tb" / "learner") as board:
        board.write_row(row())
        board.write_row(row(update=60))
    assert not board.enabled
    warnings = [r.getMessage() for r in caplog.records if r.name == "cogexplore.stats"]
    assert len(warnings) == 1 and "TensorBoard off" in warnings[0] and str(tmp_path / "tb") in warnings[0]
    assert TensorBoardLog(None).enabled is False


@pytest.mark.parametrize("left", [b"", b"\0" * 60], ids=["empty", "nul-bytes"])
def test_a_log_whose_header_a_power_loss_took_gets_one_again(tmp_path: Path, left: bytes):
    # A power loss right after a run's start can leave its log empty or NULs: the resumed learner's
    # rows were appended without a header, and every reader took the first row for the header.
    path = tmp_path / "learner.csv"
    path.write_bytes(left)
    assert rewind(tmp_path, LearnerRow, 0) == 0
    with CsvLog(tmp_path, LearnerRow) as log:
        log.write(row(time_s=2.0, update=20))
    t = summarize_learner_log(path)
    assert t is not None and (t.updates, t.learner_s) == (20, 2.0)
    assert [r for r in read_csv(path) if r][0] == list(LearnerRow.columns())
