"""Emit asset instances and scene presets into a ``mujoco.MjSpec`` with the editing API.

One call of ``add_asset`` adds one instance: a body named after the instance, its geoms, joints and annotation
sites, all prefixed ``<name>/`` so that predicates and skills can find them. Presets (table textures,
backgrounds, lighting) change materials, the skybox, the floor and lights instead of adding objects.

Backends: the compiler emits one scene for every backend. MJX cannot collide cylinders or ellipsoids with boxes and
meshes, so colliding cylinders and ellipsoids become convex hull meshes (``primitive_hull``) everywhere: the
backends then simulate the same geometry. Cloth uses MuJoCo flex, which MJX does not implement; a plan with cloth
lists ``flex`` in its ``requires`` (``dojo.compiler.plan_features``) and ``dojo run`` sends it to a backend that
has it, saying so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import mujoco
import numpy as np
from scipy.spatial import ConvexHull

from dojo.compiler.asset_geometry import MJX_UNPAIRED_PRIMITIVES, mesh_hulls, primitive_hull, primitive_volume

DEFAULT_RGBA = (0.6, 0.6, 0.6, 1.0)
TORSIONAL_FRICTION = 0.005
ROLLING_FRICTION = 0.0001
VISUAL_GROUP = 1
"""Geom group of decorative geoms (no collision, no mass)."""
THREAD_SOLREF = (0.004, 1.0)
THREAD_SOLIMP = (0.99, 0.995, 0.001)
"""Stiffness of a thread's equality constraint: a time constant of twice the 2 ms physics step, and an impedance
near 1. MuJoCo's defaults (0.02 s, 0.9-0.95) let a 0.3 kg carriage sag 5 mm off its thread under gravity alone
(the constraint's regularisation scales with the light hinge's inverse inertia); these hold it within 0.1 mm,
0.4 mm under a 10 N push (measured on the threaded nut)."""
ANNOTATION_GROUP = 4
"""Site group of annotations: hidden by default renderers, visible in the viewer on demand."""

_PRIMITIVES = {
    "box": mujoco.mjtGeom.mjGEOM_BOX,
    "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
    "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
    "ellipsoid": mujoco.mjtGeom.mjGEOM_ELLIPSOID,
}
_BUILTINS = {
    "checker": mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
    "gradient": mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
    "flat": mujoco.mjtBuiltin.mjBUILTIN_FLAT,
}
_MARKS = {
    "none": mujoco.mjtMark.mjMARK_NONE,
    "edge": mujoco.mjtMark.mjMARK_EDGE,
    "cross": mujoco.mjtMark.mjMARK_CROSS,
    "random": mujoco.mjtMark.mjMARK_RANDOM,
}


@dataclass(frozen=True)
class AssetHandles:
    """Names of what one ``add_asset`` call created, for predicates, samplers and skills."""

    name: str
    """Instance name; every element below starts with ``<name>``."""
    asset_id: str
    body: str
    """Root body (for cloth: the body holding the flex vertices)."""
    bodies: tuple[str, ...]
    """Root body first, then one per link."""
    geoms: tuple[str, ...]
    joints: tuple[str, ...]
    """Articulation joints ``<name>/<joint>`` (not the free joint)."""
    free_joint: str | None
    """``<name>/free`` for movable assets, None for fixtures and cloth."""
    sites: dict[str, str] = field(default_factory=dict)
    """Annotation name -> site name ``<name>/<annotation>``."""
    flex: str | None = None
    """Flex name for cloth."""
    scale: float = 1.0


def _scaled(vec: Sequence[float] | None, scale: float, default: Sequence[float] = (0.0, 0.0, 0.0)) -> list[float]:
    return [float(v) * scale for v in (vec if vec is not None else default)]


class _Emitter:
    """Builds one instance; keeps the running lists of created names."""

    def __init__(self, world: mujoco.MjSpec, asset: dict[str, Any], name: str, scale: float,
                 rgba: Sequence[float] | None, base_dir: Path) -> None:
        self.world, self.asset, self.name, self.scale, self.base_dir = world, asset, name, float(scale), base_dir
        self.rgba = list(rgba) if rgba is not None else list(asset.get("rgba", DEFAULT_RGBA))
        self.friction = [float(asset.get("friction", 1.0)), TORSIONAL_FRICTION, ROLLING_FRICTION]
        self.geoms: list[str] = []

    def mesh(self, label: str, verts: np.ndarray, faces: np.ndarray) -> str:
        """Add one hull mesh named like its geom. Meshes are per instance, not shared by scale: scenes that
        differ only in an object's scale then differ only in vertex values, not in their list of meshes."""
        mesh = self.world.add_mesh(name=f"{self.name}/{label}", uservert=verts.ravel().tolist(),
                                   userface=faces.ravel().tolist())
        return mesh.name

    def geoms_into(self, body: mujoco.MjsBody, geoms: list[dict[str, Any]], mass: float, tag: str) -> None:
        """Add the spec geoms to ``body``; colliding ones share ``mass`` by volume."""
        s = self.scale
        pieces: list[tuple[dict[str, Any], str, dict[str, Any], float]] = []
        for gi, g in enumerate(geoms):
            gname = g.get("name", f"{tag}g{gi}")
            if g["type"] == "mesh":
                hulls = mesh_hulls(self.base_dir / g["mesh"], g.get("mesh_scale"))
                for k, h in enumerate(hulls):
                    label = gname if len(hulls) == 1 else f"{gname}_{k}"
                    mesh = self.mesh(label, h.vertices * s, h.faces)
                    pieces.append((g, label, {"type": mujoco.mjtGeom.mjGEOM_MESH, "meshname": mesh}, h.volume * s**3))
            elif g["type"] in MJX_UNPAIRED_PRIMITIVES and not g.get("visual"):
                verts, faces = primitive_hull(g["type"], _scaled(g["size"], s))
                mesh = self.mesh(gname, verts, faces)
                pieces.append((g, gname, {"type": mujoco.mjtGeom.mjGEOM_MESH, "meshname": mesh},
                               float(ConvexHull(verts).volume)))
            else:
                size = _scaled(g["size"], s)
                pieces.append((g, gname, {"type": _PRIMITIVES[g["type"]], "size": size + [0.0] * (3 - len(size))},
                               primitive_volume(g["type"], size)))
        total = sum(v for g, _, _, v in pieces if not g.get("visual"))
        for g, label, kind, vol in pieces:
            geom = body.add_geom(name=f"{self.name}/{label}", pos=_scaled(g.get("pos"), s),
                                 quat=list(g.get("quat", (1.0, 0.0, 0.0, 0.0))), rgba=list(g.get("rgba", self.rgba)),
                                 friction=self.friction, **kind)
            if g.get("visual"):
                geom.contype, geom.conaffinity, geom.group, geom.density = 0, 0, VISUAL_GROUP, 0.0
            else:
                geom.mass = mass * vol / total if total > 0 else 0.0
            self.geoms.append(geom.name)

    def annotations(self, bodies: dict[str | None, mujoco.MjsBody]) -> dict[str, str]:
        sites = {}
        for a in self.asset.get("annotations", ()):
            body = bodies[a.get("link")]
            site = body.add_site(name=f"{self.name}/{a['name']}", pos=_scaled(a["pos"], self.scale),
                                 quat=list(a.get("quat", (1.0, 0.0, 0.0, 0.0))), group=ANNOTATION_GROUP,
                                 rgba=[0.1, 0.8, 0.2, 0.3])
            if "size" in a:
                site.type = mujoco.mjtGeom.mjGEOM_BOX
                site.size = _scaled(a["size"], self.scale)
            else:
                site.size = [0.005 * self.scale, 0.0, 0.0]
            sites[a["name"]] = site.name
        return sites


