"""Bounds of the supervised pipeline: the training's epochs, the dataset's world index."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shared.expert.expert import SupervisedError
from shared.expert.dataset import DriveConfig, SupervisedDataset, generate_dataset
from shared.expert.supervised import MAX_EPOCHS, TrainSettings
from tests.shared.expert.test_expert import SMALL_SENSOR, TEST_ENV


@pytest.mark.parametrize("epochs", [MAX_EPOCHS + 1, 10**30, True, 0])
def test_epochs_past_the_bound_are_refused(epochs) -> None:
    # 10**30 epochs were taken: a training that never ends, with a count no JSON reader keeps exact in the card
    with pytest.raises(SupervisedError, match=rf"epochs must be an integer in \[1, {MAX_EPOCHS}\]"):
        TrainSettings(epochs=epochs)
    assert TrainSettings(epochs=MAX_EPOCHS).epochs == MAX_EPOCHS


@pytest.mark.timeout(120)  # the unbounded count trained for ever
def test_the_pretrain_command_refuses_huge_epochs_before_collecting(tmp_path, capsys) -> None:
    from services.cli import main

    out = tmp_path / "sl.safetensors"
    rc = main(["pretrain", "--worlds", "box-room", "--frames", "8", "--epochs", str(10**30), "--out", str(out),
               "--quiet", "--device", "cpu"])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and "epochs" in err and "Traceback" not in err and len(err.splitlines()) == 1
    assert not out.exists() and not any(tmp_path.iterdir())  # refused before any data was collected


def test_a_dataset_of_more_than_256_worlds_keeps_each_frames_world(tmp_path) -> None:
    # world 256's frames were stored as world 0 (a uint8 index wrapped)
    worlds = ["box-room"] * 257
    ds = generate_dataset(tmp_path / "d", worlds=worlds, frames=2 * len(worlds), sensor_cfg=SMALL_SENSOR,
                          env_cfg=TEST_ENV, drive_cfg=DriveConfig(episode_steps=2), seed=0, test_fraction=0.3,
                          progress=False)
    index = np.asarray(ds.worlds)
    np.testing.assert_array_equal(index, np.repeat(np.arange(len(worlds)), 2))
    assert np.asarray(SupervisedDataset.open(ds.root).worlds)[-1] == 256
    # a dataset of up to 256 worlds keeps its one-byte layout: datasets written before stay readable and reused
    small = generate_dataset(tmp_path / "s", worlds=["box-room", "corridor"], frames=8, sensor_cfg=SMALL_SENSOR,
                             env_cfg=TEST_ENV, drive_cfg=DriveConfig(episode_steps=2), seed=0, test_fraction=0.3,
                             progress=False)
    assert small.worlds.dtype == np.uint8
    assert json.loads((small.root / "manifest.json").read_text())["files"]["worlds"]["dtype"] == "uint8"
