"""Where a joint target would put the robot: world-frame bounding boxes of its collision geometry, by FK.

The safety layer asks this before a command is sent: the robot's MuJoCo model (the compiler's primitives,
the same geometry that collides in simulation) is posed at the target on a private MjData, and every geom of
the moving links (everything below each arm's base, fingers included, at the commanded opening) is bounded by
an axis-aligned box. The checks are on those boxes: the lowest point against the table plane, all of them
against the workspace box. The fixed bases are left out: they are mounted on the table. The two arms against
each other: the pairs of left- and right-arm geoms whose boxes come close are measured exactly (MuJoCo's
`mj_geomDistance`, the same primitives), so that a target crossing the arms is refused before it is sent.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import mujoco
import numpy as np

from dojo.backends.mujoco.kinematics import RobotIndex


class RobotGeometry:
    """Forward kinematics of the robot's collision geometry on a private copy of the model's data."""

    def __init__(self, model: mujoco.MjModel, robot: Mapping[str, Any]) -> None:
        self.model, self.data = model, mujoco.MjData(model)
        self.index = RobotIndex.build(model, robot)
        bases = set(self.index.bases.tolist())
        body = model.geom_bodyid
        moving = [g for g in range(model.ngeom)
                  if model.body_rootid[body[g]] in bases and body[g] not in bases]
        self.geoms = np.asarray(moving, dtype=int)
        base_list = self.index.bases.tolist()
        self.arm = np.asarray([base_list.index(model.body_rootid[body[g]]) for g in moving], dtype=int)
        """Which arm (0 left, 1 right) each of `geoms` belongs to."""
        self._finger_adr = np.asarray([[model.joint(j).qposadr[0] for j in pair] for pair in robot["finger_joints"]])
        self.max_width = float(robot["gripper_max_width"])

    def boxes(self, joint_pos: np.ndarray, gripper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-frame (lower, upper) corners [G, 3] of every moving robot geom with the arms at `joint_pos`
        [2, J] and the grippers at `gripper` [2] (0..1)."""
        m, d = self.model, self.data
        d.qpos[self.index.qpos_adr] = joint_pos
        d.qpos[self._finger_adr] = (np.clip(gripper, 0.0, 1.0) * self.max_width / 2.0)[:, None]
        mujoco.mj_kinematics(m, d)
        g = self.geoms
        center = d.geom_xpos[g]
        rot = d.geom_xmat[g].reshape(-1, 3, 3)
        size = m.geom_size[g]
        kind = m.geom_type[g]
        half = np.empty_like(center)
        box = kind == mujoco.mjtGeom.mjGEOM_BOX
        half[box] = np.einsum("gij,gj->gi", np.abs(rot[box]), size[box])
        sphere = kind == mujoco.mjtGeom.mjGEOM_SPHERE
        half[sphere] = size[sphere, :1]
        capsule = kind == mujoco.mjtGeom.mjGEOM_CAPSULE
        half[capsule] = np.abs(rot[capsule][:, :, 2]) * size[capsule, 1:2] + size[capsule, :1]
        other = ~(box | sphere | capsule)
        half[other] = m.geom_rbound[g][other][:, None]
        return center - half, center + half

    def arms_gap(self, lo: np.ndarray, hi: np.ndarray, within: float) -> float:
        """The smallest distance between the left and the right arm's geoms (negative: they overlap), as posed
        by the last `boxes()` call, whose corners `lo`, `hi` are given; `within` when no two geoms' boxes are
        that close (only those pairs are measured)."""
        left, right = np.flatnonzero(self.arm == 0), np.flatnonzero(self.arm == 1)
        gap = np.maximum(lo[left, None, :] - hi[None, right, :], lo[None, right, :] - hi[left, None, :]).max(axis=2)
        best, fromto = within, np.zeros(6)
        for i, j in zip(*np.nonzero(gap < within)):
            distance = mujoco.mj_geomDistance(self.model, self.data, int(self.geoms[left[i]]),
                                              int(self.geoms[right[j]]), within, fromto)
            best = min(best, float(distance))
        return best
