"""`color_of`: an object takes the colour an earlier object drew for the episode (a nut the colour of its screw),
in its own asset's shade of it; naming an object that is not listed before it is an error at that field."""

from __future__ import annotations

import copy

import pytest
from dojo.compiler.scene_sample import sample_scene
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.task_checks import task_problems


@pytest.fixture(scope="module")
def library() -> SpecLibrary:
    return SpecLibrary.load([], strict=False)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_each_nut_has_its_screws_colour(library, seed):
    task = library.get("task", "fasten_screws")
    objects = {o.name: o for o in sample_scene(library, task, "standard", seed).objects}
    screws = [objects[f"screw_{k}"] for k in "abc"]
    assert len({s.color for s in screws}) == 3
    assert {s.color for s in screws} <= {"red", "blue", "gray", "yellow", "purple"}
    nut_shades = {c["name"]: c["rgba"] for c in library.get("asset", "threaded_nut").data["colors"]}
    for k, screw in zip("abc", screws):
        nut = objects[f"nut_{k}"]
        assert nut.color == screw.color and nut.rgba == nut_shades[screw.color]
        assert nut.attributes["color"] == screw.color


def test_color_of_must_name_an_earlier_object(library):
    task = copy.deepcopy(library.get("task", "fasten_screws").data)
    objects = task["scene"]["objects"]
    objects[3]["color_of"] = "nut_b"  # listed after nut_a
    objects[4]["color_of"] = "screw_z"
    problems = [(path, message) for path, message, _ in task_problems(task)]
    assert (("scene", "objects", 3, "color_of"), "'color_of' names 'nut_b', which is not an object listed before "
                                                 "this one") in [(p, m.split(" (")[0]) for p, m in problems]
    assert any(path == ("scene", "objects", 4, "color_of") and "screw_z" in m for path, m in problems)
