"""The keyed-insertion mechanisms (insert_key, plug_in_charger): the lock's cylinder stays locked until a key is
seated in its keyway (the task's events: lock at the start, unlock when `plugged` first holds), and a plug aimed
3 mm off does not go in. Their expert and zero smoke tests are in test_precision_tasks.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
from dojo.backends.registry import BackendOptions, make_backend
from dojo.compiler.plan import Plan
from dojo.experts.validity import plan_files, run_policy

TORQUE = 0.05
"""N m on the cylinder's hinge: far more than its damping needs to turn it a quarter turn in a few steps."""


def cylinder_after(plan: Plan, path, key_offset: tuple[float, float, float] | None, steps: int = 12) -> float:
    """The cylinder's angle after `steps` control steps of the arms holding still and TORQUE on its hinge, with the
    key set down in the keyway shifted by `key_offset` (m, in the keyway's frame; None: the key stays in its
    stand)."""
    backend = make_backend("mujoco", BackendOptions(settings={"threads": 1}, plan_paths={plan.hash: str(path)}))
    try:
        backend.load([plan])
        backend.reset([0])
        data = backend._slots[0].data
        model = data.model
        hinge = model.joint("lock/plug")
        if key_offset is not None:
            site = data.site(plan.objects["lock"]["sites"]["keyhole"])
            rot = site.xmat.reshape(3, 3)
            floor = site.xpos - rot[:, 2] * model.site_size[site.id][2]
            yaw = math.atan2(rot[1, 0], rot[0, 0])
            free = model.joint(plan.objects["key"]["free_joint"]).qposadr[0]
            data.qpos[free:free + 7] = [*(floor + rot @ np.asarray(key_offset)), math.cos(yaw / 2), 0.0, 0.0,
                                        math.sin(yaw / 2)]
        data.qfrc_applied[hinge.dofadr[0]] = TORQUE
        home = plan.robot["home_qpos"]
        arms = [home[j] for j in plan.robot["arm_joints"]]
        hold = np.asarray([*arms[:6], 1.0, *arms[6:], 1.0], np.float32)[None]
        for _ in range(steps):
            backend.step(hold, [0], mode="joint")
        return float(data.qpos[hinge.qposadr[0]])
    finally:
        backend.close()


@pytest.fixture(scope="module")
def key_plan(library, plan_cache):
    path = plan_files(library, ["insert_key"], 1, plan_cache)["insert_key"][0]
    return Plan.load(path), path


def test_the_cylinder_is_locked_until_the_key_is_seated(key_plan):
    plan, path = key_plan
    assert abs(cylinder_after(plan, path, None)) < 1e-3
    # the key on the lock's top beside the keyway, 3 mm off its line: still locked
    assert abs(cylinder_after(plan, path, (0.003, 0.0, 0.028))) < 1e-3
    # seated on the keyway's floor: unlocked, and the torque turns the cylinder (and the key) round
    assert cylinder_after(plan, path, (0.0, 0.0, 0.0005)) > 0.3


def test_a_plug_aimed_3_mm_off_does_not_go_in(library, plan_cache):
    """The tolerance binds: the expert believing the keyway 3 mm from where it is (`dojo.experts.perturbed`) stands
    the key on the rim, and `plug` gives up rather than forcing it in along the rim."""
    from dojo.experts.perturbed import PerturbedOracle

    files = plan_files(library, ["insert_key"], 1, plan_cache)["insert_key"]
    outcomes = run_policy(PerturbedOracle({"distance": 0.003}), files, num_envs=1)
    assert [o.success for o in outcomes] == [False], outcomes
