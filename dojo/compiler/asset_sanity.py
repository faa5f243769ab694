"""Physical sanity of an asset, for `dojo validate --strict`: its meshes load and are closed where they collide,
its mass is plausible for its volume, its lengths are metres, and a lighting preset's lights add up to at most
white.

The schema cannot see any of it: a mesh exported in millimetres is a valid spec that puts a 80 m mug on the table;
an open mesh gives MuJoCo no volume to spread the mass over; a 5 kg grape makes the gripper drop it. Each is
reported with the figure measured, so the author sees what to fix. Masses are checked as densities (mass over the
volume the compiler gives the colliding geoms: mesh pieces' convex hulls, primitives' own volumes), since MuJoCo
derives every body's inertia from the same geoms and masses: a plausible density is a plausible inertia.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import trimesh

from dojo.compiler.asset_emit import LIGHT_DEFAULTS
from dojo.compiler.asset_geometry import asset_bounds, load_mesh, mesh_hulls, primitive_volume
from dojo.compiler.pack_audit import Finding
from dojo.compiler.spec_library import Spec

DENSITY_RANGE = (10.0, 25_000.0)
"""kg/m^3 a body's mass over its collision volume may have: expanded foam to beyond the densest metal (the
built-in assets span 90 to 6,000)."""
MAX_FREE_SIZE = 1.0
"""Largest extent (m) of a movable object at its largest scale: more is no manipulation task."""
MAX_FIXED_SIZE = 2.5
"""Largest extent (m) of a fixture (the table is 1.2 m)."""
MIN_SIZE = 0.005
"""Smallest largest-extent (m) of any object: less is a size written in the wrong unit."""
MAX_FREE_MASS = 5.0
"""Mass (kg) of a movable object at its largest scale: the arms lift about 1.5 kg each."""
LIGHT_SUM_MAX = 1.0
"""Most a lighting preset's ambient and diffuse colours may add up to in any channel (headlight and every light):
MuJoCo's renderer clamps the summed light at 1 before the texture multiplies it, MuJoCo Warp's ray tracer (the
batched cameras) does not, so a brighter rig renders brighter on the GPU than on the CPU. Measured on
`stack_blocks` and `insert_tubes` at 224x224 (2026-11-29, `python -m dojo.backends.mjx.render_parity`): the standard
rig at a sum of 1.6 gave 19.4 dB PSNR between the two renderers, at 1.0 27.5 dB and every image within the
parity thresholds (a warning, not an error: the scene is right on either renderer, only not alike on both)."""


@dataclass(frozen=True)
class AssetFigures:
    """What was measured, for the report: density range (kg/m^3), largest extent (m), collision meshes checked."""

    densities: tuple[float, ...]
    largest: float
    meshes: int


@dataclass(frozen=True)
class _MeshReport:
    error: str | None
    open_edges: int
    volume: float


@functools.lru_cache(maxsize=512)
def _mesh_report(path: str, mtime_ns: int) -> _MeshReport:
    """Load one mesh file as the compiler does (vertices unmerged) and measure it; keyed by modification time."""
    try:
        mesh = load_mesh(Path(path))
    except Exception as err:  # noqa: BLE001 - any reason a mesh does not load is reported as such
        return _MeshReport(f"{type(err).__name__}: {err}", 0, 0.0)
    open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
    return _MeshReport(None, open_edges, float(mesh.volume) if open_edges == 0 else 0.0)


def _bodies(data: dict[str, Any]) -> list[tuple[str, list[dict[str, Any]], float, tuple]]:
    """(label, geoms, mass, JSON path of the body) of the root body and each link."""
    out = [("the root body", data["geoms"], float(data["mass"]), ())]
    out += [(f"link '{link['name']}'", link["geoms"], float(link["mass"]), ("links", i))
            for i, link in enumerate(data.get("links", []))]
    return out


def asset_sanity(asset: Spec) -> tuple[AssetFigures | None, list[Finding]]:
    """Check one asset spec: (figures, findings). Rigid and articulated assets get figures; a lighting preset only
    findings (`LIGHT_SUM_MAX`); other classes have nothing to check."""
    data = asset.data
    if data["class"] == "lighting":
        return None, _lighting_findings(asset)
    if data["class"] not in ("rigid", "articulated"):
        return None, []
    base_dir = asset.path.parent
    findings: list[Finding] = []
    free = data.get("base", "free" if data["class"] == "rigid" else "fixed") == "free"
    densities, meshes, total_mass = [], 0, 0.0
    for label, geoms, mass, body_path in _bodies(data):
        total_mass += mass
        volume, broken = 0.0, False
        for i, geom in enumerate(geoms):
            where = _where(asset, body_path + ("geoms", i, "mesh"))
            if geom["type"] != "mesh":
                volume += 0.0 if geom.get("visual") else primitive_volume(geom["type"], geom["size"])
                continue
            file = base_dir / geom["mesh"]
            report = _mesh_report(str(file.resolve()), file.stat().st_mtime_ns)
            if report.error:
                findings.append(Finding(f"{where}: mesh {geom['mesh']} does not load: {report.error}"))
                broken = True
                continue
            if geom.get("visual"):
                continue
            meshes += 1
            if report.open_edges:
                findings.append(Finding(f"{where}: collision mesh {geom['mesh']} is not watertight: "
                                        f"{report.open_edges} edges border a hole (a colliding mesh must be closed, "
                                        "or marked visual: true)"))
                broken = True
            elif (scaled := report.volume * float(np.prod(geom.get("mesh_scale", (1.0, 1.0, 1.0))))) <= 0:
                findings.append(Finding(f"{where}: collision mesh {geom['mesh']} encloses a volume of "
                                        f"{scaled:.3g} m^3: its faces are wound inward (inside out) or flat"))
                broken = True
            else:
                volume += sum(h.volume for h in mesh_hulls(file, geom.get("mesh_scale")))
        if broken:
            continue
        if volume <= 0:
            if free and not body_path:
                findings.append(Finding(f"{_where(asset, ('geoms',))}: asset '{asset.id}' is movable but has no "
                                        "colliding geometry (every geom is visual)"))
            continue
        density = mass / volume
        densities.append(density)
        if not DENSITY_RANGE[0] <= density <= DENSITY_RANGE[1]:
            findings.append(Finding(f"{_where(asset, body_path + ('mass',))}: {label} of asset '{asset.id}' weighs "
                                    f"{mass:g} kg for {volume * 1e6:.4g} cm^3 of colliding volume, a density of "
                                    f"{density:,.4g} kg/m^3 (plausible: {DENSITY_RANGE[0]:g} to "
                                    f"{DENSITY_RANGE[1]:,.0f}): is the mass in kg and the size in metres?"))
    top_scale = float(max(data.get("scale_range", [1.0, 1.0])))
    largest = 0.0
    try:
        lo, hi = asset_bounds(data, base_dir, top_scale)
    except ValueError:
        pass  # a mesh that does not load: reported above
    else:
        extent = hi - lo
        largest = float(np.max(extent))
        size = " x ".join(f"{e:.3g}" for e in extent) + f" m (at scale {top_scale:g})"
        limit = MAX_FREE_SIZE if free else MAX_FIXED_SIZE
        if largest > limit:
            findings.append(Finding(f"{_where(asset, ())}: asset '{asset.id}' measures {size}: lengths are metres, "
                                    f"and a {'movable object' if free else 'fixture'} may measure at most {limit:g} m "
                                    "(a mesh written in centimetres or millimetres? set mesh_scale)"))
        elif largest < MIN_SIZE:
            findings.append(Finding(f"{_where(asset, ())}: asset '{asset.id}' measures {size}: lengths are metres, "
                                    f"and an object measures at least {MIN_SIZE * 1000:g} mm"))
    heaviest = total_mass * top_scale**3
    if free and heaviest > MAX_FREE_MASS:
        findings.append(Finding(f"{_where(asset, ('mass',))}: movable asset '{asset.id}' weighs {heaviest:.3g} kg "
                                f"(at scale {top_scale:g}): the arms lift at most {MAX_FREE_MASS:g} kg"))
    return AssetFigures(tuple(densities), largest, meshes), findings


def light_sum(rig: dict[str, Any]) -> np.ndarray:
    """The ambient and diffuse colours of a lighting preset's headlight and lights added up, per channel (what a
    surface facing every light at once would receive), with the defaults the compiler emits."""
    head = rig.get("headlight", {})
    spec_head = mujoco.MjSpec().visual.headlight
    total = np.asarray(head.get("ambient", spec_head.ambient), float) + np.asarray(
        head.get("diffuse", spec_head.diffuse), float)
    for light in rig["lights"]:
        total += np.asarray(light.get("ambient", LIGHT_DEFAULTS["ambient"]), float)
        total += np.asarray(light.get("diffuse", LIGHT_DEFAULTS["diffuse"]), float)
    return total


def _lighting_findings(asset: Spec) -> list[Finding]:
    total = light_sum(asset.data["lighting"])
    if float(total.max()) <= LIGHT_SUM_MAX + 1e-9:
        return []
    sums = ", ".join(f"{v:.3g}" for v in total)
    return [Finding(f"{_where(asset, ('lighting',))}: lighting '{asset.id}' adds up to ({sums}) of ambient and "
                    f"diffuse light (headlight and lights): above {LIGHT_SUM_MAX:g}, MuJoCo's renderer saturates "
                    "and the batched cameras render brighter than it; scale the colours down", warning=True)]


def _where(asset: Spec, path: tuple) -> str:
    line, col = asset.located.locate(path)
    return f"{asset.display}:{line}:{col}"
