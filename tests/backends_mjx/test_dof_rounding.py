"""Buckets rounded up to a common DoF count (`dof_rounding`, an experiment of the benchmarks): the padding DoFs
come after the scene's own, nothing touches them, and the scene moves as it does without them (CPU MuJoCo)."""

from __future__ import annotations

import mujoco
import numpy as np
from conftest import toy_plan

from dojo.backends.mjx.bucket import make_buckets
from dojo.backends.mjx.dof_rounding import round_bucket, rounded_dofs


def test_rounded_dofs():
    assert [rounded_dofs(n, 16) for n in (1, 15, 16, 17)] == [16, 16, 16, 32]
    assert rounded_dofs(13, 1) == 13 and rounded_dofs(13, 0) == 13


def _roll(model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, ctrl: np.ndarray, steps: int) -> mujoco.MjData:
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:], data.ctrl[:] = qpos, qvel, ctrl
    for k in range(steps):
        data.ctrl[:] = ctrl * np.sin(0.05 * k)
        mujoco.mj_step(model, data)
    return data


def test_two_buckets_round_to_one_dof_count_and_move_as_before():
    buckets = make_buckets([toy_plan(task="a", seed=0), toy_plan(task="a", seed=1),
                            toy_plan(task="b", items=("ball",))])
    counts = sorted(b.model.nv for b in buckets)
    assert counts[0] != counts[1] and counts[1] <= 16
    rounded = [round_bucket(b, 16) for b in buckets]
    assert [b.model.nv for b in rounded] == [16, 16]
    for before, after in zip(buckets, rounded):
        assert after.key.startswith(before.key) and len(after.members) == len(before.members)
        assert after.table()["qpos"].shape[1] == before.table()["qpos"].shape[1] + 16 - before.model.nv
        for old, new in zip(before.members, after.members):
            nq, nv = old.model.nq, old.model.nv
            ctrl = np.full(old.model.nu, 0.5)
            a = _roll(old.model, old.qpos, old.qvel, ctrl, 200)
            b = _roll(new.model, new.qpos, new.qvel, ctrl, 200)
            assert np.abs(a.qpos).max() > 0 and not np.allclose(a.qpos, old.qpos)  # the scene moved
            np.testing.assert_allclose(b.qpos[:nq], a.qpos, atol=1e-9)
            np.testing.assert_allclose(b.qvel[:nv], a.qvel, atol=1e-9)
            np.testing.assert_array_equal(b.qpos[nq:], new.qpos[nq:])  # the padding DoFs stay where they started
            assert b.ncon == a.ncon


def test_a_bucket_already_at_a_multiple_is_left_as_it_is():
    bucket = make_buckets([toy_plan()])[0]
    assert round_bucket(bucket, bucket.model.nv) is bucket and round_bucket(bucket, 1) is bucket
