"""USD in and out: import a mesh asset from a USD file, export a compiled scene to USD for other tools.

Export is written with usd-core's ``UsdGeom`` rather than ``mujoco.usd.USDExporter``: that exporter (present in
mujoco 4.0) writes a folder of per-frame files with time samples, names prims by geom id rather than by the
geom names the rest of RoboDojo uses, tessellates every primitive, and needs Pillow. Here one ``.usda`` holds
one snapshot: analytic prims for primitives, meshes for meshes, each named after its geom, with the world pose
and colour of ``data``.
"""

from __future__ import annotations

import re
from pathlib import Path

import mujoco
import numpy as np
import trimesh
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

PLANE_EXTENT = 5.0
"""Half-size in metres used for infinite planes (size 0), which USD cannot represent."""


def load_usd_mesh(path: Path | str) -> trimesh.Trimesh:
    """All ``UsdGeom.Mesh`` prims of a USD file as one mesh in the stage's frame (metres, z up).

    Polygons are fan-triangulated and vertices are not merged, so disjoint prims stay disjoint pieces (the asset
    emitter turns each connected piece into one convex hull).
    """
    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise ValueError(f"{path}: not a USD stage")
    metres = UsdGeom.GetStageMetersPerUnit(stage) or 1.0
    z_up = UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    cache = UsdGeom.XformCache()
    verts, faces, offset = [], [], 0
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        mesh = UsdGeom.Mesh(prim)
        points = np.asarray(mesh.GetPointsAttr().Get() or [], dtype=np.float64).reshape(-1, 3)
        counts = mesh.GetFaceVertexCountsAttr().Get() or []
        indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
        if len(points) == 0 or len(counts) == 0:
            continue
        xf = np.asarray(cache.GetLocalToWorldTransform(prim), dtype=np.float64)  # row-vector convention
        world = np.c_[points, np.ones(len(points))] @ xf
        start = 0
        for n in counts:
            poly = indices[start:start + n]
            faces.extend([poly[0] + offset, poly[i] + offset, poly[i + 1] + offset] for i in range(1, n - 1))
            start += n
        verts.append(world[:, :3])
        offset += len(points)
    if not verts:
        raise ValueError(f"{path}: no UsdGeom.Mesh prim with faces")
    v = np.concatenate(verts) * metres
    if not z_up:
        v = v[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # y-up to z-up: (x, y, z) -> (x, -z, y)
    return trimesh.Trimesh(vertices=v, faces=np.asarray(faces, dtype=np.int64), process=False)


def _prim_name(name: str, fallback: str) -> str:
    clean = re.sub(r"[^A-Za-z0-9_]", "_", name) if name else fallback
    return clean if clean and not clean[0].isdigit() else f"_{clean}"


def _pose_matrix(pos: np.ndarray, xmat: np.ndarray) -> Gf.Matrix4d:
    m = np.eye(4)
    m[:3, :3] = xmat.reshape(3, 3).T  # USD: row vectors, so the rotation is transposed
    m[3, :3] = pos
    return Gf.Matrix4d(m.tolist())


def export_model_usd(model: mujoco.MjModel, data: mujoco.MjData, out_path: Path | str) -> Path:
    """Write every geom of ``model`` at its pose in ``data`` to a ``.usda`` (or ``.usd``) file; returns the path.

    Prims live under ``/World`` and are named after their geoms (characters USD forbids become ``_``); each
    carries ``displayColor``/``displayOpacity`` from the geom's (or its material's) colour and a
    ``mujoco:geom_id`` attribute. Call ``mujoco.mj_forward`` first so that the poses are current.
    """
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Usd.Stage.CreateNew(str(out))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(root.GetPrim())
    used: set[str] = set()
    for g in range(model.ngeom):
        name = _prim_name(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or "", f"geom_{g}")
        while name in used:
            name += "_"
        used.add(name)
        path = f"/World/{name}"
        gtype = int(model.geom_type[g])
        size = model.geom_size[g]
        if gtype == mujoco.mjtGeom.mjGEOM_BOX:
            gprim = UsdGeom.Cube.Define(stage, path)
            gprim.CreateSizeAttr(2.0)
            scale = Gf.Vec3f(*map(float, size))
        elif gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
            gprim = UsdGeom.Sphere.Define(stage, path)
            gprim.CreateRadiusAttr(float(size[0]))
            scale = None
        elif gtype == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
            gprim = UsdGeom.Sphere.Define(stage, path)
            gprim.CreateRadiusAttr(1.0)
            scale = Gf.Vec3f(*map(float, size))
        elif gtype in (mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_CAPSULE):
            cls = UsdGeom.Cylinder if gtype == mujoco.mjtGeom.mjGEOM_CYLINDER else UsdGeom.Capsule
            gprim = cls.Define(stage, path)
            gprim.CreateRadiusAttr(float(size[0]))
            gprim.CreateHeightAttr(float(2 * size[1]))
            gprim.CreateAxisAttr(UsdGeom.Tokens.z)
            scale = None
        elif gtype in (mujoco.mjtGeom.mjGEOM_MESH, mujoco.mjtGeom.mjGEOM_PLANE):
            gprim = UsdGeom.Mesh.Define(stage, path)
            if gtype == mujoco.mjtGeom.mjGEOM_MESH:
                mid = int(model.geom_dataid[g])
                va, vn = model.mesh_vertadr[mid], model.mesh_vertnum[mid]
                fa, fn = model.mesh_faceadr[mid], model.mesh_facenum[mid]
                pts, tris = model.mesh_vert[va:va + vn], model.mesh_face[fa:fa + fn]
            else:
                hx, hy = (float(size[0]) or PLANE_EXTENT), (float(size[1]) or PLANE_EXTENT)
                pts = np.array([[-hx, -hy, 0], [hx, -hy, 0], [hx, hy, 0], [-hx, hy, 0]])
                tris = np.array([[0, 1, 2], [0, 2, 3]])
            gprim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(pts, dtype=np.float32)))
            gprim.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(tris)))
            gprim.CreateFaceVertexIndicesAttr(Vt.IntArray(np.asarray(tris, dtype=np.int32).ravel().tolist()))
            gprim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            scale = None
        else:
            continue  # heightfields and SDF geoms have no USD counterpart here
        gprim.AddTransformOp().Set(_pose_matrix(data.geom_xpos[g], data.geom_xmat[g]))
        if scale is not None:
            gprim.AddScaleOp().Set(scale)
        matid = int(model.geom_matid[g])
        defers_to_material = matid >= 0 and np.allclose(model.geom_rgba[g], [0.5, 0.5, 0.5, 1])  # MuJoCo's rule
        rgba = model.mat_rgba[matid] if defers_to_material else model.geom_rgba[g]
        gprim.CreateDisplayColorAttr([Gf.Vec3f(*map(float, rgba[:3]))])
        gprim.CreateDisplayOpacityAttr([float(rgba[3])])
        gprim.GetPrim().CreateAttribute("mujoco:geom_id", Sdf.ValueTypeNames.Int).Set(g)
    stage.GetRootLayer().Save()
    return out

