"""Task events on the CPU backend: hide/show/spawn/remove move objects out of the scene and back at the right
control step (`at_step`, or the step after a `when` predicate first holds), a locked joint stays where it was, a
cover is put over its target, and names an event cannot act on are located spec errors."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest
from dojo.backends.mujoco.backend import MujocoBackend
from dojo.backends.world_events import PARK, EventError, compile_events
from dojo.compiler.plan import Plan, compile_plan
from dojo.compiler.spec_errors import SpecError


@pytest.fixture(scope="module")
def events_plan(library) -> Plan:
    return compile_plan(library, library.get("task", "probe_events"), "standard", 0)


def _xy(plan: Plan, data: mujoco.MjData, name: str) -> np.ndarray:
    return data.qpos[plan.model().joint(f"{name}/free").qposadr[0]:][:2].copy()


def test_objects_leave_and_come_back_on_cue(events_plan):
    plan = events_plan
    start = {n: np.asarray(plan.init_qpos)[plan.model().joint(f"{n}/free").qposadr[0]:][:2] for n in
             ("cube_0", "cube_1", "cube_2")}
    assert "events" in plan.requires
    with MujocoBackend(num_threads=1) as backend:
        backend.load([plan])
        backend.reset()
        data = backend._slots[0].data
        parked = lambda n: bool(np.linalg.norm(_xy(plan, data, n) - PARK[:2]) < 1.5)  # noqa: E731
        assert parked("cube_1") and not parked("cube_0")  # spawned later: absent from the start
        seen = []
        for _ in range(8):
            backend.step(np.zeros((1, 14)), mode="joint")
            seen.append((parked("cube_0"), parked("cube_1"), parked("cube_2")))
        button = plan.model().joint("button/press").qposadr[0]
        locked_at = float(data.qpos[button])
    # step 3 hides cube_0 and step 6 shows it; step 4 spawns cube_1, which is on the table at step 5, so cube_2
    # is removed then (a `when` event acts on the step its predicate first holds)
    assert seen == [(False, True, False), (False, True, False), (True, True, False), (True, False, False),
                    (True, False, True), (False, False, True), (False, False, True), (False, False, True)]
    assert np.allclose(_xy(plan, data, "cube_0"), start["cube_0"], atol=0.01)  # back where it was hidden
    assert np.allclose(_xy(plan, data, "cube_1"), start["cube_1"], atol=0.01)  # where the scene placed it
    assert locked_at == pytest.approx(float(plan.init_qpos[button]), abs=1e-9)


def test_cover_puts_the_occluder_over_its_target(events_plan):
    plan = dataclasses.replace(events_plan, program={**events_plan.program,
                                                     "events": [{"at_step": 0, "cover": ["cube_2", "cube_0"]}]})
    model = plan.model()
    events = compile_events(plan, model)
    data = plan.initial_data(model)
    state = events.start(data)
    assert events.fire(state, data, 1, np.zeros(0, bool))
    assert np.allclose(_xy(plan, data, "cube_2"), _xy(plan, data, "cube_0"))


def test_events_naming_what_they_cannot_move_are_errors(events_plan, library):
    bad = dataclasses.replace(events_plan, program={**events_plan.program, "events": [{"at_step": 1, "hide": "button"}]})
    with pytest.raises(EventError, match="not a movable object") as err:
        compile_events(bad, bad.model())
    assert err.value.path == ("events", 0, "hide")
    bad = dataclasses.replace(events_plan, program={**events_plan.program, "events": [{"at_step": 1, "lock": "button/slide"}]})
    with pytest.raises(EventError, match=r"joints of 'button': button/press"):
        compile_events(bad, bad.model())
    with pytest.raises(SpecError):
        spec = library.get("task", "probe_events")
        broken = dataclasses.replace(spec, data={**spec.data, "events": [{"at_step": 1, "lock": "button/slide"}]})
        compile_plan(library, broken, "standard", 0)


def test_validation_names_unknown_objects_in_events(library):
    from dojo.compiler.task_checks import task_problems

    spec = dict(library.get("task", "probe_events").data)
    spec["events"] = [{"at_step": 1, "hide": "cube_9"}, {"when": {"on": ["cueb_0", "table"]}, "cover": ["cube_0", "bin"]}]
    problems = {path: message for path, message, _ in task_problems(spec)}
    assert "unknown object 'cube_9'" in problems[("events", 0, "hide")]
    assert "unknown object 'bin'" in problems[("events", 1, "cover", 1)]
    assert "did you mean 'cube_0'" in problems[("events", 1, "when", "on", 0)]


def test_hidden_after_hides_each_copy_once_its_stage_holds(library):
    plan = compile_plan(library, library.get("task", "probe_hidden_after"), "standard", 0)
    assert "events" in plan.requires and [e["hide"] for e in plan.program["events"]] == ["mark_0", "mark_1"]
    with MujocoBackend(num_threads=1) as backend:
        backend.load([plan])
        backend.reset()
        data = backend._slots[0].data
        parked = lambda n: bool(np.linalg.norm(_xy(plan, data, n) - PARK[:2]) < 1.5)  # noqa: E731
        for _ in range(3):
            backend.step(np.zeros((1, 14)), mode="joint")
        assert not parked("mark_0") and not parked("mark_1")  # the stage has not held yet
        cube = plan.model().joint("cube/free")
        data.qpos[cube.qposadr[0] + 2] += 0.1  # the cube is lifted: the stage holds from this step
        data.qvel[cube.dofadr[0]:cube.dofadr[0] + 6] = 0.0
        for _ in range(2):
            backend.step(np.zeros((1, 14)), mode="joint")
        assert parked("mark_0") and parked("mark_1") and not parked("cube")
