"""Lay assets out side by side on the standard table, for the library's sanity checks and for looking at them.

The layout is a plain shelf packing of the assets' footprints (``asset_bounds``), so a batch of assets can be
simulated or rendered together without touching each other. This is not the task sampler (which places objects
by task constraints); it only serves validation and inspection.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import mujoco
import numpy as np

from dojo.compiler.asset_emit import AssetHandles, add_asset
from dojo.compiler.asset_geometry import asset_bounds

TABLE_TOP_Z = 0.75
TABLE_HALF_XY = (0.6, 0.4)
DROP_CLEARANCE = 0.002
"""Free objects start this far above the table so they do not begin in contact."""


@dataclass(frozen=True)
class Item:
    """One asset spec and the folder its YAML lives in."""

    asset: dict[str, Any]
    base_dir: Path


def pack(items: Sequence[Item], gap: float = 0.03) -> list[list[tuple[Item, tuple[float, float]]]]:
    """Split items into tables: each table a list of (item, (x, y) of the asset origin) that do not overlap."""
    sized = []
    for it in items:
        lo, hi = asset_bounds(it.asset, it.base_dir)
        sized.append((it, lo, hi))
    sized.sort(key=lambda s: -(s[2][0] - s[1][0]))
    tables: list[list[tuple[Item, tuple[float, float]]]] = [[]]
    x0, y0 = -TABLE_HALF_XY[0] + gap, -TABLE_HALF_XY[1] + gap
    row_x, row_depth, cursor_y = x0, 0.0, y0
    for it, lo, hi in sized:
        wx, wy = hi[0] - lo[0], hi[1] - lo[1]
        if wx > 2 * TABLE_HALF_XY[0] - 2 * gap or wy > 2 * TABLE_HALF_XY[1] - 2 * gap:
            raise ValueError(f"asset {it.asset['id']!r} ({wx:.2f} x {wy:.2f} m) does not fit on the table")
        if cursor_y + wy > TABLE_HALF_XY[1] - gap:  # next row
            row_x, cursor_y, row_depth = row_x + row_depth + gap, y0, 0.0
        if row_x + wx > TABLE_HALF_XY[0] - gap:  # next table
            tables.append([])
            row_x, cursor_y, row_depth = x0, y0, 0.0
        tables[-1].append((it, (float(row_x - lo[0]), float(cursor_y - lo[1]))))
        cursor_y += wy + gap
        row_depth = max(row_depth, wx)
    return [t for t in tables if t]


def table_scene(table: Item, placed: Sequence[tuple[Item, tuple[float, float]]], *,
                timestep: float = 0.002) -> tuple[mujoco.MjSpec, dict[str, AssetHandles]]:
    """A spec with the table asset (instance 'table') and the placed assets (instances named by asset id)."""
    spec = mujoco.MjSpec()
    spec.option.timestep = timestep
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0.0, 0.0, 0.05],
                            rgba=[0.3, 0.3, 0.32, 1.0])
    add_asset(spec, table.asset, "table", (0.0, 0.0, 0.0), base_dir=table.base_dir)
    handles = {}
    for it, (x, y) in placed:
        lo, _ = asset_bounds(it.asset, it.base_dir)
        z = TABLE_TOP_Z - float(lo[2]) + (DROP_CLEARANCE if it.asset.get("base", "free") == "free" else 0.0)
        name = it.asset["id"]
        handles[name] = add_asset(spec, it.asset, name, (x, y, z), base_dir=it.base_dir)
    return spec, handles


def settle_report(model: mujoco.MjModel, data: mujoco.MjData, handles: dict[str, AssetHandles],
                  seconds: float = 2.0) -> dict[str, dict[str, float]]:
    """Simulate ``seconds``; per instance: NaN flag, lowest point (m), end linear speed (m/s) and angular speed
    (rad/s) of its fastest body, deepest contact penetration (m)."""
    for _ in range(int(round(seconds / model.opt.timestep))):
        mujoco.mj_step(model, data)
    report: dict[str, dict[str, float]] = {}
    deepest: dict[int, float] = {}
    for c in data.contact[: data.ncon]:
        for g in (c.geom1, c.geom2):
            if g < 0:
                continue  # flex contacts name no geom
            b = int(model.geom_bodyid[g])
            deepest[b] = min(deepest.get(b, 0.0), float(c.dist))
    for name, h in handles.items():
        body_ids = [model.body(b).id for b in h.bodies]
        geom_ids = [model.geom(g).id for g in h.geoms]
        if h.flex is not None:
            fid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_FLEX, h.flex)
            adr, num = model.flex_vertadr[fid], model.flex_vertnum[fid]
            lowest = float(np.min(data.flexvert_xpos[adr:adr + num, 2]))
        else:
            lowest = _lowest_point(model, data, geom_ids)
        speed = spin = 0.0
        for b in body_ids:
            vel = np.zeros(6)
            mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, b, vel, 0)
            spin, speed = max(spin, float(np.linalg.norm(vel[:3]))), max(speed, float(np.linalg.norm(vel[3:])))
        report[name] = {
            "nan": float(not np.all(np.isfinite(data.xpos[body_ids]))),
            "lowest": lowest,
            "speed": speed,
            "spin": spin,
            "penetration": -min((deepest.get(b, 0.0) for b in body_ids), default=0.0),
        }
    return report


def _lowest_point(model: mujoco.MjModel, data: mujoco.MjData, geom_ids: Sequence[int]) -> float:
    """Lowest world z reached by the colliding geoms (exact per primitive; mesh: lowest hull vertex)."""
    low = np.inf
    for g in geom_ids:
        if not (model.geom_contype[g] or model.geom_conaffinity[g]):
            continue
        z, rot, size = float(data.geom_xpos[g][2]), data.geom_xmat[g].reshape(3, 3), model.geom_size[g]
        gtype, az = int(model.geom_type[g]), abs(float(rot[2, 2]))
        if gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
            bottom = z - size[0]
        elif gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
            bottom = z - az * size[1] - size[0]
        elif gtype == mujoco.mjtGeom.mjGEOM_CYLINDER:
            bottom = z - az * size[1] - size[0] * np.sqrt(max(0.0, 1.0 - az * az))
        elif gtype == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
            bottom = z - float(np.linalg.norm(rot[2] * size))
        elif gtype == mujoco.mjtGeom.mjGEOM_BOX:
            bottom = z - float(np.abs(rot[2]) @ size)
        elif gtype == mujoco.mjtGeom.mjGEOM_MESH:
            mid = int(model.geom_dataid[g])
            verts = model.mesh_vert[model.mesh_vertadr[mid]:model.mesh_vertadr[mid] + model.mesh_vertnum[mid]]
            bottom = z + float(np.min(verts @ rot[2]))
        else:
            continue
        low = min(low, float(bottom))
    return low
