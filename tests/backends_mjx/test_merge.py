"""Buckets merged across tasks (`make_buckets(merge=True)`, `lanes`): which tasks merge (merge_groups.py: only where
the merged model stays within the growth bound and is one structure), the slots, each task's program moved into the
merged model, the lanes' selection, and the same physics as separate buckets (one compilation)."""

from __future__ import annotations

import dataclasses
import math
import random

import numpy as np
import pytest
from conftest import toy_plan

from dojo.backends.mjx.backend import PlanLayout
from dojo.backends.mjx.batch import Engine
from dojo.backends.mjx.bucket import make_buckets
from dojo.backends.mjx.lanes import bucket_programs, select_lanes
from dojo.backends.mjx.merge_groups import GROWTH
from dojo.backends.mjx.pad import PARK_ORIGIN
from dojo.backends.program_types import ProgramOutput

ITEMS = {"toy": (), "pair": ("ball", "box"), "twin": ("ball", "ball")}
"""Three toy tasks: a block alone; a block, a ball and a box; a block and two balls."""


def _plans():
    return [toy_plan(task=task, seed=s, items=items, block_size=0.03 + 0.005 * k)
            for k, (task, items) in enumerate(ITEMS.items()) for s in range(2)]


def _slots(member) -> dict[str, str]:
    """The plan's object bodies -> the slot each fills."""
    return {old: new for new, old in member.padded.names.items() if old in {o["body"] for o in
                                                                            member.plan.objects.values()}}


def test_tasks_share_one_bucket_with_the_most_of_each_slot_kind_and_stable_slots():
    """The full union (`growth=math.inf`): the three tasks' union (block, box, two balls: 25 DoFs) is 1.32x the
    largest task's own (19), past the default bound, and what is tested here is the slots of one union."""
    plans = _plans()
    assert len(make_buckets(plans)) == 3
    [bucket] = make_buckets(plans, merge=True, growth=math.inf)
    assert bucket.tasks == ("pair", "toy", "twin")
    model = bucket.model
    slots = [model.body(i).name for i in range(model.nbody) if model.body(i).name.startswith("slot")]
    assert len(slots) == 4  # block, box, and two balls (twin's two, not pair's one plus twin's two)
    by_task: dict[str, list] = {}
    for member in bucket.members:
        by_task.setdefault(member.plan.task, []).append(member)
    for task, members in by_task.items():
        first = _slots(members[0])
        assert all(_slots(m) == first for m in members), task  # every plan of a task: the same slots
        assert len(first) == 1 + len(ITEMS[task])
        for member in members:
            assert sorted(member.padded.parked) == sorted(set(slots) - set(first.values()))
            for name in member.padded.parked:
                body = member.model.body(name).id
                assert member.model.body_gravcomp[body] == 1.0 and member.model.body_pos[body][2] == PARK_ORIGIN[2]
            layout = PlanLayout.build(member.model, member.plan.model(), member.padded.names)
            np.testing.assert_allclose(layout.qpos(member.qpos), member.plan.init_qpos)
    assert {task: len(m[0].padded.parked) for task, m in by_task.items()} == {"toy": 3, "pair": 1, "twin": 1}


def _tasks_by_bucket(buckets) -> list[tuple[str, ...]]:
    return sorted(b.tasks for b in buckets)


def test_tasks_whose_objects_are_the_same_kinds_merge_at_no_growth():
    """A block and a ball, sized differently per task: the merged model is each task's own, so even `growth=0`
    merges them."""
    plans = [toy_plan(task=task, seed=s, items=("ball",), block_size=size)
             for task, size in (("left", 0.03), ("right", 0.04)) for s in range(2)]
    assert len(make_buckets(plans)) == 2
    [bucket] = make_buckets(plans, merge=True, growth=0.0)
    assert bucket.tasks == ("left", "right") and len(bucket.members) == 4
    own = make_buckets(plans)[0].model
    assert (bucket.model.nv, bucket.model.ngeom) == (own.nv, own.ngeom)


