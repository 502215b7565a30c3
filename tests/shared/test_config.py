"""What every process of a run must share with its learner (shared.config.MUST_MATCH_FIELDS), the
default preset, and values that must be refused, parsed or written back as they are."""

from __future__ import annotations

import dataclasses
import tomllib

import pytest

from shared.config import (
    DEFAULT_PRESET,
    MUST_MATCH_FIELDS,
    ConfigError,
    ConfigMismatchError,
    RunConfig,
    config_differences,
    from_dict,
    load_preset,
    parse_override,
    parse_world_list,
    require_same_run,
    to_toml,
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


@pytest.mark.parametrize("name,value", [
    ("dqn.lr", 10**400),  # a float field given an integer too large for a float: was an OverflowError
    ("train.total_updates", 10**400),  # the learner's total / replay_ratio overflowed
    ("train.seed", 2**64),  # torch.manual_seed refused it in the learner, a traceback
    ("train.replay_ratio", 1e-305),  # total_updates / replay_ratio transitions: infinite
    ("env.reward_collision", -1e308),  # finite, but -inf in the float32 transitions carry
    ("env.reward_move", 1e39),
    ("env.speed_table", ["train"]),  # was "[env] unhashable type: 'list'"
], ids=lambda v: v if isinstance(v, str) else type(v).__name__)
def test_values_that_broke_a_run_later_are_config_errors_now(name: str, value: object) -> None:
    field_name = name.split(".")[1]
    with pytest.raises(ConfigError, match=rf"\] {field_name} = .* is invalid") as info:
        RunConfig().with_overrides({name: value})
    assert len(str(info.value)) < 300 and "\n" not in str(info.value)


def test_the_largest_seed_an_actor_can_derive_its_own_from_is_accepted() -> None:
    from shared.config import MAX_SEED

    assert RunConfig().with_overrides({"train.seed": MAX_SEED}).train.seed == MAX_SEED
    assert MAX_SEED * 1000 + 100_001 < 2**63  # services/actor: seed * 1000 + index + 1


def test_set_values_that_are_no_toml_are_the_text_without_the_spaces_around_it() -> None:
    assert parse_override("dqn.optimizer = adam") == ("dqn.optimizer", "adam")
    assert parse_override("env.world=a=b") == ("env.world", "a=b")
    assert parse_override("dqn.lr = 1e-3") == ("dqn.lr", 1e-3)
    assert parse_override("dqn.lr=1\nx = 2") == ("dqn.lr", "1\nx = 2")  # two TOML keys are no one value
    key, value = parse_override("train.seed=" + "9" * 5000)  # beyond Python's int-digits limit: was a ValueError
    assert key == "train.seed" and value == "9" * 5000
    with pytest.raises(ConfigError, match=r"seed = '9{20}.*\(5002 characters\) is invalid"):
        RunConfig().with_overrides({key: value})


def test_a_string_with_control_characters_survives_the_saved_config() -> None:
    cfg = RunConfig().with_overrides({"env.world": 'a\tb\nc\r\x01\x7f"\\d'})
    assert from_dict(tomllib.loads(to_toml(cfg))) == cfg


def test_a_procedural_seed_is_listed_as_its_world_is_named() -> None:
    # 'procedural:0201' is the world 'procedural:201': a list that wrote it so must overlap a range holding 201
    # (model select refuses test worlds among its validation worlds by these names)
    assert parse_world_list("procedural:0201, procedural:201, procedural:200-202, procedural:000") == (
        "procedural:201", "procedural:200", "procedural:202", "procedural:0")
    assert set(parse_world_list("procedural:0201")) & set(parse_world_list("procedural:200-202"))


def test_text_that_cannot_be_saved_is_refused_naming_its_field() -> None:
    # an undecodable byte on the command line arrives as a lone surrogate: it passed every check, and
    # writing the run's config.toml then failed with a UnicodeEncodeError traceback
    with pytest.raises(ConfigError, match=r"^\[env\] extra_worlds = '\\udcff' is invalid: text in UTF-8"):
        RunConfig().with_overrides({"env.extra_worlds": "\udcff"})
    cfg = RunConfig().with_overrides({"env.world": "wörld-€"})
    assert from_dict(tomllib.loads(to_toml(cfg))) == cfg


def test_no_start_index_is_written_as_the_error_says() -> None:
    key, value = parse_override("env.start_index=none")
    assert RunConfig().with_overrides({key: value}).env.start_index is None
    with pytest.raises(ConfigError) as info:
        RunConfig().with_overrides(dict([parse_override("env.start_index=-1")]))
    allowed = str(info.value).partition("is invalid: ")[2]
    assert allowed.split()[0] == "none", allowed  # was "None", which --set reads as the text 'None' and refuses


@pytest.mark.parametrize("device", ["cuda:x", "cuda:", "cuda:-1", "cuda:1.5", "cuda:0 "])
def test_a_device_is_a_cuda_index_or_a_name(device: str) -> None:
    # these passed the config and failed only when the run had started, as torch read them
    with pytest.raises(ConfigError, match=r"^\[train\] device = .* is invalid: 'auto', 'cpu', 'cuda' or 'cuda:<n>'"):
        RunConfig().with_overrides({"train.device": device})
    assert RunConfig().with_overrides({"train.device": "cuda:1"}).train.device == "cuda:1"


def test_an_epsilon_that_would_rise_during_training_is_refused() -> None:
    # eps_start 0.05 under the default eps_end 0.1 (a fine-tuning --set without eps_end) rose to 0.1
    with pytest.raises(ConfigError, match=r"^\[explore\] eps_end = 0.1 is invalid: at most eps_start \(0.05\)"):
        RunConfig().with_overrides({"explore.eps_start": 0.05})
    cfg = RunConfig().with_overrides({"explore.eps_start": 0.05, "explore.eps_end": 0.05})
    assert (cfg.explore.eps_start, cfg.explore.eps_end) == (0.05, 0.05)  # a constant epsilon is one
    # where the schedule is not run, eps_start is not read: no error for it
    for unused in ({"explore.per_actor": True}, {"explore.eps_decay_steps": 0}):
        assert RunConfig().with_overrides({"explore.eps_start": 0.05, **unused}).explore.eps_end == 0.1


def test_a_sensor_blind_nearer_than_the_collision_distance_is_a_real_kinects_and_accepted() -> None:
    # A Kinect reads nothing nearer than about 0.5-0.8 m: with min_range_m past the collision distance
    # the depth rule cannot fire, and a contact alone ends the episode (as on the real robot).
    assert RunConfig().with_overrides({"sensor.min_range_m": 0.8}).sensor.min_range_m == 0.8
