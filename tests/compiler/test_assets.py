"""The asset library: schema, library invariants and counts, emission, physical sanity, MJX and USD.

Physical sanity is checked by laying the whole library out on the standard table in a few batches and simulating
each batch for 2 s: nothing may explode, fall through the table, keep moving or end up interpenetrating.
"""

from __future__ import annotations

import importlib.util
import json
from collections import Counter
from pathlib import Path
from typing import Any, Iterator

import jsonschema
import mujoco
import numpy as np
import pytest
import referencing
import yaml

import dojo.assets
import dojo.specs
from dojo.compiler.asset_emit import (
    add_asset,
    apply_background,
    apply_lighting,
    apply_table_texture,
)
from dojo.compiler.asset_gallery import TABLE_TOP_Z, Item, pack, settle_report, table_scene
from dojo.compiler.asset_geometry import HULL_VERTEX_CAP, asset_bounds, convex_hull, mesh_hulls
from dojo.compiler.usd_io import export_model_usd, load_usd_mesh

LIBRARY = Path(dojo.assets.__file__).parent
SCHEMAS = Path(dojo.specs.__file__).parent / "schemas"
PHYSICAL = ("rigid", "articulated", "cloth")

# Settling thresholds after 2 s of simulation.
SINK_TOL = 0.005  # m below the table top
END_SPEED = 0.02  # m/s, linear speed and angular speed times the asset's radius
PENETRATION = 0.005  # m
CLUTTER_FOOTPRINT = 0.15  # m; the sampler packs clutter as circles, so long objects crowd a region out


def _asset_files() -> list[Path]:
    return sorted(p for p in LIBRARY.rglob("*.yaml"))


@pytest.fixture(scope="module")
def validator() -> jsonschema.Draft202012Validator:
    common = json.loads((SCHEMAS / "common.schema.json").read_text())
    schema = json.loads((SCHEMAS / "asset.schema.json").read_text())
    registry = referencing.Registry().with_resource(common["$id"], referencing.Resource.from_contents(common))
    return jsonschema.Draft202012Validator(schema, registry=registry)


@pytest.fixture(scope="module")
def library() -> dict[str, Item]:
    items = {}
    for path in _asset_files():
        asset = yaml.safe_load(path.read_text())
        assert asset["id"] not in items, f"duplicate asset id {asset['id']} in {path}"
        items[asset["id"]] = Item(asset, path.parent)
    return items


def _physical(library: dict[str, Item]) -> list[Item]:
    return [it for it in library.values() if it.asset["class"] in PHYSICAL and it.asset["id"] != "table"]


# --- schema ---------------------------------------------------------------------------------------------------


def _walk(node: Any, path: str = "") -> Iterator[tuple[str, Any]]:
    if isinstance(node, dict):
        yield path, node
        for k, v in node.items():
            yield from _walk(v, f"{path}/{k}")
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _walk(v, f"{path}/{i}")


def test_schema_is_valid_documented_and_routes_paths_through_relpath(validator) -> None:
    schema = validator.schema
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema["$id"] == "https://robodojo.dev/schemas/asset.schema.json"
    undocumented, open_objects, raw_paths = [], [], []
    for path, node in _walk(schema):
        if path.startswith("/examples"):
            continue
        for name, prop in node.get("properties", {}).items() if isinstance(node.get("properties"), dict) else ():
            if "description" not in prop:
                undocumented.append(f"{path}/properties/{name}")
            if name in ("mesh", "file") and prop.get("$ref") != "common.schema.json#/$defs/relpath":
                raw_paths.append(f"{path}/properties/{name}")
        if node.get("type") == "object" and node.get("additionalProperties") is not False:
            open_objects.append(path)
    assert not undocumented, undocumented
    assert not open_objects, open_objects
    assert not raw_paths, raw_paths
    for example in schema["examples"]:
        validator.validate(example)


