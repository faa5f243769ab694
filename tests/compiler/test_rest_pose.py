"""Objects that start lying down (`rest: side`): the compiler turns them onto their side, puts their footprint in
the region and their lowest point on the table, and they settle there lying; objects without `rest` stand as
they always did."""

from __future__ import annotations

import copy
import dataclasses
import math

import mujoco
import numpy as np
import pytest
from dojo.backends.predicates import UPRIGHT_DEGREES
from dojo.compiler.plan import compile_plan
from dojo.compiler.rest_pose import rest_quat, rested_box
from dojo.compiler.robot_emit import TABLE_TOP_Z
from dojo.compiler.scene_sample import sample_scene
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.task_card import task_card
from dojo.compiler.task_checks import task_problems
from dojo.experts.validity import policies, run_policy

LYING = "piper_stand_up_bottles"


@pytest.fixture(scope="module")
def library() -> SpecLibrary:
    return SpecLibrary.load()


def _lowest_z(model: mujoco.MjModel, data: mujoco.MjData, body: int) -> float:
    """The lowest point of a body's collision meshes and primitives (their world bounding boxes)."""
    lows = []
    for g in range(model.ngeom):
        if model.geom_bodyid[g] == body and model.geom_contype[g]:
            rot = data.geom_xmat[g].reshape(3, 3)
            centre = data.geom_xpos[g] + rot @ model.geom_aabb[g, :3]
            lows.append(centre[2] - np.abs(rot)[2] @ model.geom_aabb[g, 3:])
    return float(min(lows))


def test_a_lying_object_settles_on_its_side_with_its_yaw_sampled(library):
    task = library.get("task", LYING)
    region = task.data["scene"]["regions"]["bottle"]
    yaws = set()
    for seed in (0, 1):
        plan = compile_plan(library, task, "standard", seed)
        model, data = plan.model(), plan.initial_data()
        body = model.body(plan.objects["bottle"]["body"]).id
        axis = data.xmat[body].reshape(3, 3)[:, 2]
        assert abs(axis[2]) < math.sin(math.radians(3)), axis  # its bottom-to-top axis lies flat
        placed = plan.scene["objects"][0]
        assert placed["rest"] == "side" and plan.settle["redraws"] == 0
        yaw = math.radians(placed["yaw_deg"])
        assert axis[:2] == pytest.approx([math.cos(yaw), math.sin(yaw)], abs=0.02)  # up turned to +x, then yawed
        yaws.add(round(placed["yaw_deg"], 6))
        assert _lowest_z(model, data, body) == pytest.approx(TABLE_TOP_Z, abs=0.002)  # resting on the table
        half_length = plan.objects["bottle"]["half_extents"][0]
        middle = data.xpos[body] + data.xmat[body].reshape(3, 3) @ np.array([0.0, 0.0, half_length])
        low = np.subtract(region["center"], np.divide(region["size"], 2))
        high = np.add(region["center"], np.divide(region["size"], 2))
        assert np.all(middle[:2] >= low) and np.all(middle[:2] <= high)  # its middle, not its bottom, in the region
    assert len(yaws) == 2
    assert "- `bottle`: bottle_water, in region `bottle`, lying on its side" in task_card(task, "Stand it up.", {})


def test_a_lying_bottle_is_not_upright_so_doing_nothing_scores_nothing(library, tmp_path):
    plan = compile_plan(library, library.get("task", LYING), "standard", 0)
    model, data = plan.model(), plan.initial_data()
    tilt = math.degrees(math.acos(data.xmat[model.body(plan.objects["bottle"]["body"]).id][8]))
    assert tilt > UPRIGHT_DEGREES
    plan.save(tmp_path / "plan.json")
    outcome = run_policy(policies()["zero"], [tmp_path / "plan.json"], num_envs=1, max_steps=20)[0]
    assert not outcome.success and outcome.score == 0.0


def test_the_same_object_standing_keeps_its_old_placement(library):
    """Without `rest` the entry samples exactly what it did before rest poses existed: the same frame position,
    and a record without a `rest` key (so standing scenes keep their digests)."""
    task = library.get("task", LYING)
    data = copy.deepcopy(task.data)
    del data["scene"]["objects"][0]["rest"]
    standing = sample_scene(library, dataclasses.replace(task, data=data), "standard", 0)
    lying = sample_scene(library, task, "standard", 0)
    assert "rest" not in standing.to_json()["objects"][0] and lying.to_json()["objects"][0]["rest"] == "side"
    assert standing.objects[0].yaw_deg == lying.objects[0].yaw_deg
    assert standing.objects[0].pos[2] == TABLE_TOP_Z and lying.objects[0].pos[2] > TABLE_TOP_Z + 0.03
    assert standing.objects[0].half_extents[2] > lying.objects[0].half_extents[2]  # a tall bottle, a low one
    assert rest_quat("upright", 30.0) == [math.cos(math.radians(15)), 0.0, 0.0, math.sin(math.radians(15))]
    lo, hi = np.array([-0.1, -0.2, 0.0]), np.array([0.1, 0.2, 0.5])
    anchor, t_lo, t_hi = rested_box("upright", lo, hi)
    assert not anchor.any() and np.array_equal(t_lo, lo) and np.array_equal(t_hi, hi)
    anchor, t_lo, t_hi = rested_box("side", lo, hi)  # up becomes +x: the 0.5 m length lies along x
    assert np.allclose(t_hi - t_lo, [0.5, 0.4, 0.2]) and np.allclose(anchor, [0.25, 0.0, -0.1])


def test_contents_cannot_go_into_a_lying_container():
    scene = {"regions": {"r": {"center": [0, 0], "size": [0.3, 0.3]}},
             "objects": [{"name": "cup", "asset": "pouring_cup", "region": "r", "rest": "side"},
                         {"name": "ball", "asset": "ball_small", "inside": "cup"}]}
    problems = task_problems({"scene": scene, "success": {"on": ["ball", "cup"]}, "instruction": "Pour."})
    assert any(path == ("scene", "objects", 1, "inside") and "lies on its side" in message
               for path, message, _ in problems), problems
    scene["objects"][0]["rest"] = "upright"
    assert not task_problems({"scene": scene, "success": {"on": ["ball", "cup"]}, "instruction": "Pour."})
