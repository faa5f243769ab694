"""Lanes: the predicate programs of one bucket, one per distinct program, selected per environment.

A bucket of one task (`make_buckets`) has one program: every member compiles to the same layout and, in the padded
model, the same state index; only params differ. A merged bucket (`make_buckets(merge=True)`) holds several tasks,
so it has one *lane* per distinct (layout, state index): every member's program is compiled against its own plan
(`compile_program`) and its `StateIndex` moved into the padded model by name (`remap_index`: bodies, sites and
joints through `PaddedPlan.names`, geoms through their bodies), and members whose programs are then equal share a
lane (all plans of one task do, since a task's objects always fill the same slots).

The tick evaluates every lane's program on the whole batch (a lane's params table has a row for every member;
rows of other lanes' members repeat one of its own, so those rows compute harmless values that are thrown away)
and picks each environment's outputs by its member's lane (`select_lanes`). Outputs are padded to the widest lane:
stage steps with -1 (never reached), terms with False. Each lane keeps its own memory for the whole batch; a reset
row gets fresh memory in every lane, so a refill into another lane starts clean.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import mujoco
import numpy as np

from dojo.backends.predicate_program import compile_program, stack_params
from dojo.backends.predicate_state import BODY, SITE, StateIndex
from dojo.backends.program_types import ProgramLayout, ProgramOutput

from dojo.backends.mjx.bucket import Bucket

Array = Any


@dataclass(frozen=True)
class Lane:
    """One program of a bucket: its layout, its state index in the padded model, params per bucket member."""

    layout: ProgramLayout
    index: StateIndex
    params: dict[str, np.ndarray]  # [members, ...]


@dataclass(frozen=True)
class BucketPrograms:
    """A bucket's lanes and each member's lane (int32 [members])."""

    lanes: tuple[Lane, ...]
    member_lane: np.ndarray

    def layout_of(self, member: int) -> ProgramLayout:
        """The program layout of a bucket member (its stage and term names)."""
        return self.lanes[int(self.member_lane[member])].layout


def _ids_by_name(padded: mujoco.MjModel, source: mujoco.MjModel, obj: mujoco.mjtObj, count: int,
                 names: dict[str, str]) -> dict[int, int]:
    """{source id: padded id} for elements of type `obj` named alike (padded names mapped back by `names`)."""
    out = {}
    for k in range(count):
        name = mujoco.mj_id2name(padded, obj, k)
        if name is None:
            continue
        src = mujoco.mj_name2id(source, obj, names.get(name, name))
        if src >= 0:
            out[src] = k
    return out


def remap_index(index: StateIndex, source: mujoco.MjModel, padded: mujoco.MjModel,
                names: dict[str, str]) -> StateIndex:
    """`index` (compiled against the plan's own model `source`) moved into its padded model.

    Frames and joints are looked up by name (`names`: padded name -> plan name, for renamed slot elements); a geom
    belongs to the atom of its body, so padded geoms take their body's atom and parked slots' geoms none."""
    bodies = _ids_by_name(padded, source, mujoco.mjtObj.mjOBJ_BODY, padded.nbody, names)
    sites = _ids_by_name(padded, source, mujoco.mjtObj.mjOBJ_SITE, padded.nsite, names)
    joints = _ids_by_name(padded, source, mujoco.mjtObj.mjOBJ_JOINT, padded.njnt, names)

    def moved(table: dict[int, int], ident: int, what: str) -> int:
        if ident not in table:
            raise ValueError(f"{what} {ident} of the plan has no named counterpart in the padded model")
        return table[ident]

    frame_id = tuple(moved(bodies, i, "body") if k == BODY else moved(sites, i, "site") if k == SITE else i
                     for k, i in zip(index.frame_kind, index.frame_id))
    qpos_joint = {int(source.jnt_qposadr[j]): j for j in range(source.njnt)}
    dof_joint = {int(source.jnt_dofadr[j]): j for j in range(source.njnt)}
    qpos_adr = tuple(int(padded.jnt_qposadr[moved(joints, qpos_joint[a], "joint")]) for a in index.qpos_adr)
    dof_adr = tuple(int(padded.jnt_dofadr[moved(joints, dof_joint[a], "joint")]) for a in index.dof_adr)
    body_atom = {int(source.geom_bodyid[g]): atom for g, atom in enumerate(index.geom_atom) if atom < index.n_atoms}
    padded_atom = {bodies[b]: atom for b, atom in body_atom.items() if b in bodies}
    missing = set(body_atom) - set(bodies)
    if missing:
        raise ValueError(f"bodies {sorted(missing)} of the plan's contact atoms have no named counterpart")
    geom_atom = tuple(padded_atom.get(int(padded.geom_bodyid[g]), index.n_atoms) for g in range(padded.ngeom))
    return replace(index, frame_id=frame_id, qpos_adr=qpos_adr, dof_adr=dof_adr, geom_atom=geom_atom)


def bucket_programs(bucket: Bucket) -> BucketPrograms:
    """Compile every member's program, move its index into the padded model and group members into lanes."""
    keys: dict[tuple[ProgramLayout, StateIndex], int] = {}
    member_lane, compiled = [], []
    for member in bucket.members:
        source = member.plan.model()
        program = compile_program(member.plan, source)
        index = remap_index(program.index, source, member.model, member.padded.names)
        lane = keys.setdefault((program.layout, index), len(keys))
        member_lane.append(lane)
        compiled.append(program.params)
    lanes = []
    for (layout, index), lane in keys.items():
        own = [k for k, l in enumerate(member_lane) if l == lane]
        rows = [compiled[k] if member_lane[k] == lane else compiled[own[0]] for k in range(len(compiled))]
        lanes.append(Lane(layout, index, stack_params(rows)))
    return BucketPrograms(tuple(lanes), np.asarray(member_lane, np.int32))


def select_lanes(xp: Any, lane: Array, outputs: Sequence[ProgramOutput]) -> dict[str, Array]:
    """Each environment's outputs from its lane (`lane` int [B]): success [B], score [B], stage_step [B, S] and
    terms [B, T], padded to the widest lane (-1: stage never reached; False: no such term)."""
    stages = max(o.stage_step.shape[-1] for o in outputs)
    terms = max(o.terms.shape[-1] for o in outputs)

    def widen(a: Array, width: int, fill: Any) -> Array:
        pad = xp.full(a.shape[:-1] + (width - a.shape[-1],), fill, dtype=a.dtype)
        return xp.concatenate([a, pad], axis=-1)

    first = outputs[0]
    out = {"success": first.success, "score": first.score, "stage_step": widen(first.stage_step, stages, -1),
           "terms": widen(first.terms, terms, False)}
    for k, o in enumerate(outputs[1:], start=1):
        here = lane == k
        out = {"success": xp.where(here, o.success, out["success"]),
               "score": xp.where(here, o.score, out["score"]),
               "stage_step": xp.where(here[:, None], widen(o.stage_step, stages, -1), out["stage_step"]),
               "terms": xp.where(here[:, None], widen(o.terms, terms, False), out["terms"])}
    return out
