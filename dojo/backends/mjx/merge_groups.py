"""Which tasks of one robot share a merged bucket: a greedy clustering that merges only where it is cheap.

A bucket merged across tasks (`make_buckets(merge=True)`) carries, in every environment, a slot for each object
any of its tasks needs (pad.py): parked slots still cost, since their free joints are degrees of freedom (mass
matrix, solver) and their geoms are in the broadphase. Merging every task of a robot into one union is therefore
slower than not merging at all (`GROWTH`). A merge pays off only where the union is barely larger than its largest
member, e.g. two tasks whose objects are the same kinds.

The unit of clustering is a `Unit`: the plans of one bucket that `merge=False` makes (one task's plans of one
setting and sub-steps, padded alone, by structure: one task normally gives one unit, one whose plans differ in
something padding does not equalise, such as the skybox or the objects, one per structure), measured padded with
every object a slot. `cluster` merges units greedily, the pair with the least estimated growth first, while the
union's estimated size stays within `1 + growth` of its largest unit's own and the union really is one structure
(asked of the caller, which compiles). So `growth=0` merges only what costs nothing, never more buckets than
`merge=False`, and `growth=math.inf` every task whose scene allows it.
"""

from __future__ import annotations

import heapq
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

import mujoco

from dojo.compiler.plan import Plan

from dojo.backends.mjx.pad import PaddedPlan, ParsedPlans, frame_key, slotted_bodies

GROWTH = 0.5
"""How much larger (in degrees of freedom and in geoms, each) a merged model may be than its largest member's own.
Measured on an H100 under MuJoCo Warp (24 simulation tasks x 2 standard plans): a bucket costs about 1 ms per
physics sub-step whatever its size (launch-bound), so fewer buckets are faster; but one union per robot (nv 579,
662 geoms in every bucket, against 22-88 DoFs and 33-117 geoms per task) ran 10x slower than 29 separate buckets
at 4,096 environments. Bounded merges paid: at 4,096 environments growth 0.5 (13 buckets) ran 258k physics steps/s
and 0.25 (17 buckets) 224k; at 16,384, 0.5 ran 643k against 545k for the 29 separate buckets (README, speed).
At the protocol's 1,200 environments on the split tick (`backend.streams`, H200, 2026-12-02) 1.0 was the fastest:
0.5 (13 buckets) 254k, 0.75 (10) 267k, 1.0 (9) 272k, 1.5 and 2.0 (7) 221k. At 1.0 later that day: 279k at 1,200,
556k at 4,096 and 717k at 16,384, where the 29 separate buckets had run 1.43-1.49M on streams (physics only, other
days): merging stops paying as the GPU fills. In one run at 16,384 (H200, 2026-12-02, fewer resting contacts by
then) the 29 separate buckets on the split tick ran 1.456M and growth 1.0 974k. 0.5 stays the growth of
`merge=true` and of the padding of separate buckets; `merge=auto` (the default) merges where `choose_merge` finds
few environments per task, at `AUTO_GROWTH`."""

AUTO_BELOW = 64
"""`backend.merge=auto` merges where the run has fewer environments than this per (task, setting), on streams.
Why: a lane (`streams`) costs about the same per physics sub-step up to a few hundred worlds, so with few
environments per bucket the lanes' count sets the tick and merging pays; with many, the merged models' parked
slots do. Measured on one H200 (2026-12-03, MuJoCo Warp, split tick, Warp kernels cached; README, speed), the
bench's 84 plans in 47 separate buckets against 14 merged at growth 1.0 (`dojo bench sim backend.impl=warp
num_envs=N modes=[streams,merged_streams] backend.merge_growth=1.0 steps=20`): 1,200 environments 288.8k and
360.8k physics steps/s (1.25x merged; 28.6 environments a group), 2,048 441.9k and 520.4k (1.18x; 48.8), 4,096
722.7k and 735.6k (1.02x; 97.5); at 16,384 the separate buckets ran 1.48M and 9 merged at growth 2.0 600k
(0.41x). So merging pays up to about 100 a group; the bound keeps to where it pays clearly. The protocol itself
(`dojo run`, 850 plans, 1,200 environments, 42.5 per task and setting) ran 3,270-3,320 interactions/s merged at
growth 1.0 (46 buckets) against 1,838-1,903 in its 141 separate buckets (earlier that day, another H200 machine)."""

