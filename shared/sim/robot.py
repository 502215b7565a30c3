"""The TurtleBot-like robot: a planar disc on slide-x, slide-y and hinge-yaw joints,
driven by velocity actuators so that its contacts with walls register (mocap bodies
would pass through them).

``build_model`` adds the robot to a world's static scene and compiles it; ``Robot``
wraps the compiled model with pose access, unicycle commands and contact queries.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from shared.config import EnvConfig, SensorConfig

ROBOT_BODY = "robot"
ROBOT_GEOM = "robot_base"
CAMERA_NAME = "depth_camera"
FLOOR_GEOM = "floor"
ROBOT_HEIGHT_M = 0.30  # TurtleBot 2 base + plates; the camera sits above it
# Velocity-servo gain (N*s/m and N*m*s/rad) and mass: stiff enough that the disc reaches the
# commanded velocity within a couple of physics steps, so displacement per control period
# matches v*T to a few millimetres.
_KV_LINEAR = 3000.0
_KV_ANGULAR = 300.0
_MASS_KG = 6.0
ROBOT_CONTACT_BITS = 1
"""The robot geom's contype and conaffinity: an obstacle collides with it only if its own contype or
conaffinity shares a bit with these."""
ROBOT_GEOM_GROUP = 5
"""The robot body's geom group, which no world geom may use: the GL depth camera hides this group
(the robot must not see itself) and would hide a world geom in it too."""
MAX_TWIST_MPS = 2.0
MAX_TWIST_RPS = 6.0
"""The fastest command the robot takes (a TurtleBot 3 does 0.26 m/s and 1.8 rad/s); tens of m/s
would carry the disc through a wall between two contact checks."""

# A spec nobody edits: MuJoCo's built-in <option>, <size>, <compiler> mass settings and <default>
# values. The robot and its physics take these, not a world file's, which could otherwise disable
# contacts or actuation, limit the robot's joints or starve it of memory.
_BUILTIN = mujoco.MjSpec()
_OPTION_FIELDS = tuple(f for f in dir(_BUILTIN.option) if not f.startswith("_"))
_SIZE_FIELDS = ("memory", "nstack", "njmax", "nconmax")
_MASS_FIELDS = ("settotalmass", "boundmass", "boundinertia", "balanceinertia", "inertiafromgeom")
ARENA_BASE_BYTES = 1 << 20
ARENA_PER_GEOM_BYTES = 1 << 10
"""The MjData arena (contacts, constraints, scratch stack) ``build_model`` gives a world: this base
plus this much per geom. MuJoCo's default is 13 MiB or more per MjData whatever the model, sized for
many moving bodies; here one disc moves. Measured use: ~1.4 KB a step in a procedural world, 0.34 MB
for a 1024 x 1024 per-pixel image and 121 contacts among 4086 geoms (the ray cast's stack grows
~36 B per geom, a contact ~1.5 KB). An env keeps an MjData for every world it plays (an actor 100),
and those arenas reserved 1.3 GB of heap, resident wherever reused or huge pages touch them."""


def add_robot(spec: mujoco.MjSpec, env: EnvConfig, sensor: SensorConfig) -> None:
    """Add the robot body, joints, actuators and camera site to ``spec`` (in place), each element
    from MuJoCo's built-in defaults, not the world's ``<default>``."""
    base = _BUILTIN.default
    body = spec.worldbody.add_body(default=base, name=ROBOT_BODY, pos=[0.0, 0.0, 0.0])
    unlimited = mujoco.mjtLimited.mjLIMITED_FALSE
    body.add_joint(default=base, name="robot_x", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[1, 0, 0], damping=0.0,
                   limited=unlimited)
    body.add_joint(default=base, name="robot_y", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 1, 0], damping=0.0,
                   limited=unlimited)
    body.add_joint(default=base, name="robot_yaw", type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1], damping=0.0,
                   limited=unlimited)
    r = env.robot_radius_m
    body.add_geom(
        default=base,
        name=ROBOT_GEOM,
        type=mujoco.mjtGeom.mjGEOM_CYLINDER,
        size=[r, ROBOT_HEIGHT_M / 2, 0.0],
        pos=[0.0, 0.0, ROBOT_HEIGHT_M / 2 + 0.01],  # 1 cm clearance: no floor contact
        mass=_MASS_KG,
        rgba=[0.2, 0.2, 0.25, 1.0],
        contype=ROBOT_CONTACT_BITS,
        conaffinity=ROBOT_CONTACT_BITS,
        group=ROBOT_GEOM_GROUP,
    )
    # The camera looks along the body's +x axis (the heading). MuJoCo cameras look along
    # their local -z with +y up, hence the rotation (xyaxes).
    # Intrinsics (not fovy) so that the GL renderer sees the same 57 x 43 degree pinhole
    # with non-square pixels as the ray-cast camera; sensor_size only sets the length unit.
    fx = (sensor.width / 2) / math.tan(math.radians(sensor.hfov_deg) / 2)
    fy = (sensor.height / 2) / math.tan(math.radians(sensor.vfov_deg) / 2)
    body.add_camera(
        default=base,
        name=CAMERA_NAME,
        pos=[sensor.mount_forward_m, 0.0, sensor.mount_height_m],
        xyaxes=[0, -1, 0, 0, 0, 1],
        resolution=[sensor.width, sensor.height],
        sensor_size=[sensor.width * 1e-5, sensor.height * 1e-5],
        focal_pixel=[fx, fy],
        principal_pixel=[0.0, 0.0],
    )
    for joint, kv in (("robot_x", _KV_LINEAR), ("robot_y", _KV_LINEAR), ("robot_yaw", _KV_ANGULAR)):
        act = spec.add_actuator(default=base, name=f"vel_{joint}", target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_velocity(kv=kv)
        act.ctrllimited = False
        act.forcelimited = False


def build_model(world_mjcf: str, env: EnvConfig, sensor: SensorConfig) -> mujoco.MjModel:
    """Compile a world's static scene with the robot added, under MuJoCo's built-in physics options
    and sizes whatever the world's MJCF sets (its ``<option>`` and ``<size>`` only concern moving
    bodies, and the robot is the only one), with an offscreen buffer that holds the camera's image and
    an arena sized for one moving disc (:data:`ARENA_BASE_BYTES`)."""
    spec = mujoco.MjSpec.from_string(world_mjcf)
    for field in _OPTION_FIELDS:
        setattr(spec.option, field, getattr(_BUILTIN.option, field))
    for field in _SIZE_FIELDS:
        setattr(spec, field, getattr(_BUILTIN, field))
    for field in _MASS_FIELDS:
        setattr(spec.compiler, field, getattr(_BUILTIN.compiler, field))
    spec.option.timestep = env.physics_timestep_s
    spec.option.gravity = [0.0, 0.0, 0.0]  # planar robot: no need to carry its weight
    # Stiff velocity servos on a light disc are unstable under explicit Euler; the implicit
    # integrator treats actuator damping implicitly and stays stable at any gain.
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    # The GL depth camera renders offscreen into this buffer: it must hold the image, whatever
    # MuJoCo's 640 x 480 default or the world's <visual><global offwidth> says.
    spec.visual.global_.offwidth = max(_BUILTIN.visual.global_.offwidth, sensor.width)
    spec.visual.global_.offheight = max(_BUILTIN.visual.global_.offheight, sensor.height)
    add_robot(spec, env, sensor)
    spec.memory = ARENA_BASE_BYTES + ARENA_PER_GEOM_BYTES * len(spec.geoms)
    return spec.compile()


@dataclass
class Robot:
    """Pose access, unicycle control and contact queries on a compiled model."""

    model: mujoco.MjModel
    data: mujoco.MjData

    def __post_init__(self) -> None:
        m = self.model
        self.body_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, ROBOT_BODY)
        self.geom_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, ROBOT_GEOM)
        self.floor_id = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, FLOOR_GEOM)
        self._qadr = np.array([m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)]
                               for j in ("robot_x", "robot_y", "robot_yaw")])
        self._dadr = np.array([m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)]
                               for j in ("robot_x", "robot_y", "robot_yaw")])
        self._act = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, f"vel_{j}")
                              for j in ("robot_x", "robot_y", "robot_yaw")])

    def set_pose(self, x: float, y: float, yaw: float) -> None:
        """Teleport the robot (zero velocity) and update kinematics."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self._qadr] = (x, y, yaw)
        mujoco.mj_forward(self.model, self.data)

    def state(self) -> np.ndarray:
        """The robot's full physical state (positions and velocities of its three joints)."""
        return np.concatenate([self.data.qpos[self._qadr], self.data.qvel[self._dadr]])

    def set_state(self, state: np.ndarray) -> None:
        """Restore a :meth:`state` exactly (velocities included, unlike :meth:`set_pose`)."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self._qadr] = state[:3]
        self.data.qvel[self._dadr] = state[3:]
        mujoco.mj_forward(self.model, self.data)

    def pose(self) -> tuple[float, float, float]:
        """(x, y, yaw) with yaw wrapped to (-pi, pi]."""
        x, y, yaw = self.data.qpos[self._qadr]
        return float(x), float(y), float(math.atan2(math.sin(yaw), math.cos(yaw)))

    def drive(self, linear_mps: float, angular_rps: float, substeps: int) -> bool:
        """Hold a unicycle command for ``substeps`` physics steps.

        The world-frame velocity targets follow the heading every step, so the disc
        moves along the arc a real differential drive would. Returns True if the robot
        body touched an obstacle at any step, its final pose included.
        """
        m, d = self.model, self.data
        qadr, act = self._qadr, self._act
        touched = False
        for _ in range(substeps):
            yaw = d.qpos[qadr[2]]
            d.ctrl[act[0]] = linear_mps * math.cos(yaw)
            d.ctrl[act[1]] = linear_mps * math.sin(yaw)
            d.ctrl[act[2]] = angular_rps
            mujoco.mj_step(m, d)
            if not touched and d.ncon:
                touched = self.touching_obstacle()
        mujoco.mj_forward(m, d)  # kinematics of the final state, for the camera
        # mj_step detects contacts before it integrates, so the motion of the last step is only
        # checked by the closing mj_forward's collision pass.
        if not touched and d.ncon:
            touched = self.touching_obstacle()
        return touched

    def touching_obstacle(self) -> bool:
        """True if the robot's body is in contact with any geom but the floor."""
        d = self.data
        for i in range(d.ncon):
            c = d.contact[i]
            g1, g2 = c.geom1, c.geom2
            if self.geom_id in (g1, g2):
                other = g2 if g1 == self.geom_id else g1
                if other != self.floor_id and c.dist <= 0.0:
                    return True
        return False
