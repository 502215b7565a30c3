"""Worlds with real MuJoCo: built-ins, procedural generation, user MJCF files, start checks."""

import hashlib
import math
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from shared.config import EnvConfig
from shared.sim import maps
from shared.sim.env import ExploreEnv
from shared.sim.robot import ROBOT_GEOM_GROUP
from shared.sim.world import (
    BUILTIN_WORLDS,
    NUM_STARTS,
    SceneBuilder,
    StartChecker,
    StartPose,
    World,
    WorldError,
    canonical_world_name,
    load_world,
    obstacle_geom_count,
    procedural_world,
    validate_starts,
    world_summary,
)

RADIUS = EnvConfig().robot_radius_m


def _assert_connected_with_starts(world: World) -> None:
    grid = maps.occupancy_grid(world)
    labels, count = maps.free_components(grid, RADIUS)
    assert count == 1, f"{world.name}: traversable space in {count} pieces"
    for s in world.starts:
        ix, iy = grid.world_to_cell(s.x, s.y)
        assert labels[iy, ix] == 0, f"{world.name}: start {s.name} is not in the traversable space"


@pytest.mark.parametrize("name", ["paper-indoor", "corridor"])
def test_builtin_world_has_12_valid_starts_and_is_connected(name):
    world = load_world(name)
    assert world.kind == "builtin" and world.name == name
    assert len(world.starts) == NUM_STARTS
    assert len({s.name for s in world.starts}) == NUM_STARTS and all(s.name for s in world.starts)
    checks = validate_starts(world)
    assert all(c.ok for c in checks)
    assert min(c.clearance_m for c in checks) >= 0.1
    assert min(c.free_ahead_m for c in checks) >= 1.0
    assert 2 < obstacle_geom_count(world) <= 80
    _assert_connected_with_starts(world)


def test_paper_indoor_is_about_12_m_and_has_narrow_gaps():
    world = load_world("paper-indoor")
    assert world.size_m == (12.0, 12.0)
    grid = maps.occupancy_grid(world)
    # The two hall boxes 0.3 m apart: the gap between them is free space the robot cannot enter.
    assert grid.is_free(-1.55, 3.3)
    trav = maps.traversable(grid, RADIUS)
    ix, iy = grid.world_to_cell(-1.55, 3.3)
    assert not trav[iy, ix]
    assert 0.55 < maps.free_area_m2(grid) / (12 * 12) < 0.95


def test_box_room_is_kept_for_tests():
    world = load_world("box-room")
    assert set(BUILTIN_WORLDS) >= {"box-room", "paper-indoor", "corridor"}
    validate_starts(world)
    _assert_connected_with_starts(world)


@pytest.mark.parametrize("name", ["paper-indoor", "corridor", "procedural:1"])
@pytest.mark.parametrize("table", ["train", "test"])
def test_first_step_from_every_start_is_collision_free_for_every_action(name, table):
    env = ExploreEnv(world=name, speed_table=table)
    try:
        for i in range(len(env.world.starts)):
            for action in range(5):
                env.reset(seed=0, options={"start_index": i})
                _, _, terminated, _, info = env.step(action)
                assert not terminated, f"{name} start {i} action {action}: {info['collision_cause']}"
    finally:
        env.close()


def test_procedural_is_deterministic_per_seed_and_differs_across_seeds():
    a, b = procedural_world(3), procedural_world(3)
    assert a.mjcf == b.mjcf and a.starts == b.starts and a.extent == b.extent
    c = procedural_world(4)
    assert c.mjcf != a.mjcf and c.starts != a.starts
    assert load_world("procedural:3") == a


@pytest.mark.parametrize("seed", [0, 1, 2, 5, 11])
def test_procedural_worlds_are_connected_with_12_valid_starts(seed):
    world = load_world(f"procedural:{seed}")
    assert world.kind == "procedural"
    w, h = world.size_m
    assert 8.0 <= w <= 14.0 and 8.0 <= h <= 14.0
    assert len(world.starts) == NUM_STARTS
    validate_starts(world)
    _assert_connected_with_starts(world)
    assert obstacle_geom_count(world) <= 80


@pytest.mark.parametrize("name", ["procedural:abc", "procedural:-1", "procedural:", "procedural: 5"])
def test_bad_procedural_seed_is_rejected(name):
    with pytest.raises(WorldError, match="seed"):
        load_world(name)


def test_unknown_world_name_lists_the_choices():
    with pytest.raises(WorldError, match="paper-indoor"):
        load_world("no-such-world")