AUTO_GROWTH = 1.0
"""The growth `backend.merge=auto` merges with where `merge_growth` is not set: the fastest measured on the
protocol's own run (H200, 2026-12-03, `dojo run backend=mjx policy=zero suite=robodojo_sim episodes=50 seeds=[0]
num_envs=1200 backend.merge=true backend.merge_growth=G`): 3,270-3,320 interactions/s at 1.0 (46 buckets, load
158 s), 2,705 at 2.0 (27 buckets, load 157 s), 2,911 at 0.5 (70 buckets, load 175 s, earlier that day on another
machine)."""


def task_groups(plans: Iterable[Plan]) -> int:
    """How many distinct (task, setting, sub-steps) the plans hold: the fewest buckets `merge=False` can make them
    (`choose_merge`'s `groups`)."""
    return len({(p.task, p.setting, p.n_substeps) for p in plans})


def choose_merge(requested: bool | str, growth: float | None, streams: bool, environments: int, groups: int
                 ) -> tuple[bool, float, str]:
    """(whether the backend merges buckets across tasks, the growth it pads and merges with, why, for the log).

    `requested`: `backend.merge`, true, false or `auto`; `growth`: `backend.merge_growth`, None where unset (then
    `GROWTH`, or `AUTO_GROWTH` where auto merges); `streams`: whether the physics runs on streams (auto merges only
    there: that is where it was measured); `environments`: the run's slots; `groups`: its plans' `task_groups`, so
    `environments / groups` is the most environments a separate bucket can average."""
    if requested not in (True, False, "auto"):
        raise ValueError(f"backend.merge takes true, false or auto, not {requested!r}")
    plain = GROWTH if growth is None else float(growth)
    if requested != "auto":
        return bool(requested), plain, "as set"
    if not streams:
        return False, plain, "auto: the physics is not on streams"
    per_group = environments / max(groups, 1)
    if per_group >= AUTO_BELOW:
        return False, plain, f"auto: {per_group:.0f} environments per task and setting, {AUTO_BELOW} or more"
    return (True, AUTO_GROWTH if growth is None else float(growth),
            f"auto: {per_group:.1f} environments per task and setting, fewer than {AUTO_BELOW}, on streams")


@dataclass(frozen=True)
class Cost:
    """The size of a model that the simulation pays per environment: degrees of freedom and geoms."""

    nv: int
    ngeom: int


@dataclass(frozen=True)
class Unit:
    """Plans of one task that share one structure (a `merge=False` bucket's), and what their model is made of with
    every object a slot."""

    key: str
    plans: tuple[Plan, ...]
    own: Cost
    """Its own padded model's size."""
    frame: Cost
    """The part outside the slots (robot, table, fixed scenery): the same in every union the unit can join."""
    slots: dict[str, int]
    """Slot key -> how many slots of that key its model has."""
    per_slot: dict[str, Cost]
    """Slot key -> one slot's size (a key fixes the structure, so every slot of it costs the same)."""

    @classmethod
    def measure(cls, key: str, plans: Sequence[Plan], padded: PaddedPlan, model: mujoco.MjModel) -> Unit:
        """A unit of `plans` from one of them padded (`padded`, its `slot_keys`) and compiled (`model`)."""
        per_slot: dict[str, Cost] = {}
        for j, slot_key in enumerate(padded.slot_keys):
            per_slot[slot_key] = _subtree_cost(model, f"slot{j}")
        slots = dict(Counter(padded.slot_keys))
        own = Cost(model.nv, model.ngeom)
        in_slots = _total(slots, per_slot)
        return cls(key, tuple(plans), own, Cost(own.nv - in_slots.nv, own.ngeom - in_slots.ngeom), slots, per_slot)

    @classmethod
    def of_plan(cls, plan: Plan, frame: ET.Element, slotted: Sequence[tuple[str, ET.Element]]) -> Unit:
        """A unit of one plan, counted from its MJCF (`pad.slotted_bodies`: the model without its slot bodies, and
        those bodies with their keys) without compiling it."""
        per_slot = {key: xml_cost(body) for key, body in slotted}
        slots = dict(Counter(key for key, _ in slotted))
        outside, inside = xml_cost(frame.find("worldbody")), _total(slots, per_slot)
        return cls(plan.sort_key, (plan,), _plus(outside, inside), outside, slots, per_slot)


_JOINT_DOFS = {"free": 6, "ball": 3, "slide": 1, "hinge": 1}


def xml_cost(element: ET.Element) -> Cost:
    """DoFs and geoms of an MJCF subtree read from the XML (a joint's type defaults to hinge, as in MuJoCo)."""
    nv = sum(6 if el.tag == "freejoint" else _JOINT_DOFS[el.get("type", "hinge")]
             for el in element.iter() if el.tag in ("freejoint", "joint"))
    return Cost(nv, sum(1 for _ in element.iter("geom")))


