"""Parity of `mjx` against `mujoco`: the same plans, the same controls, states compared step by step.

Both sides start from each plan's initial state and receive, every control step, the plan's initial controls
with a +-`swing` rad offset on the arm joints alternating every step (arms move, servos and contacts work). The
MuJoCo side steps the plan's own model in float64; the MJX side steps the plan inside its (padded) bucket with
`Engine`, in float32, all plans in one batch. After each control step the MJX state is mapped back to the plan's
layout and compared: the largest position difference of any joint (radians or metres; free joints by their
position part) and, for each free body, its position. A plan passes while its largest difference stays within
`tolerance` for the whole run. `format_table` prints the rows as the agreement table.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Sequence

import jax
import mujoco
import numpy as np

from dojo.backends.mjx.backend import PlanLayout
from dojo.backends.mjx.batch import Engine
from dojo.backends.mjx.bucket import make_buckets

DEFAULT_TOLERANCE = 0.01
"""1 cm / 0.01 rad: float32 MJX against float64 MuJoCo drifts at the 1e-4 level over a few seconds of servoing;
contact-rich moments (a gripper closing on an object) can leave it sooner, which is what the table shows."""


@dataclass
class ParityRow:
    """One plan's agreement: worst joint-position difference, worst free-body position difference, and the
    first control step at which the tolerance was exceeded (None = never)."""

    task: str
    setting: str
    seed: int
    steps: int
    max_joint_err: float
    max_body_err: float
    first_exceeded: int | None
    ok: bool


def _swing(model: mujoco.MjModel, plan: Any, swing: float) -> np.ndarray:
    grippers = set(plan.robot.get("gripper_actuators", ()))
    return np.asarray([0.0 if mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) in grippers else swing
                       for a in range(model.nu)])


def parity_report(plans: Sequence[Any], steps: int, tolerance: float = DEFAULT_TOLERANCE, swing: float = 0.1,
                  impl: str = "jax") -> list[ParityRow]:
    """Run every plan `steps` control steps on both backends and return one row per plan (input order)."""
    buckets = make_buckets(plans)
    where = {m.plan.hash: (k, i) for k, b in enumerate(buckets) for i, m in enumerate(b.members)}
    layouts = {m.plan.hash: PlanLayout.build(m.model, m.plan.model(), m.padded.names) for b in buckets for m in b.members}
    sizes = [len(b.members) for b in buckets]
    engine = Engine(buckets, sizes, impl)
    members = [np.arange(n, dtype=np.int32) for n in sizes]
    base = [np.stack([m.ctrl for m in b.members]).astype(np.float32) for b in buckets]
    offsets = [np.stack([_swing(m.model, m.plan, swing) for m in b.members]).astype(np.float32) for b in buckets]
    engine.tick(members, [np.ones(n, bool) for n in sizes], [np.zeros(n, bool) for n in sizes], base)
    cpu = []
    for plan in plans:
        model = plan.model()
        cpu.append((model, plan.initial_data(model), _swing(model, plan, swing)))
    joint_err = np.zeros(len(plans))
    body_err = np.zeros(len(plans))
    first: list[int | None] = [None] * len(plans)
    for t in range(1, steps + 1):
        sign = 1.0 if t % 2 else -1.0
        engine.tick(members, [np.zeros(n, bool) for n in sizes], [np.ones(n, bool) for n in sizes],
                    [b + sign * o for b, o in zip(base, offsets)])
        qpos = [np.asarray(q) for q in jax.device_get(tuple(d.qpos for d in engine.data))]
        for p, plan in enumerate(plans):
            model, data, offset = cpu[p]
            data.ctrl[:] = np.asarray(plan.init_ctrl) + sign * offset
            mujoco.mj_step(model, data, nstep=plan.n_substeps)
            k, i = where[plan.hash]
            q = layouts[plan.hash].qpos(qpos[k][i])
            j_err, b_err = _errors(model, q, data.qpos)
            joint_err[p], body_err[p] = max(joint_err[p], j_err), max(body_err[p], b_err)
            if first[p] is None and max(j_err, b_err) > tolerance:
                first[p] = t
    return [ParityRow(plan.task, plan.setting, plan.seed, steps, float(joint_err[p]), float(body_err[p]), first[p],
                      first[p] is None) for p, plan in enumerate(plans)]


def _errors(model: mujoco.MjModel, q: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """Largest hinge/slide difference and largest free-body position difference."""
    joint, body = 0.0, 0.0
    for j in range(model.njnt):
        a = model.jnt_qposadr[j]
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            body = max(body, float(np.abs(q[a:a + 3] - ref[a:a + 3]).max()))
        elif model.jnt_type[j] in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            joint = max(joint, float(abs(q[a] - ref[a])))
    return joint, body


def format_table(rows: Sequence[ParityRow], tolerance: float = DEFAULT_TOLERANCE) -> str:
    """The agreement table: one line per plan and a summary line."""
    head = f"{'task':24} {'setting':9} {'seed':>5} {'steps':>5} {'joint err':>10} {'body err':>10} {'exceeded':>8}  ok"
    lines = [head, "-" * len(head)]
    for r in rows:
        exceeded = "-" if r.first_exceeded is None else str(r.first_exceeded)
        lines.append(f"{r.task:24} {r.setting:9} {r.seed:5d} {r.steps:5d} {r.max_joint_err:10.2e} "
                     f"{r.max_body_err:10.2e} {exceeded:>8}  {'yes' if r.ok else 'NO'}")
    passed = sum(r.ok for r in rows)
    lines.append(f"{passed}/{len(rows)} plans within {tolerance:g} for the whole run "
                 f"({100.0 * passed / max(1, len(rows)):.1f}%)")
    return "\n".join(lines)


def rows_as_dicts(rows: Sequence[ParityRow]) -> list[dict[str, Any]]:
    return [asdict(r) for r in rows]
