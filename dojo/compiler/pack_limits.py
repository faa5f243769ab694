"""Safety limits of a task contribution: bounds on what a stranger's pack may make the benchmark load and run.

The YAML reader already keeps specs data (no tags, no code keys, no interpolation, no path leaving the pack). A
pack can still be abusive while being data: a million-vertex mesh, a 16k texture, a thousand objects, a day-long
horizon, gigabytes of files, or a symlink that reads a file outside the pack. These limits are far above what a
manipulation task needs (the built-in tasks use at most 28 objects, 312 mesh vertices, 1024-pixel textures and
2,200 control steps) and far below what would hurt a machine that compiles and runs every contributed task.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from PIL import Image

from dojo.compiler.asset_geometry import MESH_SUFFIXES, load_mesh, mesh_hulls
from dojo.compiler.horizon import task_horizon
from dojo.compiler.pack_audit import Finding, protocol_settings
from dojo.compiler.scene_sample import setting_config
from dojo.compiler.spec_errors import display_path
from dojo.compiler.spec_library import Spec, SpecLibrary
from dojo.compiler.spec_schema import collect_marked


@dataclass(frozen=True)
class PackLimits:
    """The bounds, in one place (the report quotes them)."""

    max_objects: int = 64
    """Bodies a scene may hold: fixtures and objects (counted with their `count`) plus the most clutter."""
    max_mesh_bytes: int = 16 << 20
    """Size of one mesh file (read before its vertices are counted)."""
    max_mesh_vertices: int = 100_000
    max_mesh_faces: int = 200_000
    max_mesh_pieces: int = 64
    """Connected pieces of one mesh file: each becomes one collision hull, and so one geom per instance."""
    max_texture_side: int = 2048
    """Width and height of an image texture, in pixels."""
    max_pack_bytes: int = 64 << 20
    """All files under the pack folder together."""
    min_horizon: int = 25
    max_horizon: int = 7_500
    """Episode length in control steps (1 s to 5 min at 25 Hz): the horizon, or the fallback of an `auto` one."""


def task_safety(library: SpecLibrary, task: Spec, assets: list[Spec], limits: PackLimits
                ) -> tuple[str, list[Finding]]:
    """The limits one task's scene, assets and horizon must keep: (figure, findings)."""
    findings: list[Finding] = []
    scene = task.data["scene"]
    placed = sum(int(entry.get("count", 1)) for entry in scene.get("fixtures", []) + scene["objects"])
    clutter = max(int(setting_config(task.data, s)["clutter"][1]) for s in protocol_settings(library, task))
    if placed + clutter > limits.max_objects:
        line, col = task.located.locate(("scene", "objects"))
        findings.append(Finding(f"{task.display}:{line}:{col}: the scene holds up to {placed + clutter} objects "
                                f"({placed} placed, {clutter} clutter): at most {limits.max_objects}"))
    horizon = task_horizon(task.data)
    if not limits.min_horizon <= horizon <= limits.max_horizon:
        key = "horizon" if task.data["horizon"] != "auto" else "horizon_fallback"
        line, col = task.located.locate((key,))
        findings.append(Finding(f"{task.display}:{line}:{col}: {key} {horizon} control steps is outside "
                                f"{limits.min_horizon}..{limits.max_horizon}"))
    vertices = 0
    for asset in assets:
        for use in collect_marked(asset.kind, asset.data, "x-relpath"):
            file = asset.path.parent / str(use.value)
            line, col = asset.located.locate(use.path)
            where = f"{asset.display}:{line}:{col}"
            if file.suffix.lower() in MESH_SUFFIXES:
                count, problems = _mesh_limits(file, where, limits)
                vertices = max(vertices, count)
                findings += problems
            elif file.suffix.lower() == ".png":
                findings += _texture_limits(file, where, limits)
    figure = f"{placed + clutter} object(s), horizon {horizon}" + (f", meshes up to {vertices:,} vertices"
                                                                   if vertices else "")
    return figure, findings


def _mesh_limits(file: Path, where: str, limits: PackLimits) -> tuple[int, list[Finding]]:
    size = file.stat().st_size
    if size > limits.max_mesh_bytes:
        return 0, [Finding(f"{where}: mesh {file.name} is {size / 2**20:.1f} MiB: at most "
                           f"{limits.max_mesh_bytes / 2**20:.0f} MiB")]
    try:
        mesh = load_mesh(file)
    except Exception:  # noqa: BLE001 - a file that does not parse is the asset check's to report, with its reason
        return 0, []
    out = []
    if len(mesh.vertices) > limits.max_mesh_vertices or len(mesh.faces) > limits.max_mesh_faces:
        out.append(Finding(f"{where}: mesh {file.name} has {len(mesh.vertices):,} vertices and {len(mesh.faces):,} "
                           f"faces: at most {limits.max_mesh_vertices:,} and {limits.max_mesh_faces:,}"))
    else:
        try:
            pieces = len(mesh_hulls(file))
        except ValueError:
            pieces = 0  # no solid piece: the asset check says so
        if pieces > limits.max_mesh_pieces:
            out.append(Finding(f"{where}: mesh {file.name} has {pieces} separate pieces (one collision hull each): "
                               f"at most {limits.max_mesh_pieces}"))
    return len(mesh.vertices), out


def _texture_limits(file: Path, where: str, limits: PackLimits) -> list[Finding]:
    try:
        with Image.open(file) as image:  # reads the header only
            width, height = image.size
    except OSError as err:
        return [Finding(f"{where}: texture {file.name} is not a readable image: {err}")]
    if max(width, height) > limits.max_texture_side:
        return [Finding(f"{where}: texture {file.name} is {width}x{height} pixels: at most "
                        f"{limits.max_texture_side} a side")]
    return []


def pack_safety(pack: Path, limits: PackLimits) -> tuple[str, list[Finding]]:
    """Pack-wide limits: total size, and no symlink under the pack that leads out of it (a path in a spec is
    checked where it is written; a linked file or folder would let any later reader leave the pack)."""
    root = pack.resolve() if pack.is_dir() else pack.parent.resolve()
    findings: list[Finding] = []
    total = 0
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            path = Path(folder) / name
            if path.is_symlink():
                target = path.resolve()
                if target != root and root not in target.parents:
                    findings.append(Finding(f"{display_path(path)}: a symlink out of the pack (to {target}): "
                                            "not allowed"))
                continue
            if name in files:
                total += path.stat().st_size
    if total > limits.max_pack_bytes:
        findings.append(Finding(f"{display_path(root)}: the pack's files take {total / 2**20:.1f} MiB: at most "
                                f"{limits.max_pack_bytes / 2**20:.0f} MiB"))
    return f"{total / 2**20:.2f} MiB", findings