def _subtree_cost(model: mujoco.MjModel, body: str) -> Cost:
    """DoFs and geoms of a top-level body and every body below it."""
    inside = model.body_rootid == model.body(body).id
    return Cost(int(model.body_dofnum[inside].sum()), int(model.body_geomnum[inside].sum()))


def _total(slots: dict[str, int], per_slot: dict[str, Cost]) -> Cost:
    return Cost(sum(n * per_slot[k].nv for k, n in slots.items()), sum(n * per_slot[k].ngeom for k, n in slots.items()))


class Union:
    """The size of units padded together, kept as it grows: a unit's effect is read from its own slot keys only, so
    first-fit grouping costs one pass over the plans (recomputing each candidate group from its units was quadratic:
    2.1 s for 4,096 plans of one task on the H200 host's CPU, 2026-11-28, four times that for twice the plans).

    Padded together, units get the frame's largest part and, per slot key, the most slots any unit needs (pad.py takes
    the max per key, not the sum); the bound's reference is the largest DoFs and the most geoms of any unit's own."""

    def __init__(self, units: Sequence[Unit] = ()) -> None:
        self.slots: dict[str, int] = {}
        self.per_slot: dict[str, Cost] = {}
        self.slotted = Cost(0, 0)
        self.frame = Cost(0, 0)
        self.ref = Cost(0, 0)
        for unit in units:
            self.add(unit)

    def _with(self, unit: Unit) -> tuple[Cost, Cost, Cost]:
        """(frame, slotted, ref) of the union with `unit` added, without adding it."""
        nv, ngeom = self.slotted.nv, self.slotted.ngeom
        for key, n in unit.slots.items():
            extra = n - self.slots.get(key, 0)
            if extra > 0:
                cost = self.per_slot.get(key, unit.per_slot[key])
                nv, ngeom = nv + extra * cost.nv, ngeom + extra * cost.ngeom
        frame = Cost(max(self.frame.nv, unit.frame.nv), max(self.frame.ngeom, unit.frame.ngeom))
        ref = Cost(max(self.ref.nv, unit.own.nv), max(self.ref.ngeom, unit.own.ngeom))
        return frame, Cost(nv, ngeom), ref

    def add(self, unit: Unit) -> None:
        self.frame, self.slotted, self.ref = self._with(unit)
        for key, n in unit.slots.items():
            self.slots[key] = max(self.slots.get(key, 0), n)
            self.per_slot.setdefault(key, unit.per_slot[key])

    @property
    def estimate(self) -> Cost:
        return _plus(self.frame, self.slotted)

    def fits(self, unit: Unit, growth: float) -> bool:
        """Whether the union with `unit` added stays within `1 + growth` of its largest unit (`_bounded`)."""
        frame, slotted, ref = self._with(unit)
        return _bounded(_plus(frame, slotted), ref, growth)


def _plus(a: Cost, b: Cost) -> Cost:
    return Cost(a.nv + b.nv, a.ngeom + b.ngeom)


def _bounded(union: Cost, ref: Cost, growth: float) -> bool:
    return union.nv <= (1.0 + growth) * ref.nv and union.ngeom <= (1.0 + growth) * ref.ngeom


def estimate(units: Sequence[Unit]) -> Cost:
    """The size of the model the units' plans get when padded together (`Union`)."""
    return Union(units).estimate


def largest(units: Sequence[Unit]) -> Cost:
    """The bound's reference: the largest DoFs and the most geoms of any one unit's own model."""
    return Union(units).ref


def _growth(union: Union) -> float:
    """How much larger the union is than its largest unit: the larger of the two ratios, minus one."""
    return max(union.estimate.nv / max(union.ref.nv, 1), union.estimate.ngeom / max(union.ref.ngeom, 1)) - 1.0


Cluster = tuple[Unit, ...]


def _keys(cluster: Cluster) -> tuple[str, ...]:
    return tuple(u.key for u in cluster)


