"""Granular contents: objects an entry puts `inside` a container are laid in its `inside` box at compile time,
settle there, and a spec that asks for more than fits, or names no container, is refused with a located error."""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np
import pytest
from dojo.compiler.plan import compile_plan
from dojo.compiler.scene_sample import LayoutError, content_names, sample_scene
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.task_checks import task_problems

TASK = "pour_balls_into_vase"


@pytest.fixture(scope="module")
def library() -> SpecLibrary:
    return SpecLibrary.load([], strict=False)


def _balls(scene) -> list:
    return [o for o in scene.objects if o.group == "balls"]


def test_contents_start_inside_the_container_without_overlapping(library):
    task = library.get("task", TASK)
    scene = sample_scene(library, task, "standard", 3)
    cup = next(o for o in scene.objects if o.name == "cup")
    balls = _balls(scene)
    assert len(balls) == 10 and content_names(task.data["scene"]) == {b.name for b in balls}
    centres = np.array([[b.pos[0], b.pos[1], b.pos[2] + b.half_extents[2]] for b in balls])
    radius = max(b.half_extents[0] for b in balls)
    assert np.all(np.hypot(*(centres[:, :2] - cup.pos[:2]).T) + radius <= 0.025 + 1e-9)  # the inside box's circle
    gaps = [np.linalg.norm(p - q) for i, p in enumerate(centres) for q in centres[i + 1:]]
    assert min(gaps) >= 2 * radius
    assert centres[:, 2].min() - radius >= cup.pos[2] and centres[:, 2].max() + radius <= cup.pos[2] + 0.095
    again = sample_scene(library, task, "standard", 3)
    assert [b.pos for b in _balls(again)] == [b.pos for b in balls]  # same seed, same scene


def test_the_compiled_plan_starts_with_every_ball_settled_in_the_cup(library):
    plan = compile_plan(library, library.get("task", TASK), "standard", 0)
    model, data = plan.model(), plan.initial_data()
    cup = data.xpos[model.body(plan.objects["cup"]["body"]).id]
    for name in sorted(n for n, o in plan.objects.items() if o["group"] == "balls"):
        ball = data.xpos[model.body(plan.objects[name]["body"]).id]
        assert math.hypot(*(ball[:2] - cup[:2])) < 0.03 and cup[2] < ball[2] < cup[2] + 0.1, name


def test_more_contents_than_fit_are_refused_naming_the_container(library):
    task = library.get("task", TASK)
    data = copy.deepcopy(task.data)
    next(e for e in data["scene"]["objects"] if e["name"] == "ball")["count"] = 25
    with pytest.raises(LayoutError, match="do not fit inside cup"):
        sample_scene(library, dataclasses.replace(task, data=data), "standard", 0)


def test_inside_must_name_an_object_listed_before():
    scene = {"regions": {"r": {"center": [0, 0], "size": [0.1, 0.1]}},
             "objects": [{"name": "ball", "asset": "ball_small", "inside": "cup"},
                         {"name": "cup", "asset": "pouring_cup", "region": "r"}]}
    problems = task_problems({"scene": scene, "success": {"on": ["ball", "cup"]}, "instruction": "Pour."})
    assert any(path[-1] == "inside" and "'cup'" in message for path, message, _ in problems), problems