def add_asset(world: mujoco.MjSpec, asset: dict[str, Any], name: str, pos: Sequence[float],
              quat: Sequence[float] = (1.0, 0.0, 0.0, 0.0), scale: float = 1.0,
              rgba: Sequence[float] | None = None, *, base_dir: Path) -> AssetHandles:
    """Add one instance of ``asset`` (a validated asset spec dict) to ``world`` and return what it created.

    ``pos``/``quat`` place the asset frame in the world (its origin is the centre of its footprint, so
    ``pos[2]`` is the height of the surface it rests on). ``scale`` multiplies lengths and the cube of it
    multiplies masses. ``rgba`` replaces the asset's default colour (geoms with their own colour keep it).
    ``base_dir`` is the folder of the asset's YAML, against which mesh paths resolve.
    """
    cls = asset["class"]
    if cls in ("texture", "background", "lighting"):
        raise ValueError(f"asset {asset['id']!r} is a {cls} preset: use apply_table_texture/apply_background/"
                         "apply_lighting, not add_asset")
    if "/" in name or not name:
        raise ValueError(f"instance name {name!r} must be non-empty and contain no '/'")
    if cls == "cloth":
        return _add_cloth(world, asset, name, pos, quat, scale, rgba)
    em = _Emitter(world, asset, name, scale, rgba, Path(base_dir))
    root = world.worldbody.add_body(name=name, pos=[float(p) for p in pos], quat=[float(q) for q in quat])
    base = asset.get("base", "free" if cls == "rigid" else "fixed")
    root.mocap = base == "kinematic"  # posed by an actor every step (dojo.backends.demonstrator)
    free_joint = None
    if base == "free":
        free_joint = root.add_freejoint(name=f"{name}/free").name
    mass3 = scale**3
    em.geoms_into(root, asset["geoms"], asset["mass"] * mass3, "")
    bodies: dict[str | None, mujoco.MjsBody] = {None: root}
    joints = []
    for link in asset.get("links", ()):
        body = bodies[link.get("parent")].add_body(name=f"{name}/{link['name']}", pos=_scaled(link.get("pos"), scale),
                                                   quat=list(link.get("quat", (1.0, 0.0, 0.0, 0.0))))
        bodies[link["name"]] = body
        # MuJoCo skips parent-child contacts only when the parent is not welded to the world, so a fixed base would
        # collide with its own links; excluding the pair makes links behave the same on free and fixed bases.
        world.add_exclude(bodyname1=bodies[link.get("parent")].name, bodyname2=body.name)
        j = link["joint"]
        is_slide = j["type"] == "slide"
        # Slide values are lengths and scale with the asset; hinge values are radians in the spec and follow the
        # world's compiler angle unit (MjSpec defaults to degrees).
        lin = scale if is_slide else (180.0 / np.pi if world.compiler.degree else 1.0)
        joint = body.add_joint(
            name=f"{name}/{j['name']}",
            type=mujoco.mjtJoint.mjJNT_SLIDE if is_slide else mujoco.mjtJoint.mjJNT_HINGE,
            axis=[float(a) for a in j["axis"]], pos=_scaled(j.get("pos"), scale),
            range=[float(r) * lin for r in j["range"]], limited=mujoco.mjtLimited.mjLIMITED_TRUE,
            damping=float(j.get("damping", 0.0)), stiffness=float(j.get("stiffness", 0.0)),
            springref=float(j.get("springref", 0.0)) * lin, frictionloss=float(j.get("frictionloss", 0.0)),
            armature=float(j.get("armature", 0.0)),
        )
        joints.append(joint.name)
        em.geoms_into(body, link["geoms"], link["mass"] * mass3, f"{link['name']}_")
    for thread in asset.get("threads", ()):
        _add_thread(world, name, thread, scale)
    sites = em.annotations(bodies)
    body_names = tuple(b.name for b in bodies.values())
    return AssetHandles(name=name, asset_id=asset["id"], body=root.name, bodies=body_names, geoms=tuple(em.geoms),
                        joints=tuple(joints), free_joint=free_joint, sites=sites, scale=float(scale))