def test_a_task_that_would_grow_the_union_past_the_bound_stays_apart():
    """`pair` (block, ball, box: 19 DoFs) and `twin` (block, two balls: 19): their union (block, box, two balls)
    has 25, 1.32x the larger's. A bound of 0.25 keeps them apart; the default, 0.5, merges them. `toy` (a block)
    fits inside either; ties go by task, so at 0.25 it joins `pair`."""
    pair, twin = ([p for p in _plans() if p.task == task] for task in ("pair", "twin"))
    assert 0.25 < 0.32 < GROWTH
    assert _tasks_by_bucket(make_buckets(pair + twin, merge=True, growth=0.25)) == [("pair",), ("twin",)]
    [both] = make_buckets(pair + twin, merge=True)
    assert both.tasks == ("pair", "twin") and both.model.nv == 25
    assert _tasks_by_bucket(make_buckets(_plans(), merge=True, growth=0.25)) == [("pair", "toy"), ("twin",)]


def test_tasks_that_do_not_compile_to_one_structure_stay_apart_at_any_growth():
    """A task with another timestep (an option: structure to MJX) never joins a cluster, not even under the full
    union, so its bucket does not carry the others' slots; the tasks that agree with each other still merge."""
    plans = [toy_plan(task=task, seed=s, items=("box",) if task == "bee" else ("ball",))
             for task in ("ant", "bee", "cat") for s in range(2)]
    plans = [dataclasses.replace(p, hash=p.hash + "-fast", model_xml=p.model_xml.replace(
        'timestep="0.004"', 'timestep="0.002"')) if p.task == "bee" else p for p in plans]
    merged = make_buckets(plans, merge=True, growth=math.inf)
    assert _tasks_by_bucket(merged) == [("ant", "cat"), ("bee",)]
    assert [b.model.nv for b in merged] == [13, 13]  # pusher, block and one ball or box each: no parked slot


def test_merged_buckets_are_the_same_whatever_the_order_of_the_plans():
    plans = _plans()
    want = [(b.key, sorted(m.plan.hash for m in b.members)) for b in make_buckets(plans, merge=True)]
    for seed in range(3):
        shuffled = random.Random(seed).sample(plans, len(plans))
        got = [(b.key, sorted(m.plan.hash for m in b.members)) for b in make_buckets(shuffled, merge=True)]
        assert got == want


def test_a_task_padded_in_several_groups_merges_the_same_whatever_the_order_of_its_plans():
    """`general_pickup` draws other objects each episode, so its plans pad in several groups, and with growth 1.0
    those merge with one another: the clusters must not depend on which group came first (they did, when a unit
    was named after its group's place in the plans' order)."""
    from dojo.compiler.plan import compile_plan
    from dojo.compiler.spec_library import SpecLibrary

    library = SpecLibrary.load([])
    plans = [compile_plan(library, library.get("task", "general_pickup"), "standard", seed) for seed in range(8)]
    want = [(b.key, sorted(m.plan.hash for m in b.members)) for b in make_buckets(plans, merge=True, growth=1.0)]
    assert len(want) > 1
    for seed in range(2):
        shuffled = random.Random(seed).sample(plans, len(plans))
        got = [(b.key, sorted(m.plan.hash for m in b.members))
               for b in make_buckets(shuffled, merge=True, growth=1.0)]
        assert got == want


SIMULATION_TASKS = ("build_tower", "classify_objects", "cover_blocks", "deposit_coin", "dlc", "fasten_screws",
                    "general_pickup", "imitate_sorting_sequence", "insert_key", "insert_tubes",
                    "match_and_pick_from_conveyor", "pick_from_conveyor_by_image", "play_tic_tac_toe",
                    "play_xylophone", "plug_in_charger", "pour_balls_into_vase", "press_by_number", "push_t",
                    "put_bottles_into_dustbin", "stack_blocks", "stack_blocks_by_language", "stack_bowls",
                    "swap_blocks", "swap_t")


def test_merged_simulation_tasks_stay_within_the_bound_of_their_largest_member():
    """The 24 simulation tasks (standard seed 0): fewer buckets than separate ones, some holding several tasks, and
    each merged model's DoFs and geoms within `1 + GROWTH` of the largest separate bucket among its plans'."""
    from dojo.compiler.plan import compile_plan
    from dojo.compiler.spec_library import SpecLibrary

    library = SpecLibrary.load([])
    plans = [compile_plan(library, library.get("task", task), "standard", 0) for task in SIMULATION_TASKS]
    separate, merged = make_buckets(plans), make_buckets(plans, merge=True)
    own = {m.plan.hash: b.model for b in separate for m in b.members}
    assert len(merged) < len(separate)
    assert sorted(m.plan.hash for b in merged for m in b.members) == sorted(own)
    assert any(len(b.tasks) > 1 for b in merged)
    for bucket in merged:
        nv = max(own[m.plan.hash].nv for m in bucket.members)
        ngeom = max(own[m.plan.hash].ngeom for m in bucket.members)
        assert bucket.model.nv <= (1 + GROWTH) * nv and bucket.model.ngeom <= (1 + GROWTH) * ngeom, bucket.tasks