def test_validate_starts_names_each_bad_start():
    b = SceneBuilder("probe", (-3.0, -3.0, 3.0, 3.0))
    b.boundary()
    b.wall(1.0, -3.0, 1.0, 3.0)  # near face at x = 0.95
    starts = [StartPose(-2.0, 0.0, 0.0, "fine"),
              StartPose(0.3, 0.0, 0.0, "facing-wall"),    # 0.65 m free ahead
              StartPose(0.8, 0.0, math.pi, "in-wall"),     # disc overlaps the wall
              StartPose(0.72, 0.0, math.pi, "too-close")]  # 0.05 m clearance
    world = b.build("probe", starts)
    with pytest.raises(WorldError) as err:
        validate_starts(world)
    msg = str(err.value)
    assert "world 'probe'" in msg and "'fine'" not in msg
    assert "'facing-wall'" in msg and "straight ahead" in msg
    assert "'in-wall'" in msg and "inside or touching" in msg
    assert "'too-close'" in msg and "needs >= 0.1 m" in msg
    # Numbered from 1, as every table and `worlds starts` number them.
    assert "start 2 'facing-wall'" in msg and "start 3 'in-wall'" in msg and "start 4 'too-close'" in msg


def test_a_pose_that_is_not_finite_is_no_valid_start():
    checker = StartChecker(load_world("box-room"))
    for pose in ((math.nan, 0.0, 0.0), (0.0, math.inf, 0.0), (0.0, 0.0, math.nan)):
        check = checker.check(*pose)
        assert not check.ok and check.touching and "not finite" in check.problems[0]
    assert checker.check(0.0, 0.0, -math.pi / 2).ok  # the checker goes on as before


def test_canonical_world_names_load_one_world():
    assert canonical_world_name("procedural:007") == "procedural:7"
    assert canonical_world_name("procedural:0") == "procedural:0"
    assert canonical_world_name("box-room") == "box-room" and canonical_world_name("procedural:x") == "procedural:x"
    assert load_world("procedural:007") is load_world("procedural:7")


# ---------------------------------------------------------------------------
# User MJCF files
# ---------------------------------------------------------------------------

_ROOM = """
<mujoco model="user-room">
  <compiler angle="degree"/>
  {head}
  <worldbody>
    {floor}
    <geom name="north" type="box" pos="0 3 1" size="3 0.1 1"/>
    <geom name="south" type="box" pos="0 -3 1" size="3 0.1 1"/>
    <geom name="east" type="box" pos="3 0 1" size="0.1 3 1"/>
    <geom name="west" type="box" pos="-3 0 1" size="0.1 3 1"/>
    <body name="pillar" pos="1.5 1.5 0"><geom type="cylinder" size="0.3 1" pos="0 0 1"/></body>
    {sites}
  </worldbody>
</mujoco>
"""


def _write(tmp_path: Path, name: str, sites: str, floor: str = '<geom name="ground" type="plane" size="0 0 1"/>',
           extra: str = "", head: str = "") -> Path:
    path = tmp_path / name
    path.write_text(_ROOM.format(floor=floor, sites=sites + extra, head=head))
    return path


def test_user_world_loads_with_start_yaw_from_site_orientation(tmp_path):
    path = _write(tmp_path, "room.xml",
                  '<site name="start_south" pos="0 -2 0" euler="0 0 90"/>'
                  '<site name="start_west" pos="-2 0.5 0" quat="0.3826834 0 0 0.9238795"/>'  # 135 degrees
                  '<site name="marker" pos="0 0 0"/>')
    world = load_world(str(path))
    assert world.kind == "file" and world.name == str(path)
    assert [s.name for s in world.starts] == ["start_south", "start_west"]
    south, west = world.starts
    assert (south.x, south.y) == pytest.approx((0.0, -2.0))
    assert south.yaw == pytest.approx(math.pi / 2, abs=1e-6)
    assert west.yaw == pytest.approx(3 * math.pi / 4, abs=1e-6)
    assert world.extent == pytest.approx((-3.1, -3.1, 3.1, 3.1))
    assert 'name="floor"' in world.mjcf and 'name="ground"' not in world.mjcf  # plane renamed
    grid = maps.occupancy_grid(world)
    assert not grid.is_free(1.5, 1.5) and grid.is_free(0.0, 0.0)  # the pillar in a child body
    env = ExploreEnv(world=str(path))
    try:
        env.reset(seed=0, options={"start_index": 1})
        assert env.robot.pose()[2] == pytest.approx(3 * math.pi / 4, abs=1e-6)
    finally:
        env.close()


def test_user_world_without_a_plane_gets_a_floor(tmp_path):
    path = _write(tmp_path, "nofloor.xml", '<site name="start_a" pos="0 0 0"/>', floor="")
    world = load_world(str(path))
    assert 'name="floor"' in world.mjcf
    validate_starts(world)


def test_broken_xml_names_the_file_and_mujocos_message(tmp_path):
    path = tmp_path / "broken.xml"
    path.write_text("<mujoco><worldbody><geom type='box' size='1 1 1'</worldbody></mujoco>")
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert str(path) in str(err.value) and "cannot parse" in str(err.value) and "XML" in str(err.value)


def test_missing_file_is_named(tmp_path):
    with pytest.raises(WorldError, match="does not exist"):
        load_world(str(tmp_path / "nowhere.xml"))


