"""Warp's contact and constraint buffers: sized from the plans, overflow detected and reported, never silent;
the backend's choice of implementation. CPU only (MuJoCo Warp's side is in test_warp_gpu.py, `-m gpu`)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import mujoco
import numpy as np
import pytest
from conftest import toy_plan

from dojo.backends.mjx import batch
from dojo.backends.mjx.batch import (OVERFLOW_FLAGS, REST_MARGIN, CapacityOverflow, Engine, contact_capacity,
                                     decode_overflow, rest_constraints, rest_counts)
from dojo.backends.mjx.bucket import Member, make_buckets


@pytest.fixture(scope="module")
def crowded():
    """A bucket whose resting layout already has many contacts: ten balls on the floor."""
    plans = [toy_plan(setting="random", seed=0, clutter=("ball",) * 10)]
    return make_buckets(plans)[0]


def test_capacity_covers_the_resting_contacts_with_margin(crowded):
    data = mujoco.MjData(crowded.model)
    data.qpos[:] = crowded.members[0].qpos
    mujoco.mj_forward(crowded.model, data)
    assert rest_constraints(crowded) == (data.ncon, data.nefc) and data.ncon >= 10
    contacts, rows = contact_capacity(crowded)
    assert contacts >= REST_MARGIN * data.ncon and rows >= REST_MARGIN * data.nefc
    assert rows >= 6 * contacts  # every contact can take its rows (elliptic cones, condim up to 6)


def test_each_member_is_counted_as_a_fresh_mjdata_counts_it_in_any_order():
    """One MjData serves every member (reset to each in turn): a member counted after a crowded one must not keep
    what the crowded one had."""
    plans = [toy_plan(setting="random", seed=s, clutter=("ball",) * n) for s, n in ((0, 10), (1, 0), (2, 4), (3, 1))]
    bucket = make_buckets(plans)[0]
    assert len(bucket.members) == 4

    def fresh(member: Member) -> tuple[int, int]:
        data = mujoco.MjData(member.model)
        data.qpos[:], data.qvel[:], data.ctrl[:] = member.qpos, member.qvel, member.ctrl
        mujoco.mj_forward(member.model, data)
        return int(data.ncon), int(data.nefc)

    expected = [fresh(m) for m in bucket.members]
    assert len(set(expected)) == 4  # every member rests differently
    assert rest_counts(bucket) == expected
    bucket.members.reverse()
    assert rest_counts(bucket) == expected[::-1]
    assert rest_constraints(bucket) == (max(c for c, _ in expected), max(r for _, r in expected))


def test_a_members_state_outside_its_joints_is_its_own():
    """A kinematic (mocap) wall is placed by each member's model, not by the member counted before: against the
    block in the first plan, clear of it in the second."""
    plans = []
    for seed, y in ((0, 0.04), (1, 0.5)):
        plan = toy_plan(seed=seed, fixture_y=y)
        plans.append(dataclasses.replace(plan, model_xml=plan.model_xml.replace('<body name="wall"',
                                                                                '<body name="wall" mocap="true"')))
    bucket = make_buckets(plans)[0]
    assert len(bucket.members) == 2 and bucket.members[0].model.nmocap == 1
    touching, clear = rest_counts(bucket)
    assert touching[0] > clear[0]
    bucket.members.reverse()
    assert rest_counts(bucket) == [clear, touching]


def test_capacity_is_raised_by_what_the_plans_have_at_rest(crowded, monkeypatch):
    monkeypatch.setattr(batch, "rest_constraints", lambda bucket: (1000, 9000))
    contacts, rows = contact_capacity(crowded)
    assert contacts == REST_MARGIN * 1000 and rows >= REST_MARGIN * 9000


def test_decode_overflow_counts_worlds_per_buffer_and_ignores_solver_iterations():
    bits = np.asarray([0, 1 << 3, (1 << 3) | (1 << 0), 1 << 9, 1 << 10])
    assert decode_overflow(bits) == {"contacts (naconmax)": 2, "constraint rows (njmax)": 1}
    assert decode_overflow(np.zeros(4, np.int32)) == {}
    assert (1 << 9) not in OVERFLOW_FLAGS and (1 << 10) not in OVERFLOW_FLAGS


def _engine_with_overflow(bucket, bits):
    """An engine whose (warp) data carries the given per-world overflow bits; nothing is compiled."""
    engine = Engine.__new__(Engine)
    engine.arrays = [SimpleNamespace(bucket=bucket)]
    engine._data = (SimpleNamespace(_impl=SimpleNamespace(overflow=np.asarray(bits, np.int32))),)  # what `data` reads
    return engine


def test_engine_reports_overflow_by_bucket_and_raises_with_the_capacity(crowded):
    clean = _engine_with_overflow(crowded, [0, 0, 1 << 9])
    assert clean.overflows() == {}
    clean.check_overflow()
    bad = _engine_with_overflow(crowded, [0, 1 << 3, 1 << 3, 1 << 2])
    assert bad.overflows() == {crowded.key: {"broadphase pairs (naconmax)": 1, "contacts (naconmax)": 2}}
    contacts, rows = contact_capacity(crowded)
    with pytest.raises(CapacityOverflow, match=rf"contacts \(naconmax\) in 2 world\(s\).*{contacts} contacts"):
        bad.check_overflow()


def test_jax_data_has_no_overflow_to_report(crowded):
    """impl='jax' allocates every candidate contact: its data has no overflow field, and nothing is reported."""
    engine = Engine.__new__(Engine)
    engine.arrays = [SimpleNamespace(bucket=crowded)]
    engine._data = (SimpleNamespace(_impl=SimpleNamespace()),)
    assert engine.overflows() == {}


def test_backend_runs_jax_for_auto_without_a_gpu_and_warp_only_where_warp_lang_is():
    from dojo.backends.mjx.backend import MjxBackend
    from dojo.backends.mjx.cache import describe_impl, warp_available, warp_installed

    if warp_available():
        pytest.skip("this machine runs MuJoCo Warp on a GPU (tests/backends_mjx/test_warp_gpu.py)")
    assert MjxBackend(impl="auto").impl == "jax" and MjxBackend(impl=None).impl == "jax"
    if warp_installed():
        assert MjxBackend(impl="warp").impl == "warp" and "Warp's CPU device" in describe_impl("warp")
    else:
        with pytest.raises(RuntimeError, match="warp-lang"):
            MjxBackend(impl="warp")


def test_jax_on_a_cpu_points_to_warp_where_warp_lang_is(caplog):
    """A real task's tick under `jax` compiled for 20 minutes on the 2-core machine and then failed in LLVM; the
    backend says so, and names the implementation that runs there, when it is installed."""
    import logging

    from dojo.backends.mjx.backend import MjxBackend
    from dojo.backends.mjx.cache import warp_available, warp_installed

    if warp_available():
        pytest.skip("this machine runs MuJoCo Warp on a GPU")
    with caplog.at_level(logging.WARNING, logger="dojo.backends.mjx.backend"):
        MjxBackend(impl="jax")
    assert ("backend.impl=warp" in caplog.text) == warp_installed()
    caplog.clear()
    if warp_installed():
        with caplog.at_level(logging.WARNING, logger="dojo.backends.mjx.backend"):
            MjxBackend(impl="warp")
        assert "backend.impl=warp" not in caplog.text
