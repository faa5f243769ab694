"""The three robot specs: schema, compiled kinematics against the spec's own figures, servos, gripper, cameras.

The kinematic reference here is written independently of the emitter (Rodrigues rotations over the spec's
offsets and axes), so a wrong frame convention in either place shows up as a mismatch.
"""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import mujoco
import numpy as np
import pytest
import yaml
from referencing import Registry, Resource

from dojo.compiler.robot_emit import (
    add_robot,
    apply_home,
    build_robot_model,
    build_robot_world,
    gripper_to_width,
    width_to_gripper,
)

ROOT = Path(__file__).resolve().parents[2]
SCHEMAS = ROOT / "specs" / "schemas"
ROBOT_IDS = ("arx_x5_bimanual", "piper_bimanual", "piperx_bimanual")
TABLE_TOP_Z = 0.75
# Tracking tolerance for a 0.3 rad, 0.5 Hz sine on every joint, sampled at 25 Hz and held between samples:
# the servo lags the newest target by about one control period (0.94 rad/s * 40 ms = 0.038 rad).
TRACKING_TOL_RAD = 0.05


def _load(path: Path):
    return json.loads(path.read_text()) if path.suffix == ".json" else yaml.safe_load(path.read_text())


@pytest.fixture(scope="module")
def validator() -> jsonschema.Draft202012Validator:
    common = _load(SCHEMAS / "common.schema.json")
    schema = _load(SCHEMAS / "robot.schema.json")
    registry = Registry().with_resource(common["$id"], Resource.from_contents(common))
    return jsonschema.Draft202012Validator(schema, registry=registry)


@pytest.fixture(scope="module", params=ROBOT_IDS)
def robot(request) -> dict:
    return _load(ROOT / "specs" / "robots" / f"{request.param}.yaml")


@pytest.fixture(scope="module")
def built(robot):
    world, handles = build_robot_world(robot)
    return world.compile(), handles


def _rot(axis, angle: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _quat_mat(q) -> np.ndarray:
    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, np.asarray(q, float) / np.linalg.norm(q))
    return m.reshape(3, 3)


def _reference_fk(robot: dict, placement: dict, q: np.ndarray):
    """Joint anchors, joint axes (world) and the ee site pose, straight from the spec's figures."""
    r = _quat_mat(placement["quat"])
    p = np.asarray(placement["pos"], float)
    anchors, axes = [], []
    for joint, angle in zip(robot["arm"]["joints"], q):
        p = p + r @ np.asarray(joint["offset"], float)
        axis = np.asarray(joint["axis"], float) / np.linalg.norm(joint["axis"])
        anchors.append(p)
        axes.append(r @ axis)
        r = r @ _rot(axis, angle)
    g = robot["arm"]["gripper"]
    approach = np.asarray(g["approach"], float) / np.linalg.norm(g["approach"])
    opening = np.asarray(g["axis"], float) / np.linalg.norm(g["axis"])
    ee_pos = p + r @ (np.asarray(g["mount"], float) + g["tcp"] * approach)
    ee_mat = r @ np.column_stack([approach, opening, np.cross(approach, opening)])
    return np.array(anchors), np.array(axes), ee_pos, ee_mat


def _arm_qpos(model, handles, side: str) -> list[int]:
    return [model.joint(n).qposadr[0] for n in handles.arm_joints if n.startswith(side + "_")]


def _walk(schema, path="$"):
    """Yield (path, subschema) for every schema object reachable inside `schema`."""
    if isinstance(schema, dict):
        yield path, schema
        for key, value in schema.items():
            if key in ("examples", "default", "const", "enum", "if"):  # values and conditions, not definitions
                continue
            yield from _walk(value, f"{path}.{key}")
    elif isinstance(schema, list):
        for i, value in enumerate(schema):
            yield from _walk(value, f"{path}[{i}]")


def test_schema_is_documented_and_closed(validator):
    schema = validator.schema
    jsonschema.Draft202012Validator.check_schema(schema)
    for path, sub in _walk(schema):
        for name, prop in sub.get("properties", {}).items():
            if prop is False:  # "this key is not allowed here" inside if/then
                continue
            assert "description" in prop, f"{path}.properties.{name} has no description"
        if sub.get("type") == "object":
            assert sub.get("additionalProperties") is False, f"{path} is an open object"
    assert len(schema["examples"]) == 1
    validator.validate(schema["examples"][0])


