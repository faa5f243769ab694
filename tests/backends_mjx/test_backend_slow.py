"""MjxBackend and parity on real plans (two 6-DoF arms): minutes of XLA compilation on a CPU, hence slow."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dojo.compiler.plan import compile_plan
from dojo.compiler.spec_library import SpecLibrary

PACK = Path(__file__).resolve().parents[1] / "specs" / "pack"
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def plans():
    library = SpecLibrary.load([PACK])
    task = library.get("task", "stack_test")
    return [compile_plan(library, task, "standard", seed) for seed in range(2)]


def test_backend_matches_cpu_and_refills_without_recompiling(plans):
    from dojo.backends.mjx.backend import MjxBackend
    from dojo.backends.mujoco.backend import MujocoBackend

    mjx_backend = MjxBackend()
    mjx_backend.load(plans)
    with MujocoBackend(num_threads=1) as cpu:
        cpu.load(plans)
        hold = np.stack([o["state"]["joint_pos"] for o in cpu.reset()]).astype(np.float64)
        first = mjx_backend.reset()
        np.testing.assert_allclose(first[0]["state"]["joint_pos"], hold[0], atol=1e-5)
        for _ in range(5):
            a, b = mjx_backend.step(hold), cpu.step(hold)
        np.testing.assert_allclose(a.obs[0]["state"]["ee_pose"], b.obs[0]["state"]["ee_pose"], atol=1e-4)
        assert a.steps.tolist() == b.steps.tolist() == [5, 5]
        assert a.success.tolist() == b.success.tolist()
        assert a.terms == b.terms and a.terms[0]  # each success condition, named, as the CPU backend says it
        assert np.abs(mjx_backend.qpos() - np.stack([s.data.qpos for s in cpu._slots])).max() < 1e-2
    mjx_backend.reset([1], [plans[0]])
    assert mjx_backend.step(hold[:1], [1]).steps.tolist() == [1]
    assert mjx_backend._engine.compilations() == 1


def test_parity_table_on_real_plans(plans):
    from dojo.backends.mjx.parity import format_table, parity_report

    rows = parity_report(plans, steps=25)
    print(format_table(rows))
    assert all(r.ok for r in rows), format_table(rows)


def test_ee_modes_solve_the_same_ik_as_cpu(plans):
    """ee targets 3 cm forward and 2 cm up: both backends reach them alike; every mode runs one compiled tick."""
    from dojo.backends.mjx.backend import MjxBackend
    from dojo.backends.mujoco.backend import MujocoBackend

    mjx_backend = MjxBackend()
    mjx_backend.load(plans)
    mjx_backend.reset()
    with MujocoBackend(num_threads=1) as cpu:
        cpu.load(plans)
        obs = cpu.reset()
        target = np.stack([o["state"]["ee_pose"] for o in obs])
        target[:, :, 0] += 0.03
        target[:, :, 2] += 0.02
        grip = np.stack([o["state"]["gripper"] for o in obs])[..., None]
        action = np.concatenate([target, grip], -1).reshape(len(plans), 16)
        for _ in range(4):
            a, b = mjx_backend.step(action, mode="ee"), cpu.step(action, mode="ee")
    reached = np.stack([o["state"]["ee_pose"][:, :3] for o in a.obs])
    np.testing.assert_allclose(reached, np.stack([o["state"]["ee_pose"][:, :3] for o in b.obs]), atol=1e-4)
    np.testing.assert_allclose(reached, target[..., :3], atol=2e-3)
    held = mjx_backend.step(np.zeros((2, 16)), mode="delta_ee")  # zero deltas: stay (the zero quaternion counts)
    assert held.clipped.tolist() == [2, 2]
    mjx_backend.step(np.stack([o["state"]["joint_pos"] for o in held.obs]), mode="joint")
    assert mjx_backend._engine.compilations() == 1
