"""``eval.jsonl``'s evaluation key: what makes two evaluations the same, world content included."""

from __future__ import annotations

from pathlib import Path

from shared.evaluation.eval_log import evaluation_digest, evaluation_key
from shared.evaluation.protocol import file_world_sha256

ROOM = """<mujoco><worldbody>
<geom type="box" pos="0 3 1" size="3 0.1 1"/><geom type="box" pos="0 -3 1" size="3 0.1 1"/>
<geom type="box" pos="3 0 1" size="0.1 3 1"/><geom type="box" pos="-3 0 1" size="0.1 3 1"/>
<geom type="cylinder" pos="{pillar_x} 0.5 1" size="0.3 1"/><site name="start_a" pos="-2 0 0"/>
</worldbody></mujoco>"""
"""A user's MJCF room with one start; the pillar at x = 2 is off the start's way, at -0.6 in it."""


def write_room(path: Path, pillar_x: float = 2.0) -> Path:
    """``path`` holding :data:`ROOM` with its pillar at ``pillar_x``."""
    path.write_text(ROOM.format(pillar_x=pillar_x))
    return path


ROW = {"policy_version": 12, "weights_sha256": "ab" * 32, "world": "box-room", "protocol": "robust",
       "protocol_config": {"name": "robust", "start_jitter_m": 0.05, "start_jitter_deg": 3.0,
                           "sensor_noise_std_m": 0.0012, "sensor_noise_quadratic_per_m": 0.0019,
                           "sensor_dropout_prob": 0.0},
       "episodes_per_start": 1, "max_steps": 3, "seed": 0}


def test_a_built_in_worlds_evaluation_keeps_the_digest_it_had_before_world_content_was_keyed() -> None:
    # its runs' eval.jsonl rows and their eval-<v>-<8 hex> files must still stand for it
    assert file_world_sha256("box-room") is None and file_world_sha256("procedural:7") is None
    assert evaluation_digest(evaluation_key(ROW)) == "4f5839ddb8a115f3f3075cccde2ab4170017ced90eed709cee36213ed60cf6a8"


def test_a_world_files_content_is_part_of_its_evaluations_key(tmp_path: Path) -> None:
    # Keyed by its path alone, an MJCF file edited since stood for what was evaluated on the old file.
    world = write_room(tmp_path / "room.xml")
    row = {**ROW, "world": str(world), "world_sha256": file_world_sha256(str(world))}
    before = evaluation_key(row)
    write_room(world, pillar_x=-0.6)
    edited = evaluation_key({**row, "world_sha256": file_world_sha256(str(world))})
    assert before != edited and evaluation_digest(before) != evaluation_digest(edited)
    assert evaluation_key({**ROW, "world": str(world)}) not in (before, edited)  # a row from before the digest
