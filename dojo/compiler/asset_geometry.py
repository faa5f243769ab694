"""Geometry of asset specs: mesh files reduced to small convex hulls, volumes and bounding boxes.

MJX collides meshes through their convex hulls and its convex-convex routines slow down sharply with hull size,
so every mesh piece is reduced to a hull of at most ``HULL_VERTEX_CAP`` vertices here, before MuJoCo sees it.
Mesh files are split into connected pieces (vertices are not merged on load, so a generator can ship a concave
object as touching convex parts) and each piece becomes one hull. The same functions give the sampler the
footprint of an asset, which it needs to place objects without overlap.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull

HULL_VERTEX_CAP = 64
"""Most vertices one collision hull may have (MJX's convex collision wants small hulls)."""

MESH_SUFFIXES = (".obj", ".stl", ".usda", ".usd", ".usdc")


@dataclass(frozen=True)
class Hull:
    """One convex piece of a mesh file at unit asset scale."""

    vertices: np.ndarray  # (n, 3) float64, n <= HULL_VERTEX_CAP
    faces: np.ndarray  # (m, 3) int32, outward-facing triangles of the hull
    volume: float


def load_mesh(path: Path) -> trimesh.Trimesh:
    """A mesh file as one trimesh, vertices unmerged (as written: touching pieces stay separate pieces)."""
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"{path}: unsupported mesh format {path.suffix!r} (use one of {', '.join(MESH_SUFFIXES)})")
    if path.suffix.lower().startswith(".usd"):
        from dojo.compiler.usd_io import load_usd_mesh

        return load_usd_mesh(path)
    loaded = trimesh.load(str(path), process=False, force="mesh")
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError(f"{path}: no triangles found")
    return loaded


def _farthest_points(points: np.ndarray, k: int) -> np.ndarray:
    """Deterministic farthest-point subsample: keeps the extremes that shape a hull."""
    chosen = [int(np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(k - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(points - points[nxt], axis=1))
    return points[chosen]


def convex_hull(points: np.ndarray, cap: int = HULL_VERTEX_CAP) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and outward triangles of the convex hull of ``points``, with at most ``cap`` vertices.

    Uses scipy's Qhull directly (trimesh's hull needs networkx to fix windings); when the hull has more than
    ``cap`` vertices it is rebuilt from a farthest-point subsample of them.
    """
    pts = np.asarray(points, dtype=np.float64)
    while True:
        hull = ConvexHull(pts)
        if len(hull.vertices) <= cap:
            break
        pts = _farthest_points(pts[hull.vertices], cap)
    keep = np.unique(hull.simplices)
    remap = np.full(len(pts), -1)
    remap[keep] = np.arange(len(keep))
    verts, faces = pts[keep], remap[hull.simplices]
    centre = verts.mean(axis=0)
    tri = verts[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = np.einsum("ij,ij->i", normals, tri.mean(axis=1) - centre) < 0
    faces[flip] = faces[flip][:, ::-1]
    return verts, faces.astype(np.int32)


def _pieces(mesh: trimesh.Trimesh) -> list[np.ndarray]:
    """Vertex sets of the connected pieces of a mesh (faces connected through shared vertex indices)."""
    faces = np.asarray(mesh.faces)
    n = len(mesh.vertices)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    used = np.unique(faces)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    return [verts[used[labels[used] == lab]] for lab in np.unique(labels[used])]


@functools.lru_cache(maxsize=256)
def _hulls_cached(path: str, mesh_scale: tuple[float, float, float]) -> tuple[Hull, ...]:
    hulls = []
    for piece in _pieces(load_mesh(Path(path))):
        verts = piece * np.asarray(mesh_scale)
        if len(verts) < 4 or np.linalg.matrix_rank(verts - verts.mean(axis=0), tol=1e-9) < 3:
            continue  # flat or degenerate piece: nothing to collide with
        hv, hf = convex_hull(verts)
        hulls.append(Hull(hv, hf, ConvexHull(hv).volume))
    if not hulls:
        raise ValueError(f"{path}: no solid piece in the mesh")
    return tuple(hulls)


def mesh_hulls(path: Path, mesh_scale: Sequence[float] | None = None) -> tuple[Hull, ...]:
    """Convex pieces of a mesh file (cached), with ``mesh_scale`` applied."""
    scale = tuple(float(s) for s in (mesh_scale or (1.0, 1.0, 1.0)))
    return _hulls_cached(str(Path(path).resolve()), scale)


MJX_UNPAIRED_PRIMITIVES = ("cylinder", "ellipsoid")
"""Primitives MJX's JAX collision table cannot pair with boxes or meshes (mujoco-mjx 3.x has no cylinder-box,
cylinder-mesh, ellipsoid-box or ellipsoid-mesh functions): colliding ones are emitted as convex hull meshes."""


def _circle(n: int) -> np.ndarray:
    angles = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.stack([np.cos(angles), np.sin(angles)], axis=1)


def primitive_hull(gtype: str, size: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Convex hull mesh standing in for a cylinder (a 16-gon prism, 32 vertices) or an ellipsoid (a scaled UV
    sphere of 12 longitudes x 5 latitude rings plus the poles, 62 vertices): both within the cap."""
    if gtype == "cylinder":
        ring, h = _circle(16) * size[0], size[1]
        pts = np.concatenate([np.c_[ring, np.full(16, -h)], np.c_[ring, np.full(16, h)]])
    elif gtype == "ellipsoid":
        rings = [np.c_[_circle(12) * np.cos(lat), np.full(12, np.sin(lat))]
                 for lat in np.linspace(-np.pi / 2, np.pi / 2, 7)[1:-1]]
        pts = np.concatenate(rings + [np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])]) * np.asarray(size[:3])
    else:
        raise ValueError(f"no hull stand-in for {gtype!r}")
    return convex_hull(pts)


