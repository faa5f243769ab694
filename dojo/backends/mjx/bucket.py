"""Buckets: plans whose compiled models share one MJX structure, with the values that differ per environment.

MJX traces one XLA program per model structure. Every `int`, `bytes` and `np.ndarray` field of `mjx.Model` is
static (part of the traced program), every `jax.Array` field is a value. Two models with equal static fields and
equal array shapes therefore run under one compiled program, with the differing value fields batched per
environment through `jax.vmap`'s `in_axes`. `structural_signature` hashes exactly that, from the MjModel, without
building an `mjx.Model` per plan (which for meshes computes convex hulls).

A bucket keeps, for each of its plans (a *member*), the values of the varying fields and the initial state, as a
table with one row per member. The batch holds per environment only the member index; the model an environment
simulates is gathered from the table inside the jitted step. Refilling a finished environment with the next
queued episode of the bucket is then a change of one integer, never a new shape, so it never recompiles.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import os
import typing
from collections import defaultdict
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator, Sequence

import mujoco
import numpy as np
from mujoco.mjx._src import types as mjx_types

from dojo.compiler.plan import Plan

from dojo.backends.mjx.merge_groups import GROWTH, Cluster, Unit, cluster, padding_groups, plans_of
from dojo.backends.mjx.pad import PaddedPlan, ParsedPlans, pad_group

_HINTS = typing.get_type_hints(mjx_types.Model)
_OPT_HINTS = typing.get_type_hints(mjx_types.Option)
STATIC_FIELDS = tuple(f.name for f in dataclasses.fields(mjx_types.Model)
                      if _HINTS[f.name] in (int, bool, bytes, np.ndarray, np.uint64))
VALUE_FIELDS = tuple(f.name for f in dataclasses.fields(mjx_types.Model) if _HINTS[f.name] is mjx_types.jax.Array)
_OPT_STATIC = tuple(n for n, t in _OPT_HINTS.items() if n != "_impl" and t is not mjx_types.jax.Array)
_OPT_VALUES = tuple(n for n, t in _OPT_HINTS.items() if t is mjx_types.jax.Array)
_SIZE_CANDIDATES = tuple(name for name in dir(mujoco.MjModel) if name.startswith("n")
                         and isinstance(getattr(mujoco.MjModel, name), property))
"""MjModel's properties that may be sizes (nq, nv, narena, nuserdata, ...; also `names`, `numeric_data`, which
are not): an MjData made for one model fits another whose sizes are all the same (`member_data`)."""


def structural_signature(model: mujoco.MjModel) -> str:
    """Hash of everything MJX treats as structure: static fields' contents, value fields' shapes, options."""
    h = hashlib.sha256()
    for name in STATIC_FIELDS:
        value = getattr(model, name)
        h.update(name.encode())
        h.update(np.ascontiguousarray(value) if isinstance(value, np.ndarray) else repr(value).encode())
    for name in VALUE_FIELDS:
        h.update(f"{name}{np.shape(getattr(model, name))}".encode())
    for name in _OPT_STATIC + _OPT_VALUES:  # options are the robot's; differing values split rather than batch
        h.update(f"{name}{np.asarray(getattr(model.opt, name)).tolist()}".encode())
    return h.hexdigest()


@dataclass
class Member:
    """One plan inside a bucket: its padded model and initial state in the bucket's layout."""

    padded: PaddedPlan
    model: mujoco.MjModel
    qpos: np.ndarray
    qvel: np.ndarray
    ctrl: np.ndarray

    @property
    def plan(self) -> Plan:
        return self.padded.plan