@pytest.mark.parametrize("path", _asset_files(), ids=lambda p: p.stem)
def test_asset_spec_validates(path: Path, validator) -> None:
    errors = [f"{list(e.absolute_path)}: {e.message}" for e in validator.iter_errors(yaml.safe_load(path.read_text()))]
    assert not errors, errors


def test_schema_rejects_common_mistakes(validator) -> None:
    base = {"kind": "asset", "version": 1, "id": "x", "class": "rigid", "category": "block", "names": ["x"],
            "mass": 0.1, "geoms": [{"type": "box", "size": [0.01, 0.01, 0.01]}]}
    validator.validate(base)
    for bad in (
        {**base, "colour": [1, 0, 0, 1]},  # unknown key
        {**base, "geoms": [{"type": "mesh"}]},  # mesh without file
        {**base, "geoms": [{"type": "box"}]},  # primitive without size
        {k: v for k, v in base.items() if k != "mass"},  # rigid without mass
        {**base, "class": "articulated"},  # articulated without links
        {**base, "annotations": [{"name": "a", "kind": "handle", "pos": [0, 0, 0]}]},  # unknown annotation kind
    ):
        assert list(validator.iter_errors(bad)), bad


# --- library invariants and counts ----------------------------------------------------------------------------


def test_library_files_are_consistent(library: dict[str, Item]) -> None:
    problems = []
    for aid, it in library.items():
        a = it.asset
        where = f"{it.base_dir.name}/{aid}"
        if not (it.base_dir / f"{aid}.yaml").is_file():
            problems.append(f"{where}: file name is not the id")
        if it.base_dir.name != a["category"]:
            problems.append(f"{where}: folder is not the category {a['category']}")
        links = [None] + [link["name"] for link in a.get("links", ())]
        for i, link in enumerate(a.get("links", ())):
            if link.get("parent") not in links[: i + 1]:
                problems.append(f"{where}: link {link['name']} has an unknown or later parent")
        names = [ann["name"] for ann in a.get("annotations", ())]
        if len(names) != len(set(names)):
            problems.append(f"{where}: duplicate annotation names")
        for ann in a.get("annotations", ()):
            if ann.get("link") not in links:
                problems.append(f"{where}: annotation {ann['name']} on unknown link")
        geoms = list(a.get("geoms", ())) + [g for link in a.get("links", ()) for g in link["geoms"]]
        gnames = [g["name"] for g in geoms if "name" in g]
        if len(gnames) != len(set(gnames)):
            problems.append(f"{where}: duplicate geom names")
        for g in geoms:
            if "mesh" in g and not (it.base_dir / g["mesh"]).is_file():
                problems.append(f"{where}: missing mesh {g['mesh']}")
        if "clutter" in a.get("sets", ()):
            if a["class"] != "rigid" or a.get("base", "free") != "free":
                problems.append(f"{where}: clutter must be movable rigid objects")
            lo, hi = asset_bounds(a, it.base_dir)
            if max(hi[:2] - lo[:2]) > CLUTTER_FOOTPRINT:
                problems.append(f"{where}: clutter wider than {CLUTTER_FOOTPRINT} m")
    assert not problems, problems


def test_backgrounds_keep_their_skyboxes_cheap_to_compile(library: dict[str, Item]) -> None:
    """No camera of the built-in tasks sees the sky (the floor fills every view), yet generating 256-pixel faces
    was 60% of compiling an `insert_tubes` scene: a built-in gradient sky stays at the default's size or below."""
    from dojo.compiler.asset_emit import SKYBOX_SIZE

    backgrounds = [it.asset for it in library.values() if it.asset["class"] == "background"]
    assert backgrounds and SKYBOX_SIZE <= 64
    for asset in backgrounds:
        sky = asset["background"]["skybox"]
        assert sky["builtin"] != "gradient" or sky.get("size", SKYBOX_SIZE) <= SKYBOX_SIZE, (asset["id"], sky)


