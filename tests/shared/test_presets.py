"""Presets: every preset file loads and builds; bad values are rejected with clear errors."""

import dataclasses

import pytest

from shared.config import (
    ConfigError,
    DQNConfig,
    ExploreConfig,
    ModelConfig,
    ReplayConfig,
    TrainConfig,
    load_preset,
    preset_names,
)
from shared.learning.dqn import caffe_lr_to_torch
from shared.learning.model import QNetwork, pool3_shape


def test_required_presets_exist_and_all_load():
    names = preset_names()
    assert {"paper", "fast", "smoke", "tiny"} <= set(names)
    for name in names:
        cfg = load_preset(name)
        net = QNetwork(cfg.model, cfg.sensor)
        assert net.pool3_shape == pool3_shape(cfg.sensor)


def test_paper_preset_is_the_paper_with_every_improvement_off():
    cfg = load_preset("paper")
    assert (cfg.dqn.batch_size, cfg.dqn.gamma, cfg.dqn.momentum) == (32, 0.85, 0.99)
    assert cfg.dqn.lr == pytest.approx(caffe_lr_to_torch(1e-7))
    assert cfg.dqn.optimizer == "sgd" and cfg.dqn.loss == "mse" and cfg.dqn.conv_lr_scale < 1
    assert not cfg.dqn.double_dqn and cfg.dqn.n_step == 1 and not cfg.model.dueling
    assert not cfg.replay.prioritized and cfg.replay.capacity == 3000
    assert (cfg.sensor.width, cfg.sensor.height) == (160, 120) and cfg.model.dropout == 0.5
    assert (cfg.env.reward_collision, cfg.env.reward_move, cfg.env.collision_distance_m) == (-100.0, 1.0, 0.55)


def test_fast_smoke_and_tiny_presets():
    fast = load_preset("fast")
    assert fast.dqn.double_dqn and fast.dqn.loss == "huber" and fast.dqn.optimizer == "adam"
    assert fast.dqn.n_step == 3 and fast.replay.capacity >= 50_000 and 1e-4 <= fast.dqn.lr <= 5e-4
    assert (fast.sensor.width, fast.sensor.height) == (160, 120)  # the paper's network
    smoke = load_preset("smoke")
    assert smoke.train.total_updates == 50 and smoke.sensor.width <= 64
    tiny = load_preset("tiny")
    assert (tiny.sensor.width, tiny.sensor.height) == (40, 30) and tiny.model.fc1 <= 128


def test_robust_preset_is_fast_40x30_trained_under_the_robust_protocols_conditions_and_beyond():
    from shared.evaluation import PROTOCOLS

    robust, fast, test = load_preset("robust-40x30"), load_preset("fast-40x30"), PROTOCOLS["robust"]
    assert (robust.env.start_jitter_m, robust.env.start_jitter_deg) == (0.10, 6.0)
    assert (robust.env.start_jitter_m, robust.env.start_jitter_deg) == (2 * test.start_jitter_m,
                                                                        2 * test.start_jitter_deg)
    assert robust.sensor == test.sensor(fast.sensor) and robust.sensor.noise_std_m > 0
    assert (fast.env.start_jitter_m, fast.env.start_jitter_deg, fast.sensor.noise_std_m) == (0.0, 0.0, 0.0)
    # at twice the learning rate, falling to a tenth over 100000 updates, and trained that long
    assert (robust.dqn.lr, robust.dqn.lr_decay_updates, robust.dqn.lr_final_scale) == (2 * fast.dqn.lr, 100000, 0.1)
    assert fast.dqn.lr_decay_updates == 0 and robust.train.total_updates > robust.dqn.lr_decay_updates
    same = dataclasses.replace(robust, sensor=fast.sensor,
                               env=dataclasses.replace(robust.env, start_jitter_m=0.0, start_jitter_deg=0.0,
                                                       extra_world_prob=fast.env.extra_world_prob),
                               dqn=dataclasses.replace(robust.dqn, lr=fast.dqn.lr, lr_decay_updates=0),
                               train=dataclasses.replace(robust.train, total_updates=fast.train.total_updates))
    assert same == fast  # everything else is fast-40x30's


@pytest.mark.parametrize("section,field,value,match", [
    ("dqn", "gamma", 1.5, "gamma"), ("dqn", "n_step", 0, "n_step"), ("dqn", "optimizer", "rmsprop", "optimizer"),
    ("dqn", "lr", 0.0, "lr"), ("dqn", "loss", "l1", "loss"), ("dqn", "momentum", 1.0, "momentum"),
    ("dqn", "batch_size", 0, "batch_size"), ("dqn", "target_sync_every", 0, "target_sync_every"),
    ("replay", "capacity", 1, "capacity"), ("replay", "priority_alpha", 2.0, "priority_alpha"),
    ("model", "fc1", 0, "fc1"), ("model", "dropout", 1.0, "dropout"), ("model", "dueling", "yes", "dueling"),
    ("explore", "eps_end", 1.5, "eps_end"), ("explore", "eps_decay_steps", -1, "eps_decay_steps"),
    ("train", "device", "tpu", "device"), ("train", "keep_checkpoints", 0, "keep_checkpoints"),
    ("train", "replay_ratio", 0.0, "replay_ratio"),
    ("sensor", "width", 4, "width"),
    ("env", "start_jitter_m", 2.0, "start_jitter_m"), ("env", "start_jitter_deg", 90, "start_jitter_deg"),
    # TOML's true is Python's 1: a count or an index is never a switch (one-step episodes, start 0)
    ("env", "max_episode_steps", True, "max_episode_steps"), ("env", "start_index", False, "start_index"),
    ("dqn", "batch_size", True, "batch_size"), ("train", "total_updates", True, "total_updates"),
])
def test_bad_values_in_a_preset_file_are_rejected(tmp_path, section, field, value, match):
    path = tmp_path / "bad.toml"
    literal = f'"{value}"' if isinstance(value, str) else repr(value).lower() if isinstance(value, bool) else value
    path.write_text(f"[{section}]\n{field} = {literal}\n")
    with pytest.raises(ConfigError, match=rf"\[{section}\] {field}"):
        load_preset(path)


def test_unknown_fields_sections_and_presets_are_rejected(tmp_path):
    path = tmp_path / "typo.toml"
    path.write_text("[dqn]\ngama = 0.9\n")
    with pytest.raises(ConfigError, match="unknown field"):
        load_preset(path)
    path.write_text("[dqm]\ngamma = 0.9\n")
    with pytest.raises(ConfigError, match="unknown section"):
        load_preset(path)
    with pytest.raises(ConfigError, match="unknown preset"):
        load_preset("no-such-preset")


def test_learning_dataclasses_validate_directly():
    with pytest.raises(ConfigError, match="gamma"):
        DQNConfig(gamma=-0.1)
    with pytest.raises(ConfigError, match="capacity"):
        ReplayConfig(capacity=2.5)
    with pytest.raises(ConfigError, match="fc2"):
        ModelConfig(fc2=True)
    with pytest.raises(ConfigError, match="apex_base"):
        ExploreConfig(apex_base=2.0)
    with pytest.raises(ConfigError, match="checkpoint_every"):
        TrainConfig(checkpoint_every=0)


@pytest.mark.parametrize("field", ["batch_size", "target_sync_every", "n_step"])
def test_booleans_are_not_integers(field):
    with pytest.raises(ConfigError, match=field):
        DQNConfig(**{field: True})
