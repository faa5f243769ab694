"""The perturbed expert (`dojo.experts.perturbed`): the targets of its fitting steps, and only those, believed a set
distance off in a horizontal direction drawn from the episode, the same every run. Its figures (it fails on most
seeds of each tolerance task) are the validity table's `perturbed` column (README)."""

from __future__ import annotations

import numpy as np
import pytest
from dojo.compiler.plan import compile_plan
from dojo.experts.oracle import ScriptedExpert
from dojo.experts.perturbed import PERTURB_DISTANCE, PerturbedOracle, aim_offsets, fits, has_fits
from dojo.experts.validity import plan_files, policies, run_policy, runs


@pytest.fixture(scope="module")
def screw_plan(library):
    return compile_plan(library, library.get("task", "fasten_screws"), "standard", 0)


def test_fitting_steps_are_those_of_skills_registered_as_fits(library):
    assert fits([{"skill": "grasp", "object": "a"}, {"skill": "insert", "object": "a", "target": "rack/hole_1"},
                 {"skill": "place", "object": "b", "target": "rack/hole_2"},
                 {"skill": "screw", "object": "s", "target": "nut/socket"}]) == ["rack/hole_1", "nut/socket"]
    assert has_fits(library.get("task", "fasten_screws")) and has_fits(library.get("task", "insert_tubes"))
    assert not has_fits(library.get("task", "build_tower"))
    assert runs("perturbed", library.get("task", "deposit_coin"))
    assert not runs("perturbed", library.get("task", "stack_blocks"))


def test_each_target_is_believed_the_distance_off_horizontally_the_same_every_run(library, screw_plan):
    steps = list(library.get("task", "fasten_screws").data["expert"])
    offsets = aim_offsets(screw_plan, steps, PERTURB_DISTANCE)
    assert sorted(offsets) == ["nut_a/socket", "nut_b/socket", "nut_c/socket"]
    for offset in offsets.values():
        assert np.linalg.norm(offset) == pytest.approx(PERTURB_DISTANCE) and offset[2] == 0.0
    assert len({tuple(np.round(o, 9)) for o in offsets.values()}) == 3  # a direction per target
    again = aim_offsets(screw_plan, steps, PERTURB_DISTANCE)
    assert all(np.array_equal(offsets[k], again[k]) for k in offsets)


def test_the_perturbed_expert_sees_its_targets_moved_and_nothing_else(library, screw_plan):
    steps = list(library.get("task", "fasten_screws").data["expert"])
    expert = PerturbedOracle({"distance": 0.005}).new_expert(screw_plan)
    plain = ScriptedExpert(screw_plan, steps)
    for e in (expert, plain):
        e.observe(np.asarray(screw_plan.init_qpos, float), np.zeros(e.model.nv))
    shift = aim_offsets(screw_plan, steps, 0.005)["nut_a/socket"]
    moved = expert.ctx.scene.site("nut_a", "socket").center - plain.ctx.scene.site("nut_a", "socket").center
    assert np.allclose(moved, shift)
    assert np.allclose(expert.ctx.scene.site("nut_a", "top").center, plain.ctx.scene.site("nut_a", "top").center)
    assert np.allclose(expert.ctx.scene.box("screw_a").center, plain.ctx.scene.box("screw_a").center)
    assert policies(perturb=0.004)["perturbed"].distance == 0.004


class _KeptExperts(PerturbedOracle):
    """The perturbed expert, each episode's scripted expert kept to look at afterwards."""

    def __init__(self, config: dict | None = None) -> None:
        super().__init__(config)
        self.made: list[ScriptedExpert] = []

    def new_expert(self, plan):
        expert = super().new_expert(plan)
        self.made.append(expert)
        return expert


@pytest.mark.parametrize("task, part, opening", [("insert_tubes", "tube_0", "rack/hole_1"),
                                                  ("plug_in_charger", "charger", "strip/socket")])
def test_a_fit_aimed_3_mm_off_gives_up_and_puts_the_part_back(library, plan_cache, task, part, opening):
    """`insert` and `plug` push a few millimetres in and, when the part stands on the rim (the charger) or is pushed
    aside on its way in (a tube's rounded end cams along the rim), give up without letting go over the opening: the
    part is set down where it stood at the start, so that no later step (home opens the grippers) drops it in."""
    files = plan_files(library, [task], 1, plan_cache)[task]
    policy = _KeptExperts({"distance": PERTURB_DISTANCE})
    [outcome] = run_policy(policy, files, num_envs=1)
    ctx = policy.made[-1].ctx
    assert not outcome.success
    assert any(f.startswith(f"{part} did not enter") for f in ctx.failures), ctx.failures
    start, end = ctx.start_scene.box(part).center[:2], ctx.scene.box(part).center[:2]
    hole = ctx.scene.site(*opening.split("/")).center[:2]
    assert float(np.linalg.norm(end - start)) < 0.5 * float(np.linalg.norm(end - hole)), (start, end, hole)