def test_library_counts(library: dict[str, Item]) -> None:
    physical = _physical(library)
    by_class = Counter(it.asset["class"] for it in library.values())
    categories = {it.asset["category"] for it in physical}
    clutter = [it for it in physical if "clutter" in it.asset.get("sets", ())]
    assert len(physical) >= 60, len(physical)
    assert len(categories) >= 20, sorted(categories)
    assert len(clutter) >= 25, len(clutter)
    assert by_class["texture"] >= 6 and by_class["background"] >= 4 and by_class["lighting"] >= 4, by_class
    articulated = {it.asset["category"] for it in physical if it.asset["class"] == "articulated"}
    assert {"drawer", "box", "laptop", "toaster", "button", "safe"} <= articulated, articulated
    assert by_class["cloth"] >= 1
    usd_meshes = [g for it in physical for g in it.asset.get("geoms", ()) if g.get("mesh", "").endswith(".usda")]
    assert usd_meshes, "at least one asset must load its mesh from USD"


def test_library_is_small() -> None:
    total = sum(p.stat().st_size for p in LIBRARY.rglob("*") if p.is_file())
    assert total < 5_000_000, total


def test_mesh_generator_reproduces_the_shipped_meshes(tmp_path: Path) -> None:
    script = LIBRARY / "tools" / "make_meshes.py"
    if not script.is_file():
        pytest.skip("the mesh generator is a checkout tool, not shipped in the wheel")
    spec = importlib.util.spec_from_file_location("make_meshes", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(tmp_path)
    generated = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*.obj"))
    assert generated
    for rel in generated:
        assert (tmp_path / rel).read_bytes() == (LIBRARY / rel).read_bytes(), rel


# --- meshes ---------------------------------------------------------------------------------------------------


def test_convex_hull_caps_vertices() -> None:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(2000, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    verts, faces = convex_hull(points)
    assert len(verts) <= HULL_VERTEX_CAP
    assert faces.min() >= 0 and faces.max() < len(verts)
    centroid = verts.mean(axis=0)
    tri = verts[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(np.einsum("ij,ij->i", normals, tri.mean(axis=1) - centroid) > 0), "faces must point outwards"


def test_every_mesh_piece_is_a_small_hull(library: dict[str, Item]) -> None:
    checked = 0
    for it in library.values():
        for g in list(it.asset.get("geoms", ())) + [g for ln in it.asset.get("links", ()) for g in ln["geoms"]]:
            if g["type"] == "mesh":
                hulls = mesh_hulls(it.base_dir / g["mesh"], g.get("mesh_scale"))
                assert all(4 <= len(h.vertices) <= HULL_VERTEX_CAP and h.volume > 0 for h in hulls), it.asset["id"]
                checked += len(hulls)
    assert checked > 100


# --- emission -------------------------------------------------------------------------------------------------


def _table_world(library: dict[str, Item]) -> mujoco.MjSpec:
    spec = mujoco.MjSpec()
    table = library["table"]
    add_asset(spec, table.asset, "table", (0, 0, 0), base_dir=table.base_dir)
    return spec


def test_add_asset_names_scale_and_colour(library: dict[str, Item]) -> None:
    spec = _table_world(library)
    mug = library["mug"]
    h = add_asset(spec, mug.asset, "mug_1", (0.1, 0.0, TABLE_TOP_Z), scale=1.1, rgba=(0, 0, 1, 1),
                  base_dir=mug.base_dir)
    drawer = library["cabinet_drawer"]
    hd = add_asset(spec, drawer.asset, "drawer", (-0.3, 0.0, TABLE_TOP_Z), base_dir=drawer.base_dir)
    model = spec.compile()
    assert h.body == "mug_1" and h.free_joint == "mug_1/free"
    assert set(h.sites) == {"handle", "handle_hole", "inside", "top"}
    assert all(name.startswith("mug_1/") for name in h.geoms + tuple(h.sites.values()))
    assert hd.free_joint is None and hd.joints == ("drawer/slide",) and hd.bodies == ("drawer", "drawer/drawer")
    assert model.body("mug_1").mass[0] == pytest.approx(mug.asset["mass"] * 1.1**3, rel=1e-6)
    assert np.allclose(model.geom(h.geoms[0]).rgba, (0, 0, 1, 1))  # instance colour
    assert np.allclose(model.geom("mug_1/handle_outer").size, np.array([0.005, 0.007, 0.03]) * 1.1)
    assert model.site("mug_1/top").pos[2] == pytest.approx(0.095 * 1.1)
    assert model.jnt_range[model.joint("drawer/slide").id] == pytest.approx([0.0, 0.22])
    assert np.all(model.mesh_vertnum <= HULL_VERTEX_CAP)


def test_add_asset_rejects_misuse(library: dict[str, Item]) -> None:
    spec = _table_world(library)
    with pytest.raises(ValueError, match="preset"):
        add_asset(spec, library["wood_light"].asset, "tex", (0, 0, 0), base_dir=LIBRARY)
    with pytest.raises(ValueError, match="'/'"):
        add_asset(spec, library["mug"].asset, "a/b", (0, 0, 0), base_dir=library["mug"].base_dir)


def test_asset_bounds_match_the_compiled_geometry(library: dict[str, Item]) -> None:
    for aid in ("mug", "bowl_large", "t_shape", "laptop", "banana"):
        it = library[aid]
        lo, hi = asset_bounds(it.asset, it.base_dir)
        spec = mujoco.MjSpec()
        add_asset(spec, it.asset, "a", (0, 0, 0), base_dir=it.base_dir)
        model = spec.compile()
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        assert lo[2] == pytest.approx(0.0, abs=2e-3), aid  # the asset frame sits on its resting surface
        for g in range(model.ngeom):
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH:
                mid = model.geom_dataid[g]
                v = model.mesh_vert[model.mesh_vertadr[mid]:model.mesh_vertadr[mid] + model.mesh_vertnum[mid]]
                world = data.geom_xpos[g] + v @ data.geom_xmat[g].reshape(3, 3).T
                assert np.all(world >= lo - 1e-6) and np.all(world <= hi + 1e-6), aid


def test_presets_apply(library: dict[str, Item]) -> None:
    presets = {c: [it for it in library.values() if it.asset["class"] == c]
               for c in ("texture", "background", "lighting")}
    for tex, bg, light in zip(presets["texture"], presets["background"] * 2, presets["lighting"] * 2):
        spec = _table_world(library)
        mat = apply_table_texture(spec, tex.asset, base_dir=tex.base_dir)
        floor = apply_background(spec, bg.asset, base_dir=bg.base_dir)
        lights = apply_lighting(spec, light.asset)
        model = spec.compile()
        assert model.geom_matid[model.geom("table/top").id] == model.material(mat).id
        assert model.geom(floor).type[0] == mujoco.mjtGeom.mjGEOM_PLANE
        assert mujoco.mjtTexture.mjTEXTURE_SKYBOX in model.tex_type
        assert model.nlight == len(lights) == len(light.asset["lighting"]["lights"])
    with pytest.raises(KeyError, match="no geom"):
        apply_table_texture(mujoco.MjSpec(), presets["texture"][0].asset)
    with pytest.raises(ValueError, match="already has a background"):
        apply_background(spec, presets["background"][0].asset)


# --- physics --------------------------------------------------------------------------------------------------


def test_every_asset_settles_on_the_table(library: dict[str, Item]) -> None:
    failures = []
    tables = pack(_physical(library))
    assert len(tables) <= 6, "the library should fit a handful of tables"
    for placed in tables:
        spec, handles = table_scene(library["table"], placed)
        model = spec.compile()
        assert np.all(model.mesh_vertnum <= HULL_VERTEX_CAP)
        report = settle_report(model, mujoco.MjData(model), handles, seconds=2.0)
        for name, r in report.items():
            it = library[handles[name].asset_id]
            lo, hi = asset_bounds(it.asset, it.base_dir)
            radius = float(np.max(np.abs(np.concatenate([lo[:2], hi[:2], [hi[2] - lo[2]]]))))
            if (r["nan"] or r["lowest"] < TABLE_TOP_Z - SINK_TOL or r["speed"] > END_SPEED
                    or r["spin"] * radius > END_SPEED or r["penetration"] > PENETRATION):
                failures.append((name, {k: round(v, 4) for k, v in r.items()}))
    assert not failures, failures


def _joint_scene(library: dict[str, Item]) -> tuple[mujoco.MjModel, list[dict[str, Any]]]:
    articulated = [it for it in _physical(library) if it.asset["class"] == "articulated"]
    (placed,) = pack(articulated)
    spec, handles = table_scene(library["table"], placed)
    model = spec.compile()
    joints = []
    for h in handles.values():
        spec_joints = {ln["joint"]["name"]: ln["joint"] for ln in library[h.asset_id].asset["links"]}
        for jname in h.joints:
            j = model.joint(jname)
            joints.append({"name": jname, "dof": int(j.dofadr[0]), "qpos": int(j.qposadr[0]),
                           "range": j.range.copy(), "spec": spec_joints[jname.split("/", 1)[1]],
                           "slide": j.type[0] == mujoco.mjtJoint.mjJNT_SLIDE})
    return model, joints


def _run(model: mujoco.MjModel, data: mujoco.MjData, seconds: float) -> None:
    for _ in range(int(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)


def test_articulated_joints_respect_their_limits(library: dict[str, Item]) -> None:
    model, joints = _joint_scene(library)
    for sign, side in ((1.0, 1), (-1.0, 0)):
        data = mujoco.MjData(model)
        for j in joints:  # push every joint hard past the limit on this side
            data.qfrc_applied[j["dof"]] = sign * (10.0 if j["slide"] else 2.0)  # N or N m
        _run(model, data, 1.0)
        for j in joints:
            q, limit = data.qpos[j["qpos"]], j["range"][side]
            tol = 0.005 if j["slide"] else 0.03
            assert (q <= limit + tol) if side else (q >= limit - tol), (j["name"], q, limit)
            assert abs(q - limit) < (0.2 * (j["range"][1] - j["range"][0])), f"{j['name']} did not reach its limit"


def test_springs_return_their_joints(library: dict[str, Item]) -> None:
    model, joints = _joint_scene(library)
    sprung = [j for j in joints if j["spec"].get("stiffness", 0) > 0]
    assert {j["name"] for j in sprung} >= {"toaster/lever", "push_button/press"}
    data = mujoco.MjData(model)
    for j in sprung:
        rest = float(np.clip(data.qpos[j["qpos"]], *j["range"]))
        far = j["range"][0] if abs(j["range"][0] - rest) > abs(j["range"][1] - rest) else j["range"][1]
        j["rest"], j["far"] = rest, far
        data.qfrc_applied[j["dof"]] = 10.0 * np.sign(far - rest)
    _run(model, data, 0.5)
    for j in sprung:
        travel = (data.qpos[j["qpos"]] - j["rest"]) / (j["far"] - j["rest"])
        assert travel > 0.9, f"{j['name']} was not pushed to its far end"
    data.qfrc_applied[:] = 0.0
    _run(model, data, 1.0)
    for j in sprung:
        assert abs(data.qpos[j["qpos"]] - j["rest"]) < 0.1 * abs(j["far"] - j["rest"]), f"{j['name']} did not return"


def test_cloth_drapes_over_the_table_edge_without_blowing_up(library: dict[str, Item]) -> None:
    towel = library["towel"]
    spec, handles = table_scene(library["table"], [(towel, (0.55, 0.0))])  # half of it hangs over the edge
    model = spec.compile()
    data = mujoco.MjData(model)
    _run(model, data, 1.5)
    fid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_FLEX, handles["towel"].flex)
    verts = data.flexvert_xpos[model.flex_vertadr[fid]:model.flex_vertadr[fid] + model.flex_vertnum[fid]]
    assert data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number == 0
    assert np.all(np.isfinite(verts))
    assert verts[:, 2].min() < TABLE_TOP_Z - 0.05, "the overhanging half should hang down"
    assert verts[:, 2].max() < TABLE_TOP_Z + 0.01
    corner = data.site_xpos[model.site(handles["towel"].sites["corner_pp"]).id]
    assert np.min(np.linalg.norm(verts - corner, axis=1)) < 1e-6, "corner annotations ride on their vertex"


def test_mjx_accepts_rigid_and_articulated_assets(library: dict[str, Item]) -> None:
    from mujoco import mjx

    sample = [it for it in _physical(library) if it.asset["class"] != "cloth"][::4]
    tables = pack(sample)  # a wide asset (a conveyor belt) can fill a table on its own: every table is checked
    for placed in tables:
        spec, _ = table_scene(library["table"], placed)
        model = spec.compile()
        mx = mjx.put_model(model)  # raises NotImplementedError for collision pairs MJX lacks
        assert mx.ngeom == model.ngeom
    assert sum(len(placed) for placed in tables) == len(sample) >= 10


# --- USD ------------------------------------------------------------------------------------------------------


def test_usd_mesh_import(library: dict[str, Item]) -> None:
    vase = load_usd_mesh(library["vase"].base_dir / "vase.usda")
    assert len(vase.faces) > 100
    assert np.allclose(vase.bounds, [[-0.07, -0.07, 0.0], [0.07, 0.07, 0.2]], atol=2e-3)


def test_usd_export_round_trip(library: dict[str, Item], tmp_path: Path) -> None:
    from pxr import Usd, UsdGeom

    spec = _table_world(library)
    for k, aid in enumerate(("mug", "block_cube", "apple", "test_tube")):
        it = library[aid]
        add_asset(spec, it.asset, aid, (0.15 * k - 0.2, 0.05, TABLE_TOP_Z + 0.002), base_dir=it.base_dir)
    model = spec.compile()
    data = mujoco.MjData(model)
    _run(model, data, 0.2)
    out = export_model_usd(model, data, tmp_path / "scene.usda")
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    prims = {p.GetAttribute("mujoco:geom_id").Get(): p for p in stage.Traverse() if p.HasAttribute("mujoco:geom_id")}
    assert sorted(prims) == list(range(model.ngeom))
    cache = UsdGeom.XformCache()
    for g, prim in prims.items():
        xf = np.asarray(cache.GetLocalToWorldTransform(prim))
        assert np.allclose(xf[3, :3], data.geom_xpos[g], atol=1e-6), prim.GetPath()
        colour = UsdGeom.Gprim(prim).GetDisplayColorAttr().Get()[0]
        assert np.allclose(colour, model.geom_rgba[g][:3], atol=1e-6)
    reloaded = load_usd_mesh(out)  # the exported mesh geoms come back at their world poses
    for g in np.flatnonzero(model.geom_type == mujoco.mjtGeom.mjGEOM_MESH):
        mid = model.geom_dataid[g]
        v = model.mesh_vert[model.mesh_vertadr[mid]:model.mesh_vertadr[mid] + model.mesh_vertnum[mid]]
        world = data.geom_xpos[g] + v @ data.geom_xmat[g].reshape(3, 3).T
        nearest = np.min(np.linalg.norm(reloaded.vertices[None, :, :] - world[:, None, :], axis=2), axis=1)
        assert nearest.max() < 1e-5