def test_spec_validates(validator, robot):
    errors = [f"{list(e.absolute_path)}: {e.message}" for e in validator.iter_errors(robot)]
    assert not errors
    assert robot["kind"] == "robot" and robot["version"] == 1 and robot["source"]


def test_schema_rejects_unknown_keys_and_bad_geoms(validator, robot):
    bad = json.loads(json.dumps(robot))
    bad["arm"]["joints"][0]["lenght"] = 0.1
    assert not validator.is_valid(bad)
    bad = json.loads(json.dumps(robot))
    bad["arm"]["joints"][0]["geoms"] = [{"type": "capsule", "pos": [0, 0, 0], "radius": 0.02}]
    assert not validator.is_valid(bad)


def test_zero_pose_anchors_are_the_spec_offsets(robot, built):
    model, handles = built
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    for placement in robot["arms"]:
        side = placement["name"]
        names = [n for n in handles.arm_joints if n.startswith(side + "_")]
        anchors = np.array([data.joint(n).xanchor for n in names])
        r = _quat_mat(placement["quat"])
        offsets = np.array([j["offset"] for j in robot["arm"]["joints"]], float)
        expected = np.asarray(placement["pos"]) + np.cumsum(offsets, axis=0) @ r.T
        np.testing.assert_allclose(anchors, expected, atol=1e-9)


def test_random_pose_fk_matches_spec(robot, built):
    model, handles = built
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    ranges = np.array([j["range"] for j in robot["arm"]["joints"]], float)
    link_lengths = np.linalg.norm([j["offset"] for j in robot["arm"]["joints"]][1:], axis=1)
    for _ in range(5):
        for placement, site in zip(robot["arms"], handles.ee_sites):
            side = placement["name"]
            q = rng.uniform(ranges[:, 0], ranges[:, 1])
            data.qpos[_arm_qpos(model, handles, side)] = q
            mujoco.mj_kinematics(model, data)
            names = [n for n in handles.arm_joints if n.startswith(side + "_")]
            anchors = np.array([data.joint(n).xanchor for n in names])
            axes = np.array([data.joint(n).xaxis for n in names])
            ref_anchors, ref_axes, ee_pos, ee_mat = _reference_fk(robot, placement, q)
            np.testing.assert_allclose(anchors, ref_anchors, atol=1e-9)
            np.testing.assert_allclose(axes, ref_axes, atol=1e-9)
            np.testing.assert_allclose(np.linalg.norm(np.diff(anchors, axis=0), axis=1), link_lengths, atol=1e-9)
            np.testing.assert_allclose(data.site(site).xpos, ee_pos, atol=1e-9)
            np.testing.assert_allclose(data.site(site).xmat.reshape(3, 3), ee_mat, atol=1e-6)


def test_joint_limits_axes_and_servo_ranges(robot, built):
    model, handles = built
    for side in handles.arms:
        for joint in robot["arm"]["joints"]:
            name = f"{side}_{joint['name']}"
            j = model.joint(name)
            assert j.limited[0] == 1
            np.testing.assert_allclose(j.range, joint["range"])
            np.testing.assert_allclose(j.axis, np.asarray(joint["axis"]) / np.linalg.norm(joint["axis"]), atol=1e-12)
            act = model.actuator(f"{name}_pos")
            np.testing.assert_allclose(act.ctrlrange, joint["range"])
            limit = joint["actuator"]["force_limit"]
            np.testing.assert_allclose(act.forcerange, [-limit, limit])


def test_action_layout(robot, built):
    model, handles = built
    n = len(robot["arm"]["joints"])
    assert handles.action_dim == 2 * (n + 1) == model.nu
    assert handles.actuators[n] == "left_gripper" and handles.actuators[-1] == "right_gripper"
    assert [a.removesuffix("_pos") for a in handles.actuators if a.endswith("_pos")] == list(handles.arm_joints)
    assert handles.ee_sites == ("left_ee", "right_ee")
    assert handles.n_substeps == 20 and handles.control_hz == 25


