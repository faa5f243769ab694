"""The experts' IK (mink on a per-arm chain model): the chain matches the scene's arm, goals are reached."""

from __future__ import annotations

import mujoco
import numpy as np
from dojo.compiler.plan import Plan
from dojo.experts.motion import ArmPlanner
from dojo.experts.validity import plan_files


def _planner(library, plan_cache) -> tuple[ArmPlanner, np.ndarray]:
    plan = Plan.load(plan_files(library, ["stack_blocks"], 1, plan_cache)["stack_blocks"][0])
    model = plan.model()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    planner = ArmPlanner(model, plan.robot, plan.control_hz)
    planner.sync(data)
    home = np.asarray([[plan.robot["home_qpos"][j] for j in plan.robot["arm_joints"][a * 6:(a + 1) * 6]]
                       for a in range(2)])
    return planner, home


def test_chain_model_matches_the_scene_arm(library, plan_cache):
    planner, _ = _planner(library, plan_cache)
    rng = np.random.default_rng(0)
    for arm in range(2):
        chain = planner.arms[arm]
        for _ in range(5):
            q = rng.uniform(planner.lo, planner.hi)
            pose = planner.fk(q, arm)
            chain.configuration.update(q[arm])
            np.testing.assert_allclose(chain.configuration.data.site_xpos[chain.site], pose.pos, atol=1e-9)
            np.testing.assert_allclose(chain.configuration.data.site_xmat[chain.site].reshape(3, 3), pose.rot,
                                       atol=1e-9)


def test_ik_reaches_reachable_goals_and_keeps_the_other_arm(library, plan_cache):
    planner, home = _planner(library, plan_cache)
    rng = np.random.default_rng(1)
    for k in range(20):
        arm = k % 2
        target = home.copy()
        target[arm] = np.clip(target[arm] + rng.normal(0.0, 0.3, 6), planner.lo[arm], planner.hi[arm])
        goal = planner.fk(target, arm)
        q, err = planner.ik(home, arm, goal)
        assert err < 1e-3
        np.testing.assert_array_equal(q[1 - arm], home[1 - arm])
        assert np.all(q >= planner.lo - 1e-9) and np.all(q <= planner.hi + 1e-9)
    far = planner.fk(home, 0).shifted([0.0, 0.0, 5.0])  # out of reach: the closest pose, a large error
    _, err = planner.ik(home, 0, far)
    assert err > 1.0