def test_file_without_start_sites_is_rejected(tmp_path):
    path = _write(tmp_path, "nostarts.xml", '<site name="marker" pos="0 0 0"/>')
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert str(path) in str(err.value) and "start_" in str(err.value)


def test_start_inside_an_obstacle_names_file_and_site(tmp_path):
    path = _write(tmp_path, "inside.xml", '<site name="start_ok" pos="0 -2 0" euler="0 0 90"/>'
                                          '<site name="start_in_pillar" pos="1.5 1.5 0"/>')
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    msg = str(err.value)
    assert str(path) in msg and "start_in_pillar" in msg and "inside or touching" in msg
    assert "start_ok" not in msg


def test_start_touching_an_obstacle_names_file_and_site(tmp_path):
    # Centre 0.1 m from the pillar's surface: the 0.18 m disc overlaps it by 8 cm.
    x = 1.5 - 0.3 - 0.1
    path = _write(tmp_path, "touch.xml", f'<site name="start_touching" pos="{x} 1.5 0" euler="0 0 180"/>')
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert str(path) in str(err.value) and "start_touching" in str(err.value)
    assert "inside or touching" in str(err.value)


@pytest.mark.parametrize("body, what", [
    ('<body name="door" pos="0 0 0"><joint type="hinge" axis="0 0 1"/><geom type="box" size="0.1 0.5 1" pos="0 0 1"/></body>',
     "door"),
    ('<body name="ball" pos="-1 -1 0.5"><freejoint/><geom type="sphere" size="0.1"/></body>', "ball"),
])
def test_bodies_that_can_move_are_rejected(tmp_path, body, what):
    path = _write(tmp_path, "moving.xml", '<site name="start_a" pos="0 -2 0"/>', extra=body)
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert str(path) in str(err.value) and "not static" in str(err.value) and what in str(err.value)