@pytest.fixture(scope="module")
def real_plans():
    from dojo.compiler.plan import compile_plan
    from dojo.compiler.spec_library import SpecLibrary

    library = SpecLibrary.load([])
    return [compile_plan(library, library.get("task", task), "standard", seed)
            for task in ("push_t", "stack_blocks", "swap_blocks", "stack_bowls") for seed in range(2)]


def test_real_tasks_merge_into_one_bucket_and_their_programs_read_the_same_state(real_plans):
    """Four built-in tasks (one with an exclude inside its button) on one robot, merged in full (`growth=math.inf`,
    past the default bound): one bucket instead of four, one lane per task, and each member's program, moved into
    the merged model, reads at the initial state what it reads in the plan's own model (positions, rotations,
    joints, contacts)."""
    import mujoco

    from dojo.backends.predicate_program import compile_program
    from dojo.backends.predicate_state import mujoco_state

    assert len(make_buckets(real_plans)) == 4
    [bucket] = make_buckets(real_plans, merge=True, growth=math.inf)
    programs = bucket_programs(bucket)
    assert len(programs.lanes) == 4
    tasks = [m.plan.task for m in bucket.members]
    assert all((programs.member_lane[i] == programs.member_lane[j]) == (tasks[i] == tasks[j])
               for i in range(len(tasks)) for j in range(len(tasks)))
    touching = []
    for k, member in enumerate(bucket.members):
        lane = programs.lanes[programs.member_lane[k]]
        assert programs.layout_of(k) == lane.layout
        source = member.plan.model()
        own = compile_program(member.plan, source)
        data = mujoco.MjData(member.model)
        data.qpos[:], data.qvel[:], data.ctrl[:] = member.qpos, member.qvel, member.ctrl
        mujoco.mj_forward(member.model, data)
        want = mujoco_state(own.index, own.params["const_pos"], member.plan.initial_data(source))
        got = mujoco_state(lane.index, lane.params["const_pos"][k], data)
        assert np.array_equal(got["contact"], want["contact"]), member.plan.task
        touching.append(bool(want["contact"].any()))
        for name in ("pos", "mat", "qpos", "qvel"):
            np.testing.assert_allclose(got[name], want[name], atol=1e-6, err_msg=f"{member.plan.task} {name}")
    assert sum(touching) >= 2  # contacts between atoms were compared, not only empty matrices


def test_warp_contact_budget_of_a_merged_bucket_counts_only_the_slots_members_use(real_plans):
    """Most slots of a merged bucket are parked; their geoms never touch, so the contacts allocated per world are
    what the most demanding task needs on its own, not what the union of every task's objects would (the full
    union, `growth=math.inf`, so that the union holds four tasks' objects)."""
    from dojo.backends.mjx.batch import contact_capacity

    separate, [merged] = make_buckets(real_plans), make_buckets(real_plans, merge=True, growth=math.inf)
    contacts, rows = contact_capacity(merged)
    assert contacts == max(contact_capacity(b)[0] for b in separate)
    assert rows >= max(contact_capacity(b)[1] for b in separate)
    model = merged.model
    assert contacts < 4 * int(np.sum((model.geom_contype != 0) | (model.geom_conaffinity != 0)))


