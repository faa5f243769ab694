"""What the scripted experts know about a scene: object boxes, annotation sites, regions and targets.

Everything is read from an MjData holding the simulator state (the oracle's privileged copy), grounded in the
plan: object names -> bodies and geoms, `<object>/<annotation>` sites, regions on the table or on a fixture.
Boxes are computed from the collision geoms in the object's own frame, so they are right for any asset origin
and for clutter assets that carry no annotation beyond `top`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from dojo.compiler.robot_emit import TABLE_TOP_Z

UPRIGHT = 0.99
"""A round geom whose axis has at least this vertical component stands upright (`Scene.upright_round`)."""


@dataclass(frozen=True)
class Box:
    """An object's collision box: world centre [3], rotation [3, 3] (world = rot @ local), half extents [3]."""

    center: np.ndarray
    rot: np.ndarray
    half: np.ndarray

    @property
    def top(self) -> float:
        return float(self.center[2] + np.abs(self.rot[2]) @ self.half)

    @property
    def bottom(self) -> float:
        return float(self.center[2] - np.abs(self.rot[2]) @ self.half)


@dataclass(frozen=True)
class Target:
    """Where to put something: a world point [3] on the support surface and, for containers and holes, the
    half extents of the placement box (zero for a surface)."""

    point: np.ndarray
    half: np.ndarray
    container: bool