def _add_thread(world: mujoco.MjSpec, name: str, thread: dict[str, Any], scale: float) -> None:
    """A screw thread: the slide joint's value held at pitch/2pi times the hinge's (both in the model's units,
    metres and radians, whatever the spec's angle unit), by a joint equality as the grippers' finger sync is, so
    the CPU and MJX backends simulate the same coupling."""
    ratio = float(thread["pitch"]) * scale / (2.0 * np.pi)
    world.add_equality(name=f"{name}/{thread['hinge']}_thread", type=mujoco.mjtEq.mjEQ_JOINT,
                       name1=f"{name}/{thread['slide']}", name2=f"{name}/{thread['hinge']}",
                       data=[0.0, ratio, 0.0, 0.0, 0.0] + [0.0] * 7, solref=list(THREAD_SOLREF),
                       solimp=list(THREAD_SOLIMP) + [0.5, 2.0])


def _add_cloth(world: mujoco.MjSpec, asset: dict[str, Any], name: str, pos: Sequence[float], quat: Sequence[float],
               scale: float, rgba: Sequence[float] | None) -> AssetHandles:
    """A flex grid cloth (MuJoCo's flexcomp), lying flat with its lowest vertices ``radius`` above ``pos``."""
    c = asset["cloth"]
    radius = float(c.get("radius", 0.004)) * scale
    root = world.worldbody.add_body(name=name, pos=[float(pos[0]), float(pos[1]), float(pos[2]) + radius],
                                    quat=[float(q) for q in quat])
    spacing = float(c["spacing"]) * scale
    # Edge equality constraints hold the cloth's stretch and the elasticity model only bends it: MuJoCo refuses
    # both on one flex, and stretch elasticity alone goes unstable at the 2 ms step once the cloth drapes.
    flex = root.make_flex(f"{name}/cloth", type="grid", dim=2, count=[int(c["count"][0]), int(c["count"][1]), 1],
                          spacing=[spacing, spacing, spacing], radius=radius, mass=float(c["mass"]) * scale**2,
                          equality=1)
    flex.young = float(c.get("young", 5e4))
    flex.poisson = float(c.get("poisson", 0.2))
    flex.thickness = float(c.get("thickness", 0.002)) * scale
    flex.damping = float(c.get("damping", 0.002))
    flex.elastic2d = 1  # bending only
    flex.selfcollide = mujoco.mjtFlexSelf.mjFLEXSELF_NONE
    flex.friction = [float(asset.get("friction", 1.0)), TORSIONAL_FRICTION, ROLLING_FRICTION]
    flex.rgba = list(rgba if rgba is not None else c.get("rgba", asset.get("rgba", DEFAULT_RGBA)))
    nx, ny = int(c["count"][0]), int(c["count"][1])
    bodies = (root.name,) + tuple(f"{name}/cloth_{i}" for i in range(nx * ny))
    sites = {}
    for a in asset.get("annotations", ()):
        # Cloth annotations ride on the nearest vertex so that they follow the cloth as it folds.
        x, y, z = _scaled(a["pos"], scale)
        i = min(max(round(x / spacing + (nx - 1) / 2), 0), nx - 1)
        j = min(max(round(y / spacing + (ny - 1) / 2), 0), ny - 1)
        vertex = world.body(f"{name}/cloth_{i * ny + j}")
        offset = [x - (i - (nx - 1) / 2) * spacing, y - (j - (ny - 1) / 2) * spacing, z]
        site = vertex.add_site(name=f"{name}/{a['name']}", pos=offset, group=ANNOTATION_GROUP,
                               size=[0.005 * scale, 0.0, 0.0], rgba=[0.1, 0.8, 0.2, 0.3])
        sites[a["name"]] = site.name
    return AssetHandles(name=name, asset_id=asset["id"], body=root.name, bodies=bodies, geoms=(), joints=(),
                        free_joint=None, sites=sites, flex=flex.name, scale=float(scale))


