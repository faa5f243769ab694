"""Action modes, clipping with counts, non-finite detection and damped-least-squares IK, over an array namespace.

Layouts (DESIGN section 4, xpolicylab.embodiments), per environment, for two arms of J joints each:
- `joint`, D = 2 (J + 1): `[left j1..jJ, left gripper, right j1..jJ, right gripper]`, radians, grippers
  0 (closed) .. 1 (open).
- `ee`, D = 16: per arm `[x, y, z, qw, qx, qy, qz, gripper]`, the end-effector site's pose in that arm's base
  frame (metres), the same frame as the observation's `ee_pose`.
- `delta_joint`: joint offsets added to the measured joint positions; grippers absolute.
- `delta_ee`: per arm `[dx, dy, dz, dqw, dqx, dqy, dqz, gripper]`: a translation added to the measured ee
  position and a rotation applied to the measured orientation (q_target = dq * q_now), base frame; gripper
  absolute.

Every function takes `xp` (numpy or jax.numpy) first, is branch-free and batched over the leading axis N, so the
MJX backend reuses it under jit with `jnp`. `solve_ik` takes the forward kinematics as a callback: the CPU
backend passes MuJoCo's (`dojo.backends.mujoco.kinematics`), the MJX backend its own.

Limits: arm joints to their ranges, grippers to [0, 1], ee positions to a box of +-`reach` in the base frame,
a quaternion of zero length to the measured orientation. Each clipped element counts one (`clipped` [N]).
A row with any non-finite value is reported by `nonfinite` (the backend ends that episode) and treated as
all-zero here so that the rest of the batch is unaffected.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from dojo.backends.rotations import quat_mul, quat_normalize, quat_to_mat, rotation_error

Array = Any
ACTION_MODES = ("joint", "ee", "delta_joint", "delta_ee")
EE_PER_ARM = 8
IK_ITERATIONS = 20
IK_DAMPING = 0.05
IK_MAX_STEP = 0.4
"""Largest joint change (rad) of one IK iteration: keeps DLS from overshooting far from the solution."""
IK_ROT_WEIGHT = 0.3
"""Metres of position error that weigh as much as one radian of orientation error."""
IK_TOLERANCE = 1e-4
"""Early-exit tolerance of the CPU backend's IK: 0.1 mm, or 0.02 degrees of orientation."""


@dataclass(frozen=True)
class ArmLimits:
    """Limits of the two arms: joint ranges [2, J], gripper width at 1.0, ee reach (box half size, metres)."""

    joint_lo: np.ndarray
    joint_hi: np.ndarray
    max_width: float
    reach: float = 1.0

    @property
    def joints_per_arm(self) -> int:
        return int(self.joint_lo.shape[-1])


def action_dim(mode: str, joints_per_arm: int = 6) -> int:
    """Width D of one action in `mode`."""
    if mode in ("joint", "delta_joint"):
        return 2 * (joints_per_arm + 1)
    if mode in ("ee", "delta_ee"):
        return 2 * EE_PER_ARM
    raise ValueError(f"unknown action mode {mode!r}; choose one of {ACTION_MODES}")


def nonfinite(xp: Any, actions: Array) -> Array:
    """bool[N]: rows with a NaN or an infinity."""
    return ~xp.all(xp.isfinite(actions), axis=-1)


def clip_counted(xp: Any, x: Array, lo: Any, hi: Any) -> tuple[Array, Array]:
    """x clipped to [lo, hi] and, per row, how many elements were outside (x [N, ...])."""
    out = (x < lo) | (x > hi)
    count = xp.sum(xp.reshape(out, (x.shape[0], -1)), axis=-1).astype(xp.int32)
    return xp.clip(x, lo, hi), count


def _finite_or_zero(xp: Any, actions: Array) -> Array:
    """Rows with a non-finite value replaced by zeros (the backend ends those episodes and must not apply
    them; zeros keep NaNs out of batched maths such as IK solves over the whole batch)."""
    return xp.where(nonfinite(xp, actions)[:, None], 0.0, actions)


def joint_targets(xp: Any, actions: Array, q_now: Array, limits: ArmLimits, delta: bool
                  ) -> tuple[Array, Array, Array]:
    """`joint` / `delta_joint` actions [N, 2(J+1)] -> arm joint targets [N, 2, J], grippers [N, 2] (0..1) and
    clipped counts [N]. `q_now` [N, 2, J] are the measured arm joints (for deltas)."""
    n, j = actions.shape[0], limits.joints_per_arm
    a = xp.reshape(_finite_or_zero(xp, actions), (n, 2, j + 1))
    q = a[..., :j] + (q_now if delta else 0.0)
    q, c1 = clip_counted(xp, q, limits.joint_lo, limits.joint_hi)
    grip, c2 = clip_counted(xp, a[..., j], 0.0, 1.0)
    return q, grip, c1 + c2


