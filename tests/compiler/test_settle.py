"""Compile-time settling: wait for rest, reject layouts whose objects slide or topple, redraw deterministically."""

from __future__ import annotations

import re

import mujoco
import pytest

from dojo.compiler import plan as plan_module
from dojo.compiler.plan import SETTLE_REDRAWS, compile_plan
from dojo.compiler.scene_sample import LayoutError
from dojo.compiler.scene_settle import MAX_SECONDS, MIN_SECONDS, SettleResult, settle
from dojo.compiler.spec_library import SpecLibrary


def _world(body_xml: str, floor_euler: str = "0 0 0", body_attrs: str = 'pos="0 0 0"'
           ) -> tuple[mujoco.MjModel, mujoco.MjData]:
    model = mujoco.MjModel.from_xml_string(f"""
    <mujoco><option timestep="0.002"/><worldbody>
      <geom name="floor" type="plane" size="1 1 0.1" euler="{floor_euler}"/>
      <body name="thing" {body_attrs}>{body_xml}</body>
    </worldbody></mujoco>""")
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def test_a_resting_object_settles_in_the_minimum_time() -> None:
    model, data = _world('<freejoint/><geom type="box" size="0.03 0.03 0.03" pos="0 0 0.032"/>')
    result = settle(model, data, {"cube": "thing"})
    assert result.ok and result.at_rest and result.disturbed == {}
    assert result.seconds == pytest.approx(MIN_SECONDS)
    assert not data.qvel.any()  # the initial state starts still


def test_an_object_that_topples_is_reported() -> None:
    """A tall bar standing on one edge falls over and lies turned by about 90 degrees."""
    model, data = _world('<freejoint/><geom type="box" size="0.01 0.01 0.1" pos="0 0 0.1"/>',
                         body_attrs='pos="0 0 0.002" euler="0 8 0"')
    result = settle(model, data, {"bar": "thing"})
    assert not result.ok
    turned = re.search(r"turned (\d+) deg", result.disturbed["bar"])
    assert turned and int(turned.group(1)) > 60


def test_an_object_that_keeps_rolling_is_not_at_rest() -> None:
    model, data = _world('<freejoint/><geom type="sphere" size="0.03" pos="0 0 0.031"/>', floor_euler="0 4 0")
    result = settle(model, data, {"ball": "thing"})
    assert not result.ok
    assert not result.at_rest or "ball" in result.disturbed
    assert result.seconds <= MAX_SECONDS + 0.1


def test_loose_contents_are_at_rest_when_their_centre_is_still() -> None:
    """A ball spinning in place about the vertical (nothing in a 3-D contact stops that) has not moved: as loose
    contents it is at rest after the minimum time; an ordinary object turning as fast is still moving."""
    ball = '<freejoint/><geom type="sphere" size="0.01" pos="0 0 0.01" condim="3"/>'
    for loose, expect_rest in ((frozenset({"ball"}), True), (frozenset(), False)):
        model, data = _world(ball)
        data.qvel[5] = 0.2  # rad/s about z: 1.1 degrees a window, above REST_TURN_DEG
        result = settle(model, data, {"ball": "thing"}, loose)
        assert result.at_rest is expect_rest
        assert result.seconds == pytest.approx(MIN_SECONDS if expect_rest else MAX_SECONDS)


@pytest.fixture(scope="module")
def library() -> SpecLibrary:
    return SpecLibrary.load()


def test_a_rejected_layout_is_redrawn_deterministically(library: SpecLibrary, monkeypatch: pytest.MonkeyPatch) -> None:
    """The first layout is declared disturbed: the compiler takes the next stream of the same seed, the same one
    every time, and records the redraw in the plan."""
    task = library.get("task", "stack_blocks")
    original = compile_plan(library, task, "standard", 4)
    assert original.settle["redraws"] == 0

    def first_is_bad(model: mujoco.MjModel, data: mujoco.MjData, free: dict[str, str],
                     loose: frozenset[str] = frozenset()) -> SettleResult:
        result = settle(model, data, free, loose)
        calls.append(result)
        return result if len(calls) > 1 else SettleResult(result.seconds, True, {"block_a": "moved 9 cm"})

    monkeypatch.setattr(plan_module, "settle", first_is_bad)
    calls: list[SettleResult] = []
    first = compile_plan(library, task, "standard", 4)
    calls = []
    second = compile_plan(library, task, "standard", 4)
    assert first.settle["redraws"] == second.settle["redraws"] == 1
    assert first.scene == second.scene and first.init_qpos == second.init_qpos
    assert first.scene != original.scene
    assert first.hash == original.hash  # the hash names the inputs; the redraw is decided by them


def test_a_layout_that_never_settles_fails_naming_the_objects(library: SpecLibrary,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    def never(model: mujoco.MjModel, data: mujoco.MjData, free: dict[str, str],
              loose: frozenset[str] = frozenset()) -> SettleResult:
        return SettleResult(MAX_SECONDS, False, {"block_b": "moved 3.0 cm, turned 45 deg"})

    monkeypatch.setattr(plan_module, "settle", never)
    with pytest.raises(LayoutError) as err:
        compile_plan(library, library.get("task", "stack_blocks"), "random", 2)
    message = str(err.value)
    assert "stack_blocks" in message and "seed 2" in message and "random" in message
    assert f"{SETTLE_REDRAWS} layouts" in message and "block_b: moved 3.0 cm" in message