class Scene:
    """Read-only views of one plan's objects in the state held by `data` (call after mj_forward)."""

    def __init__(self, plan: Any, model: mujoco.MjModel, data: mujoco.MjData,
                 shifts: dict[str, np.ndarray] | None = None) -> None:
        self.plan, self.model, self.data = plan, model, data
        self.shifts = dict(shifts or {})
        """World offsets of annotations (`object/annotation`) from where they are: where an expert believes them
        to be (the perturbed expert, `dojo.experts.perturbed`, aims its fits off by a few millimetres)."""
        self.table_z = TABLE_TOP_Z
        self._geoms = {name: [model.geom(g).id for g in obj["geoms"]] for name, obj in plan.objects.items()}
        self._initial_xy = self._initial_positions()

    def _initial_positions(self) -> dict[str, np.ndarray]:
        """Where each movable object started (the oracle returns objects to free spots of their region)."""
        out = {}
        for name, obj in self.plan.objects.items():
            if obj.get("free_joint"):
                adr = self.model.joint(obj["free_joint"]).qposadr[0]
                out[name] = np.asarray(self.plan.init_qpos[adr:adr + 2], dtype=float)
        return out

    def initial_xy(self, name: str) -> np.ndarray | None:
        return self._initial_xy.get(name)

    def body_pose(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        body = self.model.body(self.plan.objects[name]["body"]).id
        return self.data.xpos[body].copy(), self.data.xmat[body].reshape(3, 3).copy()

    def box(self, name: str) -> Box:
        """The object's collision geoms' bounding box in its root body frame, placed in the world."""
        pos, rot = self.body_pose(name)
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for g in self._geoms[name]:
            g_rot = self.data.geom_xmat[g].reshape(3, 3)
            centre = rot.T @ (self.data.geom_xpos[g] + g_rot @ self.model.geom_aabb[g, :3] - pos)
            half = np.abs(rot.T @ g_rot) @ self.model.geom_aabb[g, 3:]
            lo, hi = np.minimum(lo, centre - half), np.maximum(hi, centre + half)
        return Box(pos + rot @ ((lo + hi) / 2.0), rot, (hi - lo) / 2.0)

    def geom_boxes(self, name: str) -> list[Box]:
        """Each collision geom of the object as a world box (a container's floor, walls and handle)."""
        out = []
        for g in self._geoms[name]:
            g_rot = self.data.geom_xmat[g].reshape(3, 3)
            out.append(Box(self.data.geom_xpos[g] + g_rot @ self.model.geom_aabb[g, :3], g_rot.copy(),
                           self.model.geom_aabb[g, 3:].copy()))
        return out

    def width_through(self, name: str, point: np.ndarray, axis: np.ndarray) -> float:
        """How wide the object is along the horizontal unit `axis` where a vertical line through `point` meets
        it: the widest of its collision geoms that line passes through (a T gripped on its stem is as wide as
        the stem), or its whole box when the line misses every geom."""
        widths = []
        for g in self._geoms[name]:
            g_rot = self.data.geom_xmat[g].reshape(3, 3)
            centre = self.data.geom_xpos[g] + g_rot @ self.model.geom_aabb[g, :3]
            half = self.model.geom_aabb[g, 3:]
            if _vertical_line_meets(point, centre, g_rot, half):
                widths.append(2.0 * float(np.abs(g_rot.T @ axis) @ half))
        if not widths:
            box = self.box(name)
            return 2.0 * float(np.abs(box.rot.T @ axis) @ box.half)
        return max(widths)

    def floor_under(self, name: str, point: np.ndarray) -> float:
        """The highest top, below `point`, of the object's collision geoms that the vertical line through `point`
        meets: what an object put down through an opening of `name` at `point` comes to rest on (a rack's base
        under its hole, a coin bank's floor under its slot); the table if none."""
        tops = [self.table_z]
        for b in self.geom_boxes(name):
            top = float(b.center[2] + np.abs(b.rot[2]) @ b.half)
            if top <= point[2] and _vertical_line_meets(point, b.center, b.rot, b.half):
                tops.append(top)
        return max(tops)

    def upright_round(self, name: str) -> bool:
        """Whether every collision geom of the object is a sphere, or a cylinder or capsule standing upright (a
        test tube, a can): fingers grip it alike across any horizontal axis."""
        sphere, upright = int(mujoco.mjtGeom.mjGEOM_SPHERE), (int(mujoco.mjtGeom.mjGEOM_CAPSULE),
                                                               int(mujoco.mjtGeom.mjGEOM_CYLINDER))
        return all(int(self.model.geom_type[g]) == sphere or (
            int(self.model.geom_type[g]) in upright and abs(float(self.data.geom_xmat[g][8])) > UPRIGHT)
            for g in self._geoms[name])

    def has_site(self, name: str, annotation: str) -> bool:
        return annotation in self.plan.objects[name]["sites"]

    def site(self, name: str, annotation: str) -> Box:
        """An annotation as a box: site position, rotation and size (a point annotation has zero size)."""
        sid = self.model.site(self.plan.objects[name]["sites"][annotation]).id
        size = self.model.site_size[sid].copy()
        if self.model.site_type[sid] != mujoco.mjtGeom.mjGEOM_BOX:
            size = np.zeros(3)
        centre = self.data.site_xpos[sid] + self.shifts.get(f"{name}/{annotation}", 0.0)
        return Box(centre, self.data.site_xmat[sid].reshape(3, 3).copy(), size)

    def others(self, exclude: tuple[str, ...]) -> list[str]:
        return [n for n in self.plan.objects if n not in exclude]

    def highest_top(self, exclude: tuple[str, ...], near: np.ndarray, radius: float) -> float:
        """The highest object top within `radius` (planar) of `near`, or the table: what a transfer clears."""
        tops = [self.table_z]
        for name in self.others(exclude):
            box = self.box(name)
            if np.linalg.norm(box.center[:2] - near[:2]) <= radius + float(np.max(box.half[:2])):
                tops.append(box.top)
        return max(tops)

    def target(self, ref: str) -> Target:
        """The place a skill's `target` names: an annotation (`obj/name`), an object's top, or a region."""
        if "/" in ref:
            obj, annotation = ref.split("/", 1)
            site = self.site(obj, annotation)
            if np.any(site.half > 0):
                return Target(site.center - np.array([0.0, 0.0, site.half[2]]), site.half, True)
            return Target(site.center, site.half, False)
        if ref in self.plan.objects:
            if self.has_site(ref, "top"):
                return Target(self.site(ref, "top").center, np.zeros(3), False)
            box = self.box(ref)
            return Target(np.array([*box.center[:2], box.top]), np.zeros(3), False)
        region = self.plan.regions[ref]
        z = self.table_z
        if region.get("on"):
            z = self.target(region["on"]).point[2]
        return Target(np.array([*region["center"], z]), np.array([*np.asarray(region["size"]) / 2.0, 0.0]), False)

    def region_spot(self, ref: str, name: str, clearance: float) -> np.ndarray:
        """A point of region `ref` for object `name`: where it started if that lies in the region and is free,
        else the free grid point of the region farthest from every other object."""
        target = self.target(ref)
        centre, half = target.point, target.half
        others = [self.box(n) for n in self.others((name,)) if not self.plan.objects[n]["fixed"]]
        start = self.initial_xy(name)

        def gap(xy: np.ndarray) -> float:
            return min((float(np.linalg.norm(xy - b.center[:2])) for b in others), default=np.inf)

        if start is not None and np.all(np.abs(start - centre[:2]) <= half[:2]) and gap(start) >= clearance:
            return np.array([*start, centre[2]])
        grid = [centre[:2] + half[:2] * np.array([u, v]) for u in np.linspace(-0.8, 0.8, 9)
                for v in np.linspace(-0.8, 0.8, 5)]
        best = max(grid, key=gap)
        return np.array([*best, centre[2]])


def _vertical_line_meets(point: np.ndarray, centre: np.ndarray, rot: np.ndarray, half: np.ndarray) -> bool:
    """Whether the vertical line through `point` passes through the box (centre, rot, half): the line's
    parameter intervals inside each slab of the box overlap."""
    a = rot.T @ (np.asarray(point, dtype=float) - centre)
    b = rot[2]  # rot.T @ world z
    lo, hi = -np.inf, np.inf
    for i in range(3):
        if abs(b[i]) < 1e-9:
            if abs(a[i]) > half[i]:
                return False
            continue
        t0, t1 = sorted(((-half[i] - a[i]) / b[i], (half[i] - a[i]) / b[i]))
        lo, hi = max(lo, t0), min(hi, t1)
    return lo <= hi