@pytest.mark.parametrize("head, setting", [
    ('<option><flag contact="disable"/></option>', '<flag contact="disable">'),
    ('<option><flag actuation="disable"/></option>', '<flag actuation="disable">'),
    ('<option><flag constraint="disable"/></option>', '<flag constraint="disable">'),
    ('<option><flag override="enable"/></option>', '<flag override="enable">'),
    ('<option actuatorgroupdisable="0"/>', "actuatorgroupdisable"),
    ('<option wind="5 0 0"/>', "wind"),
    ('<option density="1.2" viscosity="0.1"/>', "density, viscosity"),
])
def test_physics_options_that_would_reach_the_robot_are_refused(tmp_path, head, setting):
    path = _write(tmp_path, "option.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>', head=head)
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert str(path) in str(err.value) and f"<option> sets {setting}" in str(err.value)
    assert "\n" not in str(err.value)


def test_options_the_robot_does_not_take_are_accepted(tmp_path):
    # The env sets the timestep, gravity and integrator itself; a world may say what it likes, and
    # the solver's own flags cannot change whether the robot collides.
    path = _write(tmp_path, "timestep.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>',
                  head='<option timestep="0.002" gravity="0 0 -1" integrator="RK4">'
                       '<flag warmstart="disable" energy="enable" invdiscrete="enable"/></option>')
    assert load_world(str(path)).starts[0].name == "start_a"


@pytest.mark.parametrize("attrs, what", [
    ('contype="2" conaffinity="2"', "contype 2, conaffinity 2"),
    ('contype="0" conaffinity="0"', "contype 0, conaffinity 0"),
])
def test_an_obstacle_the_robot_would_drive_through_is_refused(tmp_path, attrs, what):
    path = _write(tmp_path, "ghost.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>',
                  extra=f'<geom name="kerb" type="box" pos="-1 0 0.025" size="0.5 0.5 0.025" {attrs}/>')
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert f"'kerb' ({what})" in str(err.value) and "never collide with the robot" in str(err.value)
    # Either bit shared with the robot's is a collision.
    for ok in ('contype="3" conaffinity="0"', 'contype="0" conaffinity="1"'):
        _write(tmp_path, "solid.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>',
               extra=f'<geom name="kerb" type="box" pos="-1 0 0.025" size="0.5 0.5 0.025" {ok}/>')
        assert load_world(str(tmp_path / "solid.xml")).kind == "file"


@pytest.mark.parametrize("margin", ["0.5", "-0.1"])  # short of it, or (below 0) into it
def test_an_obstacle_that_would_stop_the_robot_short_of_it_or_let_it_in_is_refused(tmp_path, margin):
    path = _write(tmp_path, "margin.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>',
                  extra=f'<geom name="cushion" type="box" pos="-1 0 1" size="0.3 0.3 1" margin="{margin}"/>')
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert f"'cushion' ({float(margin):g} m)" in str(err.value) and "contact margin" in str(err.value)


@pytest.mark.parametrize("extra, what", [
    ('<geom name="glass" type="box" pos="-1 0 1" size="0.5 0.5 1" rgba="1 1 1 0"/>', "'glass'"),
    ('<geom name="glass" type="box" pos="-1 0 1" size="0.5 0.5 1" material="clear"/>', "'glass'"),
])
def test_an_obstacle_the_camera_cannot_see_is_refused(tmp_path, extra, what):
    head = '<asset><material name="clear" rgba="1 1 1 0"/></asset>'
    path = _write(tmp_path, "glass.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>', extra=extra, head=head)
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert what in str(err.value) and "fully transparent" in str(err.value)


def test_a_geom_in_the_robots_group_is_refused(tmp_path):
    path = _write(tmp_path, "group.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>',
                  extra=f'<geom name="pillar2" type="box" pos="-1 0 1" size="0.3 0.3 1" group="{ROBOT_GEOM_GROUP}"/>')
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert "'pillar2'" in str(err.value) and f"group {ROBOT_GEOM_GROUP}" in str(err.value)
    # Group 3, which the robot used to take (and many MJCF files use for collision geoms), is a world's.
    _write(tmp_path, "group3.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>',
           extra='<geom name="pillar2" type="box" pos="-1 0 1" size="0.3 0.3 1" group="3"/>')
    assert load_world(str(tmp_path / "group3.xml")).kind == "file"


@pytest.mark.parametrize("floor", [
    '<geom name="floor" type="box" pos="0 0 1" size="0.05 2 1"/>',   # a wall the robot would not touch
    '<geom name="floor" type="plane" pos="0 0 0.2" size="0 0 1"/>',  # a floor above the robot's wheels
    '<geom name="floor" type="plane" euler="180 0 0" size="0 0 1"/>',  # facing down
])
def test_a_floor_that_is_no_floor_is_refused(tmp_path, floor):
    path = _write(tmp_path, "floor.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>', floor=floor)
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert "geom 'floor' rises above z = 0" in str(err.value)


@pytest.mark.parametrize("floor", [
    '<geom name="floor" type="box" pos="0 0 -0.05" size="5 5 0.05"/>',  # a slab whose top is z = 0
    '<geom name="floor" type="plane" pos="0 0 -0.0001" size="0 0 1"/>',  # a hair below
    '<geom name="ground" type="plane" pos="0 0 -0.0001" size="0 0 1"/>',  # unnamed: taken as the floor
])
def test_a_floor_written_as_a_slab_or_a_hair_below_zero_is_a_floor(tmp_path, floor):
    path = _write(tmp_path, "floor.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>', floor=floor)
    env = ExploreEnv(world=str(path), start_index=0)
    try:
        env.reset(seed=0)
        for _ in range(5):
            *_, terminated, _, info = env.step(2)  # 0.6 m straight ahead in an open room
            assert not terminated, info
    finally:
        env.close()


@pytest.mark.parametrize("floor,covers", [
    ('<geom name="floor" type="plane" size="1 1 1"/>', False),  # a 2 m tile in a 6 m room
    ('<geom name="floor" type="box" pos="0 0 -0.05" size="1 5 0.05"/>', False),  # a slab, too narrow along x
    ('<geom name="floor" type="plane" size="3.1 0 1"/>', True),  # the room's width, infinite along y
    ('<geom name="floor" type="box" pos="0 0 -0.05" size="3 3 0.05" euler="0 0 90"/>', True),  # to the walls' middle
    ('<geom name="floor" type="box" pos="0 0 -0.05" size="2.1 5 0.05" euler="0 0 45"/>', False),  # turned: corners bare
])
def test_a_floor_that_ends_before_the_room_does_is_refused(tmp_path, floor, covers):
    # the camera saw no floor beyond its edge (0 m, "no return", under 95% of the image instead of 61%)
    path = _write(tmp_path, "tile.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>', floor=floor)
    if covers:
        env = ExploreEnv(world=str(path), start_index=0)
        try:
            obs, _ = env.reset(seed=0)
            assert (obs[-20:] > 0).all()  # the floor in the image's bottom rows, everywhere
        finally:
            env.close()
        return
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert "its geom 'floor' ends before the open space around the starts does" in str(err.value)


def test_a_start_site_that_is_not_finite_is_refused(tmp_path):
    path = _write(tmp_path, "nan.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>'
                                       '<site name="start_nan" pos="nan 0 0"/>')
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert "start site 'start_nan'" in str(err.value) and "finite" in str(err.value)


@pytest.mark.parametrize("obstacle", ['<geom name="crate" type="box" size="0.2 0.2 0.2" pos="nan 1 0.2"/>',
                                      '<geom name="crate" type="box" size="0.2 inf 0.2" pos="1 1 0.2"/>',
                                      '<body pos="1 nan 0"><geom name="crate" type="box" size="0.2 0.2 0.2"/></body>'])
def test_an_obstacle_placed_or_sized_by_nan_or_inf_is_refused_and_mujocos_warning_is_logged(
        tmp_path, monkeypatch, caplog, obstacle):
    """Such a geom was blamed on a start ('inside or touching an obstacle geom #1', 9 cm deep, far from
    it), and MuJoCo's NaN warning was printed and appended to MUJOCO_LOG.TXT in the folder the process
    was started from: it goes to the log instead."""
    path = _write(tmp_path, "nan.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>', extra=obstacle)
    monkeypatch.chdir(tmp_path)
    with caplog.at_level("WARNING", logger="shared.sim.world"), pytest.raises(WorldError) as err:
        load_world(str(path))
    assert "geom(s) 'crate' whose position, orientation or size is not finite" in str(err.value)
    assert ("nan" not in obstacle) or any("MuJoCo: XML contains a 'NaN'" in r.message for r in caplog.records)
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()


def test_a_size_the_robot_cannot_live_with_does_not_reach_it(tmp_path):
    # Memory for the static scene, not for the robot's contacts: the robot gets MuJoCo's default.
    path = _write(tmp_path, "memory.xml", '<site name="start_a" pos="0 -2 0" euler="0 0 90"/>',
                  head='<size memory="2K"/>')
    env = ExploreEnv(world=str(path), start_index=0)
    try:
        env.reset(seed=0)
        for _ in range(30):
            *_, terminated, _, info = env.step(2)
            if terminated:
                break
        assert terminated and info["collision_cause"] in ("depth", "contact")
    finally:
        env.close()


def test_a_body_named_robot_is_rejected(tmp_path):
    path = _write(tmp_path, "robot.xml", '<site name="start_a" pos="0 -2 0"/>',
                  extra='<body name="robot" pos="2 -2 0"><geom type="box" size="0.1 0.1 0.1" pos="0 0 0.1"/></body>')
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert str(path) in str(err.value) and "'robot'" in str(err.value)


def test_names_the_robot_needs_are_reported_when_taken(tmp_path):
    path = _write(tmp_path, "camera.xml", '<site name="start_a" pos="0 -2 0"/>',
                  extra='<camera name="depth_camera" pos="0 0 2"/>')
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert str(path) in str(err.value) and "with the robot added" in str(err.value)


def test_the_example_world_file_loads():
    path = Path(__file__).resolve().parents[3] / "shared" / "sim" / "worlds" / "two_rooms.xml"
    world = load_world(str(path))
    assert [s.name for s in world.starts] == ["start_west_room", "start_door", "start_east_room",
                                              "start_north_east"]
    assert world.starts[0].yaw == pytest.approx(math.radians(30))
    assert world.size_m == pytest.approx((8.1, 5.1))
    _assert_connected_with_starts(world)


def test_world_summary_reports_plain_facts():
    summary = world_summary("paper-indoor")
    assert summary["name"] == "paper-indoor" and summary["kind"] == "builtin"
    assert summary["size_m"] == [12.0, 12.0] and summary["num_starts"] == 12
    assert summary["num_obstacle_geoms"] == obstacle_geom_count(load_world("paper-indoor"))
    assert 70.0 < summary["free_area_m2"] < 140.0 and summary["connected"] is True
    assert world_summary("procedural:2")["kind"] == "procedural"
    assert all(type(v) in (str, int, float, bool, list) for v in summary.values())  # JSON-ready


def test_a_world_built_with_lists_still_makes_an_env():
    # The starts-fit check is cached per world: a World whose starts or extent are lists is not
    # hashable, and ExploreEnv raised TypeError for one.
    import dataclasses

    box = load_world("box-room")
    world = dataclasses.replace(box, starts=list(box.starts), extent=list(box.extent))
    env, same = ExploreEnv(world=world, start_index=0), ExploreEnv(world=box, start_index=0)
    try:
        # the same env as the tuple-built world's: the same start pose and the same first image
        depth, info = env.reset(seed=0)
        want_depth, want_info = same.reset(seed=0)
        assert np.allclose(info["pose"], want_info["pose"]) and np.array_equal(depth, want_depth)
        assert np.allclose(info["pose"][:2], (box.starts[0].x, box.starts[0].y), atol=0.5), info["pose"]
    finally:
        env.close()
        same.close()


@pytest.mark.parametrize("where", ["model", "geom", "site", "comment"])
def test_a_file_that_is_not_utf8_is_a_one_line_world_error(tmp_path, where):
    # MuJoCo reads any bytes; the names (and MJCF text) it hands back would not decode.
    text = _ROOM.format(floor='<geom name="ground" type="plane" size="0 0 1"/>', head="",
                        sites='<site name="start_a" pos="0 -2 0" euler="0 0 90"/>')
    marked = {"model": ('model="user-room"', 'model="user-r\udcffoom"'),
              "geom": ('name="ground"', 'name="gr\udcffund"'),
              "site": ('<site name="start_a" pos="0 -2 0" euler="0 0 90"/>',
                       '<site name="start_a" pos="0 -2 0" euler="0 0 90"/><site name="\udcff" pos="0 0 0"/>'),
              "comment": ('<compiler angle="degree"/>', '<!-- \udcff --><compiler angle="degree"/>')}[where]
    assert marked[0] in text
    path = tmp_path / "latin1.xml"
    path.write_bytes(text.replace(*marked, 1).encode("utf-8", "surrogateescape"))
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert str(path) in str(err.value) and "not UTF-8" in str(err.value) and "\n" not in str(err.value)


def test_a_directory_named_like_a_world_file_is_not_called_missing(tmp_path):
    (tmp_path / "world.xml").mkdir()
    with pytest.raises(WorldError, match="is not a file"):
        load_world(str(tmp_path / "world.xml"))


@pytest.mark.parametrize("orient", ['euler="0 90 0"', 'zaxis="1 0 0"', 'xyaxes="0 0 -1 0 1 0"'])
def test_a_start_site_whose_heading_points_up_or_down_is_refused(tmp_path, orient):
    # Its heading would be atan2 of rounding noise: some arbitrary direction, silently.
    path = _write(tmp_path, "tilted.xml", f'<site name="start_a" pos="0 -2 0" euler="0 0 90"/>'
                                          f'<site name="start_tilted" pos="0 0 0" {orient}/>')
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert "start site 'start_tilted'" in str(err.value) and "straight up or down" in str(err.value)
    path = _write(tmp_path, "leaning.xml", '<site name="start_a" pos="0 -2 0" euler="0 60 90"/>')
    assert load_world(str(path)).starts[0].yaw == pytest.approx(math.pi / 2, abs=1e-6)  # a tilt keeps its heading


@pytest.mark.parametrize("z", ["5", "-3", "0.5"])
def test_a_start_site_off_the_floor_is_refused(tmp_path, z):
    # only its x and y were read: a site 5 m up (a typo, a site meant for a camera) started the robot below it
    path = _write(tmp_path, "high.xml", f'<site name="start_a" pos="0 -2 0" euler="0 0 90"/>'
                                        f'<site name="start_up" pos="0 0 {z}"/>')
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    msg = str(err.value)
    assert str(path) in msg and f"start site 'start_up' is at z = {z}, off the floor" in msg and "\n" not in msg
    path = _write(tmp_path, "centred.xml", '<site name="start_a" pos="0 -2 0.15" euler="0 0 90"/>')
    assert load_world(str(path)).starts[0].y == pytest.approx(-2.0)  # at the robot's centre it marks where it stands


@pytest.mark.parametrize("pos", ["6 0 0", "20 20 0", "0 -3.5 0"])
def test_a_start_site_outside_the_walls_is_refused(tmp_path, pos):
    # the world's extent was stretched to take it in: the robot started on the open floor beyond the walls
    path = _write(tmp_path, "outside.xml", f'<site name="start_a" pos="0 -2 0" euler="0 0 90"/>'
                                           f'<site name="start_out" pos="{pos}" euler="0 0 -90"/>')
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    msg = str(err.value)
    assert str(path) in msg and "start site(s) 'start_out' at (" in msg and "start_a" not in msg
    assert "outside the walls that enclose its other starts" in msg and "\n" not in msg


def test_an_open_floor_takes_starts_anywhere_around_its_obstacles(tmp_path):
    # no walls enclose any start: every start reaches the map's edge, none lies outside the others' walls
    path = tmp_path / "open.xml"
    path.write_text('<mujoco><worldbody><geom type="cylinder" pos="0 0 1" size="0.3 1"/>'
                    '<site name="start_a" pos="3 0 0" euler="0 0 90"/><site name="start_b" pos="-1 -5 0"/>'
                    '</worldbody></mujoco>')
    world = load_world(str(path))
    assert [s.name for s in world.starts] == ["start_a", "start_b"]
    assert world.extent == pytest.approx((-1.0, -5.0, 3.0, 0.3))


def test_a_start_in_the_notch_of_an_l_shaped_room_is_outside_its_walls(tmp_path):
    # within the walls' bounding box, yet on the open floor beyond them
    walls = "".join(f'<geom type="box" pos="{x} {y} 1" size="{hx} {hy} 1"/>' for x, y, hx, hy in (
        (0, -3, 3.05, 0.05), (-3, 0, 0.05, 3.05), (3, -1.5, 0.05, 1.55), (1.5, 0, 1.55, 0.05), (0, 1.5, 0.05, 1.55),
        (-1.5, 3, 1.55, 0.05)))
    path = tmp_path / "l-room.xml"
    path.write_text(f'<mujoco><worldbody>{walls}<site name="start_in" pos="-1.5 -1.5 0"/>'
                    '<site name="start_notch" pos="2 2 0" euler="0 0 90"/></worldbody></mujoco>')
    with pytest.raises(WorldError, match=r"start site\(s\) 'start_notch' at \(2, 2\) outside the walls"):
        load_world(str(path))
    path.write_text(path.read_text().replace('pos="2 2 0"', 'pos="-1.5 1.5 0"'))  # the room's other arm
    assert len(load_world(str(path)).starts) == 2


# -- the files a world's MJCF names ------------------------------------------------------------


def write_stl(path: Path, half: float) -> None:
    """A binary STL: a 1 m high box of half-width ``half`` standing on z = 0."""
    v = [(x, y, z) for x in (-half, half) for y in (-half, half) for z in (0.0, 1.0)]
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7), (2, 7, 6), (0, 2, 6),
             (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    body = b"".join(struct.pack("<3f", 0, 0, 0) + b"".join(struct.pack("<3f", *v[i]) for i in f) + b"\0\0"
                    for f in faces)
    path.write_bytes(bytes(80) + struct.pack("<I", len(faces)) + body)


def _write_png(path: Path, shade: int) -> None:
    """A 2 x 2 grey PNG."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    rows = b"".join(b"\0" + bytes([shade]) * 6 for _ in range(2))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">2I5B", 2, 2, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


_ASSET_ROOM = """<mujoco><compiler meshdir="meshes" texturedir="textures"/>
<asset><mesh name="obstacle" file="obstacle.stl"/><hfield name="terrain" file="terrain.bin" size="1 1 0.1 0.1"/>
<texture name="paint" type="2d" file="paint.png"/>
<texture name="sky" type="cube" fileright="face.png" fileleft="face.png" fileup="face.png" filedown="face.png"
 filefront="face.png" fileback="back.png"/>
<material name="painted" texture="paint"/></asset>
<worldbody><geom name="floor" type="plane" size="0 0 1"/>
<geom type="box" pos="0 3 1" size="3 0.1 1"/><geom type="box" pos="0 -3 1" size="3 0.1 1"/>
<geom type="box" pos="3 0 1" size="0.1 3 1"/><geom type="box" pos="-3 0 1" size="0.1 3 1"/>
<geom type="mesh" mesh="obstacle" pos="1.5 1.5 0" material="painted"/><body name="bone" pos="-1.5 1.5 3"/>
<site name="start_a" pos="-1.5 -1.5 0"/><site name="start_b" pos="1.5 -1.5 0"/></worldbody>
<deformable><skin name="cloth" file="cloth.skn"/></deformable></mujoco>"""
"""A user's room with a mesh obstacle and one file of every other kind MuJoCo reads beside the MJCF."""


def write_asset_world(folder: Path, mesh_half: float = 0.3) -> Path:
    """``folder/room.xml`` (:data:`_ASSET_ROOM`) and its files: meshes/obstacle.stl (a box of half-width
    ``mesh_half``), meshes/terrain.bin, meshes/cloth.skn, textures/paint.png, face.png and back.png."""
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    (folder / "textures").mkdir(exist_ok=True)
    write_stl(folder / "meshes" / "obstacle.stl", mesh_half)
    (folder / "meshes" / "terrain.bin").write_bytes(struct.pack("<2i4f", 2, 2, 0.0, 0.1, 0.2, 0.3))
    skin = struct.pack("<4i9f3i", 3, 0, 1, 1, 0, 0, 0, 0.1, 0, 0, 0, 0.1, 0, 0, 1, 2)  # 3 vertices, 1 face
    skin += b"bone".ljust(40, b"\0") + struct.pack("<7fi3i3f", 0, 0, 0, 1, 0, 0, 0, 3, 0, 1, 2, 1, 1, 1)
    (folder / "meshes" / "cloth.skn").write_bytes(skin)
    for name, shade in (("paint.png", 10), ("face.png", 20), ("back.png", 30)):
        _write_png(folder / "textures" / name, shade)
    (folder / "room.xml").write_text(_ASSET_ROOM)
    return folder / "room.xml"


def test_a_world_file_records_the_content_of_every_file_its_mjcf_names(tmp_path):
    # An MJCF world's digest covered its text, not the mesh beside it: a replaced obstacle.stl was
    # another world under the same text.
    world = load_world(str(write_asset_world(tmp_path)))
    named = {(kind, file) for kind, file, _ in world.asset_sha256}
    assert named == {("mesh", "obstacle.stl"), ("hfield", "terrain.bin"), ("skin", "cloth.skn"),
                     ("texture", "paint.png"), ("texture", "face.png"), ("texture", "back.png")}
    before = world.asset_sha256
    edits = {"meshes/obstacle.stl": lambda p: write_stl(p, 0.5),  # another box
             "meshes/terrain.bin": lambda p: p.write_bytes(p.read_bytes()[:-4] + bytes(4)),  # another height
             "meshes/cloth.skn": lambda p: p.write_bytes(p.read_bytes().replace(b"\x00\x00\x80?", b"\x00\x00\x00?")),
             "textures/paint.png": lambda p: _write_png(p, 99), "textures/back.png": lambda p: _write_png(p, 99)}
    for file, edit in edits.items():
        path = tmp_path / file
        content = path.read_bytes()
        edit(path)
        edited = load_world(str(tmp_path / "room.xml")).asset_sha256
        assert {name for _, name, _ in set(edited) - set(before)} == {path.name}, file
        path.write_bytes(content)
    assert load_world(str(tmp_path / "room.xml")).asset_sha256 == before  # the content, not the file's time


def test_asset_files_are_found_as_mujoco_finds_them(tmp_path):
    # strippath drops a name's folders, an absolute name ignores the meshdir: the digest reads the
    # file MuJoCo reads, or a mesh elsewhere would not count.
    path = write_asset_world(tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    write_stl(elsewhere / "obstacle.stl", 0.4)
    base = load_world(str(path)).asset_sha256
    for head, file in (('<compiler strippath="true" ', "some/folder/obstacle.stl"),
                       ("<compiler ", str(elsewhere / "obstacle.stl"))):
        path.write_text(_ASSET_ROOM.replace("<compiler ", head).replace('file="obstacle.stl"', f'file="{file}"'))
        world = load_world(str(path))
        mesh = next(digest for kind, _, digest in world.asset_sha256 if kind == "mesh")
        target = tmp_path / "meshes" / "obstacle.stl" if "strippath" in head else elsewhere / "obstacle.stl"
        assert mesh == hashlib.sha256(target.read_bytes()).hexdigest(), file
    assert next(d for k, _, d in base if k == "mesh") != mesh  # the other box


def test_a_file_the_mjcf_names_that_is_missing_is_refused_by_mujoco(tmp_path):
    path = write_asset_world(tmp_path)
    (tmp_path / "meshes" / "obstacle.stl").unlink()
    with pytest.raises(WorldError) as err:
        load_world(str(path))
    assert "cannot compile it" in str(err.value) and "obstacle.stl" in str(err.value)


def test_built_in_and_procedural_worlds_name_no_files():
    assert load_world("paper-indoor").asset_sha256 == () and load_world("procedural:3").asset_sha256 == ()


_INCLUDING_ROOM = """<mujoco><asset><model name="part" file="part/part.xml"/></asset>
<worldbody><geom name="floor" type="plane" size="0 0 1"/>
<geom type="box" pos="0 3 1" size="3 0.1 1"/><geom type="box" pos="0 -3 1" size="3 0.1 1"/>
<geom type="box" pos="3 0 1" size="0.1 3 1"/><geom type="box" pos="-3 0 1" size="0.1 3 1"/>
<body pos="1.5 1.5 0"><attach model="part" body="part" prefix="p_"/></body>
<site name="start_a" pos="-1.5 -1.5 0" euler="0 0 45"/><site name="start_b" pos="1.5 -1.5 0" euler="0 0 135"/>
</worldbody></mujoco>"""
"""A room that attaches a model of its own file (``part/part.xml``) holding a mesh obstacle."""


def write_including_world(folder: Path, part_compiler: str = "", mesh_file: str = "obstacle.stl") -> Path:
    """``folder/room.xml`` (:data:`_INCLUDING_ROOM`) and ``folder/part/part.xml`` naming ``mesh_file``
    under ``<compiler part_compiler>``."""
    (folder / "part").mkdir(parents=True, exist_ok=True)
    (folder / "part" / "part.xml").write_text(
        f'<mujoco><compiler {part_compiler}/><asset><mesh name="m" file="{mesh_file}"/></asset>'
        '<worldbody><body name="part"><geom type="mesh" mesh="m"/></body></worldbody></mujoco>')
    (folder / "room.xml").write_text(_INCLUDING_ROOM)
    return folder / "room.xml"


def test_a_model_asset_whose_files_lie_beside_it_is_refused_not_loaded_with_others(tmp_path):
    # MuJoCo reads an attached model's mesh from that model's folder (or its own meshdir); the MJCF
    # text a World keeps names the bare file, found from the room's folder: a same-named mesh there
    # became the obstacle, another world than the file's, with the other mesh in its digest.
    write_stl(tmp_path / "obstacle.stl", 0.1)  # the room's own, unrelated file of that name
    for compiler, where in (("", "part"), ('meshdir="meshes"', "part/meshes")):
        path = write_including_world(tmp_path, compiler)
        (tmp_path / where).mkdir(parents=True, exist_ok=True)
        write_stl(tmp_path / where / "obstacle.stl", 0.4)
        with pytest.raises(WorldError) as err:
            load_world(str(path))
        message = str(err.value)
        assert "<model>" in message and "absolute" in message and "\n" not in message, compiler


def test_a_model_asset_whose_files_are_named_absolute_loads_with_their_digest(tmp_path):
    mesh = tmp_path / "elsewhere" / "obstacle.stl"
    mesh.parent.mkdir()
    write_stl(mesh, 0.4)
    world = load_world(str(write_including_world(tmp_path, mesh_file=str(mesh))))
    assert world.asset_sha256 == (("mesh", str(mesh), hashlib.sha256(mesh.read_bytes()).hexdigest()),)
    assert StartChecker(world).check(1.5, 1.5 - 0.4 - RADIUS - 0.05, 0.0).clearance_m < 0.1  # the mesh is there
