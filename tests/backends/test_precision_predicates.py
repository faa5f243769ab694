"""The Precision dimension's predicate words on hand-built states (positive and negative), and compiled against
the built-in tasks that use them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from dojo.backends.predicate_program import (
    ProgramError,
    ProgramLayout,
    compile_program,
    init_memory,
    program_step,
)
from dojo.compiler.plan import compile_plan
from dojo.compiler.spec_library import SpecLibrary
from dojo.language.predicates.fraction_inside import FractionInside
from dojo.language.predicates.ordered import Ordered
from dojo.language.predicates.struck import Struck

NO_PARAMS = {"frame_c": np.zeros((1, 0, 3)), "frame_h": np.zeros((1, 0, 3)), "const_pos": np.zeros((1, 0, 3)),
             "init_center": np.zeros((1, 0, 3)), "press_rest": np.zeros((1, 0)), "press_far": np.zeros((1, 0))}


def layout(success, n_order: int) -> ProgramLayout:
    return ProgramLayout(success, (), (), (), False, (), n_order)


def velocity_state(qvel: list[list[float]]) -> dict[str, np.ndarray]:
    """A state with joint velocities only: qvel is [N][nv]."""
    v = np.asarray(qvel, dtype=float)
    n = v.shape[0]
    return {"pos": np.zeros((n, 0, 3)), "mat": np.zeros((n, 0, 3, 3)), "qpos": np.zeros((n, 0)), "qvel": v,
            "contact": np.zeros((n, 0, 0), bool)}


def run(lay: ProgramLayout, velocities: list[list[list[float]]]):
    """Evaluate steps 1, 2, ... of the velocity states velocities[t] ([N][nv] each); return memory and output."""
    n = len(velocities[0])
    params = {k: np.repeat(v, n, axis=0) for k, v in NO_PARAMS.items()}
    memory = init_memory(np, lay, n)
    for t, v in enumerate(velocities, start=1):
        memory, out = program_step(np, lay, velocity_state(v), params, memory, t)
    return memory, out


BAR = Struck(dof=0, direction=-1.0, min_speed=0.05, slot=0)
"""A bar on dof 0 that rests up and is struck downwards, at 5 cm/s or faster."""


def test_a_hit_counts_and_stays_counted_after_the_bar_comes_back():
    memory, out = run(layout(BAR, 1), [[[0.0]], [[-0.12]], [[0.1]], [[0.0]]])
    assert out.success.tolist() == [True] and memory["first"].tolist() == [[2]]


def test_a_resting_or_slow_touch_is_not_a_strike():
    # a mallet laid on the bar pushes it down at 2 cm/s, then holds it down: never as fast as a hit
    _, out = run(layout(BAR, 1), [[[0.0]], [[-0.02]], [[-0.02]], [[0.0]], [[0.0]]])
    assert out.success.tolist() == [False]


def test_the_spring_bringing_the_bar_back_up_is_not_a_strike():
    _, out = run(layout(BAR, 1), [[[0.3]], [[0.1]]])
    assert out.success.tolist() == [False]


def test_min_speed_is_inclusive_and_batched():
    _, out = run(layout(BAR, 1), [[[-0.05], [-0.049], [0.0]]])
    assert out.success.tolist() == [True, False, False]


def test_ordered_strikes_need_the_first_hits_in_order():
    other = Struck(dof=1, direction=-1.0, min_speed=0.05, slot=1)
    lay = layout(Ordered((BAR, other), 2), 4)
    # env 0: bar 0 then bar 1; env 1: bar 1 first, then bar 0, then bar 1 again (its first strike was early)
    steps = [[[-0.1, 0.0], [0.0, -0.1]], [[0.0, -0.1], [-0.1, 0.0]], [[0.0, 0.0], [0.0, -0.1]]]
    memory, out = run(lay, steps)
    assert out.success.tolist() == [True, False]
    assert memory["first"][:, 2:].tolist() == [[1, 2], [2, 1]]


@pytest.fixture(scope="module")
def xylophone_plan():
    library = SpecLibrary.load([], strict=False)
    return compile_plan(library, library.get("task", "play_xylophone"), "standard", 0)


def test_struck_compiles_to_the_bar_joints_velocity_and_its_downward_sense(xylophone_plan):
    model = xylophone_plan.model()
    program = compile_program(xylophone_plan)
    bars = program.layout.success.children
    assert [b.dof for b in bars] == list(range(6))  # columns of the gathered speeds, one per bar
    assert program.index.dof_adr == tuple(int(model.joint(f"xylophone/bar_{k}").dofadr[0]) for k in range(1, 7))
    assert {b.direction for b in bars} == {-1.0} and {b.min_speed for b in bars} == {0.05}
    assert len({b.slot for b in bars}) == 6


def test_struck_names_a_joint_of_the_object(xylophone_plan):
    plan = dataclasses.replace(xylophone_plan, program={"success": {"struck": ["xylophone/bar_9", 0.05]},
                                                        "stages": []}, compiled_program={})
    with pytest.raises(ProgramError, match="bar_1"):
        compile_program(plan, xylophone_plan.model())


def test_joint_speeds_batch_across_models_of_different_sizes():
    """Two environments of one task whose models differ in size (clutter adds free joints) gather the same speed
    columns, so their states concatenate into one batch, as the CPU backend's grouped evaluation does."""
    from dojo.backends.predicate_state import StateIndex, gather_state

    index = StateIndex(frame_kind=(), frame_id=(), qpos_adr=(), geom_atom=(0,), n_atoms=1, dof_adr=(2, 5))
    states = [gather_state(np, index, np.zeros((1, 0, 3)), np.zeros((1, 1, 3)), np.zeros((1, 1, 9)),
                           np.zeros((1, 0, 3)), np.zeros((1, 0, 9)), np.zeros((1, nq)), np.zeros((1, 0), int),
                           np.zeros((1, 0), int), np.zeros((1, 0)), qvel=np.arange(nv, dtype=float)[None])
              for nq, nv in ((12, 10), (20, 16))]
    assert [st["qvel"].tolist() for st in states] == [[[2.0, 5.0]], [[2.0, 5.0]]]
    assert np.concatenate([st["qvel"] for st in states]).shape == (2, 2)