def test_home_holds_still_for_two_seconds(built):
    model, handles = built
    data = mujoco.MjData(model)
    apply_home(model, data, handles)
    assert data.ncon == 0, "the home pose touches the table"
    qadr = [model.joint(n).qposadr[0] for n in handles.home_qpos]
    start = data.qpos[qadr].copy()
    for _ in range(int(round(2.0 / model.opt.timestep))):
        mujoco.mj_step(model, data)
    assert np.all(np.isfinite(data.qpos))
    assert np.abs(data.qpos[qadr] - start).max() < 1e-4
    assert np.abs(data.qvel).max() < 1e-3


def test_servos_track_a_25hz_trajectory_with_gravity(built):
    model, handles = built
    assert np.linalg.norm(model.opt.gravity) > 9.0
    data = mujoco.MjData(model)
    apply_home(model, data, handles)
    act_ids = np.array([model.actuator(n).id for n in handles.actuators])
    arm = np.array([i for i, n in enumerate(handles.actuators) if n not in handles.gripper_actuators])
    qadr = np.array([model.joint(n).qposadr[0] for n in handles.arm_joints])
    lo, hi = model.actuator_ctrlrange[act_ids[arm]].T
    home = np.array(handles.home_ctrl)
    errors = []
    for k in range(75):  # 3 s at 25 Hz; the first second is settling
        target = home.copy()
        target[arm] = np.clip(home[arm] + 0.3 * np.sin(np.pi * k / 25 + np.arange(arm.size)), lo, hi)
        data.ctrl[act_ids] = target
        for _ in range(handles.n_substeps):
            mujoco.mj_step(model, data)
        if k >= 25:
            errors.append(np.abs(data.qpos[qadr] - target[arm]).max())
    assert max(errors) < TRACKING_TOL_RAD
    for _ in range(10 * handles.n_substeps):  # hold the last target for 0.4 s
        mujoco.mj_step(model, data)
    assert np.abs(data.qpos[qadr] - target[arm]).max() < 1e-3


def test_gripper_opens_to_max_width_and_closes(robot, built):
    model, handles = built
    data = mujoco.MjData(model)
    apply_home(model, data, handles)
    max_width = robot["arm"]["gripper"]["max_width"]
    thickness = robot["arm"]["gripper"]["finger"]["thickness"]
    for command, width in ((0.0, 0.0), (1.0, max_width), (0.5, max_width / 2)):
        for act in handles.gripper_actuators:
            data.ctrl[model.actuator(act).id] = gripper_to_width(command, max_width)
        for _ in range(250):
            mujoco.mj_step(model, data)
        for side, site in zip(handles.arms, handles.ee_sites):
            opening = data.site(site).xmat.reshape(3, 3)[:, 1]
            a = data.geom(f"{side}_finger_a_pad").xpos
            b = data.geom(f"{side}_finger_b_pad").xpos
            gap = float((a - b) @ opening) - thickness
            assert gap == pytest.approx(width, abs=1e-3)
            assert data.ten_length[model.tendon(f"{side}_gripper_width").id] == pytest.approx(width, abs=1e-3)
            tcp_to_centre = (a + b) / 2 - data.site(site).xpos
            assert abs(float(tcp_to_centre @ opening)) < 1e-6  # fingers stay symmetric about the tool point


def test_gripper_mapping():
    assert gripper_to_width(0.0, 0.08) == 0.0
    assert gripper_to_width(1.0, 0.08) == pytest.approx(0.08)
    assert gripper_to_width(1.5, 0.08) == pytest.approx(0.08)
    np.testing.assert_allclose(gripper_to_width(np.array([-1.0, 0.25]), 0.08), [0.0, 0.02])
    assert width_to_gripper(0.04, 0.08) == pytest.approx(0.5)
    assert width_to_gripper(gripper_to_width(0.3, 0.1), 0.1) == pytest.approx(0.3)


