"""Rest poses: how an object lies on its support before its yaw is applied (task schema, object `rest`).

An object stands on its asset frame's bottom by default (`upright`). `side` lays it on its side: turned 90
degrees about its own y axis, so its up axis points along world +x before the yaw turns it about world z. The
sampler places the turned object with the centre of its footprint on the sampled point and its lowest point on
the support, and the emitter gives its body the same rotation; the settle step then lets it come to rest there.
A quarter turn maps the asset's axis-aligned box onto an axis-aligned box, so the turned box is exact.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

REST_POSES = ("upright", "side")
_SIDE = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # 90 degrees about y: up becomes +x


def rest_quat(rest: str, yaw_deg: float) -> list[float]:
    """The body orientation [w, x, y, z]: the rest pose, then the yaw about world z."""
    half = math.radians(yaw_deg) / 2
    yaw = [math.cos(half), 0.0, 0.0, math.sin(half)]
    if _check(rest) == "upright":
        return yaw
    tilt = [math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0]  # `_SIDE` as a quaternion
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.array(yaw), np.array(tilt))
    return [float(q) for q in out]


def rested_box(rest: str, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(anchor, lo, hi) of an asset box (lo, hi in its own frame) in its rest pose, before yaw: lo and hi bound the
    turned box, and the anchor is the point of it that goes on the sampled footprint centre at support height,
    given relative to the object's frame origin. An upright object keeps its frame origin as the anchor (the
    asset convention puts it at the bottom centre of its footprint); a lying one is anchored at the centre of
    its turned footprint, on its lowest point."""
    if _check(rest) == "upright":
        return np.zeros(3), lo, hi
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    turned = corners @ _SIDE.T
    t_lo, t_hi = turned.min(axis=0), turned.max(axis=0)
    return np.array([(t_lo[0] + t_hi[0]) / 2, (t_lo[1] + t_hi[1]) / 2, t_lo[2]]), t_lo, t_hi


def _check(rest: str) -> str:
    if rest not in REST_POSES:
        raise ValueError(f"unknown rest pose {rest!r}; one of {', '.join(REST_POSES)}")
    return rest
