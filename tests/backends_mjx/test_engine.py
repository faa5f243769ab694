"""The batched engine on toy plans: one compilation for resets, refills and steps; parity with MuJoCo.

All tests share one engine (two buckets of 4 environments), so the module compiles one tick program.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from conftest import toy_plan

from dojo.backends.mjx.batch import Engine
from dojo.backends.mjx.bucket import make_buckets
from dojo.backends.mjx.parity import format_table, parity_report

B = 4


@pytest.fixture(scope="module")
def engine():
    plans = ([toy_plan(seed=s) for s in range(3)]
             + [toy_plan(setting="random", seed=s, clutter=c) for s, c in enumerate([("ball",), ("ball", "ball")])])
    buckets = make_buckets(plans)
    assert len(buckets) == 2
    return Engine(buckets, [B] * len(buckets), "jax")


def _flags(engine, value):
    return [np.full(a.size, value) for a in engine.arrays]


def _ctrl(engine, value):
    return [np.full((a.size, a.bucket.model.nu), value, np.float32) for a in engine.arrays]


def test_reset_refill_and_step_compile_once(engine):
    members = [np.arange(B) % len(a.bucket.members) for a in engine.arrays]
    engine.tick(members, _flags(engine, True), _flags(engine, False), _ctrl(engine, 0.0))
    for arr, data, mem in zip(engine.arrays, engine.data, members):
        np.testing.assert_allclose(np.asarray(data.qpos), arr.bucket.table()["qpos"][mem], atol=1e-6)
        assert np.all(np.asarray(data.time) == 0)
    engine.tick(members, _flags(engine, False), _flags(engine, True), _ctrl(engine, 0.2))
    dt = [a.bucket.model.opt.timestep * a.bucket.n_substeps for a in engine.arrays]
    before = [np.asarray(d.qpos).copy() for d in engine.data]
    # refill: env 0 of each bucket gets another member and restarts; env 1 is held; the rest step on
    refill = [np.roll(m, 1) for m in members]
    resets = [np.eye(1, B, 0, dtype=bool)[0] for _ in engine.arrays]
    stepping = [np.asarray([False, False, True, True]) for _ in engine.arrays]
    engine.tick(refill, resets, stepping, _ctrl(engine, 0.2))
    for arr, data, mem, old, step in zip(engine.arrays, engine.data, refill, before, dt):
        qpos, time = np.asarray(data.qpos), np.asarray(data.time)
        np.testing.assert_allclose(qpos[0], arr.bucket.table()["qpos"][mem[0]], atol=1e-6)
        np.testing.assert_allclose(qpos[1], old[1])
        assert time[0] == 0 and time[1] == pytest.approx(step) and time[2] == pytest.approx(2 * step)
        assert qpos[2, 0] > old[2, 0]  # the slider moves towards its 0.2 m target
    assert engine.compilations() == 1


def test_a_tick_hands_its_program_leaves_and_rebuilds_the_data_once_when_read(engine, monkeypatch):
    """MJX flattens its dataclasses in Python and hashes every NumPy field of a model (crc32) each time, which cost
    milliseconds per jitted call on a GPU host: a tick passes leaves taken once, and nothing of MJX is flattened;
    nor the data's empty arrays, each of which a call would handle all the same."""
    from mujoco.mjx._src import dataclasses as mjx_dataclasses

    members = [np.arange(B) % len(a.bucket.members) for a in engine.arrays]
    engine.tick(members, _flags(engine, False), _flags(engine, True), _ctrl(engine, 0.1))
    seen = engine.data
    assert engine.data is seen
    times = [np.asarray(d.time) for d in seen]  # the tick donates the arrays it is given
    hashed = []
    wrap = mjx_dataclasses._NumPyArrayHashWrapper.__init__
    monkeypatch.setattr(mjx_dataclasses._NumPyArrayHashWrapper, "__init__",
                        lambda self, arr: hashed.append(arr.shape) or wrap(self, arr))
    engine.tick(members, _flags(engine, False), _flags(engine, True), _ctrl(engine, 0.1))
    assert hashed == []
    assert engine.data is not seen
    # the fields the toy scenes lack (tendons: empty arrays) are not handed to the program, yet read back whole
    assert engine._data_empty and all(x.size for x in engine._data_leaves)
    assert all(np.asarray(d.ten_length).shape == (B, 0) for d in engine.data)
    for old, new in zip(times, engine.data):
        assert np.all(np.asarray(new.time) > old)


def test_parity_with_mujoco_on_toy_plans():
    plans = [toy_plan(seed=s) for s in range(2)]
    rows = parity_report(plans, steps=10)
    table = format_table(rows)
    assert "2/2 plans" in table, table
    assert all(r.ok and r.max_joint_err < 1e-3 for r in rows), table
