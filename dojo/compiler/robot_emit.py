"""Emit a robot spec into a MuJoCo world with the MjSpec editing API, and name what the backends need.

Every robot is two identical arms. The spec writes each link in the arm's zero-pose frame (see
robot.schema.json), so a link body sits at its joint's anchor with identity orientation relative to its parent,
and the written offsets are exactly the distances between joint anchors: the forward kinematics test checks the
compiled model against them.

Choices that are the same for every robot, and why:
- Geometry is primitives only (capsule, box, sphere): MJX collides them, meshes would need convex hulls.
- Robot geoms have contype 2 / conaffinity 1: they touch the world (table, objects) but not each other, so the
  folded zero pose and the arms' shared workspace never produce self-contacts (the real arms have no
  self-collision model either; the policy is responsible for not crossing the arms).
- Moving bodies get gravcomp = 1: the real ARX and AgileX controllers compensate gravity in firmware, and it
  lets the position servos track without a steady-state sag. Payloads are not compensated.
- Each gripper is two slide joints kept equal by a joint equality; a fixed tendon sums them, so the tendon
  length is the opening width and one position servo on it takes the width in metres as its control. Pads
  have torsional friction (condim 4) and stiff contacts, and `apply_physics` sets an elliptic cone with a high
  impratio, so a squeezed object neither sinks into the pads nor creeps out of them.

Action and state layout (joint mode, D = 14): [left joints 1..6, left gripper, right joints 1..6, right
gripper]; grippers are normalised 0 (closed) .. 1 (open at max_width); `gripper_to_width` maps them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable, Sequence

import mujoco
import numpy as np

from dojo.compiler.robot_frames import frame_from_axes, look_at_quat, primitive_volume, unit

ROBOT_CONTYPE = 2
ROBOT_CONAFFINITY = 1
TABLE_TOP_Z = 0.75
TABLE_HALF_SIZE = (0.6, 0.4)
CAMERA_NAMES = ("head", "left_wrist", "right_wrist")

_INTEGRATORS = {
    "euler": mujoco.mjtIntegrator.mjINT_EULER,
    "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
    "rk4": mujoco.mjtIntegrator.mjINT_RK4,
}
_CONES = {"pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL, "elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC}
_GEOM_TYPES = {
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
    "box": mujoco.mjtGeom.mjGEOM_BOX,
    "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
}
_DEFAULT_LINK_RGBA = (0.82, 0.82, 0.85, 1.0)
# Finger pads: stiffer contacts than MuJoCo's default (0.02 s) so a squeezed object sinks in ~0.5 mm, not ~5 mm;
# priority 1 makes the pad's contact parameters win over the object's.
_PAD_TIMECONST = 0.005
_DEFAULT_FINGER_RGBA = (0.15, 0.15, 0.15, 1.0)


@dataclass(frozen=True)
class RobotHandles:
    """Names (and home values) of everything a backend reads or drives, in action order.

    Action order everywhere: left arm joints, left gripper, right arm joints, right gripper.
    """

    robot_id: str
    arms: tuple[str, ...]
    arm_joints: tuple[str, ...]
    finger_joints: tuple[tuple[str, str], ...]
    gripper_tendons: tuple[str, ...]
    gripper_actuators: tuple[str, ...]
    actuators: tuple[str, ...]
    ee_sites: tuple[str, ...]
    cameras: tuple[str, ...]
    home_qpos: dict[str, float]
    home_ctrl: tuple[float, ...]
    gripper_max_width: float
    control_hz: float
    n_substeps: int

    @property
    def action_dim(self) -> int:
        """Length of a joint-mode action (14 for two 6-DoF arms)."""
        return len(self.actuators)


def gripper_to_width(gripper: Any, max_width: float) -> Any:
    """Normalised gripper command (0 closed .. 1 open, clipped) -> finger opening in metres."""
    return np.clip(gripper, 0.0, 1.0) * max_width


def width_to_gripper(width: Any, max_width: float) -> Any:
    """Finger opening in metres -> normalised gripper state 0 (closed) .. 1 (open), clipped."""
    return np.clip(np.asarray(width) / max_width, 0.0, 1.0)


def apply_physics(world: mujoco.MjSpec, robot: dict) -> None:
    """Set the world's physics options to those the robot's servos and grasps were tuned for."""
    physics = robot.get("physics", {})
    world.option.timestep = physics.get("timestep", 0.002)
    world.option.integrator = _INTEGRATORS[physics.get("integrator", "implicitfast")]
    world.option.cone = _CONES[physics.get("cone", "elliptic")]
    world.option.impratio = physics.get("impratio", 10.0)


def add_robot(world: mujoco.MjSpec, robot: dict) -> RobotHandles:
    """Add both arms, grippers, servos and cameras of a validated robot spec to `world`; return their names."""
    if world.compiler.degree:
        raise ValueError("add_robot writes joint ranges in radians: set world.compiler.degree = False first")
    arm = robot["arm"]
    joints = arm["joints"]
    home = robot["home"]
    _check_semantics(robot)

    gripper = arm["gripper"]
    max_width = float(gripper["max_width"])
    home_width = float(gripper_to_width(home["gripper"], max_width))

    arm_joints: list[str] = []
    finger_joints: list[tuple[str, str]] = []
    tendons: list[str] = []
    gripper_acts: list[str] = []
    actuators: list[str] = []
    ee_sites: list[str] = []
    home_qpos: dict[str, float] = {}
    home_ctrl: list[float] = []

    for placement in robot["arms"]:
        side = placement["name"]
        base = world.worldbody.add_body(name=f"{side}_base", pos=placement["pos"], quat=placement["quat"])
        _add_geoms(base, arm["base"]["geoms"], f"{side}_base", None, arm["base"].get("rgba", _DEFAULT_LINK_RGBA))
        parent = base
        for joint_spec, q_home in zip(joints, home["joints"]):
            name = f"{side}_{joint_spec['name']}"
            parent = _add_link(world, parent, joint_spec, name)
            arm_joints.append(name)
            actuators.append(f"{name}_pos")
            home_qpos[name] = float(q_home)
            home_ctrl.append(float(q_home))
        pair, tendon, act, site = _add_gripper(world, parent, gripper, side)
        finger_joints.append(pair)
        tendons.append(tendon)
        gripper_acts.append(act)
        actuators.append(act)
        ee_sites.append(site)
        home_qpos.update({pair[0]: home_width / 2.0, pair[1]: home_width / 2.0})
        home_ctrl.append(home_width)
        _add_camera(parent, f"{side}_wrist", robot["cameras"]["wrist"])

    _add_camera(world.worldbody, "head", robot["cameras"]["head"])

    _fit_offscreen_buffer(world, robot["cameras"].values())

    timestep = robot.get("physics", {}).get("timestep", 0.002)
    control_hz = float(robot.get("control_hz", 25))
    return RobotHandles(
        robot_id=robot["id"],
        arms=tuple(p["name"] for p in robot["arms"]),
        arm_joints=tuple(arm_joints),
        finger_joints=tuple(finger_joints),
        gripper_tendons=tuple(tendons),
        gripper_actuators=tuple(gripper_acts),
        actuators=tuple(actuators),
        ee_sites=tuple(ee_sites),
        cameras=CAMERA_NAMES,
        home_qpos=home_qpos,
        home_ctrl=tuple(home_ctrl),
        gripper_max_width=max_width,
        control_hz=control_hz,
        n_substeps=max(1, round(1.0 / (control_hz * timestep))),
    )


def build_robot_world(robot: dict) -> tuple[mujoco.MjSpec, RobotHandles]:
    """A world with a floor, the standard table and the robot: for tests, `dojo show` and robot-only demos."""
    world = mujoco.MjSpec()
    world.modelname = robot["id"]
    world.compiler.degree = False
    apply_physics(world, robot)
    # With MuJoCo's headlight (0.1 ambient + 0.4 diffuse) the lights add up to 1 per channel, the bound the task
    # scenes' lighting presets keep (`asset_sanity.LIGHT_SUM_MAX`): past it MuJoCo's renderer clamps and MuJoCo
    # Warp's tracer does not, and the two would show this world differently.
    world.worldbody.add_light(name="key", pos=[0.0, -0.6, 2.6], dir=[0.0, 0.25, -1.0], diffuse=[0.35, 0.35, 0.35])
    world.worldbody.add_light(name="fill", pos=[0.0, 1.5, 2.0], dir=[0.0, -0.6, -1.0], diffuse=[0.15, 0.15, 0.15])
    world.worldbody.add_geom(
        name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3.0, 3.0, 0.05], rgba=[0.45, 0.47, 0.5, 1.0]
    )
    half_z = TABLE_TOP_Z / 2.0
    world.worldbody.add_geom(
        name="table",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        pos=[0.0, 0.0, half_z],
        size=[TABLE_HALF_SIZE[0], TABLE_HALF_SIZE[1], half_z],
        rgba=[0.93, 0.93, 0.9, 1.0],
    )
    handles = add_robot(world, robot)
    return world, handles


def build_robot_model(robot: dict) -> mujoco.MjModel:
    """Compile `build_robot_world(robot)` into a model."""
    world, _ = build_robot_world(robot)
    return world.compile()


def apply_home(model: mujoco.MjModel, data: mujoco.MjData, handles: RobotHandles) -> None:
    """Put the robot's joints at the home pose with zero velocity, aim the servos there, and run forward."""
    for name, value in handles.home_qpos.items():
        joint = model.joint(name)
        data.qpos[joint.qposadr[0]] = value
        data.qvel[joint.dofadr[0]] = 0.0
    for name, value in zip(handles.actuators, handles.home_ctrl):
        data.ctrl[model.actuator(name).id] = value
    mujoco.mj_forward(model, data)


