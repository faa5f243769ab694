"""Program evaluation (stages, order, memory, score) on hand-built states, and compilation of real plans."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest
from dojo.backends.predicate_program import (
    Press,
    ProgramError,
    ProgramLayout,
    compile_program,
    init_memory,
    program_step,
    stack_params,
)
from dojo.backends.predicate_state import gather_state, mujoco_state
from dojo.language.predicates.connectives import AllOf, AnyOf, Not
from dojo.language.predicates.joint_bound import JointBound
from dojo.language.predicates.ordered import Ordered
from dojo.language.predicates.pressed import Pressed


def layout(success, stages=(), names=None, weights=None, sequential=False, presses=(), n_order=0) -> ProgramLayout:
    names = names or tuple(f"s{k}" for k in range(len(stages)))
    weights = weights or (1.0,) * len(stages)
    return ProgramLayout(success, tuple(stages), tuple(names), tuple(weights), sequential, tuple(presses), n_order)


def joint_state(q: list[list[float]]) -> dict[str, np.ndarray]:
    """A state with joints only: q is [N][J]."""
    q = np.asarray(q, dtype=float)
    n = q.shape[0]
    return {"pos": np.zeros((n, 0, 3)), "mat": np.zeros((n, 0, 3, 3)), "qpos": q,
            "contact": np.zeros((n, 0, 0), bool)}


NO_PARAMS = {"frame_c": np.zeros((1, 0, 3)), "frame_h": np.zeros((1, 0, 3)), "const_pos": np.zeros((1, 0, 3)),
             "init_center": np.zeros((1, 0, 3)), "press_rest": np.zeros((1, 0)), "press_far": np.zeros((1, 0))}


def run(lay: ProgramLayout, qs: list[list[list[float]]], params=None):
    """Evaluate consecutive steps 1, 2, ... of the joint states qs[t] ([N][J] each); return the last output."""
    n = len(qs[0])
    params = params or {k: np.repeat(v, n, axis=0) for k, v in NO_PARAMS.items()}
    memory = init_memory(np, lay, n)
    for t, q in enumerate(qs, start=1):
        memory, out = program_step(np, lay, joint_state(q), params, memory, t)
    return memory, out


AT_LEAST = lambda j, v: JointBound(j, v, True)


def test_stages_latch_record_first_step_and_weight_the_score():
    lay = layout(AT_LEAST(0, 1.0), [AT_LEAST(0, 0.5), AT_LEAST(0, 1.0)], weights=(1.0, 3.0))
    _, out = run(lay, [[[0.6]], [[0.2]]])
    assert out.stage_step.tolist() == [[1, -1]] and not out.success[0]
    assert out.score[0] == pytest.approx(25.0)  # stays reached after q fell back
    _, out = run(lay, [[[0.6]], [[0.2]], [[1.0]]])
    assert out.stage_step.tolist() == [[1, 3]] and out.success[0] and out.score[0] == pytest.approx(100.0)


def test_a_full_score_is_exactly_100_whatever_the_weights_sum_to_in_float32():
    """Weights whose float32 sum rounds (ten of 0.1) once gave 100.0000076 on a GPU (a TF32 matmul), which the
    results store refuses; every stage reached must score 100 exactly, and never more."""
    import jax.numpy as jnp

    weights = (0.1,) * 10 + (0.7, 1e-3)
    lay = layout(AT_LEAST(0, 0.0), [AT_LEAST(0, 0.0)] * len(weights), weights=weights)
    for xp in (np, jnp):
        memory = init_memory(xp, lay, 1)
        params = {k: xp.asarray(v) for k, v in NO_PARAMS.items()}
        _, out = program_step(xp, lay, {k: xp.asarray(v) for k, v in joint_state([[1.0]]).items()}, params, memory, 1)
        assert float(out.score[0]) == 100.0


def test_success_needs_every_stage():
    lay = layout(AT_LEAST(0, 1.0), [AT_LEAST(1, 1.0)])
    _, out = run(lay, [[[1.0, 0.0]]])
    assert not out.success[0] and out.score[0] == 0.0


def test_sequential_stages_count_only_after_earlier_ones():
    stages = [AT_LEAST(1, 1.0), AT_LEAST(0, 1.0)]
    qs = [[[1.0, 0.0]], [[1.0, 1.0]]]
    _, out = run(layout(AT_LEAST(0, 9.0), stages, sequential=True), qs)
    assert out.stage_step.tolist() == [[2, 2]]
    _, out = run(layout(AT_LEAST(0, 9.0), stages, sequential=False), qs)
    assert out.stage_step.tolist() == [[2, 1]]


def test_ordered_needs_first_times_in_order():
    lay = layout(Ordered((AT_LEAST(0, 1.0), AT_LEAST(1, 1.0)), 0), n_order=2)
    # env 0: joint 0 first, then joint 1; env 1: the other way round
    memory, out = run(lay, [[[1.0, 0.0], [0.0, 1.0]], [[0.0, 1.0], [1.0, 0.0]]])
    assert out.success.tolist() == [True, False]
    assert memory["first"].tolist() == [[1, 2], [2, 1]]


def test_boolean_combinators():
    a, b = AT_LEAST(0, 1.0), AT_LEAST(1, 1.0)
    q = [[[1.0, 0.0], [1.0, 1.0], [0.0, 0.0]]]
    assert run(layout(AllOf((a, b))), q)[1].success.tolist() == [False, True, False]
    assert run(layout(AnyOf((a, b))), q)[1].success.tolist() == [True, True, False]
    assert run(layout(Not(a)), q)[1].success.tolist() == [False, False, True]
    assert run(layout(AllOf(())), q)[1].success.tolist() == [True] * 3   # forall over an empty group
    assert run(layout(AnyOf(())), q)[1].success.tolist() == [False] * 3  # exists over an empty group


def test_pressed_counts_presses_across_steps():
    lay = layout(Pressed(0, 2), [Pressed(0, 1)], presses=[Press(0, None)])
    params = {**NO_PARAMS, "press_rest": np.zeros((1, 1)), "press_far": np.full((1, 1), -0.01)}
    memory, out = run(lay, [[[0.0]], [[-0.009]], [[-0.006]], [[-0.009]], [[0.0]]], params)
    assert memory["press_count"].tolist() == [[1]] and out.stage_step.tolist() == [[2]] and not out.success[0]
    _, out = run(lay, [[[0.0]], [[-0.009]], [[0.0]], [[-0.009]]], params)
    assert out.success[0]


def test_no_stages_scores_success():
    _, out = run(layout(AT_LEAST(0, 1.0)), [[[1.0], [0.0]]])
    assert out.score.tolist() == [100.0, 0.0]


# ---- compilation against real plans ----

def state_after(plan, qpos: np.ndarray, settle_steps: int = 0) -> mujoco.MjData:
    model = plan.model()
    data = plan.initial_data(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    if settle_steps:
        mujoco.mj_step(model, data, nstep=settle_steps)
    return data


def evaluate(plan, program, data):
    memory = init_memory(np, program.layout, 1)
    state = mujoco_state(program.index, program.params["const_pos"], data)
    return program_step(np, program.layout, state, stack_params([program.params]), memory, 1)[1]


def test_compiled_frames_use_geometry_not_asset_origins(stack_plan, probe_plan):
    stack = compile_program(stack_plan)
    assert np.allclose(stack.params["frame_h"][0], [0.02, 0.02, 0.02])  # block: centred box
    probe = compile_program(probe_plan)
    cube = probe.index.frame_kind.index(0)  # the first body frame is cube_0 (bottom-centre origin)
    assert np.allclose(probe.params["frame_c"][cube], [0.0, 0.0, 0.02], atol=1e-9)
    assert probe.layout.presses == (Press(probe.layout.presses[0].joint, None),)  # one slot per button
    assert probe.params["press_rest"].tolist() == [0.0] and probe.params["press_far"].tolist() == [-0.01]


def test_on_holds_after_placing_the_block_on_the_plate(stack_plan, set_free_pose):
    program = compile_program(stack_plan)
    qpos = np.asarray(stack_plan.init_qpos)
    plate = stack_plan.initial_data().xpos[stack_plan.model().body("plate").id]
    assert not evaluate(stack_plan, program, state_after(stack_plan, qpos)).stage_step[0, 1] >= 0
    set_free_pose(stack_plan, qpos, "block", plate + [0.02, 0.0, 0.04])
    out = evaluate(stack_plan, program, state_after(stack_plan, qpos, settle_steps=100))
    assert out.stage_step[0].tolist() == [-1, 1]  # placed (not lifted): score 2/3, no success
    assert out.score[0] == pytest.approx(200.0 / 3.0) and not out.success[0]


def test_inside_forall_and_exists_on_the_probe_task(probe_plan, set_free_pose):
    program = compile_program(probe_plan)
    model, data0 = probe_plan.model(), probe_plan.initial_data()
    bin_inside = data0.site_xpos[model.site("bin/inside").id]
    qpos = np.asarray(probe_plan.init_qpos)
    set_free_pose(probe_plan, qpos, "cube_0", bin_inside + [0.03, 0.0, -0.02])
    out = evaluate(probe_plan, program, state_after(probe_plan, qpos, settle_steps=50))
    assert out.stage_step[0].tolist() == [1, -1, -1]  # exists, not forall
    set_free_pose(probe_plan, qpos, "cube_1", bin_inside + [-0.03, 0.0, -0.02])
    out = evaluate(probe_plan, program, state_after(probe_plan, qpos, settle_steps=50))
    assert out.stage_step[0].tolist() == [1, 1, -1] and not out.success[0]  # the button was not pressed


def test_touched_and_joint_predicates_compile_against_the_model(probe_plan):
    program = {"success": {"all": [{"touched": ["cube_0", "table"]}, {"joint_at_most": ["button/press", 0.002]},
                                   {"not": {"touched": ["cube_0", "robot"]}}, {"upright": "cube_1"}]},
               "stages": [], "stage_order": "any"}
    plan = dataclasses.replace(probe_plan, program=program, compiled_program={})
    out = evaluate(plan, compile_program(plan, probe_plan.model()), probe_plan.initial_data())
    assert out.success.tolist() == [True]


@pytest.mark.parametrize("success, message", [
    ({"on": ["ghost", "bin"]}, "ghost"),
    ({"inside": ["cube_0", "bin/nowhere"]}, "no annotation 'nowhere'"),
    ({"upright": "_"}, "outside forall"),
    ({"joint_at_least": ["button/twist", 0.1]}, "no such joint"),
])
def test_unresolved_names_are_reported(probe_plan, success, message):
    plan = dataclasses.replace(probe_plan, program={"success": success, "stages": []}, compiled_program={})
    with pytest.raises(ProgramError, match=message):
        compile_program(plan, probe_plan.model())


def test_program_step_runs_under_jax_jit():
    """The same definitions trace with jax.numpy (one tiny jit: compiling costs seconds on CPU)."""
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    lay = layout(AnyOf((Ordered((AT_LEAST(0, 1.0), AT_LEAST(1, 1.0)), 0), Pressed(0, 1))),
                 [AT_LEAST(0, 1.0), Not(AT_LEAST(1, 5.0))], sequential=True, presses=[Press(0, None)], n_order=2)
    params = {**{k: np.repeat(v, 2, axis=0) for k, v in NO_PARAMS.items()},
              "press_rest": np.zeros((2, 1)), "press_far": np.full((2, 1), -1.0)}
    step = jax.jit(lambda state, memory, t: program_step(jnp, lay, state, params, memory, t))
    memory_j, memory_n = init_memory(jnp, lay, 2), init_memory(np, lay, 2)
    for t, q in enumerate([[[1.0, 0.0], [0.0, 1.0]], [[0.0, 1.0], [-0.9, 0.0]]], start=1):
        state = joint_state(q)
        memory_j, out_j = step({k: jnp.asarray(v) for k, v in state.items()}, memory_j, t)
        memory_n, out_n = program_step(np, lay, state, params, memory_n, t)
    assert np.asarray(out_j.success).tolist() == out_n.success.tolist() == [True, False]  # env 1 misses stage 0
    assert np.allclose(np.asarray(out_j.score), out_n.score)
    assert np.asarray(out_j.stage_step).tolist() == out_n.stage_step.tolist()


def test_gather_and_program_trace_together_under_jax_jit(probe_plan, set_free_pose):
    """What the MJX backend runs: gather_state + program_step on batched simulation arrays, under jit."""
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    program = compile_program(probe_plan)
    model, data0 = probe_plan.model(), probe_plan.initial_data()
    qpos = np.asarray(probe_plan.init_qpos)
    set_free_pose(probe_plan, qpos, "cube_1", data0.site_xpos[model.site("bin/inside").id] + [0.0, 0.0, -0.02])
    data = state_after(probe_plan, qpos, settle_steps=20)
    params = stack_params([program.params])
    c = data.contact
    arrays = [a[None] for a in (data.xpos, data.xmat, data.site_xpos, data.site_xmat, data.qpos, c.geom1, c.geom2,
                                c.dist)]

    def evaluate_jax(*arrays):
        state = gather_state(jnp, program.index, params["const_pos"], *arrays)
        return program_step(jnp, program.layout, state, params, init_memory(jnp, program.layout, 1), 1)[1]

    out_j = jax.jit(evaluate_jax)(*arrays)
    out_n = evaluate(probe_plan, program, data)
    assert np.asarray(out_j.stage_step).tolist() == out_n.stage_step.tolist() == [[1, -1, -1]]
    assert np.allclose(np.asarray(out_j.score), out_n.score)


def test_batched_state_reads_a_stacked_data_object(probe_plan):
    """`batched_state` (the MJX backend's entry) agrees with the per-MjData path on a stacked Data-like."""
    from types import SimpleNamespace

    from dojo.backends.predicate_state import batched_state

    plan = dataclasses.replace(probe_plan, compiled_program={}, program={"success": {"all": [
        {"touched": ["cube_0", "table"]}, {"inside": ["cube_1", "bin"]}, {"on": ["cube_1", "cubes"]}]}, "stages": []})
    program = compile_program(plan, probe_plan.model())
    data = state_after(probe_plan, np.asarray(probe_plan.init_qpos), settle_steps=5)
    contact = SimpleNamespace(geom=np.stack([data.contact.geom] * 2), dist=np.stack([data.contact.dist] * 2))
    stacked = SimpleNamespace(contact=contact, **{k: np.stack([getattr(data, k)] * 2)
                                                  for k in ("xpos", "xmat", "site_xpos", "site_xmat", "qpos", "qvel")})
    const = np.stack([program.params["const_pos"]] * 2)
    batched = batched_state(np, program.index, const, stacked)
    single = mujoco_state(program.index, program.params["const_pos"], data)
    for key, value in single.items():
        assert np.array_equal(batched[key], np.concatenate([value, value])), key
    assert single["contact"].any()  # the cubes rest on the table