def primitive_volume(gtype: str, size: Sequence[float]) -> float:
    """Volume of a MuJoCo primitive given its half-sizes."""
    if gtype == "box":
        return 8.0 * size[0] * size[1] * size[2]
    if gtype == "sphere":
        return 4.0 / 3.0 * math.pi * size[0] ** 3
    if gtype == "cylinder":
        return math.pi * size[0] ** 2 * 2.0 * size[1]
    if gtype == "capsule":
        return math.pi * size[0] ** 2 * 2.0 * size[1] + 4.0 / 3.0 * math.pi * size[0] ** 3
    if gtype == "ellipsoid":
        return 4.0 / 3.0 * math.pi * size[0] * size[1] * size[2]
    raise ValueError(f"unknown primitive {gtype!r}")


def _quat_matrix(quat: Sequence[float] | None) -> np.ndarray:
    if quat is None:
        return np.eye(3)
    w, x, y, z = np.asarray(quat, dtype=np.float64) / np.linalg.norm(quat)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _primitive_corners(gtype: str, size: Sequence[float]) -> np.ndarray:
    if gtype == "box":
        half = np.asarray(size[:3])
    elif gtype == "sphere":
        half = np.full(3, size[0])
    elif gtype == "cylinder":
        half = np.array([size[0], size[0], size[1]])
    elif gtype == "capsule":
        half = np.array([size[0], size[0], size[1] + size[0]])
    elif gtype == "ellipsoid":
        half = np.asarray(size[:3])
    else:
        raise ValueError(f"unknown primitive {gtype!r}")
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    return signs * half


def geom_points(geom: dict[str, Any], base_dir: Path) -> np.ndarray:
    """Points bounding one spec geom, in its link frame at unit asset scale."""
    if geom["type"] == "mesh":
        pts = np.concatenate([h.vertices for h in mesh_hulls(base_dir / geom["mesh"], geom.get("mesh_scale"))])
    else:
        pts = _primitive_corners(geom["type"], geom["size"])
    return pts @ _quat_matrix(geom.get("quat")).T + np.asarray(geom.get("pos", (0.0, 0.0, 0.0)))


def asset_bounds(asset: dict[str, Any], base_dir: Path, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (lo, hi) of a rigid or articulated asset in its own frame, links at joint value 0.

    Cloth is reported as its flat sheet. The sampler uses this as the asset's footprint.
    """
    if asset["class"] == "cloth":
        c = asset["cloth"]
        half = np.array([(c["count"][0] - 1) * c["spacing"] / 2, (c["count"][1] - 1) * c["spacing"] / 2,
                         c.get("radius", 0.005)])
        return -half * scale + np.array([0, 0, half[2] * scale]), half * scale + np.array([0, 0, half[2] * scale])
    if asset["class"] not in ("rigid", "articulated"):
        raise ValueError(f"asset {asset['id']!r} of class {asset['class']!r} has no geometry")
    frames: dict[str | None, tuple[np.ndarray, np.ndarray]] = {None: (np.zeros(3), np.eye(3))}
    pts = [geom_points(g, base_dir) for g in asset["geoms"]]
    for link in asset.get("links", ()):
        ppos, prot = frames[link.get("parent")]
        rot = prot @ _quat_matrix(link.get("quat"))
        pos = ppos + prot @ np.asarray(link.get("pos", (0.0, 0.0, 0.0)))
        frames[link["name"]] = (pos, rot)
        pts.extend(geom_points(g, base_dir) @ rot.T + pos for g in link["geoms"])
    allpts = np.concatenate(pts) * scale
    return allpts.min(axis=0), allpts.max(axis=0)
