"""The foresight probe: how many decisions before each collision a policy last had a safe plan."""

import json

import numpy as np
import pytest

from shared.config import EnvConfig, SensorConfig
from shared.evaluation.foresight import ForesightProbe, foresight_summary
from shared.evaluation.protocol import evaluate_policy

SENSOR = SensorConfig(width=40, height=30)


def test_summary_counts_decisions_back_from_each_collision():
    episodes = [[True, True, False, False, False],  # collided: last safe decision 4 before the end
                [True] * 6,                          # collided with a safe plan at its last decision
                [False, False],                      # collided with no safe plan at all
                [True, False, False]]                # reached the cap: not a collision
    out = foresight_summary(episodes, [True, True, True, False], horizon=24)
    assert out["collisions"] == 3 and out["without_a_safe_plan_at_any_decision"] == 1
    assert out["decisions_from_the_last_safe_state"]["median"] == pytest.approx(2.5)  # of 4 and 1
    assert out["within_3_decisions"] == 1 and out["more_than_10_decisions"] == 0
    with pytest.raises(ValueError, match="episodes"):
        foresight_summary(episodes, [True], horizon=24)


def straight(depth_m):
    return 2  # never turns: drives into whatever is ahead


def test_the_probe_only_observes_and_finds_the_last_safe_state_before_a_head_on_collision():
    run = dict(world="box-room", sensor_cfg=SENSOR, episodes_per_start=1, max_steps=80, progress=False, seed=3)
    plain = evaluate_policy(straight, **run)
    probe = ForesightProbe(straight, SENSOR, EnvConfig())
    probed = evaluate_policy(probe, **run)
    assert [e.steps for e in probed.episodes] == [e.steps for e in plain.episodes]  # the same commands
    assert [len(flags) for flags in probe.episodes] == [e.steps for e in probed.episodes]
    collided = [e.terminated for e in probed.episodes]
    assert any(collided)
    out = probe.summary(collided)
    assert out["collisions"] == sum(collided)
    # driving straight at a wall: turning was still safe some decisions before the wall, not at the end
    found = 0
    for flags, hit in zip(probe.episodes, collided):
        if hit and any(flags):
            assert not flags[-1] and flags[np.flatnonzero(flags)[-1]]
            found += 1
    assert found >= 1, "no collision had a safe state before it: the check above never ran"
    with pytest.raises(ValueError, match="horizon"):
        ForesightProbe(straight, SENSOR, EnvConfig(), horizon=99)


def test_evaluate_prints_the_probe_per_world_and_pooled(capsys):
    from services.cli import main

    assert main(["evaluate", "--policy", "reactive", "--world", "box-room,corridor", "--episodes-per-start", "1",
                 "--max-steps", "40", "--foresight", "--quiet"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith('{"world')
             or line.startswith('{"worlds')]
    per_world = [line for line in lines if "world" in line and "foresight" in line]
    pooled = [line for line in lines if "worlds" in line and "foresight" in line]
    assert [line["world"] for line in per_world] == ["box-room", "corridor"]
    assert len(pooled) == 1 and pooled[0]["foresight"]["collisions"] == sum(
        line["foresight"]["collisions"] for line in per_world)
