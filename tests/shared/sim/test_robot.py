"""The robot with real MuJoCo: its physics is cogexplore's whatever a world's MJCF says, and its
contacts are reported to the last physics step."""

import math

import mujoco
import numpy as np
import pytest

from shared.config import EnvConfig, SensorConfig
from shared.sim.robot import ROBOT_HEIGHT_M, Robot, build_model

RADIUS = EnvConfig().robot_radius_m
WALL_FACE_X = 1.0


def _scene(head: str = "") -> str:
    """A floor and a wall whose face is at x = WALL_FACE_X, with ``head`` before the worldbody (the
    wall's contact settings explicit: a world's own geoms are load_world_file's to check)."""
    return (f'<mujoco>{head}<worldbody><geom name="floor" type="plane" size="0 0 1"/>'
            f'<geom name="wall" type="box" pos="{WALL_FACE_X + 0.05} 0 1" size="0.05 2 1" contype="1" '
            'conaffinity="1" margin="0"/></worldbody></mujoco>')


def _robot(mjcf: str) -> Robot:
    model = build_model(mjcf, EnvConfig(), SensorConfig(width=8, height=8))
    return Robot(model, mujoco.MjData(model))


def _drive_from(robot: Robot, x: float, linear: float, substeps: int) -> bool:
    robot.set_pose(x, 0.0, 0.0)
    return robot.drive(linear, 0.0, substeps)


@pytest.mark.parametrize("head", [
    '<option><flag contact="disable"/></option>',
    '<option><flag constraint="disable"/></option>',
    '<option><flag actuation="disable"/></option>',
    '<option actuatorgroupdisable="0"/>',
    '<option wind="-50 0 0" density="1000" viscosity="10"/>',
    '<size memory="2K"/>',
    '<default><joint limited="true" range="-0.3 0.3" armature="5" frictionloss="100" stiffness="1000"/></default>',
    '<default><general gear="0" ctrllimited="true" ctrlrange="0 0"/></default>',
    '<default><geom contype="0" conaffinity="0" margin="0.5" friction="0 0 0"/></default>',
    '<compiler settotalmass="1000"/>',
])
def test_a_worlds_mjcf_settings_do_not_reach_the_robot(head):
    plain, hostile = _robot(_scene()), _robot(_scene(head))
    # Free driving: the same physics to the bit, whatever the world set.
    for robot in (plain, hostile):
        _drive_from(robot, -2.0, 0.25, 50)
    np.testing.assert_array_equal(hostile.state(), plain.state())
    assert hostile.pose()[0] == pytest.approx(-2.0 + 0.25 * 0.5, abs=0.01)
    # Driving into the wall: it stops the robot, and the contact is reported.
    assert _drive_from(hostile, WALL_FACE_X - RADIUS - 0.2, 0.5, 100)
    assert hostile.pose()[0] < WALL_FACE_X - RADIUS + 0.02


def test_a_contact_made_in_the_last_physics_step_is_reported():
    robot = _robot(_scene())
    # 1 mm from the wall, one physics step of 0.25 m/s moves the disc 2 mm: into contact only after
    # that step's motion, which mj_step checks before it moves.
    assert _drive_from(robot, WALL_FACE_X - RADIUS - 0.001, 0.25, substeps=1)
    assert robot.touching_obstacle()
    # 3 mm away, the step ends short of the wall: no contact, none reported.
    assert not _drive_from(robot, WALL_FACE_X - RADIUS - 0.003, 0.25, substeps=1)
    assert not robot.touching_obstacle()


def test_the_robot_stands_clear_of_the_floor():
    robot = _robot(_scene())
    assert not _drive_from(robot, -2.0, 0.25, 10)
    assert robot.data.geom_xpos[robot.geom_id][2] == pytest.approx(ROBOT_HEIGHT_M / 2 + 0.01)


def test_the_arena_is_sized_for_one_disc_and_holds_a_pile_up_of_contacts():
    # MuJoCo's default arena is 13 MiB per MjData, and an actor keeps an MjData for each of its 100
    # worlds: 1.3 GB of heap for a disc that uses ~1.4 KB a step.
    posts = "".join(f'<geom type="cylinder" pos="{0.12 * math.cos(a):.4f} {0.12 * math.sin(a):.4f} 0.5" '
                    f'size="0.01 0.5" contype="1" conaffinity="1"/>'
                    for a in np.linspace(0, 2 * math.pi, 40, endpoint=False))
    mjcf = _scene().replace("</worldbody>", posts + "</worldbody>")
    robot = _robot(mjcf)
    assert robot.model.narena < 2 * 2**20
    # dropped inside a ring of 40 posts: every one touches the disc, and all their contacts fit
    warnings_before = robot.data.warning[mujoco.mjtWarning.mjWARN_CONTACTFULL].number
    assert _drive_from(robot, 0.0, 0.3, 10)
    assert robot.data.maxuse_con >= 40
    assert robot.data.maxuse_arena < robot.model.narena / 4
    assert robot.data.warning[mujoco.mjtWarning.mjWARN_CONTACTFULL].number == warnings_before
