"""Quaternion and rotation-matrix maths over an array namespace, batched over leading axes.

Every function takes `xp` (numpy or jax.numpy) first and uses only operations both provide, without in-place
writes, so the CPU backend (NumPy) and the MJX backend (JAX, under jit and vmap) share one definition.
Quaternions are MuJoCo's `[w, x, y, z]`; matrices act on column vectors (world = R @ local), as `xmat`.
"""

from __future__ import annotations

from typing import Any

Array = Any


def quat_normalize(xp: Any, q: Array, eps: float = 1e-12) -> Array:
    """Unit quaternion with w >= 0 (the same rotation, one sign, so differences are well defined)."""
    q = q / xp.maximum(xp.linalg.norm(q, axis=-1, keepdims=True), eps)
    return q * xp.where(q[..., :1] < 0, -1.0, 1.0)


def quat_mul(xp: Any, a: Array, b: Array) -> Array:
    """Hamilton product a * b (apply b, then a)."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return xp.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


def quat_to_mat(xp: Any, q: Array) -> Array:
    """[..., 4] unit quaternion -> [..., 3, 3] rotation matrix."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def mat_to_quat(xp: Any, m: Array) -> Array:
    """[..., 3, 3] rotation matrix -> [..., 4] unit quaternion (w >= 0).

    Branch-free (Shepperd's method evaluated for all four pivots, the best-conditioned one selected with
    `where`), so it traces under jit and is exact near 180 degree rotations too.
    """
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    candidates = xp.stack([
        xp.stack([1 + m00 + m11 + m22, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                  m[..., 1, 0] - m[..., 0, 1]], axis=-1),
        xp.stack([m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0],
                  m[..., 0, 2] + m[..., 2, 0]], axis=-1),
        xp.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22,
                  m[..., 1, 2] + m[..., 2, 1]], axis=-1),
        xp.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1],
                  1 - m00 - m11 + m22], axis=-1),
    ], axis=-2)  # [..., 4 pivots, 4]
    pivot = xp.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22],
                     axis=-1)
    best = xp.argmax(pivot, axis=-1)
    onehot = (xp.arange(4) == best[..., None]).astype(m.dtype)
    q = xp.sum(candidates * onehot[..., :, None], axis=-2)
    return quat_normalize(xp, q)


def rotation_error(xp: Any, current: Array, target: Array) -> Array:
    """Rotation vector (axis * angle, world frame) taking `current` to `target`, both [..., 3, 3].

    Uses the quaternion of R_target R_current^T, whose vector part times 2 is the small-angle error and whose
    full angle is recovered with atan2, so IK converges from large orientation errors as well.
    """
    q = mat_to_quat(xp, target @ xp.swapaxes(current, -1, -2))
    vec = q[..., 1:]
    s = xp.linalg.norm(vec, axis=-1, keepdims=True)
    angle = 2.0 * xp.arctan2(s, q[..., :1])
    return vec * xp.where(s > 1e-9, angle / xp.maximum(s, 1e-9), 2.0)


def yaw_of(xp: Any, m: Array) -> Array:
    """Heading of a frame about world z: the angle of its x axis projected on the ground plane."""
    return xp.arctan2(m[..., 1, 0], m[..., 0, 0])


def wrap_angle(xp: Any, a: Array) -> Array:
    """Angle difference wrapped to [-pi, pi]."""
    return xp.arctan2(xp.sin(a), xp.cos(a))