def frame_state(points: list[list[list[float]]]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """A state of frames only (points[N][F] positions, identity orientations) and params whose last frame is a
    10 cm box centred on its origin (a container's `inside` box); the others are points."""
    pos = np.asarray(points, dtype=float)
    n, f = pos.shape[:2]
    state = {"pos": pos, "mat": np.broadcast_to(np.eye(3), (n, f, 3, 3)).copy(), "qpos": np.zeros((n, 0)),
             "qvel": np.zeros((n, 0)), "contact": np.zeros((n, 0, 0), bool)}
    half = np.zeros((n, f, 3))
    half[:, -1] = 0.05
    params = {**{k: np.repeat(v, n, axis=0) for k, v in NO_PARAMS.items()}, "frame_c": np.zeros((n, f, 3)),
              "frame_h": half, "const_pos": np.zeros((n, f, 3)), "init_center": np.zeros((n, f, 3))}
    return state, params


def fraction(node: FractionInside, points) -> list[bool]:
    state, params = frame_state(points)
    lay = layout(node, 0)
    return program_step(np, lay, state, params, init_memory(np, lay, len(points)), 1)[1].success.tolist()


IN, OUT = [0.0, 0.0, 0.02], [0.3, 0.0, 0.02]


def test_fraction_inside_counts_the_members_in_the_container():
    four = (0, 1, 2, 3)
    envs = [[IN, IN, IN, OUT, [0, 0, 0]], [IN, IN, OUT, OUT, [0, 0, 0]], [OUT, OUT, OUT, OUT, [0, 0, 0]]]
    assert fraction(FractionInside(four, 4, 0.75), envs) == [True, False, False]
    assert fraction(FractionInside(four, 4, 0.5), envs) == [True, True, False]
    assert fraction(FractionInside(four, 4, 1.0), [[IN, IN, IN, IN, [0, 0, 0]]] + envs[:1]) == [True, False]


def test_fraction_inside_compares_exactly_at_the_boundary():
    ten = tuple(range(10))
    seven_in = [IN] * 7 + [OUT] * 3 + [[0, 0, 0]]
    assert fraction(FractionInside(ten, 10, 0.7), [seven_in]) == [True]
    assert fraction(FractionInside(ten, 10, 0.71), [seven_in]) == [False]


@pytest.fixture(scope="module")
def pour_plan():
    library = SpecLibrary.load([], strict=False)
    return compile_plan(library, library.get("task", "pour_balls_into_vase"), "standard", 0)


def test_fraction_inside_compiles_over_the_group_and_the_containers_inside_box(pour_plan):
    program = compile_program(pour_plan)
    node = program.layout.success
    assert isinstance(node, FractionInside) and len(node.members) == 10 and node.fraction == 0.9
    assert program.index.frame_kind[node.container] == 1  # the vase's `inside` placement site
    plan = dataclasses.replace(pour_plan, program={"success": {"fraction_inside": ["marbles", "vase", 0.5]},
                                                   "stages": []}, compiled_program={})
    with pytest.raises(ProgramError, match="marbles"):
        compile_program(plan, pour_plan.model())