SKYBOX_SIZE = 64
"""Pixels per face edge of a skybox whose spec names no size. Generating a 256-pixel gradient sky (256x1536) was
7.6 of the 12.4 ms a table-top scene of two arms took to compile (CI machine, 2026-11-29), and no built-in task's
camera sees the sky; a smooth gradient loses nothing at 64."""


def _add_texture(world: mujoco.MjSpec, name: str, tex: dict[str, Any], ttype: mujoco.mjtTexture,
                 base_dir: Path | None) -> mujoco.MjsTexture:
    if world.texture(name) is not None:
        return world.texture(name)
    if tex["builtin"] == "file":
        if base_dir is None:
            raise ValueError(f"texture {name!r} reads a file: pass base_dir")
        return world.add_texture(name=name, type=ttype, file=str(Path(base_dir) / tex["file"]))
    size = int(tex.get("size", 512 if ttype == mujoco.mjtTexture.mjTEXTURE_2D else SKYBOX_SIZE))
    return world.add_texture(
        name=name, type=ttype, builtin=_BUILTINS[tex["builtin"]], width=size, height=size,
        rgb1=list(tex.get("rgb1", (0.6, 0.6, 0.6))), rgb2=list(tex.get("rgb2", (0.3, 0.3, 0.3))),
        mark=_MARKS[tex.get("mark", "none")], markrgb=list(tex.get("markrgb", (0.0, 0.0, 0.0))),
        random=float(tex.get("random", 0.0)),
    )


