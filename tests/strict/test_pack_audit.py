"""The static checks of `dojo validate --strict` (no simulation): which loader problems are safety problems, the
safety limits, and asset sanity, each on a file made to break exactly one rule."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dojo.compiler.asset_sanity import asset_sanity
from dojo.compiler.pack_audit import own_assets, pack_tasks
from dojo.compiler.pack_limits import PackLimits, pack_safety, task_safety
from dojo.compiler.spec_library import SpecLibrary

HERE = Path(__file__).parent
BROKEN = HERE / "broken_pack"
MALFORMED = HERE.parent / "specs" / "malformed"
SPEC_PACK = HERE.parent / "specs" / "pack"
SAFETY = {"absolute_path", "dotdot_path", "python_tag", "include_tag", "target_key", "oc_resolver",
          "eval_resolver", "billion_laughs", "recursive_alias"}
"""Files of the malformed corpus whose one problem breaks a safety rule (code, reading outside the pack, bounds)."""


def test_loader_marks_exactly_the_safety_problems(tmp_path: Path) -> None:
    """The malformed corpus, loaded at once: each file's problems are safety problems exactly when the file breaks
    a safety rule."""
    pack = tmp_path / "pack"
    shutil.copytree(SPEC_PACK, pack)
    (pack / "extra").mkdir()
    for path in MALFORMED.glob("*.yaml"):
        shutil.copy(path, pack / "extra" / f"{path.stem.split('__')[-1]}.yaml")
    flags: dict[str, set[bool]] = {}
    for problem in SpecLibrary.load([pack], strict=False).problems:
        if Path(problem.file).is_relative_to(pack / "extra"):
            flags.setdefault(Path(problem.file).stem, set()).add(problem.safety)
    assert SAFETY < set(flags) and len(flags) >= 40
    assert {stem for stem, seen in flags.items() if True in seen} == SAFETY
    assert all(seen == {True} for stem, seen in flags.items() if stem in SAFETY)


def test_a_symlink_out_of_the_pack_and_an_oversized_pack(tmp_path: Path) -> None:
    pack = tmp_path / "pack"
    shutil.copytree(SPEC_PACK, pack)
    (pack / "assets" / "secret.obj").symlink_to("/etc/hostname")
    figure, findings = pack_safety(pack, PackLimits())
    assert [f.message for f in findings] == [f"{pack / 'assets' / 'secret.obj'}: a symlink out of the pack (to "
                                             f"{Path('/etc/hostname').resolve()}): not allowed"]
    _, findings = pack_safety(pack, PackLimits(max_pack_bytes=100))
    assert any("the pack's files take" in f.message and "at most 0 MiB" in f.message for f in findings)


def test_mesh_and_texture_limits(tmp_path: Path) -> None:
    library = SpecLibrary.load([BROKEN], strict=False)
    task = library.get("task", "giant_mesh")
    assets = own_assets(library, task)
    assert [a.id for a in assets] == ["giant_mug"]
    figure, findings = task_safety(library, task, assets, PackLimits())
    assert not findings and figure == "1 object(s), horizon 300, meshes up to 26 vertices"
    _, findings = task_safety(library, task, assets, PackLimits(max_mesh_vertices=20))
    assert [_located(f.message) for f in findings] == [
        ("broken_pack/assets/giant_mug.yaml:11:24", "mesh mug_in_millimetres.obj has 26 vertices and 48 faces: "
                                                   "at most 20 and 200,000")]

    pack = tmp_path / "pack"
    shutil.copytree(SPEC_PACK, pack)
    Image.fromarray(np.zeros((8, 3000, 3), np.uint8)).save(pack / "assets" / "wide.png")
    (pack / "assets" / "wide_texture.yaml").write_text(
        "kind: asset\nversion: 1\nid: wide_texture\nclass: texture\ncategory: table_texture\nnames: [wood]\n"
        "texture: {builtin: file, file: wide.png}\n")
    (pack / "tasks" / "textured.yaml").write_text(
        (SPEC_PACK / "tasks" / "stack_test.yaml").read_text().replace("id: stack_test", "id: textured")
        .replace("standard: {clutter: [0, 0]}", "standard: {clutter: [0, 0], table_texture: wide_texture}"))
    library = SpecLibrary.load([pack], strict=False)
    assert not [p for p in library.problems if Path(p.file).is_relative_to(pack)]
    task = library.get("task", "textured")
    _, findings = task_safety(library, task, own_assets(library, task), PackLimits())
    assert [f.message.split(": ", 1)[1] for f in findings] == [
        "texture wide.png is 3000x8 pixels: at most 2048 a side"]


def test_object_count_and_horizon_bounds() -> None:
    library = SpecLibrary.load([BROKEN], strict=False)
    task = library.get("task", "too_many_objects")
    _, findings = task_safety(library, task, [], PackLimits())
    assert [_located(f.message) for f in findings] == [
        ("broken_pack/tasks/too_many_objects.yaml:13:5", "the scene holds up to 75 objects (75 placed, 0 clutter): "
                                                         "at most 64")]
    _, findings = task_safety(library, library.get("task", "unsolvable"), [], PackLimits(max_horizon=200))
    assert [_located(f.message) for f in findings] == [
        ("broken_pack/tasks/unsolvable.yaml:18:10", "horizon 300 control steps is outside 25..200")]


def test_every_builtin_asset_is_sane() -> None:
    for asset in SpecLibrary.load([]).of_kind("asset"):
        figures, findings = asset_sanity(asset)
        assert not findings, [f.message for f in findings]


def test_asset_sanity_measures_what_is_wrong(tmp_path: Path) -> None:
    library = SpecLibrary.load([BROKEN], strict=False)
    _, findings = asset_sanity(library.get("asset", "giant_mug"))
    messages = [f.message.split(": ", 1)[1] for f in findings]
    assert "asset 'giant_mug' measures 80 x 80 x 100 m (at scale 1): lengths are metres" in messages[1]
    assert "a density of 6.25e-07 kg/m^3" in messages[0]
    _, findings = asset_sanity(library.get("asset", "open_cup"))
    assert [f.message.split(": ", 1)[1] for f in findings] == [
        "collision mesh open_cup.obj is not watertight: 12 edges border a hole (a colliding mesh must be closed, or "
        "marked visual: true)"]
    assert _located(findings[0].message)[0] == "broken_pack/assets/open_cup.yaml:11:24"  # at the file name

    # the same closed mesh with every face wound inward: negative volume
    pack = tmp_path / "pack"
    shutil.copytree(SPEC_PACK, pack)
    lines = (BROKEN / "assets" / "mug_in_millimetres.obj").read_text().splitlines()
    flipped = [" ".join(["f"] + ln.split()[1:][::-1]) if ln.startswith("f ") else ln for ln in lines]
    (pack / "assets" / "inside_out.obj").write_text("\n".join(flipped) + "\n")
    (pack / "assets" / "inside_out.yaml").write_text(
        "kind: asset\nversion: 1\nid: inside_out\nclass: rigid\ncategory: thing\nnames: [thing]\nmass: 0.1\n"
        "geoms:\n  - {type: mesh, mesh: inside_out.obj, mesh_scale: [0.001, 0.001, 0.001]}\n")
    (pack / "assets" / "lead_feather.yaml").write_text(
        "kind: asset\nversion: 1\nid: lead_feather\nclass: rigid\ncategory: thing\nnames: [thing]\nmass: 4.0\n"
        "geoms:\n  - {type: box, size: [0.01, 0.01, 0.01]}\n")
    (pack / "assets" / "glare.yaml").write_text(  # the standard rig as it was before 2026-11-29
        "kind: asset\nversion: 1\nid: glare\nclass: lighting\ncategory: lighting\nnames: [glare]\nlighting:\n"
        "  headlight: {ambient: [0.3, 0.3, 0.3], diffuse: [0.4, 0.4, 0.4]}\n"
        "  lights:\n    - {name: key, pos: [0, -1, 2.5], dir: [0, 0.4, -1], diffuse: [0.6, 0.6, 0.6]}\n"
        "    - {name: fill, pos: [1, 1, 2.5], dir: [-0.4, -0.4, -1], diffuse: [0.3, 0.3, 0.5]}\n")
    library = SpecLibrary.load([pack], strict=False)
    _, findings = asset_sanity(library.get("asset", "glare"))
    assert len(findings) == 1 and findings[0].warning
    assert "lighting 'glare' adds up to (1.6, 1.6, 1.8) of ambient and diffuse light" in findings[0].message
    assert findings[0].message.split(": ", 1)[0].endswith("glare.yaml:8:3")  # at the rig
    _, findings = asset_sanity(library.get("asset", "inside_out"))
    assert [f.message.split(": ", 1)[1] for f in findings] == [
        "collision mesh inside_out.obj encloses a volume of -0.00048 m^3: its faces are wound inward (inside out) "
        "or flat"]
    _, findings = asset_sanity(library.get("asset", "lead_feather"))
    assert len(findings) == 1 and "a density of 5e+05 kg/m^3 (plausible: 10 to 25,000)" in findings[0].message


def _located(message: str) -> tuple[str, str]:
    """(where, what) of a finding, `where` from the pack folder on (display paths depend on the working folder)."""
    where, what = message.split(": ", 1)
    return where[where.index("broken_pack"):], what


def test_pack_rows_include_a_task_the_loader_refused() -> None:
    library = SpecLibrary.load([BROKEN], strict=False)
    rows = {t.task_id: t for t in pack_tasks(library, BROKEN)}
    assert sorted(rows) == ["code_injection", "giant_mesh", "open_mesh", "too_many_objects", "trivially_solved",
                            "unsolvable", "unstable"]
    assert rows["code_injection"].spec is None and rows["unstable"].spec is not None
