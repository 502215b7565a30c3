"""Evaluation results: the record's invariants, aggregation, the JSON schema, Table III and
the test protocol on the real environment (box-room, test speeds, tiny step caps)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shared.config import SensorConfig
from shared.evaluation import PROTOCOLS, ProtocolConfig
from shared.evaluation.protocol import episode_seed, run_protocol
from shared.evaluation.results import (
    SCHEMA_ID,
    EpisodeResult,
    EvalResults,
    ResultsError,
    aggregate,
    load_results,
    save_results,
    table_markdown,
    to_json,
    validate_results_json,
)
from shared.sim.env import ExploreEnv


def ep(start: int, k: int, steps: int, cause: str | None = None, cap: bool = False, dist: float = 1.0,
       path: float = 5.0, cov: float = 0.5, traj: bool = False) -> EpisodeResult:
    return EpisodeResult(start_index=start, episode=k, steps=steps, terminated=cause is not None,
                         truncated=cap, collision_cause=cause, distance_m=dist, path_length_m=path,
                         coverage_m2=10.0 * cov, coverage_fraction=cov,
                         trajectory_xy=tuple((0.1 * i, 0.0) for i in range(steps + 1)) if traj else ())


PAPER = {"protocol": PROTOCOLS["paper"].to_dict()}
EPISODES = [
    ep(0, 0, 10, "depth", dist=1.0, cov=0.2),
    ep(0, 1, 200, cap=True, dist=3.0, cov=0.6),
    ep(1, 0, 4, "contact", dist=0.5, cov=0.1),
    ep(1, 1, 6, "depth", dist=0.7, cov=0.3, traj=True),
]


# -- the record -----------------------------------------------------------------------------


@pytest.mark.parametrize("kwargs,match", [
    (dict(terminated=True, collision_cause=None), "cause go together"),
    (dict(terminated=False, collision_cause="depth"), "cause go together"),
    (dict(terminated=True, truncated=True, collision_cause="depth"), "both terminated"),
    (dict(steps=-1), r"episode\.steps: expected an integer in \[0, 2147483647\]"),
    (dict(steps=int("9" * 400)), r"episode\.steps: expected an integer in"),  # not an OverflowError later
    (dict(distance_m=1.5), r"distance_m: expected at most path_length_m = 1\.0"),
    (dict(collision_cause="wall", terminated=True), r"collision_cause"),
    (dict(coverage_fraction=1.5), r"coverage_fraction"),
    (dict(distance_m=float("nan")), r"distance_m"),
    (dict(steps=3, trajectory_xy=((0.0, 0.0), (1.0, 0.0))), r"2 points for 3 steps"),
    (dict(terminated=1, collision_cause="depth"), r"terminated: expected true or false"),
])
def test_episode_invariants(kwargs: dict, match: str) -> None:
    base = dict(start_index=0, episode=0, steps=3, terminated=False, truncated=False, collision_cause=None,
                distance_m=1.0, path_length_m=1.0, coverage_m2=1.0, coverage_fraction=0.1)
    base.update(kwargs)
    with pytest.raises(ResultsError, match=match):
        EpisodeResult(**base)


def test_episode_accepts_numpy_trajectory() -> None:
    e = EpisodeResult(0, 0, 2, False, True, None, 1.0, 1.0, 1.0, 0.1, np.array([[0, 0], [1, 0], [2, 0.5]]))
    assert e.trajectory_xy == ((0.0, 0.0), (1.0, 0.0), (2.0, 0.5))


# -- aggregation ----------------------------------------------------------------------------


def test_aggregate_numbers() -> None:
    s = aggregate(EPISODES)
    o = s["overall"]
    assert o["episodes"] == 4
    assert o["mean_steps"] == pytest.approx((10 + 200 + 4 + 6) / 4)
    assert o["mean_distance_m"] == pytest.approx((1.0 + 3.0 + 0.5 + 0.7) / 4)
    assert o["mean_path_length_m"] == pytest.approx(5.0)
    assert o["mean_coverage_pct"] == pytest.approx(100 * (0.2 + 0.6 + 0.1 + 0.3) / 4)
    assert o["mean_coverage_m2"] == pytest.approx(10 * (0.2 + 0.6 + 0.1 + 0.3) / 4)
    assert o["collisions"] == {"depth": 2, "contact": 1}
    assert o["collision_episodes"] == 3
    assert o["reached_cap"] == 1
    assert [p["start_index"] for p in s["per_start"]] == [0, 1]
    p0, p1 = s["per_start"]
    assert p0["mean_steps"] == pytest.approx(105.0) and p0["reached_cap"] == 1
    assert p0["collisions"] == {"depth": 1, "contact": 0}
    assert p1["mean_distance_m"] == pytest.approx(0.6) and p1["collisions"] == {"depth": 1, "contact": 1}
    assert p0["std_steps"] == pytest.approx(95.0)


def test_aggregate_refuses_nothing() -> None:
    with pytest.raises(ResultsError, match="zero episodes"):
        aggregate([])


# -- the JSON document ----------------------------------------------------------------------


def test_json_round_trip(tmp_path) -> None:
    results = EvalResults(tuple(EPISODES), {"model": "DRL 500", "policy_version": 500, **PAPER})
    doc = json.loads(to_json(results))
    assert doc["schema"] == SCHEMA_ID
    assert doc["summary"]["overall"]["reached_cap"] == 1
    back = validate_results_json(to_json(results))
    assert back.episodes == results.episodes
    assert back.meta == {"model": "DRL 500", "policy_version": 500, **PAPER}
    assert back.protocol == PROTOCOLS["paper"]
    path = save_results(results, tmp_path / "r" / "results.json")
    assert load_results(path).episodes == results.episodes
    assert list(path.parent.iterdir()) == [path]  # no temporary file beside it


def _doc() -> dict:
    return json.loads(to_json(EvalResults(tuple(EPISODES), {"model": "m", **PAPER})))


@pytest.mark.parametrize("mutate,match", [
    (lambda d: d.update(schema="other/1"), "schema: expected"),
    (lambda d: d.pop("summary"), "missing \\['summary'\\]"),
    (lambda d: d.update(extra=1), "unknown \\['extra'\\]"),
    (lambda d: d.update(episodes=[]), "non-empty list"),
    (lambda d: d["episodes"][1].update(steps=-3), r"episodes\[1\]\.steps: expected an integer in \[0, 2147483647\], got -3"),
    (lambda d: d["episodes"][2].pop("distance_m"), r"episodes\[2\]: missing fields \['distance_m'\]"),
    (lambda d: d["episodes"][3]["trajectory_xy"].__setitem__(2, [0.0, "x"]), r"episodes\[3\]\.trajectory_xy\[2\]"),
    (lambda d: d["episodes"][1].update(episode=0), "appears twice"),
    (lambda d: d["summary"]["overall"].update(mean_steps=99.0), r"summary\.overall\.mean_steps"),
    (lambda d: d["summary"]["per_start"][1]["collisions"].update(depth=5), r"summary\.per_start\[1\]\.collisions\.depth"),
    (lambda d: d.update(meta=[1]), "meta: expected an object"),
    # The protocol is part of the schema: results without it (or with a broken one) are refused.
    (lambda d: d["meta"].pop("protocol"), "meta.protocol: missing; results must say which test protocol"),
    (lambda d: d["meta"]["protocol"].pop("start_jitter_deg"), r"meta\.protocol: .*missing \['start_jitter_deg'\]"),
    (lambda d: d["meta"]["protocol"].update(start_jitter_m=-1), r"meta\.protocol: .*start_jitter_m = -1"),
    # An integer too large for a float (JSON has no limit) is refused, not an OverflowError.
    (lambda d: d["meta"]["protocol"].update(start_jitter_deg=10 ** 400), r"meta\.protocol: .*start_jitter_deg = 1000"),
    (lambda d: d.update(schema="cogexplore.eval-results/1"), "written before results recorded their test protocol"),
])
def test_validation_names_the_problem(mutate, match: str) -> None:
    doc = _doc()
    mutate(doc)
    with pytest.raises(ResultsError, match=match):
        validate_results_json(doc)


RUN = {"starts": [0, 1], "episodes_per_start": 2, "max_steps": 200}


def _run_doc(episodes=tuple(EPISODES), **meta) -> dict:
    """A document whose meta says what run it was, as the protocol writes it; its summary consistent."""
    return json.loads(to_json(EvalResults(tuple(episodes), {"model": "m", **PAPER, **RUN, **meta})))


@pytest.mark.parametrize("doc,match", [
    # an episode dropped (and the summary recomputed): it would stand for the full run in a report
    (lambda: _run_doc(EPISODES[:3]), r"episodes: 3 for meta\.starts \[0, 1\] x 2 .*missing \[\(1, 1\)\]"),
    (lambda: _run_doc(starts=[0, 1, 2]), r"missing \[\(2, 0\), \(2, 1\)\]"),
    (lambda: _run_doc(episodes_per_start=1), r"unexpected \[\(0, 1\), \(1, 1\)\]"),
    (lambda: _run_doc(episodes_per_start=10 ** 18), r"episodes: 4 for meta\.starts"),  # bounded work
    (lambda: _run_doc(max_steps=100), r"episodes\[1\]\.steps: 200 is past meta\.max_steps = 100"),
    (lambda: _run_doc(max_steps=0), r"meta\.max_steps: expected an integer >= 1"),
    # "reached cap" counts the truncated episodes: each must have reached it, and every other one collided
    (lambda: _run_doc([*EPISODES[:1], ep(0, 1, 150, cap=True, dist=3.0), *EPISODES[2:]]),
     r"episodes\[1\]: 150 steps, terminated False, truncated True; an episode ends at a collision"),
    (lambda: _run_doc([*EPISODES[:1], ep(0, 1, 150, dist=3.0), *EPISODES[2:]]),
     r"episodes\[1\]: 150 steps, terminated False, truncated False"),
    (lambda: _run_doc(starts="all"), r"meta\.starts: expected a non-empty list"),
])
def test_episodes_must_be_the_run_their_meta_records(doc, match: str) -> None:
    assert validate_results_json(_run_doc()).meta["starts"] == [0, 1]
    with pytest.raises(ResultsError, match=match):
        validate_results_json(doc())


def test_validation_rejects_bad_text(tmp_path) -> None:
    with pytest.raises(ResultsError, match="is not readable JSON"):
        validate_results_json("{nope")
    with pytest.raises(ResultsError, match="does not exist"):
        load_results(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**_doc(), "schema": "x"}))
    with pytest.raises(ResultsError, match=r"bad\.json: schema"):
        load_results(bad)


def test_results_refuse_non_json_meta() -> None:
    with pytest.raises(ResultsError, match="meta"):
        EvalResults(tuple(EPISODES), {"x": float("nan")})


def test_results_without_a_protocol_are_not_saved_or_loaded(tmp_path) -> None:
    unlabelled = EvalResults(tuple(EPISODES), {"model": "m"})
    with pytest.raises(ResultsError, match="meta.protocol: missing"):
        save_results(unlabelled, tmp_path / "r.json")
    assert not (tmp_path / "r.json").exists()
    with pytest.raises(ResultsError, match="meta.protocol: missing"):
        _ = unlabelled.protocol
    # A file written before the protocol was recorded (schema 1, no meta.protocol) names itself and the fix.
    old = _doc()
    old["schema"] = "cogexplore.eval-results/1"
    old["meta"].pop("protocol")
    (tmp_path / "old.json").write_text(json.dumps(old))
    with pytest.raises(ResultsError, match=r"old\.json: schema 'cogexplore.eval-results/1' .*\(--protocol paper"):
        load_results(tmp_path / "old.json")


# -- Table III ------------------------------------------------------------------------------


def test_table_layout_and_bold_best() -> None:
    other = [ep(0, 0, 50, "depth", dist=4.0, cov=0.9), ep(2, 0, 7, "depth", dist=0.2, cov=0.05)]
    table = table_markdown({"DRL 500": EvalResults(tuple(EPISODES)), "DRL 4000": other})
    lines = table.strip().splitlines()
    assert lines[0] == "| Metric | Model | 1 | 2 | 3 | All |"
    assert lines[1] == "|---|---|---:|---:|---:|---:|"
    assert len(lines) == 2 + 3 * 2
    assert lines[2] == "| Count | DRL 500 | **105.0** | **5.0** | - | **55.0** |"
    assert lines[3] == "|  | DRL 4000 | 50.0 | - | **7.0** | 28.5 |"
    assert lines[4].startswith("| Distance (m) | DRL 500 | 2.0 | **0.6** | - |")
    assert lines[5].startswith("|  | DRL 4000 | **4.0** | - | **0.2** |")
    assert lines[6].startswith("| Coverage (%) | DRL 500 | 40.0 | **20.0** | - |")
    # A results JSON object works as well as the results themselves.
    assert table_markdown({"a": _doc()}) == table_markdown({"a": EvalResults(tuple(EPISODES))})


def test_table_of_one_model_has_no_bold() -> None:
    assert "**" not in table_markdown({"only": EPISODES})


def test_a_name_in_a_table_stays_the_name_as_written() -> None:
    # `cogexplore.evaluate(lambda d: 2).table()` named its row <lambda>, which GitHub took for an
    # HTML tag and hid; a checkpoint named run_*best*_a|b became emphasis and two cells.
    table = table_markdown({"<lambda>": EPISODES, "run_*best*_a|b": EPISODES})
    assert "| \\<lambda\\> |" in table and "| run\\_\\*best\\*\\_a\\|b |" in table


def test_a_name_with_a_line_break_stays_in_its_row() -> None:
    table = table_markdown({"two\nlines": EPISODES, "other": EPISODES})
    lines = table.splitlines()
    assert all(line.startswith("|") for line in lines), table
    assert any("| two lines |" in line for line in lines)


# -- the protocol on the real environment ----------------------------------------------------


def make_env(noise: float = 0.0):
    return lambda: ExploreEnv(world="box-room", speed_table="test", sensor=SensorConfig(noise_std_m=noise))


def roomiest_side(depth_m: np.ndarray):
    """A depth-only reflex: straight while both halves have room, else turn to the roomier one."""
    h, w = depth_m.shape
    seen = np.where(depth_m > 0, depth_m, 4.0)
    left, right = seen[:, : w // 2].mean(), seen[:, w // 2:].mean()
    action = 2 if min(left, right) > 1.4 else (0 if left > right else 4)
    q = np.array([left, 0.0, min(left, right), 0.0, right])
    return action, q


def test_protocol_runs_every_start_times_episodes() -> None:
    seen_shapes = set()

    def policy(depth_m):
        seen_shapes.add((depth_m.shape, depth_m.dtype))
        return roomiest_side(depth_m)

    results = run_protocol(policy, make_env(), starts=[0, 2, 3], episodes_per_start=2, max_steps=25,
                           seed=3, progress=False, meta={"model": "reflex"})
    assert [(e.start_index, e.episode) for e in results.episodes] == [(s, k) for s in (0, 2, 3) for k in (0, 1)]
    assert seen_shapes == {((120, 160), np.dtype(np.float32))}
    assert results.meta["model"] == "reflex" and results.meta["max_steps"] == 25
    assert results.meta["speed_table"] == "test" and results.meta["world"] == "box-room"
    for e in results.episodes:
        assert 1 <= e.steps <= 25
        assert e.truncated == (e.steps == 25 and not e.terminated)
        assert len(e.trajectory_xy) == e.steps + 1
        start, end = np.array(e.trajectory_xy[0]), np.array(e.trajectory_xy[-1])
        assert e.distance_m == pytest.approx(float(np.linalg.norm(end - start)), abs=1e-9)
        steps_len = np.linalg.norm(np.diff(np.array(e.trajectory_xy), axis=0), axis=1).sum()
        assert e.path_length_m == pytest.approx(float(steps_len), rel=1e-6)
        assert 0 < e.coverage_fraction <= 1 and e.coverage_m2 > 0
    # Validated on its way through JSON.
    assert validate_results_json(to_json(results)).episodes == results.episodes


def test_protocol_counts_cap_and_collisions() -> None:
    # Circling left from the centre never comes near a wall: every episode reaches the cap.
    circling = run_protocol(lambda d: (0, None), make_env(), starts=[2], episodes_per_start=2,
                            max_steps=30, progress=False)
    assert aggregate(circling.episodes)["overall"]["reached_cap"] == 2
    assert all(e.steps == 30 and e.distance_m < 0.5 < e.path_length_m for e in circling.episodes)
    # Driving straight from every start ends in a collision before the cap.
    straight = run_protocol(lambda d: (2, None), make_env(), episodes_per_start=1, max_steps=200,
                            progress=False)
    summary = aggregate(straight.episodes)["overall"]
    assert summary["episodes"] == 4 and summary["reached_cap"] == 0
    assert summary["collision_episodes"] == 4
    assert all(e.terminated and e.collision_cause in ("depth", "contact") for e in straight.episodes)


def test_protocol_is_deterministic_under_a_seed() -> None:
    # Sensor noise makes episodes differ; the seed makes them repeat.
    noisy = ProtocolConfig("custom", sensor_noise_std_m=0.05)

    def run(seed):
        return run_protocol(roomiest_side, make_env(noise=0.05), starts=[0, 1], episodes_per_start=2,
                            max_steps=40, seed=seed, progress=False, protocol=noisy).episodes

    first = run(0)
    assert run(0) == first
    assert run(1) != first  # the noise is there to repeat: another seed, other images, other paths
    assert episode_seed(0, 1, 1) != episode_seed(0, 1, 0) != episode_seed(1, 1, 0)


def test_protocol_rejects_bad_setup() -> None:
    with pytest.raises(ResultsError, match="starts"):
        run_protocol(roomiest_side, make_env(), starts=[9], episodes_per_start=1, max_steps=5, progress=False)
    with pytest.raises(ResultsError, match="max_episode_steps >= 200"):
        run_protocol(roomiest_side, lambda: ExploreEnv(world="box-room", max_episode_steps=50),
                     episodes_per_start=1, max_steps=200, progress=False)
    with pytest.raises(ResultsError, match="returned action 7"):
        run_protocol(lambda d: (7, None), make_env(), starts=[0], episodes_per_start=1, max_steps=5,
                     progress=False)
    with pytest.raises(ResultsError, match="episodes_per_start"):
        run_protocol(roomiest_side, make_env(), episodes_per_start=0, progress=False)
    # The results would name a protocol whose noise the env's sensor does not have.
    with pytest.raises(ResultsError, match=r"noise_std_m=0.05, not the paper protocol's"):
        run_protocol(roomiest_side, make_env(noise=0.05), starts=[0], episodes_per_start=1, max_steps=5,
                     progress=False)
