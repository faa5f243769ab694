"""Small frame and shape computations the robot emitter needs, kept free of MuJoCo so they are easy to test.

Robot specs describe cameras by a position and a target and the gripper by two axes, because those are the
figures a person can read off a drawing; MuJoCo wants quaternions. Link masses are given per link and spread over
the link's primitives by volume, which needs the primitives' volumes.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

Vec = Sequence[float]


def unit(v: Vec) -> np.ndarray:
    """`v` scaled to length 1; a zero vector is an error in the spec, not something to guess around."""
    a = np.asarray(v, dtype=float)
    n = float(np.linalg.norm(a))
    if n < 1e-12:
        raise ValueError(f"zero-length direction {list(v)}")
    return a / n


def mat_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion [w, x, y, z] with w >= 0 (Shepperd's method, stable near 180 deg)."""
    m = np.asarray(r, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    qa = np.asarray(q)
    qa = qa / np.linalg.norm(qa)
    return -qa if qa[0] < 0 else qa


def frame_from_axes(x_axis: Vec, y_axis: Vec) -> np.ndarray:
    """Quaternion of the frame whose x and y axes are the given directions (z = x cross y).

    The gripper's tool frame is written as approach (x) and opening direction (y); they must be perpendicular,
    since silently orthogonalising would move the tool frame away from what the spec says.
    """
    x = unit(x_axis)
    y = unit(y_axis)
    if abs(float(x @ y)) > 1e-3:
        raise ValueError(f"gripper approach {list(x_axis)} and axis {list(y_axis)} are not perpendicular")
    y = unit(y - (x @ y) * x)
    return mat_to_quat(np.column_stack([x, y, np.cross(x, y)]))


def look_at_quat(pos: Vec, target: Vec, up: Vec = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Quaternion of a MuJoCo camera at `pos` looking at `target` with image up towards `up`.

    A MuJoCo camera looks along its frame's -z with +y up in the image.
    """
    forward = unit(np.asarray(target, dtype=float) - np.asarray(pos, dtype=float))
    right = np.cross(forward, unit(up))
    if np.linalg.norm(right) < 1e-6:
        raise ValueError(f"camera at {list(pos)} looks straight along the up direction; move pos or target")
    right = unit(right)
    cam_up = np.cross(right, forward)
    return mat_to_quat(np.column_stack([right, cam_up, -forward]))


def primitive_volume(geom: dict) -> float:
    """Volume of a spec primitive (capsule, box or sphere), used to spread a link's mass over its geoms."""
    kind = geom["type"]
    if kind == "sphere":
        return 4.0 / 3.0 * np.pi * geom["radius"] ** 3
    if kind == "box":
        sx, sy, sz = geom["size"]
        return 8.0 * sx * sy * sz
    if kind == "capsule":
        r = geom["radius"]
        length = float(np.linalg.norm(np.subtract(geom["to"], geom["from"])))
        return np.pi * r * r * length + 4.0 / 3.0 * np.pi * r**3
    raise ValueError(f"unknown primitive type {kind!r}")
