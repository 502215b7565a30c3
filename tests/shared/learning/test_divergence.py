"""A run's divergence record and the rate it resumes at (shared.learning.divergence)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from shared.learning.divergence import (
    DIVERGENCE_FILE,
    MAX_BACKOFFS,
    DivergenceStreakError,
    RunDivergences,
    read_streak,
    record_divergence,
    resume_lr,
    sets_lr,
)


def _streak(folder: Path, rates: list[float]) -> list:
    for i, lr in enumerate(rates):
        streak, written = record_divergence(folder, update=10 + i, resumed_from=8, lr=lr,
                                            cause=f"weight w{i}\nholds NaN")
        assert written
    return streak


def test_each_resume_after_a_divergence_halves_the_rate_until_the_streak_is_too_long(tmp_path: Path):
    assert resume_lr([], 1e-3) == (1e-3, None)
    rates = [1e-3]
    for n in range(1, MAX_BACKOFFS + 1):
        streak = _streak(tmp_path, rates[-1:])
        lr, why = resume_lr(streak, rates[-1])
        assert lr == pytest.approx(rates[-1] / 2) and f"divergence {n} in a row" in why
        # a preset's own rate (the first one) does not undo the halving; a lower one configured is kept
        assert resume_lr(streak, rates[0])[0] == pytest.approx(rates[-1] / 2)
        lower, why = resume_lr(streak, rates[-1] / 10)
        assert lower == pytest.approx(rates[-1] / 10) and "at its configured rate" in why and "below half" in why
        rates.append(lr)
    streak = _streak(tmp_path, rates[-1:])
    assert len(streak) == MAX_BACKOFFS + 1
    with pytest.raises(DivergenceStreakError, match=f"diverged {MAX_BACKOFFS + 1} times in a row"):
        resume_lr(streak, rates[-1])
    # a rate the user chose is kept as given, however long the streak, even the one it diverged at
    for given in (3e-5, rates[-1]):
        lr, why = resume_lr(streak, given, lr_given=True)
        assert lr == given and f"at the rate given, dqn.lr={given:g}" in why
    # the causes are kept on one line
    assert all("\n" not in d.cause for d in streak) and streak[0].cause == "weight w0 holds NaN"


@pytest.mark.parametrize("text", ["{", "[]", '{"divergences": []}', '{"divergences": [{"update": 1}]}',
                                  '{"divergences": [{"update": 5, "resumed_from": 9, "lr": 0.1, "cause": "", "at": 0}]}',
                                  '{"divergences": [{"update": 5, "resumed_from": 0, "lr": NaN, "cause": "", "at": 0}]}'])
def test_a_damaged_record_is_read_as_none(tmp_path: Path, text: str, caplog):
    (tmp_path / DIVERGENCE_FILE).write_text(text)
    assert read_streak(tmp_path) == [] and "ignored the divergence record" in caplog.text
    # and a divergence recorded over it starts a streak afresh, in a file that reads back
    assert len(record_divergence(tmp_path, update=3, resumed_from=2, lr=1e-3, cause="x")[0]) == 1
    assert len(json.loads((tmp_path / DIVERGENCE_FILE).read_text())["divergences"]) == 1


def test_a_checkpoint_past_every_divergence_ends_the_streak(tmp_path: Path):
    _streak(tmp_path, [1e-3, 5e-4])  # at updates 10 and 11
    record_divergence(tmp_path, update=9, resumed_from=8, lr=2.5e-4, cause="x")  # the last, at an earlier update
    divergences = RunDivergences(tmp_path)
    divergences.saved(10, 1.25e-4)  # past the last, not past 11
    assert (tmp_path / DIVERGENCE_FILE).exists() and len(divergences.streak) == 3
    divergences.saved(12, 1.25e-4)
    assert not (tmp_path / DIVERGENCE_FILE).exists() and divergences.streak == []
    assert RunDivergences(tmp_path).streak == []


def test_a_record_that_cannot_be_written_is_not_promised(tmp_path: Path):
    (tmp_path / DIVERGENCE_FILE).mkdir()  # the file's place taken: its write fails as a full disk's would
    said = RunDivergences(tmp_path).diverged(update=3, resumed_from=2, lr=1e-3, cause="x")
    assert said == f"{DIVERGENCE_FILE} could not be written: its next start resumes at the same rate"


def test_sets_lr_reads_the_commands_set_options():
    assert sets_lr(["dqn.lr=1e-4"]) and sets_lr(["train.seed=2", " dqn.lr = 5e-5"])
    assert not sets_lr([]) and not sets_lr(None) and not sets_lr(["dqn.lr_decay_updates=0"])