def test_lanes_pick_each_env_its_own_program_outputs_padded_to_the_widest():
    two_stages = ProgramOutput(success=np.array([True, True, False, False]), score=np.full(4, 50.0, np.float32),
                               stage_step=np.array([[1, -1]] * 4, np.int32), terms=np.array([[True]] * 4))
    three_terms = ProgramOutput(success=np.array([False] * 4), score=np.full(4, 0.0, np.float32),
                                stage_step=np.zeros((4, 0), np.int32), terms=np.array([[False, True, True]] * 4))
    out = select_lanes(np, np.array([0, 1, 1, 0]), [two_stages, three_terms])
    assert out["success"].tolist() == [True, False, False, False]
    assert out["score"].tolist() == [50.0, 0.0, 0.0, 50.0]
    assert out["stage_step"].tolist() == [[1, -1], [-1, -1], [-1, -1], [1, -1]]
    assert out["terms"].tolist() == [[True, False, False], [False, True, True], [False, True, True],
                                      [True, False, False]]


def _run(buckets, plan_rows, ticks, restart):
    """Every plan of `plan_rows` ({hash: (bucket, row)}) in one env; reset, then `ticks` of a 0.2 m push; the plans in
    `restart` start their episode again halfway. Returns {hash: (qpos in the plan's layout, padded qpos, member)}
    and the engine."""
    sizes = [sum(1 for b, _ in plan_rows.values() if b == k) for k in range(len(buckets))]
    members = [np.zeros(n, np.int32) for n in sizes]
    index = {m.plan.hash: (k, i) for k, b in enumerate(buckets) for i, m in enumerate(b.members)}
    for h, (k, row) in plan_rows.items():
        members[k][row] = index[h][1]
    engine = Engine(buckets, sizes, "jax")
    ctrl = [np.full((n, 1), 0.2, np.float32) for n in sizes]
    engine.tick(members, [np.ones(n, bool) for n in sizes], [np.zeros(n, bool) for n in sizes], ctrl)
    for t in range(ticks):
        resets = [np.zeros(n, bool) for n in sizes]
        if t == ticks // 2:
            for h in restart:
                resets[plan_rows[h][0]][plan_rows[h][1]] = True
        engine.tick(members, resets, [~r for r in resets], ctrl)
    qpos = {}
    for h, (k, row) in plan_rows.items():
        member = buckets[k].members[index[h][1]]
        layout = PlanLayout.build(member.model, member.plan.model(), member.padded.names)
        qpos[h] = (layout.qpos(np.asarray(engine.data[k].qpos)[row]), np.asarray(engine.data[k].qpos)[row], member)
    return qpos, engine


def test_merged_bucket_steps_like_separate_buckets_and_keeps_parked_slots_parked():
    """Two tasks (a block; a block, a ball and a box): the same trajectories, restarts included, in one merged
    bucket as in two separate ones, with one compilation."""
    plans = [p for p in _plans() if p.task != "twin"]
    separate, [merged] = make_buckets(plans), make_buckets(plans, merge=True)
    rows_sep = {m.plan.hash: (k, i) for k, bucket in enumerate(separate) for i, m in enumerate(bucket.members)}
    rows_merged = {m.plan.hash: (0, i) for i, m in enumerate(merged.members)}
    restart = {p.hash for p in plans if p.seed == 0}
    ticks = 6
    want, _ = _run(separate, rows_sep, ticks, restart)
    got, engine = _run([merged], rows_merged, ticks, restart)
    assert engine.compilations() == 1
    assert max(w[0][0] for w in want.values()) > 0.01  # the pushers moved: the comparison is not of rest states
    for h in want:
        np.testing.assert_allclose(got[h][0], want[h][0], atol=1e-4, err_msg=h)
        _, padded_qpos, member = got[h]
        for name in member.padded.parked:
            joint = member.model.body(name).jntadr[0]
            z = padded_qpos[member.model.jnt_qposadr[joint] + 2]
            assert z == pytest.approx(PARK_ORIGIN[2], abs=1e-6), (h, name)


def test_the_backend_takes_its_merge_growth_from_the_config():
    """`backend.merge_growth` (dojo/cli/config/backend/mjx.yaml): null is the module's `GROWTH` under
    `merge=true`, `.inf` the full union."""
    from dojo.backends.mjx.merge_groups import choose_merge
    from dojo.backends.registry import BackendOptions, make_backend

    for setting, want in ((None, GROWTH), (0.5, 0.5), (math.inf, math.inf)):
        backend = make_backend("mjx", BackendOptions(settings={"merge": True, "merge_growth": setting}))
        assert backend.merge is True and backend.merge_growth == setting
        assert choose_merge(backend.merge, backend.merge_growth, False, 1, 1)[:2] == (True, want)
