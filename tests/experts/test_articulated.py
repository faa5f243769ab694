"""The `open` and `close` skills (dojo/experts/articulated.py) on the articulated test tasks of `articulated_pack`:
a cabinet drawer pulled open by its handle (slide joint), a safe's door swung open and shut again (hinge).

The oracle solves the first seeds on the `mujoco` backend; `zero` solves none (the safe task needs the door
opened before it counts it closed, since it starts closed). Grounding: the interaction point, joint and closed end
come from the compiled model, not from the asset's name.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
from dojo.compiler.plan import Plan
from dojo.compiler.spec_library import SpecLibrary
from dojo.experts.articulated import articulation
from dojo.experts.motion import Pose
from dojo.experts.skills import SkillContext
from dojo.experts.validity import plan_files, policies, run_policy
from dojo.experts.oracle import OraclePolicy

PACK = Path(__file__).parent / "articulated_pack"
TASKS = ["open_drawer_test", "open_close_safe_test"]
SEEDS = 3


@pytest.fixture(scope="module")
def files(plan_cache) -> dict[str, list[Path]]:
    return plan_files(SpecLibrary.load([PACK]), TASKS, SEEDS, plan_cache, jobs="auto")


def _context(path: Path) -> SkillContext:
    plan = Plan.load(path)
    model = plan.model()
    return SkillContext(plan, model, plan.initial_data(model))


def test_the_drawer_handle_and_slide_are_read_from_the_model(files):
    ctx = _context(files["open_drawer_test"][0])
    art = articulation(ctx, "cabinet", None)
    assert art.point == "handle" and not art.hinge
    assert (art.closed, art.open_end) == (0.0, pytest.approx(0.22))
    # the cabinet is turned to face the arms: the handle opens towards them (-y), along the slide's axis
    handle = ctx.scene.site("cabinet", "handle").center
    assert art.tangent(handle)[1] < -0.9 and np.allclose(art.tangent(handle), art.axis)


def test_the_safe_handle_sweeps_an_arc_about_the_door_hinge(files):
    ctx = _context(files["open_close_safe_test"][0])
    art = articulation(ctx, "safe", None)
    assert art.point == "handle" and art.hinge and art.closed == 0.0
    handle = ctx.scene.site("safe", "handle").center
    # moved by the joint's own transform: the handle stays on its circle about the vertical axis and ends where
    # the simulator puts it at that door angle
    pose = art.moved(Pose(handle, np.eye(3)), 0.6)
    ctx.data.qpos[art.qpos_adr] = 0.6
    mujoco.mj_forward(ctx.model, ctx.data)
    assert np.allclose(pose.pos, ctx.scene.site("safe", "handle").center, atol=1e-6)


@pytest.mark.parametrize("task", TASKS)
def test_oracle_opens_and_closes(files, task):
    outcomes = run_policy(OraclePolicy({"packs": [str(PACK)]}), files[task], num_envs=SEEDS, threads=1)
    assert [o.success for o in outcomes] == [True] * SEEDS, outcomes


def test_zero_policy_does_not(files):
    outcomes = run_policy(policies()["zero"], [files[t][0] for t in TASKS], num_envs=2, threads=1)
    assert len(outcomes) == 2 and not any(o.success for o in outcomes), outcomes
    assert all(o.score == 0.0 for o in outcomes), outcomes