def test_cameras_exist_and_wrist_cameras_follow_the_arm(robot, built):
    model, handles = built
    assert handles.cameras == ("head", "left_wrist", "right_wrist")
    for name in handles.cameras:
        assert tuple(model.cam_resolution[model.camera(name).id]) == (640, 480)
    assert model.vis.global_.offwidth >= 640 and model.vis.global_.offheight >= 480
    data = mujoco.MjData(model)
    apply_home(model, data, handles)
    before = {n: data.cam(n).xpos.copy() for n in handles.cameras}
    head_dir = -data.cam("head").xmat.reshape(3, 3)[:, 2]
    to_table = np.array([0.0, 0.0, TABLE_TOP_Z]) - data.cam("head").xpos
    assert head_dir @ to_table / np.linalg.norm(to_table) > 0.95  # the head camera looks at the table centre
    data.qpos[model.joint("left_joint1").qposadr[0]] += 0.5
    mujoco.mj_forward(model, data)  # cameras are placed by mj_camlight, after kinematics
    assert np.linalg.norm(data.cam("left_wrist").xpos - before["left_wrist"]) > 0.05
    np.testing.assert_allclose(data.cam("right_wrist").xpos, before["right_wrist"])
    np.testing.assert_allclose(data.cam("head").xpos, before["head"])


def test_add_robot_refuses_a_world_in_degrees(robot):
    world = mujoco.MjSpec()
    world.compiler.degree = True
    with pytest.raises(ValueError, match="radians"):
        add_robot(world, robot)


def test_home_outside_limits_is_rejected(robot):
    bad = json.loads(json.dumps(robot))
    bad["home"]["joints"][1] = bad["arm"]["joints"][1]["range"][1] + 1.0
    with pytest.raises(ValueError, match="outside"):
        build_robot_model(bad)


def test_model_goes_to_mjx(built):
    mjx = pytest.importorskip("mujoco.mjx")
    model, _ = built
    mjx.put_model(model)


def test_closed_gripper_holds_a_cube(robot):
    """A 4 cm, 0.2 kg cube between the open fingers at home: closing squeezes it and it stays put."""
    world, handles = build_robot_world(robot)
    probe = world.compile()
    data = mujoco.MjData(probe)
    apply_home(probe, data, handles)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, data.site("left_ee").xmat)
    cube = world.worldbody.add_body(name="cube", pos=data.site("left_ee").xpos.tolist(), quat=quat.tolist())
    cube.add_freejoint(name="cube")
    cube.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02, 0.02, 0.02], mass=0.2)
    model = world.compile()
    data = mujoco.MjData(model)
    apply_home(model, data, handles)
    data.ctrl[model.actuator("left_gripper").id] = 0.0
    for _ in range(500):
        mujoco.mj_step(model, data)
    gripped = data.body("cube").xpos.copy()
    assert data.ten_length[model.tendon("left_gripper_width").id] == pytest.approx(0.04, abs=0.002)
    for _ in range(1000):
        mujoco.mj_step(model, data)
    assert np.linalg.norm(data.body("cube").xpos - gripped) < 0.002


@pytest.mark.slow
def test_mjx_steps_like_mujoco(built):
    """MJX (float32) follows MuJoCo for 0.4 s of servoing: gravcomp, tendon servo, equality and cone all go across."""
    jax = pytest.importorskip("jax")
    from mujoco import mjx

    model, handles = built
    data = mujoco.MjData(model)
    apply_home(model, data, handles)
    data.ctrl[:] = np.array(handles.home_ctrl) + np.where(
        np.isin(handles.actuators, handles.gripper_actuators), -0.01, 0.1
    )
    mx, dx = mjx.put_model(model), mjx.put_data(model, data)
    step = jax.jit(mjx.step)
    for _ in range(200):
        dx = step(mx, dx)
        mujoco.mj_step(model, data)
    np.testing.assert_allclose(np.asarray(dx.qpos), data.qpos, atol=1e-4)


def test_robot_world_lights_stay_within_what_both_renderers_show_alike(built):
    """Headlight and lights add up to at most 1 per channel, as the scenes' lighting presets must
    (`asset_sanity.LIGHT_SUM_MAX`): past it MuJoCo's renderer clamps and MuJoCo Warp's tracer does not."""
    from dojo.compiler.asset_sanity import LIGHT_SUM_MAX

    model, _ = built
    total = model.vis.headlight.ambient + model.vis.headlight.diffuse
    total = total + (model.light_ambient + model.light_diffuse).sum(axis=0)
    assert model.nlight == 2 and float(total.max()) <= LIGHT_SUM_MAX + 1e-6