def ee_targets(xp: Any, actions: Array, pos_now: Array, quat_now: Array, limits: ArmLimits, delta: bool
               ) -> tuple[Array, Array, Array, Array]:
    """`ee` / `delta_ee` actions [N, 16] -> target positions [N, 2, 3] and rotations [N, 2, 3, 3] in the base
    frames, grippers [N, 2] and clipped counts [N]. `pos_now`, `quat_now` [N, 2, 3|4]: measured ee poses."""
    n = actions.shape[0]
    a = xp.reshape(_finite_or_zero(xp, actions), (n, 2, EE_PER_ARM))
    pos = a[..., :3] + (pos_now if delta else 0.0)
    pos, c1 = clip_counted(xp, pos, -limits.reach, limits.reach)
    quat = a[..., 3:7]
    degenerate = xp.linalg.norm(quat, axis=-1) < 1e-6
    quat = quat_normalize(xp, xp.where(degenerate[..., None], xp.asarray([1.0, 0.0, 0.0, 0.0]), quat))
    quat = quat_mul(xp, quat, quat_now) if delta else xp.where(degenerate[..., None], quat_now, quat)
    grip, c2 = clip_counted(xp, a[..., 7], 0.0, 1.0)
    c3 = xp.sum(degenerate, axis=-1).astype(xp.int32)
    return pos, quat_to_mat(xp, quat_normalize(xp, quat)), grip, c1 + c2 + c3


def to_ctrl(xp: Any, q: Array, grip: Array, max_width: float) -> Array:
    """Arm joint targets [N, 2, J] and grippers [N, 2] (0..1) -> actuator controls [N, 2(J+1)] in the robot's
    actuator order (joint servos in radians, gripper servos in metres of opening)."""
    width = xp.clip(grip, 0.0, 1.0) * max_width
    return xp.reshape(xp.concatenate([q, width[..., None]], axis=-1), (q.shape[0], -1))


def pose_error(xp: Any, pos: Array, mat: Array, target_pos: Array, target_mat: Array) -> Array:
    """[M, 6] error (target - current): position, then rotation vector scaled by IK_ROT_WEIGHT."""
    return xp.concatenate([target_pos - pos, IK_ROT_WEIGHT * rotation_error(xp, mat, target_mat)], axis=-1)


def dls_step(xp: Any, jac: Array, err: Array, damping: float = IK_DAMPING) -> Array:
    """Damped least squares dq = J^T (J J^T + lambda^2 I)^-1 err for jac [M, 6, K] (rotation rows already
    weighted like `pose_error`), err [M, 6]; each dq scaled down to at most IK_MAX_STEP."""
    jjt = jac @ xp.swapaxes(jac, -1, -2) + (damping ** 2) * xp.eye(6, dtype=jac.dtype)
    dq = xp.einsum("mki,mk->mi", jac, xp.linalg.solve(jjt, err[..., None])[..., 0])
    biggest = xp.max(xp.abs(dq), axis=-1, keepdims=True)
    return dq * xp.minimum(1.0, IK_MAX_STEP / xp.maximum(biggest, 1e-12))


FK = Callable[[Array], tuple[Array, Array, Array]]
"""fk(q [M, K]) -> (ee position [M, 3], ee rotation [M, 3, 3], Jacobian [M, 6, K] with translational rows
first, rotational rows second), all in one frame (the same as the targets)."""


def solve_ik(xp: Any, fk: FK, q0: Array, target_pos: Array, target_mat: Array, lo: Array, hi: Array,
             iterations: int = IK_ITERATIONS, tol: float | None = None) -> Array:
    """Joint positions [M, K] reaching the target poses, from q0, staying within [lo, hi].

    At most `iterations` DLS steps; unreachable targets give the closest pose DLS finds, never an error.
    `tol` (NumPy callers only) stops early once every weighted pose error is below it; leave it None under
    jit, where the loop must have a fixed length.
    """
    q = q0
    for _ in range(iterations):
        q, err = ik_iteration(xp, fk, q, target_pos, target_mat, lo, hi)
        if tol is not None and float(xp.max(xp.abs(err))) < tol:
            break
    return q


def ik_iteration(xp: Any, fk: FK, q: Array, target_pos: Array, target_mat: Array, lo: Array, hi: Array
                 ) -> tuple[Array, Array]:
    """One DLS step of `solve_ik` from q: (the next q within [lo, hi], the weighted pose error at q). Jitted
    callers run it in their own fixed-length loop (`jax.lax.fori_loop`), which compiles one step, not N."""
    weight = xp.asarray([1.0, 1.0, 1.0, IK_ROT_WEIGHT, IK_ROT_WEIGHT, IK_ROT_WEIGHT])
    pos, mat, jac = fk(q)
    err = pose_error(xp, pos, mat, target_pos, target_mat)
    return xp.clip(q + dls_step(xp, jac * weight[:, None], err), lo, hi), err
