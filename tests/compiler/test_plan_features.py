"""`plan.requires`: the simulator features a plan uses, read off hand-built models, and the built-in plans."""

from __future__ import annotations

import mujoco
import pytest

from dojo.compiler.plan_features import plan_features

SCENE = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1"/>
    <geom name="wall" type="box" size="0.1 0.1 0.1" pos="2 0 0"/>
    <geom name="post" type="cylinder" size="0.05 0.1" pos="3 0 0"/>
    <body name="block" pos="0 0 0.5"><freejoint/><geom type="box" size="0.05 0.05 0.05"/></body>
    {extra}
  </worldbody>
  {equality}
</mujoco>
"""


def _features(extra: str = "", equality: str = "", task: dict | None = None) -> list[str]:
    model = mujoco.MjModel.from_xml_string(SCENE.format(extra=extra, equality=equality))
    return plan_features(model, task or {})


def test_contacts_are_the_type_pairs_that_may_touch_and_world_geoms_never_touch_each_other():
    # the block may touch the floor, the wall and the post, and itself (a second box would); world geoms never
    # touch one another, so plane-box (floor and wall) is the block's pair, not the world's
    assert _features() == ["contact:box-box", "contact:box-cylinder", "contact:box-plane"]


def test_geoms_that_collide_with_nothing_add_no_pair():
    assert "contact:box-sphere" not in _features(
        extra='<body pos="0 1 1"><freejoint/><geom type="sphere" size="0.02" contype="0" conaffinity="0"/></body>')
    assert "contact:box-sphere" in _features(
        extra='<body pos="0 1 1"><freejoint/><geom type="sphere" size="0.02"/></body>')


def test_equality_constraints_tendons_and_scripted_keys():
    extra = '<body name="b2" pos="0 1 1"><freejoint/><geom type="box" size="0.02 0.02 0.02"/></body>'
    features = _features(extra=extra, equality='<equality><weld body1="block" body2="b2"/></equality>',
                         task={"events": [{"at": 10}], "actors": []})
    assert "equality:weld" in features and "events" in features
    assert "actors" not in features  # an empty list of actors asks nothing of the backend
    assert "tendon" not in features and "flex" not in features


def test_flex_is_named():
    model = mujoco.MjModel.from_xml_string("""
    <mujoco><worldbody>
      <flexcomp name="cloth" type="grid" count="4 4 1" spacing="0.05 0.05 0.05" radius="0.005" dim="2" pos="0 0 1"/>
    </worldbody></mujoco>""")
    assert "flex" in plan_features(model, {})


@pytest.mark.parametrize("task", ["stack_blocks", "insert_tubes"])
def test_built_in_plans_list_what_they_use_and_mjx_runs_it(task):
    from dojo.backends.registry import unsupported_features
    from dojo.compiler.plan import compile_plan
    from dojo.compiler.spec_library import SpecLibrary

    library = SpecLibrary.load()
    plan = compile_plan(library, library.get("task", task), "standard", 0)
    assert plan.requires == plan_features(plan.model(), library.get("task", task).data)
    assert {"contact:box-plane", "tendon"} <= set(plan.requires)  # objects on the table; the grippers' tendons
    assert unsupported_features("mjx", plan.requires, {}) == {}
