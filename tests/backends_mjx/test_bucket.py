"""Bucketing and padding (no jit): structures, varying fields, parked slots, initial states."""

from __future__ import annotations

import jax
import mujoco
import numpy as np
from conftest import toy_plan
from mujoco import mjx

from dojo.backends.mjx.backend import PlanLayout
from dojo.backends.mjx.bucket import (VALUE_FIELDS, compiled_models, make_buckets, member_data,
                                      structural_signature)
from dojo.backends.mjx.pad import GRAVCOMP_IN_USE, PARK_ORIGIN, pad_group

RANDOM_CLUTTER = [("ball",), ("box", "ball"), (), ("ball", "ball")]


def _random_plans():
    return [toy_plan(setting="random", seed=s, clutter=c) for s, c in enumerate(RANDOM_CLUTTER)]


def test_models_compiled_on_threads_are_the_serial_ones_in_order():
    padded = pad_group(_random_plans(), "toy", every_object=False)
    threaded = compiled_models(padded)
    for pp, (model, signature) in zip(padded, threaded, strict=True):
        serial = mujoco.MjModel.from_xml_string(pp.xml)
        assert signature == structural_signature(model) == structural_signature(serial)
        for name in VALUE_FIELDS:
            np.testing.assert_array_equal(getattr(model, name), getattr(serial, name), err_msg=name)


def test_standard_plans_of_a_task_share_one_bucket_and_batch_their_poses():
    plans = [toy_plan(seed=s) for s in range(3)] + [toy_plan(task="other", block_size=0.05)]
    buckets = make_buckets(plans)
    assert [(b.tasks, len(b.members)) for b in buckets] == [(("other",), 1), (("toy",), 3)]
    toy = buckets[1]
    assert {"qpos0", "body_pos"} <= set(toy.varying)
    assert "geom_size" not in toy.varying  # same block size in every toy plan
    table = toy.table()
    assert table["body_pos"].shape == (3, toy.model.nbody, 3)
    np.testing.assert_allclose(table["qpos"], [p.init_qpos for p in plans[:3]])


def test_random_plans_with_different_clutter_share_one_padded_bucket():
    plans = _random_plans()
    [bucket] = make_buckets(plans)
    model = bucket.model
    # union of slots: one box and two balls (the most any plan has of each kind)
    slot_bodies = [model.body(i) for i in range(model.nbody) if model.body(i).name.startswith("slot")]
    assert len(slot_bodies) == 3
    assert {"geom_size", "body_gravcomp", "qpos0"} <= set(bucket.varying)
    for member, kinds in zip(bucket.members, RANDOM_CLUTTER):
        parked = member.padded.parked
        assert len(parked) == 3 - len(kinds)
        for name in parked:
            body = member.model.body(name)
            assert member.model.body_gravcomp[body.id] == 1.0
            assert member.model.body_pos[body.id][2] == PARK_ORIGIN[2]
        for name in set(f"slot{k}" for k in range(3)) - set(parked):
            assert member.model.body_gravcomp[member.model.body(name).id] == GRAVCOMP_IN_USE
        # the plan's own state comes back unchanged from the padded layout
        source = member.plan.model()
        layout = PlanLayout.build(member.model, source, member.padded.names)
        np.testing.assert_allclose(layout.qpos(member.qpos), member.plan.init_qpos)
        assert sorted(layout.qpos_plan) == list(range(source.nq))  # every plan coordinate has one source
        assert sorted(layout.qvel_plan) == list(range(source.nv))


def test_structural_signature_matches_mjx_static_structure():
    plans = _random_plans()
    [bucket] = make_buckets(plans)
    a, b = bucket.members[0].model, bucket.members[2].model
    assert structural_signature(a) == structural_signature(b)
    ta, tb = jax.tree.structure(mjx.put_model(a)), jax.tree.structure(mjx.put_model(b))
    assert ta == tb
    other = mujoco.MjModel.from_xml_string(toy_plan(task="other", block_size=0.05).model_xml)
    assert structural_signature(other) != structural_signature(a)


def test_member_data_shares_an_mjdata_only_between_models_of_one_layout():
    """Members of one structure share one MjData; a member of another (more clutter, other sizes) gets its own,
    and every one is in the state a fresh MjData of its model starts in."""
    small = make_buckets([toy_plan(seed=0), toy_plan(seed=1)])[0]
    large = make_buckets([toy_plan(setting="random", seed=2, clutter=("ball", "box"))])[0]
    members = [small.members[0], large.members[0], small.members[1]]
    seen = []
    for member, data in member_data(members):
        fresh = mujoco.MjData(member.model)
        assert data.qpos.shape == fresh.qpos.shape and data.narena == fresh.narena
        np.testing.assert_array_equal(data.qpos, fresh.qpos)
        np.testing.assert_array_equal(data.mocap_pos, fresh.mocap_pos)
        data.qpos[:] = 7.0  # what the caller writes must not reach the next member
        seen.append(id(data))
    assert seen[0] == seen[2] != seen[1]
