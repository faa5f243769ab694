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
    return [compile_plan(library, task, "standard", seed, backend="mjx") for seed in range(2)]


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
        assert np.abs(mjx_backend.qpos() - np.stack([s.data.qpos for s in cpu._slots])).max() < 1e-2
    mjx_backend.reset([1], [plans[0]])
    assert mjx_backend.step(hold[:1], [1]).steps.tolist() == [1]
    assert mjx_backend._engine.compilations() == 1


def test_parity_table_on_real_plans(plans):
    from dojo.backends.mjx.parity import format_table, parity_report

    rows = parity_report(plans, steps=25)
    print(format_table(rows))
    assert all(r.ok for r in rows), format_table(rows)