def _check_semantics(robot: dict) -> None:
    """Checks the schema cannot express: home pose length and limits, arm names, perpendicular gripper axes."""
    rid = robot["id"]
    joints = robot["arm"]["joints"]
    home = robot["home"]["joints"]
    if len(home) != len(joints):
        raise ValueError(f"robot {rid}: home.joints has {len(home)} values for {len(joints)} joints")
    for k, (joint, q) in enumerate(zip(joints, home)):
        lo, hi = joint["range"]
        if not lo <= q <= hi:
            raise ValueError(f"robot {rid}: home.joints[{k}] = {q} is outside {joint['name']} range [{lo}, {hi}]")
    names = [p["name"] for p in robot["arms"]]
    if names != ["left", "right"]:
        raise ValueError(f"robot {rid}: arms must be [left, right], got {names}")
    g = robot["arm"]["gripper"]
    frame_from_axes(g["approach"], g["axis"])


def _add_link(world: mujoco.MjSpec, parent: mujoco.MjsBody, spec: dict, name: str) -> mujoco.MjsBody:
    """One link body on its revolute joint, with its primitives and its position servo."""
    body = parent.add_body(name=f"{name}_link", pos=spec["offset"])
    body.gravcomp = 1.0
    lo, hi = spec["range"]
    body.add_joint(
        name=name,
        type=mujoco.mjtJoint.mjJNT_HINGE,
        axis=unit(spec["axis"]).tolist(),
        range=[lo, hi],
        limited=mujoco.mjtLimited.mjLIMITED_TRUE,
        armature=spec.get("armature", 0.05),
        damping=spec.get("damping", 0.0),
    )
    _add_geoms(body, spec["geoms"], name, spec["mass"], spec.get("rgba", _DEFAULT_LINK_RGBA))
    servo = spec["actuator"]
    act = world.add_actuator(name=f"{name}_pos", target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
    _make_servo(act, servo, (lo, hi))
    return body


def _make_servo(act: mujoco.MjsActuator, servo: dict, ctrlrange: tuple[float, float]) -> None:
    act.set_to_position(kp=servo["kp"], kv=servo["kv"])
    act.ctrlrange = list(ctrlrange)
    act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    act.forcerange = [-servo["force_limit"], servo["force_limit"]]
    act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE


def _add_geoms(
    body: mujoco.MjsBody, geoms: list[dict], prefix: str, mass: float | None, rgba: Sequence[float]
) -> None:
    """Primitives that collide with the world but not with the robot; `mass` (if given) spread by volume."""
    volumes = [primitive_volume(g) for g in geoms]
    total = sum(volumes)
    for k, (g, vol) in enumerate(zip(geoms, volumes)):
        geom = body.add_geom(
            name=f"{prefix}_g{k}",
            type=_GEOM_TYPES[g["type"]],
            rgba=list(rgba),
            contype=ROBOT_CONTYPE,
            conaffinity=ROBOT_CONAFFINITY,
        )
        if g["type"] == "capsule":
            geom.fromto = [*g["from"], *g["to"]]
            geom.size = [g["radius"], 0.0, 0.0]
        elif g["type"] == "sphere":
            geom.pos = g["pos"]
            geom.size = [g["radius"], 0.0, 0.0]
        else:
            geom.pos = g["pos"]
            geom.size = g["size"]
            geom.quat = g.get("quat", [1.0, 0.0, 0.0, 0.0])
        if mass is not None:
            geom.mass = mass * vol / total


def _add_gripper(
    world: mujoco.MjSpec, hand: mujoco.MjsBody, spec: dict, side: str
) -> tuple[tuple[str, str], str, str, str]:
    """Two symmetric fingers, the width tendon, the equality that couples them, the servo and the ee site."""
    frame = frame_from_axes(spec["approach"], spec["axis"]).tolist()
    finger = spec["finger"]
    half_max = spec["max_width"] / 2.0
    size = [finger["length"] / 2.0, finger["thickness"] / 2.0, finger["depth"] / 2.0]
    names = (f"{side}_finger_a", f"{side}_finger_b")
    for name, sign in zip(names, (1.0, -1.0)):
        body = hand.add_body(name=f"{name}_link", pos=spec["mount"], quat=frame)
        body.gravcomp = 1.0
        body.add_joint(
            name=name,
            type=mujoco.mjtJoint.mjJNT_SLIDE,
            axis=[0.0, sign, 0.0],
            range=[0.0, half_max],
            limited=mujoco.mjtLimited.mjLIMITED_TRUE,
            armature=0.01,
        )
        body.add_geom(
            name=f"{name}_pad",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=[size[0], sign * size[1], 0.0],
            size=size,
            mass=finger["mass"],
            friction=[finger.get("friction", 1.5), 0.005, 0.0001],
            condim=4,
            solref=[_PAD_TIMECONST, 1.0],
            priority=1,
            rgba=list(finger.get("rgba", _DEFAULT_FINGER_RGBA)),
            contype=ROBOT_CONTYPE,
            conaffinity=ROBOT_CONAFFINITY,
        )
    world.add_equality(
        name=f"{side}_finger_sync",
        type=mujoco.mjtEq.mjEQ_JOINT,
        name1=names[0],
        name2=names[1],
        data=[0.0, 1.0, 0.0, 0.0, 0.0] + [0.0] * 7,
    )
    tendon = world.add_tendon(name=f"{side}_gripper_width")
    tendon.wrap_joint(names[0], 1.0)
    tendon.wrap_joint(names[1], 1.0)
    act_name = f"{side}_gripper"
    act = world.add_actuator(name=act_name, target=tendon.name, trntype=mujoco.mjtTrn.mjTRN_TENDON)
    _make_servo(act, spec["actuator"], (0.0, spec["max_width"]))
    site_name = f"{side}_ee"
    tcp = np.asarray(spec["mount"], dtype=float) + spec["tcp"] * unit(spec["approach"])
    hand.add_site(name=site_name, pos=tcp.tolist(), quat=frame, size=[0.01, 0.0, 0.0], group=4)
    return names, tendon.name, act_name, site_name


def _add_camera(body: mujoco.MjsBody, name: str, spec: dict) -> None:
    """A camera looking from spec pos at spec target (in `body`'s frame), image up towards spec up."""
    width, height = spec.get("resolution", [640, 480])
    body.add_camera(
        name=name,
        pos=spec["pos"],
        quat=look_at_quat(spec["pos"], spec["target"], spec.get("up", (0.0, 0.0, 1.0))).tolist(),
        fovy=spec["fovy"],
        resolution=[width, height],
    )


def _fit_offscreen_buffer(world: mujoco.MjSpec, cameras: Iterable[dict]) -> None:
    """Grow the offscreen framebuffer so that every robot camera can render at its own resolution."""
    vis = world.visual.global_
    for cam in cameras:
        width, height = cam.get("resolution", [640, 480])
        vis.offwidth = max(vis.offwidth, width)
        vis.offheight = max(vis.offheight, height)
