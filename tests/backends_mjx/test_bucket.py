"""Bucketing and padding (no jit): structures, varying fields, parked slots, initial states."""

from __future__ import annotations

import dataclasses
import math
import xml.etree.ElementTree as ET
from typing import Callable

import jax
import mujoco
import numpy as np
import pytest
from conftest import toy_plan
from mujoco import mjx
from test_padding_groups import mesh_plan

from dojo.backends.mjx import bucket as bucket_module
from dojo.backends.mjx.backend import PlanLayout
from dojo.backends.mjx.bucket import Bucket, Compiler, Compiling, make_buckets, member_data, structural_signature
from dojo.backends.mjx.pad import GRAVCOMP_IN_USE, PARK_ORIGIN, PaddedPlan, ParsedPlans, pad_group
from dojo.compiler.plan import Plan

RANDOM_CLUTTER = [("ball",), ("box", "ball"), (), ("ball", "ball")]


def _random_plans():
    return [toy_plan(setting="random", seed=s, clutter=c) for s, c in enumerate(RANDOM_CLUTTER)]


def _arrays(model: mujoco.MjModel) -> dict[str, bytes]:
    """Every array of the model, bit for bit."""
    return {name: value.tobytes() for name in dir(model)
            if not name.startswith("_") and isinstance(value := getattr(model, name), np.ndarray)}


def test_models_compiled_on_threads_are_the_serial_ones_in_order_a_repeat_a_copy_of_its_own():
    """A standard plan padded twice (no slots: one MJCF twice); the repeat's model is a copy of the first's."""
    plans = _random_plans()
    padded = pad_group(plans, "toy", every_object=False) + pad_group([toy_plan(seed=0)] * 2, "toy")
    assert padded[-2].xml == padded[-1].xml
    with Compiler(plans) as compiler:
        threaded = compiler.models(padded).result()
        signatures = compiler.signatures(padded)()
    assert threaded[-2][0] is not threaded[-1][0]
    for pp, (model, signature), known in zip(padded, threaded, signatures, strict=True):
        serial = mujoco.MjModel.from_xml_string(pp.xml)
        assert signature == known == structural_signature(model) == structural_signature(serial)
        assert _arrays(model) == _arrays(serial)


class _SerialCompiling(Compiling):
    """Each padded plan compiled on its own, on the calling thread: no job shared by a repeated MJCF."""

    def result(self) -> list[tuple[mujoco.MjModel, str]]:
        models = [mujoco.MjModel.from_xml_string(pp.xml) for pp in self.padded]
        return [(model, structural_signature(model)) for model in models]


class _Forgetful(ParsedPlans):
    """Each plan parsed afresh for every padding."""

    def root(self, plan: Plan) -> ET.Element:
        return ParsedPlans().root(plan)

    def contents(self, plan: Plan) -> list[str]:
        return ParsedPlans().contents(plan)


def _serial_signatures(padded: list[PaddedPlan]) -> Callable[[], list[str]]:
    """`Compiler.signatures` with nothing remembered: every padded plan compiled."""
    return lambda: [signature for _, signature in _SerialCompiling(padded, {}, {}).result()]


def _fingerprint(buckets: list[Bucket]) -> list:
    """Everything the buckets are: keys, varying fields and, per member, its plan, padding, initial state and model."""
    return [(b.key, b.varying, [(m.plan.hash, m.padded.xml, m.padded.names, m.padded.parked, m.padded.slot_keys,
                                 m.qpos.tobytes(), m.qvel.tobytes(), m.ctrl.tobytes(), _arrays(m.model))
                                for m in b.members]) for b in buckets]


@pytest.mark.parametrize("merge", [False, True])
def test_shared_parses_and_compiles_give_the_buckets_of_plain_ones(monkeypatch, merge):
    """`make_buckets` parses each plan once for all its paddings, compiles a repeated MJCF once and takes a pair
    check's signatures from those already found: against every plan parsed for each padding and every padded plan
    compiled on its own, the buckets are the same bit for bit. The plans: tasks that merge, one whose timestep fails
    the pair check, a plan repeated under another hash (its padding repeats), and meshes of one name with other
    vertices per plan (renamed by content)."""
    plans = [toy_plan(task=task, seed=s, items=items, block_size=0.03 + 0.005 * k)
             for k, (task, items) in enumerate((("toy", ()), ("pair", ("ball", "box")), ("twin", ("ball", "ball"))))
             for s in range(2)]
    plans += [dataclasses.replace(plans[0], hash=plans[0].hash + "-again"), mesh_plan(0, (1.0,)), mesh_plan(1, (1.5,))]
    plans += [dataclasses.replace(p, task="bee", hash=f"bee-{p.hash}", model_xml=p.model_xml.replace(
        'timestep="0.004"', 'timestep="0.002"')) for p in plans[2:4]]
    shared = _fingerprint(make_buckets(plans, merge=merge, growth=math.inf))
    monkeypatch.setattr(bucket_module, "ParsedPlans", _Forgetful)
    monkeypatch.setattr(Compiler, "models", lambda self, padded: _SerialCompiling(padded, {}, {}))
    monkeypatch.setattr(Compiler, "signatures", lambda self, padded: _serial_signatures(padded))
    assert _fingerprint(make_buckets(plans, merge=merge, growth=math.inf)) == shared


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
