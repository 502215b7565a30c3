"""Key expressions: built, parsed back, valid for Zenoh, and bad names refused."""

from __future__ import annotations

import pytest
import zenoh

from shared.wire.keys import (
    MAX_NAME_LEN,
    KeyExprError,
    ParsedKey,
    RunKeys,
    parse_key,
    validate_name,
)


def test_keys_follow_the_documented_layout() -> None:
    keys = RunKeys("exp-1")
    assert keys.prefix == "cogexplore/exp-1"
    assert keys.transitions("actor-0") == "cogexplore/exp-1/transitions/actor-0"
    assert keys.all_transitions == "cogexplore/exp-1/transitions/*"
    assert keys.weights == "cogexplore/exp-1/weights"
    assert keys.weights_latest == "cogexplore/exp-1/weights/latest"
    assert keys.config == "cogexplore/exp-1/config"
    assert keys.episode_stats("actor-0") == "cogexplore/exp-1/stats/episode/actor-0"
    assert keys.learner_stats("learner") == "cogexplore/exp-1/stats/learner/learner"
    assert keys.eval_results("eval.0") == "cogexplore/exp-1/stats/eval/eval.0"
    assert keys.all_stats() == "cogexplore/exp-1/stats/**"
    assert keys.all_stats("episode") == "cogexplore/exp-1/stats/episode/*"
    assert keys.alive("learner", "l0") == "cogexplore/exp-1/alive/learner/l0"
    assert keys.all_alive() == "cogexplore/exp-1/alive/**"
    assert keys.all_alive("actor") == "cogexplore/exp-1/alive/actor/*"


def test_concrete_keys_parse_back() -> None:
    keys = RunKeys("run_2")
    assert parse_key(keys.transitions("a7")) == ParsedKey("run_2", "transitions", None, "a7")
    assert parse_key(keys.weights) == ParsedKey("run_2", "weights")
    assert parse_key(keys.weights_latest) == ParsedKey("run_2", "weights_latest")
    assert parse_key(keys.config) == ParsedKey("run_2", "config")
    assert parse_key(keys.eval_results("ev")) == ParsedKey("run_2", "stats", "eval", "ev")
    assert parse_key(keys.alive("actor", "a7")) == ParsedKey("run_2", "alive", "actor", "a7")
    # zenoh.KeyExpr (what a sample carries) parses too
    assert parse_key(zenoh.KeyExpr(keys.transitions("a7"))).source == "a7"


@pytest.mark.parametrize("key", [
    "other/run/weights", "cogexplore/run", "cogexplore/run/weights/oldest",
    "cogexplore/run/transitions", "cogexplore/run/transitions/a/b", "cogexplore/run/stats/bogus/x",
    "cogexplore/run/alive/wizard/x", "cogexplore/r*n/weights", "cogexplore/run/transitions/*",
    "cogexplore/run/config/x",
])
def test_foreign_keys_are_refused(key: str) -> None:
    with pytest.raises(KeyExprError):
        parse_key(key)


def test_keys_are_valid_zenoh_key_expressions_and_wildcards_match() -> None:
    keys = RunKeys("exp")
    for concrete in (keys.transitions("a"), keys.weights, keys.weights_latest, keys.config,
                     keys.episode_stats("a"), keys.alive("evaluator", "e")):
        zenoh.KeyExpr(concrete)  # raises on an invalid key expression
    assert zenoh.KeyExpr(keys.all_transitions).includes(zenoh.KeyExpr(keys.transitions("a")))
    assert zenoh.KeyExpr(keys.all_stats()).includes(zenoh.KeyExpr(keys.learner_stats("l")))
    assert zenoh.KeyExpr(keys.all_alive()).includes(zenoh.KeyExpr(keys.alive("actor", "a")))
    # the weights stream and the queryable do not shadow each other
    assert not zenoh.KeyExpr(keys.weights).intersects(zenoh.KeyExpr(keys.weights_latest))
    # runs are isolated
    assert not zenoh.KeyExpr(keys.all_transitions).intersects(
        zenoh.KeyExpr(RunKeys("other").transitions("a")))


@pytest.mark.parametrize("bad, fragment", [
    ("a/b", "slash"), ("a*", "wildcard"), ("a$b", "'$'"), ("a#", "'#'"), ("a?", "'?'"),
    ("a b", "whitespace"), ("a\tb", "whitespace"), ("", "empty"), ("-a", "starting"),
    (".", "starting"), ("..", "starting"), ("x" * (MAX_NAME_LEN + 1), "longer"),
])
def test_bad_names_are_refused_with_the_reason(bad: str, fragment: str) -> None:
    with pytest.raises(KeyExprError, match="run name") as info:
        RunKeys(bad)
    assert fragment in str(info.value)
    with pytest.raises(KeyExprError, match="actor id"):
        RunKeys("ok").transitions(bad)


def test_non_string_names_and_unknown_roles_are_refused() -> None:
    with pytest.raises(KeyExprError, match="must be a string"):
        validate_name(3, "actor id")
    with pytest.raises(KeyExprError, match="role 'wizard'"):
        RunKeys("ok").alive("wizard", "x")
    with pytest.raises(KeyExprError, match="stats kind"):
        RunKeys("ok").stats("mood", "x")
    assert validate_name("Actor_0.host-1") == "Actor_0.host-1"