def _add_material(world: mujoco.MjSpec, name: str, tex: dict[str, Any], base_dir: Path | None) -> str:
    if world.material(name) is None:
        texture = _add_texture(world, name, tex, mujoco.mjtTexture.mjTEXTURE_2D, base_dir)
        mat = world.add_material(name=name, texrepeat=list(tex.get("texrepeat", (1.0, 1.0))), texuniform=True,
                                 reflectance=float(tex.get("reflectance", 0.0)),
                                 rgba=list(tex.get("rgba", (1.0, 1.0, 1.0, 1.0))))
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = texture.name
    return name


def _require(asset: dict[str, Any], cls: str) -> None:
    if asset["class"] != cls:
        raise ValueError(f"asset {asset['id']!r} is a {asset['class']}, not a {cls}")


def apply_table_texture(world: mujoco.MjSpec, asset: dict[str, Any], *, geoms: Sequence[str] = ("table/top",),
                        base_dir: Path | None = None) -> str:
    """Give the named geoms (the table top by default) the preset's textured material; returns the material name."""
    _require(asset, "texture")
    mat = _add_material(world, f"texture/{asset['id']}", asset["texture"], base_dir)
    for gname in geoms:
        geom = world.geom(gname)
        if geom is None:
            raise KeyError(f"apply_table_texture: no geom named {gname!r} in the spec")
        geom.material = mat
        geom.rgba = [1.0, 1.0, 1.0, 1.0]  # the material colours the geom only where rgba is neutral
    return mat


def apply_background(world: mujoco.MjSpec, asset: dict[str, Any], *, base_dir: Path | None = None) -> str:
    """Add the preset's skybox and a textured floor plane ``background/floor`` at z = 0; returns the floor's name.

    The floor collides (objects knocked off the table land on it), so scene builders should not add another.
    """
    _require(asset, "background")
    if world.geom("background/floor") is not None:
        raise ValueError("apply_background: the scene already has a background")
    bg = asset["background"]
    _add_texture(world, f"background/{asset['id']}/sky", bg["skybox"], mujoco.mjtTexture.mjTEXTURE_SKYBOX, base_dir)
    mat = _add_material(world, f"background/{asset['id']}/floor", bg["floor"], base_dir)
    floor = world.worldbody.add_geom(name="background/floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0.0, 0.0, 0.05],
                                     material=mat)
    return floor.name


LIGHT_DEFAULTS: dict[str, tuple[float, float, float]] = {
    "diffuse": (0.7, 0.7, 0.7), "ambient": (0.0, 0.0, 0.0), "specular": (0.3, 0.3, 0.3)}
"""A lighting preset's light colours where it names none (the headlight's are MuJoCo's own)."""


def apply_lighting(world: mujoco.MjSpec, asset: dict[str, Any]) -> tuple[str, ...]:
    """Set the headlight and add the preset's lights (``light/<name>``); returns the light names."""
    _require(asset, "lighting")
    rig = asset["lighting"]
    head = rig.get("headlight", {})
    for key in ("ambient", "diffuse", "specular"):
        if key in head:
            setattr(world.visual.headlight, key, list(head[key]))
    names = []
    for spec in rig["lights"]:
        ltype = mujoco.mjtLightType.mjLIGHT_DIRECTIONAL if spec.get("directional") else mujoco.mjtLightType.mjLIGHT_SPOT
        light = world.worldbody.add_light(
            name=f"light/{spec['name']}", pos=list(spec["pos"]), dir=list(spec["dir"]), type=ltype,
            diffuse=list(spec.get("diffuse", LIGHT_DEFAULTS["diffuse"])),
            ambient=list(spec.get("ambient", LIGHT_DEFAULTS["ambient"])),
            specular=list(spec.get("specular", LIGHT_DEFAULTS["specular"])),
            castshadow=bool(spec.get("castshadow", True)), cutoff=float(spec.get("cutoff", 45.0)),
        )
        names.append(light.name)
    return tuple(names)
