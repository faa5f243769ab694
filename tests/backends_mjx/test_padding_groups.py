"""Padding a task's plans together: each plan keeps its own geometry, and the union stays bounded (no jit)."""

from __future__ import annotations

import dataclasses
import math
import random

import mujoco
import numpy as np
from conftest import toy_plan

from dojo.backends.mjx.bucket import make_buckets
from dojo.backends.mjx.merge_groups import Cost, Union, Unit, cluster, estimate, largest, padding_groups
from dojo.compiler.plan import Plan

TETRAHEDRON = np.asarray([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) * 0.04


def mesh_plan(seed: int, scales: tuple[float, ...], block: str = "box") -> Plan:
    """A random-setting toy plan whose clutter are tetrahedron meshes of the given scales, each mesh named after
    its geom as the compiler names them (`clutter_<k>/g0`): one name, other vertices, in another plan."""
    base = toy_plan(setting="random", seed=seed)
    assets = "".join(f'<mesh name="clutter_{k}/g0" vertex="{" ".join(map(str, (TETRAHEDRON * s).ravel()))}"/>'
                     for k, s in enumerate(scales))
    bodies = "".join(f'<body name="clutter_{k}" pos="{-0.3 + 0.15 * k} 0.3 0.05"><joint name="clutter_{k}/free" '
                     f'type="free"/><geom name="clutter_{k}/g0" type="mesh" mesh="clutter_{k}/g0" mass="0.05"/>'
                     f'</body>' for k in range(len(scales)))
    xml = base.model_xml.replace("<worldbody>", f"<asset>{assets}</asset><worldbody>", 1)
    xml = xml.replace("</worldbody>", bodies + "</worldbody>", 1)
    if block != "box":
        xml = xml.replace('name="block/g0" type="box"', f'name="block/g0" type="{block}"', 1)
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    clutter = {f"clutter_{k}": {"body": f"clutter_{k}", "clutter": True} for k in range(len(scales))}
    objects = {**base.objects, **clutter}
    return dataclasses.replace(base, hash=f"mesh-{seed}-{block}", model_xml=xml, objects=objects,
                               init_qpos=[float(x) for x in data.qpos], init_qvel=[0.0] * model.nv)


def vertices(model: mujoco.MjModel, geom: int) -> np.ndarray:
    mesh = model.geom_dataid[geom]
    return model.mesh_vert[model.mesh_vertadr[mesh]:model.mesh_vertadr[mesh] + model.mesh_vertnum[mesh]]


def test_plans_padded_together_keep_their_own_meshes_under_one_name():
    plans = [mesh_plan(0, (1.0,)), mesh_plan(1, (1.5,))]
    [bucket] = make_buckets(plans)
    names = [bucket.model.body(i).name for i in range(bucket.model.nbody)]
    slots = [name for name in names if name.startswith("slot")]
    assert len(slots) == 2  # two geometries, two slot keys, although both meshes were called clutter_0/g0
    for member in bucket.members:
        own = member.plan.model()
        padded = {old: new for new, old in member.padded.names.items() if new.endswith("/geom0")}
        geom = member.model.geom(padded["clutter_0/g0"]).id
        np.testing.assert_allclose(vertices(member.model, geom), vertices(own, own.geom("clutter_0/g0").id))


def test_one_mesh_is_one_slot_wherever_it_stands_in_its_plans_asset_section():
    """The same mesh, last in one plan's asset section and followed by another mesh in the next (so written with
    other whitespace after it), is one geometry: one slot, not two."""
    laid_out = [dataclasses.replace(p, model_xml=p.model_xml.replace("/><mesh", "/>\n    <mesh"))
                for p in (mesh_plan(0, (1.0,)), mesh_plan(1, (1.0, 1.5)))]
    [bucket] = make_buckets(laid_out)
    slots = [bucket.model.body(i).name for i in range(bucket.model.nbody)
             if bucket.model.body(i).name.startswith("slot")]
    assert len(slots) == 2  # the shared tetrahedron and the larger one


def test_plans_padded_together_give_the_same_buckets_whatever_their_order():
    """A slot kind's template (whose parked copies and site sizes every member gets) is not the first plan's in the
    given order: `random` plans whose clutter differs pad to the same structures, so to the same bucket keys, in any
    order."""
    from dojo.compiler.plan import compile_plan
    from dojo.compiler.spec_library import SpecLibrary

    library = SpecLibrary.load([])
    plans = [compile_plan(library, library.get("task", "push_t"), "random", seed) for seed in range(4)]
    want = [(b.key, sorted(m.plan.hash for m in b.members)) for b in make_buckets(plans)]
    for seed in range(2):
        shuffled = random.Random(seed).sample(plans, len(plans))
        assert [(b.key, sorted(m.plan.hash for m in b.members)) for b in make_buckets(shuffled)] == want


def test_padding_groups_keep_each_bucket_within_the_growth_bound():
    plans = [mesh_plan(seed, tuple(1.0 + 0.1 * seed + 0.01 * k for k in range(3))) for seed in range(4)]
    own = {p.hash: p.model() for p in plans}
    assert len(padding_groups(plans, math.inf)) == 1  # unbounded: one union of every plan's clutter
    groups = padding_groups(plans, 0.5)
    assert len(groups) == 4 and sorted(p.hash for g in groups for p in g) == sorted(p.hash for p in plans)
    for bucket in make_buckets(plans):
        largest = max(own[m.plan.hash].nv for m in bucket.members)
        assert bucket.model.nv <= 1.5 * largest
    # a plan with little clutter fits beside a larger one: its union costs at most half the larger plan again
    small = mesh_plan(9, (2.0,))
    assert [len(g) for g in padding_groups([plans[0], small], 0.5)] == [2]


def test_plans_compiled_by_another_install_pad_and_merge_as_before():
    """Plan hashes cover the compiler's and MuJoCo's versions, so another install names the same episodes otherwise;
    where plans tie, the grouping must follow task, setting and seed, not the hash. Three plans of one size whose
    clutter overlaps in a chain (1.0+1.1, 1.1+1.2, 1.2+1.3): at growth 0.4 a plan pads with one neighbour (25 DoFs
    against its own 19), never with both (31), so whichever comes first decides the groups."""
    # a shared scale stands at the same clutter index in both plans: a slot's key holds more than the scale
    plans = [mesh_plan(seed, scales) for seed, scales in enumerate([(1.0, 1.1), (1.2, 1.1), (1.2, 1.3)])]
    renamed = [dataclasses.replace(p, hash=f"{9 - p.seed}-other-install") for p in plans]  # the order reversed

    def seeds(groups: list[list[Plan]]) -> list[list[int]]:
        return sorted(sorted(p.seed for p in g) for g in groups)

    assert seeds(padding_groups(plans, 0.4)) == seeds(padding_groups(renamed, 0.4)) == [[0, 1], [2]]
    buckets = {name: seeds([[m.plan for m in b.members] for b in make_buckets(some, growth=0.4)])
               for name, some in (("plans", plans), ("renamed", renamed))}
    assert buckets["plans"] == buckets["renamed"] == [[0, 1], [2]]
    # merged, every object is a slot and the three fit one bucket, whichever install compiled them
    assert [len(b.members) for b in make_buckets(renamed, merge=True, growth=0.4)] == [3]


def test_plans_whose_frames_differ_are_never_padded_together():
    plans = [mesh_plan(0, (1.0,)), mesh_plan(1, (1.0,), block="sphere")]
    assert len(padding_groups(plans, math.inf)) == 2
    assert len(make_buckets(plans)) == 2


def test_a_union_grown_one_unit_at_a_time_matches_its_definition_at_every_step():
    """`Union` adds a unit by its own slot keys; the estimate must stay the frame's largest part plus, per key, the
    most slots any unit needs times one slot's cost, and `fits` must agree with that bound before each addition."""
    rng = random.Random(0)
    keys = [f"k{i}" for i in range(6)]
    cost = {k: Cost(rng.randint(0, 7), rng.randint(1, 5)) for k in keys}
    units = []
    for i in range(60):
        slots = {k: rng.randint(1, 4) for k in rng.sample(keys, rng.randint(0, 4))}
        frame = Cost(rng.randint(10, 30), rng.randint(10, 30))
        own = Cost(frame.nv + sum(n * cost[k].nv for k, n in slots.items()),
                   frame.ngeom + sum(n * cost[k].ngeom for k, n in slots.items()))
        units.append(Unit(f"u{i}", (), own, frame, slots, {k: cost[k] for k in slots}))

    def defined(some: list[Unit]) -> tuple[Cost, Cost]:
        most = {k: max(u.slots.get(k, 0) for u in some) for k in keys}
        union = Cost(max(u.frame.nv for u in some) + sum(n * cost[k].nv for k, n in most.items()),
                     max(u.frame.ngeom for u in some) + sum(n * cost[k].ngeom for k, n in most.items()))
        return union, Cost(max(u.own.nv for u in some), max(u.own.ngeom for u in some))

    union, verdicts = Union([units[0]]), set()
    for k, unit in enumerate(units[1:], start=2):
        expected, ref = defined(units[:k])
        for growth in (0.0, 0.3, 1.0):
            verdict = expected.nv <= (1 + growth) * ref.nv and expected.ngeom <= (1 + growth) * ref.ngeom
            assert union.fits(unit, growth) == verdict
            verdicts.add(verdict)
        union.add(unit)
        assert (union.estimate, union.ref) == (expected, ref) == (estimate(units[:k]), largest(units[:k]))
    assert verdicts == {True, False}  # the bound was met and missed along the way


def test_clusters_merge_the_least_growth_first_ties_by_keys_and_a_refused_pair_stays_apart():
    """Four units on one frame (10 DoFs, 10 geoms) with slots of 6 DoFs and 1 geom each: u1 and u2 the same slot
    (growth 0 together), u3 another, u4 two of a third. At growth 0.5: u1+u2 first; then {u1,u2}+u4 and u3+u4 both
    grow 0.27, and the tie goes to the lesser keys; the union of all four (34 DoFs against 22) is out of bounds."""
    frame, slot = Cost(10, 10), Cost(6, 1)

    def unit(key: str, slots: dict[str, int]) -> Unit:
        n = sum(slots.values())
        return Unit(key, (), Cost(10 + 6 * n, 10 + n), frame, slots, {k: slot for k in slots})

    units = [unit("u3", {"y": 1}), unit("u1", {"x": 1}), unit("u4", {"z": 2}), unit("u2", {"x": 1})]
    asked: list[tuple[tuple[str, ...], tuple[str, ...]]] = []

    def one_structure(refused: set[frozenset[str]]):
        def check(a: tuple[Unit, ...], b: tuple[Unit, ...]) -> bool:
            asked.append((tuple(u.key for u in a), tuple(u.key for u in b)))
            return not any(frozenset((x.key, y.key)) in refused for x in a for y in b)
        return check

    keys = lambda clusters: [tuple(u.key for u in c) for c in clusters]  # noqa: E731
    assert keys(cluster(units, 0.5, one_structure(set()))) == [("u1", "u2", "u4"), ("u3",)]
    assert asked == [(("u1",), ("u2",)), (("u1", "u2"), ("u4",))]
    asked.clear()
    # u2 and u4 cannot share a structure: {u1,u2}+u4 is refused, and u1+u4 (0.27) is then apart too
    assert keys(cluster(units, 0.5, one_structure({frozenset(("u2", "u4"))}))) == [("u1", "u2"), ("u3", "u4")]
    assert asked == [(("u1",), ("u2",)), (("u1", "u2"), ("u4",)), (("u3",), ("u4",))]
    assert keys(cluster(units, 0.0, one_structure(set()))) == [("u1", "u2"), ("u3",), ("u4",)]


def test_what_every_padded_plan_shares_is_written_once_into_each_plans_mjcf():
    """`pad_group` serialises the asset union and each parked slot once per group and splices the text into every
    plan's MJCF: each plan's MJCF is whole (no placeholder left, ElementTree's own form), holds every mesh of the
    union, and parks the slots it does not fill where parking puts them, the same text in every plan parking them."""
    import xml.etree.ElementTree as ET

    from dojo.backends.mjx.pad import PARK_ORIGIN, PARK_SPACING, pad_group

    plans = [mesh_plan(0, (1.0,)), mesh_plan(1, (1.5,)), mesh_plan(2, (2.0,))]
    padded = pad_group(plans, "toy")
    parked_text: dict[str, set[str]] = {}
    for pp in padded:
        assert "dojo-splice" not in pp.xml and ET.tostring(ET.fromstring(pp.xml), encoding="unicode") == pp.xml
        root = ET.fromstring(pp.xml)
        assert len(root.find("asset").findall("mesh")) == 3
        assert len(pp.parked) == 2  # three mesh kinds, one of them its own
        for slot in pp.parked:
            body = root.find(f"worldbody/body[@name='{slot}']")
            j = int(slot.removeprefix("slot"))
            assert body.get("pos") == f"{PARK_ORIGIN[0] + PARK_SPACING * j:g} {PARK_ORIGIN[1]:g} {PARK_ORIGIN[2]:g}"
            parked_text.setdefault(slot, set()).add(ET.tostring(body, encoding="unicode"))
        model = mujoco.MjModel.from_xml_string(pp.xml)
        assert model.nmesh == 3
    assert sorted(parked_text) == ["slot0", "slot1", "slot2"] and all(len(t) == 1 for t in parked_text.values())