@dataclass
class Bucket:
    """Plans sharing one structure. `varying` names the model value fields that differ between members."""

    key: str
    members: list[Member]
    varying: tuple[str, ...] = field(default_factory=tuple)

    @property
    def model(self) -> mujoco.MjModel:
        """The reference model (the first member's): shared fields and the structure come from it."""
        return self.members[0].model

    @property
    def n_substeps(self) -> int:
        return self.members[0].plan.n_substeps

    @property
    def tasks(self) -> tuple[str, ...]:
        return tuple(sorted({m.plan.task for m in self.members}))

    def table(self) -> dict[str, np.ndarray]:
        """Per-member values of the varying fields and the initial state, stacked along a leading member axis.

        The initial state includes every geom's world pose (`geom_xpos`, `geom_xmat`): MuJoCo Warp computes the
        poses of geoms welded to the world only in `make_data` and never again, so without them each environment
        would collide with, and render, member 0's fixtures (a power strip at another yaw: the charger meets its
        rim 2 mm short). A reset writes the member's poses; the engine's kinematics overwrites the moving ones."""
        rows = {name: np.stack([getattr(m.model, name) for m in self.members]) for name in self.varying}
        rows.update(qpos=np.stack([m.qpos for m in self.members]), qvel=np.stack([m.qvel for m in self.members]),
                    ctrl=np.stack([m.ctrl for m in self.members]))
        rows["geom_xpos"], rows["geom_xmat"] = self.geom_poses()
        return rows

    def geom_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Every member's geom world positions [members, ngeom, 3] and rotations [members, ngeom, 3, 3] at its
        initial state (MuJoCo's kinematics on the member's model; see `table`)."""
        positions = np.empty((len(self.members), self.model.ngeom, 3))
        rotations = np.empty((len(self.members), self.model.ngeom, 3, 3))
        for k, (member, data) in enumerate(member_data(self.members)):
            data.qpos[:] = member.qpos
            mujoco.mj_kinematics(member.model, data)
            positions[k], rotations[k] = data.geom_xpos, data.geom_xmat.reshape(-1, 3, 3)
        return positions, rotations


def member_data(members: Sequence[Member]) -> Iterator[tuple[Member, mujoco.MjData]]:
    """Each member with an MjData as a fresh one for its model would be (`mj_resetData`: mocap poses, activations
    and the rest from that model), one allocated per data layout instead of one per member: allocating was most of
    the time of a pass over thousands of members (0.8 of 0.85 ms a member on the CI machine). The layout is every
    size of the model (its integer `_SIZE_CANDIDATES`, the arena's included); a model with plugins gets its own,
    their state being made per model. Each MjData is valid until the next member is taken."""
    kept: dict[tuple[int, ...], mujoco.MjData] = {}
    for member in members:
        model = member.model
        if model.nplugin:
            yield member, mujoco.MjData(model)
            continue
        layout = tuple(size for name in _SIZE_CANDIDATES if isinstance(size := getattr(model, name), int))
        data = kept.get(layout)
        if data is None:
            data = kept[layout] = mujoco.MjData(model)
        else:
            mujoco.mj_resetData(model, data)
        yield member, data


def _initial_state(padded: PaddedPlan, model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The plan's initial qpos/qvel/ctrl moved into the padded layout; parked slots rest at their parking pose."""
    plan = padded.plan
    source = plan.model()
    qpos, qvel = model.qpos0.copy(), np.zeros(model.nv)
    src_qpos, src_qvel = np.asarray(plan.init_qpos), np.asarray(plan.init_qvel)
    for j in range(model.njnt):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
        src = mujoco.mj_name2id(source, mujoco.mjtObj.mjOBJ_JOINT, padded.names.get(name, name))
        if src < 0:
            continue
        nq = _QPOS_WIDTH[model.jnt_type[j]]
        nv = _QVEL_WIDTH[model.jnt_type[j]]
        qpos[model.jnt_qposadr[j]:model.jnt_qposadr[j] + nq] = src_qpos[source.jnt_qposadr[src]:][:nq]
        qvel[model.jnt_dofadr[j]:model.jnt_dofadr[j] + nv] = src_qvel[source.jnt_dofadr[src]:][:nv]
    if model.nu != source.nu:
        raise ValueError(f"plan {plan.hash[:12]}: padding changed the actuators ({source.nu} -> {model.nu})")
    return qpos, qvel, np.asarray(plan.init_ctrl, dtype=float)


_QPOS_WIDTH = {0: 7, 1: 4, 2: 1, 3: 1}
_QVEL_WIDTH = {0: 6, 1: 3, 2: 1, 3: 1}


def varying_fields(models: Sequence[mujoco.MjModel]) -> tuple[str, ...]:
    """The value fields whose contents differ between the models (the bucket's per-member table). Compared as
    bytes: a field that holds for thousands of members is read once per member, and `np.array_equal` cost 3.6x as
    much (0.86 against 0.24 ms a member on the CI machine). Bit for bit, so a field whose values differ only in a
    zero's sign counts as varying (a per-member copy of equal numbers), and NaNs alike everywhere do not."""
    def differs(name: str) -> bool:
        """Whether any model's `name` differs from the first model's."""
        first = np.asarray(getattr(models[0], name))
        shape, data = first.shape, first.tobytes()
        return any((value := np.asarray(getattr(m, name))).shape != shape or value.tobytes() != data
                   for m in models[1:])

    return tuple(name for name in VALUE_FIELDS if differs(name))


def _digest(xml: str) -> bytes:
    """The MJCF's SHA-256, by which `Compiler` remembers the signatures it has found."""
    return hashlib.sha256(xml.encode()).digest()


def compile_padded(xml: str) -> tuple[mujoco.MjModel, str, bytes]:
    """The model of a padded MJCF, its `structural_signature` and the MJCF's `_digest`."""
    model = mujoco.MjModel.from_xml_string(xml)
    return model, structural_signature(model), _digest(xml)


def compile_jobs(pool: Executor, padded: Iterable[PaddedPlan]) -> dict[str, Future[tuple[mujoco.MjModel, str, bytes]]]:
    """One `compile_padded` job on `pool` per distinct MJCF of `padded`, by its text."""
    jobs: dict[str, Future[tuple[mujoco.MjModel, str, bytes]]] = {}
    for pp in padded:
        if pp.xml not in jobs:
            jobs[pp.xml] = pool.submit(compile_padded, pp.xml)
    return jobs


def _signature(xml: str) -> str:
    """The `structural_signature` of a padded MJCF, its model dropped at once: the signature is all a pair check or
    the split of a task's plans into units needs, and a model takes megabytes (a suite plan's textures 1.6 MB)."""
    return structural_signature(mujoco.MjModel.from_xml_string(xml))


_Item = typing.TypeVar("_Item")

Compiled = list[tuple[PaddedPlan, mujoco.MjModel]]
"""Padded plans with their compiled models."""


@dataclass
class Compiling:
    """Padded plans whose models a `Compiler` is making (`Compiler.models`)."""

    padded: Sequence[PaddedPlan]
    jobs: dict[str, Future[tuple[mujoco.MjModel, str, bytes]]]
    """One job per distinct MJCF."""
    seen: dict[bytes, str]
    """The compiler's signatures by MJCF digest, which these join."""

    def result(self) -> list[tuple[mujoco.MjModel, str]]:
        """Each padded plan's model and signature, in order, once compiled; an MJCF repeated in `padded` gets a copy
        of its first one's model (`mj_copyModel`), so that every member still has a model of its own."""
        out: list[tuple[mujoco.MjModel, str]] = []
        taken: set[str] = set()
        for pp in self.padded:
            model, signature, digest = self.jobs[pp.xml].result()
            self.seen[digest] = signature
            out.append((copy.copy(model) if pp.xml in taken else model, signature))
            taken.add(pp.xml)
        return out

    def by_signature(self) -> dict[str, Compiled]:
        """The padded plans with their models by structural signature (`_by_signature`)."""
        found = self.result()
        return _by_signature([(pp, model) for pp, (model, _) in zip(self.padded, found, strict=True)],
                             [signature for _, signature in found])


class Compiler:
    """What one `make_buckets` call compiles: padded plans on a pool of threads, each distinct MJCF once, and the
    plans' own models (`Plan.model`, which `_initial_state` reads) on a thread beside it; with the plans parsed once
    for all their paddings (`parsed`). A context manager: leaving it stops its threads.

    Threads: MuJoCo's XML compiler and hashlib's hashing of large buffers let go of the GIL, and they are most of
    `make_buckets`' time: 120 `insert_tubes` plans spent 4.1 of 7.5 s compiling on the 2-core machine, where two
    threads compiled 2.1x as fast; on the H200 host 1,024 plans spent 2.4 s compiling and 3.7 s hashing one after
    another (2026-11-28), before the hashing moved onto the threads. One pool serves the whole call and the caller
    pads the next plans while it compiles: with a pool per padded group, groups of one plan (326 of the 505 padded
    in the suite's merge) compiled on the calling thread, and nothing was padded while a group compiled.
    The plans' own models compile on a thread of their own, behind none of the padded MJCF that the caller waits
    for.

    Once: of the 3,817 padded MJCF that the suite's merge compiled (1,150 plans of seed 0, 2026-12-03), 388
    repeated one compiled earlier in the same call: plans that padding makes identical, and pair checks
    (`_one_structure`) asking about a plan padded as its unit already was. A repeat within one `models` call gets a
    copy of the first's model; `signatures` compiles only MJCF whose signature the call has not found yet (kept by
    digest: a few dozen bytes an MJCF)."""

    def __init__(self, plans: Sequence[Plan]) -> None:
        self.parsed = ParsedPlans()
        self._signatures: dict[bytes, str] = {}
        self._pool = ThreadPoolExecutor(os.cpu_count() or 1)
        self._sources = ThreadPoolExecutor(1)
        for plan in plans:
            self._sources.submit(plan.model)

    def __enter__(self) -> Compiler:
        return self

    def __exit__(self, *exc: object) -> None:
        self._sources.shutdown(cancel_futures=True)
        self._pool.shutdown(cancel_futures=True)

    def models(self, padded: Sequence[PaddedPlan]) -> Compiling:
        """Start compiling the padded plans' models."""
        return Compiling(padded, compile_jobs(self._pool, padded), self._signatures)

    def signatures(self, padded: Sequence[PaddedPlan]) -> Callable[[], list[str]]:
        """Start finding the padded plans' structural signatures; the function returned waits for them, in order."""
        digests = [_digest(pp.xml) for pp in padded]
        jobs: dict[bytes, Future[str]] = {}
        for pp, digest in zip(padded, digests):
            if digest not in self._signatures and digest not in jobs:
                jobs[digest] = self._pool.submit(_signature, pp.xml)

        def wait() -> list[str]:
            for digest, job in jobs.items():
                self._signatures[digest] = job.result()
            return [self._signatures[digest] for digest in digests]

        return wait


def bucket_members(compiled: Compiled) -> list[Member]:
    """The padded plans as members: their models and initial states in the padded layout."""
    return [Member(pp, model, *_initial_state(pp, model)) for pp, model in compiled]


def _task_groups(plans: Sequence[Plan], task: str, growth: float, compiler: Compiler) -> list[Compiling]:
    """One task's plans (of one setting and sub-steps) padded in groups whose union stays within `1 + growth` of
    their largest plan (`merge_groups.padding_groups`), each group compiling; plans of a group that come out with
    one structure share its bucket."""
    return [compiler.models(pad_group(group, task, parsed=compiler.parsed))
            for group in padding_groups(plans, growth, compiler.parsed)]


def _by_signature(items: Sequence[_Item], signatures: Sequence[str]) -> dict[str, list[_Item]]:
    """`items` grouped by their structural signatures, in signature order, each group in the items' order."""
    out: dict[str, list[_Item]] = defaultdict(list)
    for item, signature in zip(items, signatures, strict=True):
        out[signature].append(item)
    return dict(sorted(out.items()))


def _unit_groups(by_task: dict[str, list[Plan]], robot: str, growth: float,
                 compiler: Compiler) -> list[tuple[str, list[Plan], Compiling]]:
    """The plans of each bucket `merge=False` would make (a task's plans padded alone, by structure), padded again
    with every object a slot and compiling, as (task, plans, compiling): every task's groups are padded and sent to
    the compiler before any is waited for."""
    padded = [(task, group, compiler.signatures(pad_group(group, task, parsed=compiler.parsed)))
              for task in sorted(by_task) for group in padding_groups(by_task[task], growth, compiler.parsed)]
    return [(task, alike, compiler.models(pad_group(alike, robot, every_object=True, parsed=compiler.parsed)))
            for task, group, signatures in padded for alike in _by_signature(group, signatures()).values()]


def _one_structure(a: Cluster, b: Cluster, robot: str, compiler: Compiler) -> bool:
    """Whether two clusters' plans, padded together, would compile to one structure, asked of one plan of each: what
    splits plans padded together lies outside the slots (skybox, options, equality constraints), where a cluster's
    plans agree already, and every plan padded together gets the same slots."""
    padded = pad_group([a[0].plans[0], b[0].plans[0]], robot, every_object=True, parsed=compiler.parsed)
    return len(set(compiler.signatures(padded)())) == 1


def _units(by_task: dict[str, list[Plan]], robot: str, growth: float,
           compiler: Compiler) -> tuple[list[Unit], dict[str, tuple[str, Compiled]]]:
    """The units to cluster (`_unit_groups` by structure), and each unit's signature and padded plans by its key."""
    units: list[Unit] = []
    unit_of: dict[str, tuple[str, Compiled]] = {}
    for task, alike, compiling in _unit_groups(by_task, robot, growth, compiler):
        # Named by its least plan (`Plan.sort_key`), not by its place in the plans' order: `cluster` breaks ties
        # by these keys, so that the same plans in another order, or compiled by another install, give the same
        # clusters.
        first = min(plan.sort_key for plan in alike)
        for signature, compiled in compiling.by_signature().items():
            key = f"{first}:{signature[:16]}"
            units.append(Unit.measure(key, [pp.plan for pp, _ in compiled], *compiled[0]))
            unit_of[key] = signature, compiled
    return units, unit_of


def _merged(by_task: dict[str, list[Plan]], robot: str, growth: float,
            compiler: Compiler) -> list[tuple[str, list[Member]]]:
    """The members of one robot's (setting, sub-steps) plans as (signature, members), merged across tasks where
    `merge_groups.cluster` finds it cheap. Its units are the buckets `merge=False` would make (a task's plans
    padded alone, by structure), each padded again with every object a slot to count what its objects cost; so a
    merge never makes more buckets than `merge=False`, and a cluster of one unit is that bucket, renamed."""
    units, unit_of = _units(by_task, robot, growth, compiler)
    clusters = cluster(units, growth, lambda a, b: _one_structure(a, b, robot, compiler))
    # Only a cluster of one unit keeps its unit's models: the others' are let go before the merged clusters compile,
    # whose models then take their memory instead of fresh pages. The suite's merge (1,150 plans, 1,039 of them in
    # merged clusters, 2.4 MB a model) took 51.0 s keeping them, 21.7 s of it in the kernel (page faults), and
    # 34.3 s letting go (5.4 s) on the 2-core CI machine (2026-12-03).
    alone = {c[0].key: unit_of[c[0].key] for c in clusters if len(c) == 1}
    del unit_of
    merging = [compiler.models(pad_group(plans_of(c), robot, every_object=True, parsed=compiler.parsed))
               if len(c) > 1 else None for c in clusters]
    out: list[tuple[str, list[Member]]] = []
    for c, compiling in zip(clusters, merging):
        if compiling is None:
            signature, compiled = alone[c[0].key]
            out.append((signature, bucket_members(compiled)))
        else:
            out.extend((signature, bucket_members(compiled))
                       for signature, compiled in compiling.by_signature().items())
    return out


def make_buckets(plans: Sequence[Plan], merge: bool = False, growth: float = GROWTH) -> list[Bucket]:
    """Group plans into buckets of one structure each, in a deterministic order.

    The plans of each (task, setting) are first padded to a common structure (see pad.py), so that they need few
    buckets, in groups whose padded model stays within `1 + growth` of the group's largest plan
    (`merge_groups.padding_groups`: random clutter is mostly one of a kind); settings are padded apart so that
    `standard` scenes do not carry `random` clutter slots. Different
    tasks never share a bucket. With `merge`, the tasks of each (robot, setting, sub-steps) are clustered
    (merge_groups.py: greedily, while the merged model's DoFs and geoms stay within `1 + growth` of its largest
    task's own; `growth=math.inf` merges every task whose scene allows it) and each cluster's plans are padded
    together, every object a slot (`pad_group(every_object=True)`), so a bucket's members may carry several
    tasks' programs (the backend's lanes).
    """
    by_group: dict[tuple[str, str, int], dict[str, list[Plan]]] = defaultdict(lambda: defaultdict(list))
    for plan in plans:
        by_group[plan.embodiment if merge else plan.task, plan.setting, plan.n_substeps][plan.task].append(plan)
    groups: dict[str, list[Member]] = defaultdict(list)
    with Compiler(plans) as compiler:
        if merge:
            for (name, setting, substeps) in sorted(by_group):
                for signature, members in _merged(by_group[name, setting, substeps], name, growth, compiler):
                    groups[f"{name}:{substeps}:{signature[:16]}"] += members
        else:
            compiling = [(name, found) for (name, setting, substeps) in sorted(by_group)
                         for found in _task_groups(by_group[name, setting, substeps][name], name, growth, compiler)]
            for name, found in compiling:
                for signature, compiled in found.by_signature().items():
                    groups[f"{name}:{signature[:16]}"] += bucket_members(compiled)
    return [Bucket(key, members, varying_fields([m.model for m in members])) for key, members in sorted(groups.items())]
