"""Buckets rounded up to a common count of degrees of freedom, so that MuJoCo Warp compiles its per-DoF kernels once
for several of them. An experiment of the benchmarks (`dojo bench sim|kernels dof_quantum=Q`), not yet a backend
setting: what it saves in compilation and costs at run time is measured there first.

Why. MuJoCo Warp generates its solver's kernels for a model's exact DoF count (`_solve_init_jaref_kernel`, the
Cholesky factorisations, `_linesearch_jv_fused`, the dense JTDAJ update): the 24 simulation tasks' 29 buckets
have 13 distinct counts and need 96 Warp modules on an empty kernel cache (`dojo bench kernels`), about 1.5 s of
compilation each on an H100 machine, one after another. With every count rounded up to a multiple of 16 they
need 76.

How. Each member's padded model gets the missing DoFs as bodies of one slide joint each, appended after the scene's
own top-level bodies (so every existing body, joint and address keeps its index) and parked far from it: no geom,
so nothing collides; a unit mass; the joint along x, so gravity never moves it. They start and stay at rest, and
the scene's own DoFs move as they would without them (tested on CPU MuJoCo). The price is a larger model at run
time: the mass matrix, the Jacobian's columns and the solver's factorisation grow with the DoF count (cubically
for a dense Cholesky), which is what `dojo bench sim dof_quantum=Q` measures beside the separate buckets.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from dojo.backends.mjx.bucket import Bucket, Member

PAD_ORIGIN = (-50.0, -50.0, 20.0)
"""Where the padding bodies sit (far from the scene, and from the parked slots of `pad.PARK_ORIGIN`)."""
PAD_SPACING = 1.0


def rounded_dofs(nv: int, quantum: int) -> int:
    """`nv` rounded up to a multiple of `quantum` (itself for a quantum of 1 or less)."""
    return -(-nv // quantum) * quantum if quantum > 1 else nv


def padding_bodies(count: int) -> str:
    """MJCF of `count` bodies of one slide joint each, in a row from PAD_ORIGIN."""
    x, y, z = PAD_ORIGIN
    return "".join(
        f'<body name="dof_padding{k}" pos="{x + PAD_SPACING * k} {y} {z}">'
        f'<joint name="dof_padding{k}" type="slide" axis="1 0 0"/>'
        f'<inertial pos="0 0 0" mass="1" diaginertia="1 1 1"/></body>' for k in range(count))


def _with_padding(member: Member, count: int) -> Member:
    xml = member.padded.xml
    end = xml.rindex("</worldbody>")
    xml = xml[:end] + padding_bodies(count) + xml[end:]
    model = mujoco.MjModel.from_xml_string(xml)
    if model.nv != member.model.nv + count or model.nq != member.model.nq + count:
        raise ValueError(f"padding {member.plan.hash[:12]} with {count} DoFs gave nv {model.nv}, nq {model.nq}")
    return Member(dataclasses.replace(member.padded, xml=xml), model,
                  np.concatenate([member.qpos, model.qpos0[-count:]]), np.concatenate([member.qvel, np.zeros(count)]),
                  member.ctrl)


def round_bucket(bucket: Bucket, quantum: int) -> Bucket:
    """`bucket` with its DoF count rounded up to a multiple of `quantum` (the bucket itself if it is one)."""
    count = rounded_dofs(bucket.model.nv, quantum) - bucket.model.nv
    if count == 0:
        return bucket
    return Bucket(f"{bucket.key}:nv{bucket.model.nv + count}", [_with_padding(m, count) for m in bucket.members],
                  bucket.varying)
