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

import dataclasses
import hashlib
import os
import typing
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Iterator, Sequence

import mujoco
import numpy as np
from mujoco.mjx._src import types as mjx_types

from dojo.compiler.plan import Plan

from dojo.backends.mjx.merge_groups import GROWTH, Cluster, Unit, cluster, padding_groups, plans_of
from dojo.backends.mjx.pad import PaddedPlan, pad_group

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


def _varying(models: Sequence[mujoco.MjModel]) -> tuple[str, ...]:
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


def compiled_models(padded: Sequence[PaddedPlan]) -> list[tuple[mujoco.MjModel, str]]:
    """Each padded plan's model and its `structural_signature`, made on threads, in order (with each source plan's
    own model, which `_initial_state` reads). MuJoCo's XML compiler and hashlib's hashing of large buffers let go of
    the GIL, and they are most of `make_buckets`' time: 120 `insert_tubes` plans spent 4.1 of 7.5 s compiling on
    the 2-core machine, where two threads compiled 2.1x as fast; on the H200 host 1,024 plans spent 2.4 s compiling
    and 3.7 s hashing one after another (2026-11-28), before the hashing moved onto the threads."""
    def signed(pp: PaddedPlan) -> tuple[mujoco.MjModel, str]:
        model = mujoco.MjModel.from_xml_string(pp.xml)
        return model, structural_signature(model)

    if len(padded) < 2:
        return [signed(pp) for pp in padded]
    with ThreadPoolExecutor(min(len(padded), os.cpu_count() or 1)) as pool:
        for _ in pool.map(lambda pp: pp.plan.model(), padded):
            pass
        return list(pool.map(signed, padded))


def _padded_members(plans: Sequence[Plan], name: str, every_object: bool) -> dict[str, list[Member]]:
    """The plans padded together (pad.py) and compiled, by structural signature, in signature order."""
    out: dict[str, list[Member]] = defaultdict(list)
    padded = pad_group(plans, name, every_object=every_object)
    for pp, (model, signature) in zip(padded, compiled_models(padded), strict=True):
        qpos, qvel, ctrl = _initial_state(pp, model)
        out[signature].append(Member(pp, model, qpos, qvel, ctrl))
    return dict(sorted(out.items()))


def _task_members(plans: Sequence[Plan], task: str, growth: float) -> list[tuple[str, list[Member]]]:
    """One task's plans (of one setting and sub-steps) padded in groups whose union stays within `1 + growth` of
    their largest plan (`merge_groups.padding_groups`), as (signature, members); groups that come out with one
    structure share its bucket."""
    return [item for group in padding_groups(plans, growth)
            for item in _padded_members(group, task, every_object=False).items()]


def _one_structure(a: Cluster, b: Cluster, robot: str) -> bool:
    """Whether two clusters' plans, padded together, would compile to one structure, asked of one plan of each: what
    splits plans padded together lies outside the slots (skybox, options, equality constraints), where a cluster's
    plans agree already, and every plan padded together gets the same slots."""
    padded = pad_group([a[0].plans[0], b[0].plans[0]], robot, every_object=True)
    return len({structural_signature(mujoco.MjModel.from_xml_string(pp.xml)) for pp in padded}) == 1


def _merged(by_task: dict[str, list[Plan]], robot: str, growth: float) -> list[tuple[str, list[Member]]]:
    """The members of one robot's (setting, sub-steps) plans as (signature, members), merged across tasks where
    `merge_groups.cluster` finds it cheap. Its units are the buckets `merge=False` would make (a task's plans
    padded alone, by structure), each padded again with every object a slot to count what its objects cost; so a
    merge never makes more buckets than `merge=False`, and a cluster of one unit is that bucket, renamed."""
    units: list[Unit] = []
    members_of: dict[str, list[Member]] = {}
    signatures: dict[str, str] = {}
    for task in sorted(by_task):
        for _, alike in _task_members(by_task[task], task, growth):
            # Named by content (its least plan hash), not by its place in the plans' order: `cluster` breaks ties
            # by these keys, so that the same plans in another order give the same clusters.
            first = min(m.plan.hash for m in alike)
            for signature, members in _padded_members([m.plan for m in alike], robot, every_object=True).items():
                key = f"{task}:{first[:16]}:{signature[:16]}"
                units.append(Unit.measure(key, [m.plan for m in members], members[0].padded, members[0].model))
                members_of[key], signatures[key] = members, signature
    out: list[tuple[str, list[Member]]] = []
    for units_merged in cluster(units, growth, lambda a, b: _one_structure(a, b, robot)):
        if len(units_merged) == 1:
            out.append((signatures[units_merged[0].key], members_of[units_merged[0].key]))
        else:
            out.extend(_padded_members(plans_of(units_merged), robot, every_object=True).items())
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
    for (name, setting, substeps) in sorted(by_group):
        if merge:
            for signature, members in _merged(by_group[name, setting, substeps], name, growth):
                groups[f"{name}:{substeps}:{signature[:16]}"] += members
        else:
            for signature, members in _task_members(by_group[name, setting, substeps][name], name, growth):
                groups[f"{name}:{signature[:16]}"] += members
    return [Bucket(key, members, _varying([m.model for m in members])) for key, members in sorted(groups.items())]
