"""What every process of a run must share with its learner (shared.config.MUST_MATCH_FIELDS), and the
default preset."""

from __future__ import annotations

import dataclasses

import pytest

from shared.config import (
    DEFAULT_PRESET,
    MUST_MATCH_FIELDS,
    ConfigMismatchError,
    RunConfig,
    config_differences,
    load_preset,
    require_same_run,
)


def test_every_field_named_exists() -> None:
    cfg = RunConfig()
    for name in MUST_MATCH_FIELDS:
        section, _, attr = name.partition(".")
        assert attr in {f.name for f in dataclasses.fields(getattr(cfg, section))}, name
    assert len(set(MUST_MATCH_FIELDS)) == len(MUST_MATCH_FIELDS)


@pytest.mark.parametrize("name,value", [
    ("sensor.width", 64), ("sensor.max_range_m", 5.0), ("sensor.hfov_deg", 60.0), ("model.fc1", 256),
    ("model.dueling", True), ("model.depth_encoding", "inverse"), ("model.previous_action", True),
    ("env.speed_table", "test"), ("env.control_period_s", 0.25), ("env.reward_collision", -10.0),
    ("env.collision_distance_m", 0.4), ("env.robot_radius_m", 0.2),
])
def test_a_change_that_makes_the_data_unusable_is_named(name: str, value: object) -> None:
    run = load_preset("paper")
    mine = run.with_overrides({name: value})
    assert config_differences(mine, run) == [(name, value, getattr(getattr(run, name.split(".")[0]), name.split(".")[1]))]


@pytest.mark.parametrize("name,value", [
    ("env.world", "box-room"), ("env.max_episode_steps", 50), ("env.random_start_prob", 0.5),
    ("explore.eps_end", 0.01), ("train.seed", 7), ("train.device", "cpu"), ("sensor.backend", "gl"),
    ("sensor.noise_std_m", 0.01), ("model.dropout", 0.0), ("dqn.n_step", 3), ("dqn.gamma", 0.9),
    ("replay.capacity", 500),
])
def test_a_process_may_choose_its_own_worlds_exploration_and_the_learner_its_update(name: str, value: object) -> None:
    run = load_preset("paper")
    assert config_differences(run.with_overrides({name: value}), run) == []
    require_same_run(run.with_overrides({name: value}), run)  # no error


def test_the_error_is_one_line_naming_the_first_difference_where_from_and_what_to_do() -> None:
    with pytest.raises(ConfigMismatchError) as info:
        require_same_run(load_preset("paper"), load_preset("fast-40x30"), who="this actor",
                         source="learner 'learner' of run 'x'", hint="drop --preset to use the run's configuration")
    assert str(info.value) == ("this actor's sensor.width=160 differs from the run's 40 (learner 'learner' of run 'x'; "
                               "also differ: sensor.height, model.depth_encoding, model.previous_action); drop "
                               "--preset to use the run's configuration")
    with pytest.raises(ConfigMismatchError) as info:
        require_same_run(load_preset("paper").with_overrides({"model.depth_encoding": "inverse"}), load_preset("paper"))
    assert str(info.value) == 'this process\'s model.depth_encoding="inverse" differs from the run\'s "metric"'
    with pytest.raises(ConfigMismatchError, match=r"also differ: .* and \d+ more\)$"):
        require_same_run(load_preset("paper"), load_preset("smoke").with_overrides({"env.speed_table": "test",
                                                                                     "env.reward_move": 2.0}))


def test_the_default_preset_is_the_shipped_models_recipe() -> None:
    from shared.learning.checkpoints import load_model
    from shared.learning.model import QNetwork, architecture_fingerprint

    cfg = load_preset(DEFAULT_PRESET)
    shipped = load_model("pretrained").net  # an ensemble of networks of this recipe
    assert len(shipped.members) == 4
    for member in shipped.members:
        assert architecture_fingerprint(QNetwork(cfg.model, cfg.sensor)) == architecture_fingerprint(member)
        assert cfg.sensor == member.sensor_cfg
