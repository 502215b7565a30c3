"""``cogexplore.evaluate``: the paper's protocol from Python, the same as ``cogexplore evaluate``, for
a loaded Policy or any callable."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import cogexplore
from services.cli import main
from shared.evaluation.policies import ReactivePolicy
from shared.evaluation.results import ResultsError, to_json, validate_results_json

pytestmark = pytest.mark.usefixtures("one_torch_thread")
# The tables' start 2 is start index 1.
TINY = ["--starts", "2", "--episodes-per-start", "1", "--max-steps", "15", "--quiet"]


def _cli(tmp_path: Path, *argv: str) -> dict:
    out = tmp_path / "cli.json"
    assert main(["evaluate", *argv, *TINY, "--json", str(out)]) == 0
    return json.loads(out.read_text())


def test_evaluate_a_policy_matches_the_command_line(tmp_path: Path, capsys) -> None:
    policy = cogexplore.load_policy(device="cpu")
    results = cogexplore.evaluate(policy, starts=[1], episodes_per_start=1, max_steps=15)
    assert json.loads(to_json(results)) == _cli(tmp_path, "--checkpoint", "pretrained", "--device", "cpu")
    assert isinstance(results, cogexplore.Results) and results.meta["world"] == "paper-indoor"
    assert results.mean_steps == results.summary["overall"]["mean_steps"] == results.episodes[0].steps > 0
    assert results.per_start_steps == {1: results.mean_steps}
    assert "| Count |" in results.table()
    saved = validate_results_json(results.save(tmp_path / "api.json").read_text())
    assert saved.episodes == results.episodes

    # The same protocol on the camera rendered at 640 x 480: the policy resizes every frame to its
    # 40 x 30 and starts off with the same commands (later a near tie between two commands may go
    # the other way: a pixel on an edge can take either side) and drives as long.
    fine = cogexplore.evaluate(policy, "paper-indoor", starts=[1], episodes_per_start=1, max_steps=15,
                               resolution=(640, 480))
    assert fine.meta["sensor"]["width"] == 640 and fine.meta["world"] == "paper-indoor"
    assert fine.episodes[0].steps == results.episodes[0].steps
    np.testing.assert_allclose(fine.episodes[0].trajectory_xy[:5], results.episodes[0].trajectory_xy[:5], atol=1e-9)


class _Straight:
    """A user's controller: always straight, counting what it is given."""

    def __init__(self) -> None:
        self.resets, self.shapes = 0, set()

    def reset(self) -> None:
        self.resets += 1

    def __call__(self, depth_m: np.ndarray) -> int:
        assert depth_m.dtype == np.float32
        self.shapes.add(depth_m.shape)
        return 2


def test_evaluate_a_user_callable(tmp_path: Path, capsys) -> None:
    reactive = ReactivePolicy()
    results = cogexplore.evaluate(lambda depth: reactive(depth)[0], starts=[1], episodes_per_start=1, max_steps=15)
    cli = validate_results_json(_cli(tmp_path, "--policy", "reactive"))
    assert results.episodes == cli.episodes and results.meta["sensor"] == cli.meta["sensor"]
    assert results.meta["policy"] == "callable" and "lambda" in results.meta["model"]

    straight = _Straight()
    results = cogexplore.evaluate(straight, starts=[0, 3], episodes_per_start=2, max_steps=5, resolution=(64, 48))
    assert straight.resets == len(results.episodes) == 4 and straight.shapes == {(48, 64)}
    assert sorted(results.per_start_steps) == [0, 3] and results.meta["model"] == "_Straight"
    assert {e.start_index for e in results.episodes} == {0, 3}
    # A controller returning (command, scores), as shared.evaluation.policies do, works too.
    assert cogexplore.evaluate(reactive, starts=[1], episodes_per_start=1, max_steps=15).episodes == cli.episodes


def test_evaluate_errors_are_clear() -> None:
    with pytest.raises(cogexplore.CogexploreError, match="callable depth_m -> command"):
        cogexplore.evaluate("pretrained")
    with pytest.raises(ResultsError, match="returned action 7"):
        cogexplore.evaluate(lambda depth: 7, starts=[0], episodes_per_start=1, max_steps=3)
    with pytest.raises(cogexplore.CogexploreError, match="starts"):
        cogexplore.evaluate(lambda depth: 2, starts=[99], episodes_per_start=1, max_steps=3)
    with pytest.raises(cogexplore.CogexploreError, match="episodes_per_start"):
        cogexplore.evaluate(lambda depth: 2, episodes_per_start=0)
    with pytest.raises(cogexplore.CogexploreError, match="no-such-world"):
        cogexplore.evaluate(lambda depth: 2, "no-such-world", max_steps=3)
    with pytest.raises(cogexplore.CogexploreError, match=r"width"):
        cogexplore.evaluate(lambda depth: 2, resolution=(4000, 3000), max_steps=3)
    with pytest.raises(cogexplore.CogexploreError, match=r"\(width, height\)"):
        cogexplore.evaluate(lambda depth: 2, resolution=640, max_steps=3)
    # Before, "10" ran starts 1 and 0, 1.9 and True ran start 1, and the rest were raw TypeErrors.
    for starts in ("10", [1.9], [True], 5, [0, 0]):
        with pytest.raises(cogexplore.CogexploreError, match="start"):
            cogexplore.evaluate(lambda depth: 2, starts=starts, episodes_per_start=1, max_steps=3)
    for seed in ("x", 1.5, -1):
        with pytest.raises(cogexplore.CogexploreError, match="seed"):
            cogexplore.evaluate(lambda depth: 2, seed=seed, episodes_per_start=1, max_steps=3)
    with pytest.raises(cogexplore.CogexploreError, match="protocol must be"):
        cogexplore.evaluate(lambda depth: 2, protocol=3, max_steps=3)


def test_a_resolution_a_policy_refuses_is_a_clear_error_before_any_episode() -> None:
    # Before: refused at the first step as "depth_m is 64 x 64 pixels ... crop the image to that field
    # of view first", advice for an image that has the network's field of view.
    policy = cogexplore.load_policy(device="cpu")
    with pytest.raises(cogexplore.CogexploreError, match=r"^resolution 64 x 64 is not the aspect ratio of the "
                                                         r"network's 40 x 30 camera"):
        cogexplore.evaluate(policy, resolution=(64, 64), starts=[0], episodes_per_start=1, max_steps=3)
    # a callable takes any size
    assert cogexplore.evaluate(lambda depth: 2, resolution=(64, 64), starts=[0], episodes_per_start=1,
                               max_steps=3).meta["sensor"]["width"] == 64