def cluster(units: Sequence[Unit], growth: float, one_structure: Callable[[Cluster, Cluster], bool]) -> list[Cluster]:
    """Merge units greedily into clusters, each to be padded on its own into one bucket.

    Each round merges the candidate pair of least growth (ties by the units' keys) whose union's estimated DoFs and
    geoms each stay within `1 + growth` times its largest unit's (bounding by the largest *unit*, not by the larger
    of two clusters, keeps a chain of merges from compounding) and for which `one_structure(a, b)` holds, i.e.
    their plans, padded together, compile to one structure (the caller pads one plan of each and compiles).
    A pair that fails marks every pair of their units as apart: what splits them is outside the slots (a skybox,
    an option), so it splits any later cluster holding both too, and clusters only grow. Deterministic: units and
    candidates are taken in sorted order, so the same plans always give the same clusters.

    The candidates wait in a heap, each pair's union counted once: a merge adds only the new cluster's pairs, and
    a pair of a cluster merged away is dropped when it comes up. Recounting every pair every round was cubic in the
    units: the suite's 1,150 plans (seed 0, 333 units, growth 1.0) spent 17 s of their 96 s merge counting unions
    on the CI machine (2026-12-02), 1.2 million of them for 170 merges; now 0.7 s, with the same clusters.
    """
    if not growth >= 0:  # NaN too
        raise ValueError(f"merge growth must be at least 0, got {growth}")
    alive: dict[tuple[str, ...], Cluster] = {_keys((u,)): (u,) for u in sorted(units, key=lambda u: u.key)}
    apart: set[frozenset[str]] = set()
    heap: list[tuple[float, tuple[str, ...], tuple[str, ...]]] = []

    def offer(a: Cluster, b: Cluster) -> None:
        a, b = sorted((a, b), key=_keys)
        union = Union(a + b)
        if _bounded(union.estimate, union.ref, growth):
            heapq.heappush(heap, (_growth(union), _keys(a), _keys(b)))

    listed = list(alive.values())
    for i, a in enumerate(listed):
        for b in listed[i + 1:]:
            offer(a, b)
    while heap:
        _, ka, kb = heapq.heappop(heap)
        if ka not in alive or kb not in alive:
            continue
        a, b = alive[ka], alive[kb]
        if any(frozenset((x.key, y.key)) in apart for x in a for y in b):
            continue
        if not one_structure(a, b):
            apart.update(frozenset((x.key, y.key)) for x in a for y in b)
            continue
        del alive[ka], alive[kb]
        union = tuple(sorted(a + b, key=lambda u: u.key))
        for other in list(alive.values()):
            offer(union, other)
        alive[_keys(union)] = union
    return sorted(alive.values(), key=_keys)


def padding_groups(plans: Sequence[Plan], growth: float, parsed: ParsedPlans | None = None) -> list[list[Plan]]:
    """The plans of one task and setting split into groups to pad together, each group's padded model (the union of
    its plans' clutter slots, pad.py) within `1 + growth` of its largest plan's own, DoFs and geoms each.

    Why. Clutter slots are keyed by their exact geometry, and the `random` setting scales every clutter object by a
    random factor, so nearly every clutter object of every plan is a key of its own: padded together, 256 random
    `stack_blocks` plans gave every one of them a model of 2,266 DoFs and 2,067 geoms (their own: 34-142 DoFs),
    whose parked slots every environment then simulates; and since their blocks' meshes differ too (what the frame
    holds, `pad.frame_key`), those models were 256 structures all the same. First fit, largest plans first: each
    plan joins the first group of its frame key that it fits, else starts one; plans are counted from their MJCF
    (`Unit.of_plan`), nothing is compiled.
    Groups keep the plans' given order. `parsed`: the plans already parsed (`pad.ParsedPlans`)."""
    if not growth >= 0:  # NaN too
        raise ValueError(f"padding growth must be at least 0, got {growth}")
    read = slotted_bodies(plans, parsed)
    units = [Unit.of_plan(plan, frame, slotted) for plan, (frame, slotted) in zip(plans, read)]
    frames = {unit.key: frame_key(frame) for unit, (frame, _) in zip(units, read)}
    groups: list[tuple[list[Unit], Union]] = []
    for unit in sorted(units, key=lambda u: (-u.own.nv, -u.own.ngeom, u.key)):
        for group, union in groups:
            if frames[group[0].key] == frames[unit.key] and union.fits(unit, growth):
                group.append(unit)
                union.add(unit)
                break
        else:
            groups.append(([unit], Union([unit])))
    order = {plan.hash: k for k, plan in enumerate(plans)}
    ordered = [sorted((p for u in g for p in u.plans), key=lambda p: order[p.hash]) for g, _ in groups]
    return sorted(ordered, key=lambda g: order[g[0].hash])


def plans_of(units: Cluster) -> list[Plan]:
    """Every plan of a cluster, unit by unit."""
    return [p for u in units for p in u.plans]

