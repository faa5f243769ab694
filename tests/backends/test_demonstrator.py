"""The demonstrator actor and same_order_as (imitate_sorting_sequence's): the demonstrator moves its objects into
its basket one at a time in the order drawn for the episode, and same_order_as holds only when the robot's
partners went into the basket in that same order."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from dojo.backends.mujoco.backend import MujocoBackend
from dojo.backends.predicate_program import compile_program, init_memory, program_step, stack_params
from dojo.backends.predicate_state import mujoco_state
from dojo.compiler.plan import Plan, compile_plan
from dojo.compiler.spec_library import SpecLibrary


@pytest.fixture(scope="module")
def demo_plan() -> Plan:
    library = SpecLibrary.load(strict=False)
    return compile_plan(library, library.get("task", "imitate_sorting_sequence"), "standard", 0)


def _spec(plan: Plan) -> dict:
    return plan.program["actors"][0]["demonstrator"]


def test_the_demonstrator_moves_its_objects_in_the_drawn_order(demo_plan):
    plan, spec = demo_plan, _spec(demo_plan)
    model = plan.model()
    order = spec["objects"]
    others = {"demo_basket", *spec["arm"].values()}
    assert sorted(order) == sorted(n for n in plan.objects if n.startswith("demo_") and n not in others)
    period = spec["move_steps"] + spec["pause"]
    with MujocoBackend(num_threads=1) as backend:
        backend.load([plan])
        backend.reset()
        data = backend._slots[0].data
        start = {n: data.qpos[model.joint(f"{n}/free").qposadr[0]:][:3].copy() for n in order}
        moved_at = {}
        for step in range(spec["start_step"] + period * 2 - 2):  # two moves (the others are alike)
            for n in order:
                here = data.qpos[model.joint(f"{n}/free").qposadr[0]:][:3]
                if n not in moved_at and np.linalg.norm(here - start[n]) > 0.01:
                    moved_at[n] = step
            backend.step(np.zeros((1, 14)), mode="delta_joint")
        inside = data.site_xpos[model.site(plan.objects["demo_basket"]["sites"]["inside"]).id]
        half = model.site_size[model.site(plan.objects["demo_basket"]["sites"]["inside"]).id]
        for n in order[:2]:
            pos = data.qpos[model.joint(f"{n}/free").qposadr[0]:][:3]
            assert np.all(np.abs(pos[:2] - inside[:2]) <= half[:2]), n  # in its basket after its move
    assert list(moved_at) == order[:2]  # the first two moved, in the drawn order; the others wait
    assert moved_at[order[0]] == pytest.approx(spec["start_step"] + 1, abs=1)
    assert moved_at[order[1]] - moved_at[order[0]] == pytest.approx(period, abs=1)


def test_same_order_as_holds_only_for_the_demonstrated_order(demo_plan):
    plan = demo_plan
    model = plan.model()
    program = compile_program(plan, model)
    partner = {d: d.removeprefix("demo_") for d in _spec(plan)["objects"]}
    inside = plan.initial_data(model).site_xpos[model.site(plan.objects["tray"]["sites"]["inside"]).id]

    def succeeds(robot_order: list[str]) -> bool:
        data = plan.initial_data(model)
        memory = init_memory(np, program.layout, 1)
        params = stack_params([program.params])
        out = None
        for step, name in enumerate(robot_order, start=1):
            adr = model.joint(f"{name}/free").qposadr[0]
            data.qpos[adr:adr + 3] = inside + [0.05 * (step - 3), 0.0, -0.035]  # standing on the tray's floor
            mujoco.mj_forward(model, data)
            state = mujoco_state(program.index, program.params["const_pos"], data)
            memory, out = program_step(np, program.layout, state, params, memory, step)
        return bool(out.success[0])

    shown = [partner[d] for d in _spec(plan)["objects"]]
    assert succeeds(shown)
    assert not succeeds(shown[::-1])


def test_the_arm_holds_each_object_on_its_way_and_keeps_its_links(demo_plan):
    """The visible arm (kinematic bodies posed by the actor): its hand's grip frame is at the carried object's top
    during a move, its links keep their lengths (shoulder fixed, elbow to wrist one forearm), it rests at the end."""
    plan, spec = demo_plan, _spec(demo_plan)
    model = plan.model()
    arm = spec["arm"]
    period = spec["move_steps"] + spec["pause"]
    first = spec["objects"][0]
    height = 2.0 * plan.objects[first]["half_extents"][2]
    with MujocoBackend(num_threads=1) as backend:
        backend.load([plan])
        backend.reset()
        data = backend._slots[0].data
        body = lambda name: data.xpos[model.body(plan.objects[name]["body"]).id].copy()  # noqa: E731
        shoulder = body(arm["upper"])
        grip = model.site(plan.objects[arm["hand"]]["sites"]["grip"]).id
        for _ in range(spec["start_step"] + spec["move_steps"] // 2):  # half way through the first move
            backend.step(np.zeros((1, 14)), mode="delta_joint")
        top = data.qpos[model.joint(f"{first}/free").qposadr[0]:][:3] + [0.0, 0.0, height]
        assert np.linalg.norm(data.site_xpos[grip] - top) < 0.03
        assert np.allclose(body(arm["upper"]), shoulder)
        assert np.linalg.norm(body(arm["hand"]) - body(arm["forearm"])) == pytest.approx(0.4, abs=1e-3)
        assert np.linalg.norm(body(arm["forearm"]) - shoulder) == pytest.approx(0.4, abs=1e-3)
        for _ in range(period * len(spec["objects"])):  # every move done, and the pause after the last
            backend.step(np.zeros((1, 14)), mode="delta_joint")
        rest = body(arm["hand"])
        backend.step(np.zeros((1, 14)), mode="delta_joint")
        assert np.allclose(body(arm["hand"]), rest) and rest[2] > 0.9  # retracted, up and still
