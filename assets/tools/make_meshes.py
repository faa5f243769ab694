"""Generate the asset library's mesh files (OBJ, one USDA) from code, so that every shipped mesh is reproducible.

Run from the repository root: ``python assets/tools/make_meshes.py``. Output is deterministic.

Every mesh is written as disjoint convex parts (each part has its own vertices), which the asset emitter reads
back as one convex hull per connected piece. Concave objects (bowls, cups, bins) are therefore built from wall
sectors, and solids of revolution from stacked frusta. Letter and digit glyphs are thin stroke boxes meant for
visual (non-colliding) geoms.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from dojo.compiler.asset_geometry import convex_hull

ROOT = Path(__file__).resolve().parents[1]
Part = np.ndarray  # (n, 3) vertices of one convex part
WALL_LIFT = 0.002  # how far a hollow's wall sectors stay off the table when it stands on its base disc


def ring(r: float, z: float, n: int, a0: float = 0.0, a1: float = 2 * math.pi, closed: bool = True) -> np.ndarray:
    """Points on a horizontal circle (or arc from a0 to a1) of radius r at height z."""
    angles = np.linspace(a0, a1, n, endpoint=not closed)
    return np.stack([r * np.cos(angles), r * np.sin(angles), np.full(n, z)], axis=1)


def revolve_solid(profile: list[tuple[float, float]], n: int = 16) -> list[Part]:
    """Solid of revolution as one convex frustum per profile segment; profile is [(radius, z), ...] bottom-up."""
    parts = []
    for (r0, z0), (r1, z1) in zip(profile[:-1], profile[1:]):
        if z1 - z0 < 1e-9:
            continue  # a flat cap is already the face of its neighbouring frustum
        pts = [ring(max(r0, 1e-4), z0, n), ring(max(r1, 1e-4), z1, n)]
        parts.append(np.concatenate(pts))
    return parts


def revolve_shell(profile: list[tuple[float, float]], thickness: float, sectors: int = 12, bands: int = 1,
                  base: float | None = None, n_base: int = 16, wall_lift: float = 0.0) -> list[Part]:
    """Open-topped hollow of revolution: wall sectors x bands (convex pieces) plus a solid base disc.

    ``profile`` is the outer wall [(radius, z), ...] bottom-up; the inner wall is it moved inwards by
    ``thickness``. ``base`` is the base plate thickness (default: ``thickness``). ``wall_lift`` raises the
    wall's bottom edge above the base's underside, so that the object stands on its base disc alone: one
    resting contact patch instead of one per wall sector (a scene of many such objects steps much faster).
    """
    prof = np.asarray(profile, dtype=np.float64)
    idx = np.linspace(0, len(prof) - 1, bands + 1).round().astype(int)
    parts = []
    for s in range(sectors):
        a0, a1 = 2 * math.pi * s / sectors, 2 * math.pi * (s + 1) / sectors
        for b0, b1 in zip(idx[:-1], idx[1:]):
            pts = []
            for r, z in prof[b0:b1 + 1]:
                z = z + wall_lift if z == prof[0, 1] else z
                for a in (a0, a1):
                    pts.append((r * math.cos(a), r * math.sin(a), z))
                    pts.append(((r - thickness) * math.cos(a), (r - thickness) * math.sin(a), z))
            parts.append(np.asarray(pts))
    r_bottom = prof[0, 0]
    h = base if base is not None else thickness
    parts.append(np.concatenate([ring(r_bottom, 0.0, n_base), ring(r_bottom, h, n_base)]))
    return parts


def annulus(r_out: float, r_in: float, height: float, sectors: int = 12) -> list[Part]:
    """A flat ring (a roll of tape lying down): wall sectors from r_in to r_out, z from 0 to height."""
    parts = []
    for s in range(sectors):
        a0, a1 = 2 * math.pi * s / sectors, 2 * math.pi * (s + 1) / sectors
        pts = [(r * math.cos(a), r * math.sin(a), z) for r in (r_in, r_out) for a in (a0, a1) for z in (0.0, height)]
        parts.append(np.asarray(pts))
    return parts


def upside_down(parts: list[Part]) -> list[Part]:
    """Turn parts over (z -> top - z) so that the object still rests on z = 0."""
    top = max(float(p[:, 2].max()) for p in parts)
    return [p * np.array([1.0, -1.0, -1.0]) + np.array([0.0, 0.0, top]) for p in parts]


def on_feet(parts: list[Part], radius: float, n: int = 3, lift: float = 0.0015, half: float = 0.0015) -> list[Part]:
    """Parts raised by ``lift`` onto ``n`` small inverted pyramids spaced around ``radius``, each touching the table
    at its apex: an object that would rest on a ring of wall sectors (an upturned cup on its rim, 4 contacts a
    sector) rests on ``n`` points instead (3 by default: a tripod never rocks), far cheaper to simulate."""
    raised = [p + np.array([0.0, 0.0, lift]) for p in parts]
    feet = []
    for k in range(n):
        a = 2 * math.pi * (k + 0.5) / n
        x, y = radius * math.cos(a), radius * math.sin(a)
        base = [(x + dx, y + dy, lift) for dx in (-half, half) for dy in (-half, half)]
        feet.append(np.asarray([*base, (x, y, 0.0)]))
    return raised + feet


def lying_along_x(parts: list[Part]) -> list[Part]:
    """Lay parts of an upright object (axis z) on their side, axis along +x (top at +x), resting on z = 0."""
    turned = [p[:, [2, 1, 0]] * np.array([1.0, 1.0, -1.0]) for p in parts]  # rotate -90 deg about y
    low = min(float(p[:, 2].min()) for p in turned)
    return [p - np.array([0.0, 0.0, low]) for p in turned]


def box_part(center: tuple[float, float, float], half: tuple[float, float, float]) -> Part:
    c, h = np.asarray(center), np.asarray(half)
    return np.array([c + h * np.array([sx, sy, sz]) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])


def segment_part(p0: tuple[float, float], p1: tuple[float, float], width: float, depth: float) -> Part:
    """A flat stroke box in the xy plane from p0 to p1 (z from 0 to depth)."""
    a, b = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
    d = b - a
    length = np.linalg.norm(d)
    u = d / length if length > 0 else np.array([1.0, 0.0])
    v = np.array([-u[1], u[0]])
    a, b = a - u * width / 2, b + u * width / 2
    corners = [a + v * width / 2, a - v * width / 2, b - v * width / 2, b + v * width / 2]
    return np.array([(x, y, z) for x, y in corners for z in (0.0, depth)])


def write_obj(path: Path, parts: list[Part]) -> None:
    """Write convex parts as separate OBJ objects (vertices not shared, so each reads back as one piece)."""
    lines = [f"# generated by assets/tools/make_meshes.py: {len(parts)} convex parts"]
    offset = 1
    for k, part in enumerate(parts):
        verts, faces = convex_hull(part)
        lines.append(f"o part{k}")
        lines += [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in verts]
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in faces]
        offset += len(verts)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def write_usda(path: Path, parts: list[Part]) -> None:
    """Write convex parts as one UsdGeom.Mesh prim each (exercises the USD import path)."""
    from pxr import Gf, Usd, UsdGeom, Vt

    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/Vase")
    stage.SetDefaultPrim(root.GetPrim())
    for k, part in enumerate(parts):
        verts, faces = convex_hull(part)
        mesh = UsdGeom.Mesh.Define(stage, f"/Vase/part{k}")
        mesh.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, np.round(v, 5))) for v in verts]))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(faces.ravel().tolist()))
    stage.GetRootLayer().Save()


# Stroke font on a 4 x 6 grid (x right, y up), for glyphs printed on letter and number blocks.
GLYPHS: dict[str, list[list[tuple[float, float]]]] = {
    "A": [[(0, 0), (2, 6), (4, 0)], [(1, 3), (3, 3)]],
    "B": [[(0, 0), (0, 6), (3, 6), (4, 5), (3, 3), (0, 3)], [(3, 3), (4, 1.5), (3, 0), (0, 0)]],
    "C": [[(4, 6), (0, 6), (0, 0), (4, 0)]],
    "D": [[(0, 0), (0, 6), (2.5, 6), (4, 4.5), (4, 1.5), (2.5, 0), (0, 0)]],
    "E": [[(4, 6), (0, 6), (0, 0), (4, 0)], [(0, 3), (3, 3)]],
    "F": [[(4, 6), (0, 6), (0, 0)], [(0, 3), (3, 3)]],
    "G": [[(4, 6), (0, 6), (0, 0), (4, 0), (4, 3), (2, 3)]],
    "H": [[(0, 0), (0, 6)], [(4, 0), (4, 6)], [(0, 3), (4, 3)]],
    "I": [[(2, 0), (2, 6)], [(0.5, 6), (3.5, 6)], [(0.5, 0), (3.5, 0)]],
    "J": [[(4, 6), (4, 0), (0, 0), (0, 2)]],
    "K": [[(0, 0), (0, 6)], [(4, 6), (0, 3), (4, 0)]],
    "L": [[(0, 6), (0, 0), (4, 0)]],
    "M": [[(0, 0), (0, 6), (2, 3), (4, 6), (4, 0)]],
    "N": [[(0, 0), (0, 6), (4, 0), (4, 6)]],
    "O": [[(0, 0), (0, 6), (4, 6), (4, 0), (0, 0)]],
    "P": [[(0, 0), (0, 6), (4, 6), (4, 3), (0, 3)]],
    "Q": [[(0, 0), (0, 6), (4, 6), (4, 0), (0, 0)], [(2.5, 1.5), (4.5, -0.5)]],
    "R": [[(0, 0), (0, 6), (4, 6), (4, 3), (0, 3), (4, 0)]],
    "S": [[(4, 6), (0, 6), (0, 3), (4, 3), (4, 0), (0, 0)]],
    "T": [[(0, 6), (4, 6)], [(2, 6), (2, 0)]],
    "U": [[(0, 6), (0, 0), (4, 0), (4, 6)]],
    "V": [[(0, 6), (2, 0), (4, 6)]],
    "W": [[(0, 6), (1, 0), (2, 4), (3, 0), (4, 6)]],
    "X": [[(0, 0), (4, 6)], [(0, 6), (4, 0)]],
    "Y": [[(0, 6), (2, 3), (4, 6)], [(2, 3), (2, 0)]],
    "Z": [[(0, 6), (4, 6), (0, 0), (4, 0)]],
    "0": [[(0, 0), (0, 6), (4, 6), (4, 0), (0, 0)], [(0, 0), (4, 6)]],
    "1": [[(1, 5), (2, 6), (2, 0)], [(0.5, 0), (3.5, 0)]],
    "2": [[(0, 6), (4, 6), (4, 3), (0, 3), (0, 0), (4, 0)]],
    "3": [[(0, 6), (4, 6), (4, 0), (0, 0)], [(1, 3), (4, 3)]],
    "4": [[(0, 6), (0, 3), (4, 3)], [(3, 6), (3, 0)]],
    "5": [[(4, 6), (0, 6), (0, 3), (4, 3), (4, 0), (0, 0)]],
    "6": [[(4, 6), (0, 6), (0, 0), (4, 0), (4, 3), (0, 3)]],
    "7": [[(0, 6), (4, 6), (1.5, 0)]],
    "8": [[(0, 0), (0, 6), (4, 6), (4, 0), (0, 0)], [(0, 3), (4, 3)]],
    "9": [[(4, 3), (0, 3), (0, 6), (4, 6), (4, 0), (0, 0)]],
}


def glyph_parts(ch: str, height: float = 0.03, stroke: float = 0.004, depth: float = 0.001) -> list[Part]:
    """Stroke boxes of one glyph, centred on the origin, ``height`` tall, lying on z = 0 .. depth."""
    unit = height / 6.0
    parts = []
    for poly in GLYPHS[ch]:
        for p0, p1 in zip(poly[:-1], poly[1:]):
            a = ((p0[0] - 2) * unit, (p0[1] - 3) * unit)
            b = ((p1[0] - 2) * unit, (p1[1] - 3) * unit)
            parts.append(segment_part(a, b, stroke, depth))
    return parts


def banana_parts(n: int = 7) -> list[Part]:
    """A curved banana lying on its side: frusta along a circular arc in the xy plane, resting on z = 0.

    (Lying on its back, arc in xz, it is a balanced but unstable rocker and rolls over on its own.)
    """
    radius_arc, sweep = 0.12, math.radians(75)
    thick = [0.008, 0.014, 0.018, 0.019, 0.019, 0.018, 0.014, 0.007]
    angles = np.linspace(-sweep / 2, sweep / 2, n + 1)
    parts = []
    for i in range(n):
        pts = []
        for a, r in ((angles[i], thick[i]), (angles[i + 1], thick[i + 1])):
            c = np.array([radius_arc * math.sin(a), radius_arc * (1 - math.cos(a)), 0.0])
            u, v = np.array([-math.sin(a), math.cos(a), 0.0]), np.array([0.0, 0.0, 1.0])  # normal plane of the arc
            pts.extend(c + r * (math.cos(2 * math.pi * k / 10) * u + math.sin(2 * math.pi * k / 10) * v)
                       for k in range(10))
        parts.append(np.asarray(pts))
    allpts = np.concatenate(parts)
    shift = np.array([0.0, -(allpts[:, 1].max() + allpts[:, 1].min()) / 2, -allpts[:, 2].min()])
    return [p + shift for p in parts]


def main(root: Path = ROOT) -> None:
    """Write every generated mesh under ``root`` (the library folder by default)."""
    out = {
        # Hollows that stand on their base disc (as wide as the wall's foot) keep their wall sectors WALL_LIFT off the
        # table: 4 resting contacts instead of 4 more per sector (a bowl: 60).
        "bowl/bowl.obj": revolve_shell([(0.04, 0.0), (0.058, 0.012), (0.07, 0.028), (0.076, 0.045), (0.078, 0.055)],
                                       thickness=0.005, sectors=14, bands=2, wall_lift=WALL_LIFT),
        "cup/cup.obj": revolve_shell([(0.03, 0.0), (0.04, 0.10)], thickness=0.003, sectors=12, wall_lift=WALL_LIFT),
        # poured from with balls inside: eight sectors and a wall off the table, for fewer contacts
        "cup/pouring_cup.obj": revolve_shell([(0.03, 0.0), (0.04, 0.10)], thickness=0.003, sectors=8, base=0.004,
                                             wall_lift=WALL_LIFT),
        # a straight band at the (upturned) top: the pads grip it along a line, so the cup cannot pivot in them
        "cover/cover_cup.obj": on_feet(upside_down(revolve_shell([(0.03, 0.0), (0.03, 0.03), (0.04, 0.10)],
                                                                 thickness=0.003, sectors=12, bands=2)),
                                       radius=0.0385),
        "mug/mug_body.obj": revolve_shell([(0.04, 0.0), (0.04, 0.095)], thickness=0.005, sectors=12,
                                          wall_lift=WALL_LIFT),
        "bottle/bottle.obj": revolve_solid([(0.0, 0.0), (0.033, 0.0), (0.034, 0.003), (0.034, 0.14), (0.026, 0.17),
                                            (0.013, 0.19), (0.013, 0.215), (0.0, 0.215)]),
        "bottle/wine_bottle.obj": revolve_solid([(0.0, 0.0), (0.036, 0.0), (0.037, 0.004), (0.037, 0.19),
                                                 (0.03, 0.215), (0.014, 0.24), (0.012, 0.3), (0.0, 0.3)]),
        "plate/plate.obj": revolve_shell([(0.07, 0.0), (0.10, 0.012), (0.115, 0.02)], thickness=0.004, sectors=16,
                                         bands=1, base=0.006, wall_lift=WALL_LIFT),
        # wide enough at the bottom (22.8 cm inside) for a 21.5 cm bottle to lie flat: four settle below the rim
        "dustbin/dustbin.obj": revolve_shell([(0.12, 0.0), (0.14, 0.26)], thickness=0.006, sectors=14, base=0.01),
        "pen_holder/pen_holder.obj": revolve_shell([(0.04, 0.0), (0.04, 0.11)], thickness=0.004, sectors=12,
                                                   base=0.008, wall_lift=WALL_LIFT),
        "nesting_doll/doll.obj": revolve_solid([(0.0, 0.0), (0.03, 0.0), (0.04, 0.025), (0.038, 0.055),
                                                (0.026, 0.075), (0.03, 0.095), (0.026, 0.115), (0.0, 0.125)]),
        "fruit/pear.obj": revolve_solid([(0.0, 0.0), (0.016, 0.0), (0.028, 0.006), (0.037, 0.025), (0.034, 0.05), (0.022, 0.07),
                                         (0.016, 0.088), (0.0, 0.096)]),
        "fruit/banana.obj": banana_parts(),
        "egg/egg.obj": revolve_solid([(0.0, 0.0), (0.014, 0.003), (0.021, 0.015), (0.022, 0.026), (0.018, 0.042),
                                      (0.01, 0.052), (0.0, 0.056)], n=12),
        "pen/pen_cap.obj": lying_along_x(revolve_shell([(0.0078, 0.0), (0.0078, 0.035)], thickness=0.0015,
                                                       sectors=12, base=0.003)),
        "stationery/tape_roll.obj": on_feet(annulus(0.05, 0.037, 0.048, sectors=16), radius=0.0435),
        "cleaning/spray_bottle.obj": revolve_solid([(0.0, 0.0), (0.035, 0.0), (0.035, 0.15), (0.02, 0.17),
                                                    (0.015, 0.2), (0.0, 0.2)]),
    }
    for rel, parts in out.items():
        write_obj(root / rel, parts)
    # a 3 cm solid base: a ball falling the vase's depth lands on it without sinking through a thin plate
    vase = revolve_shell([(0.045, 0.0), (0.07, 0.06), (0.07, 0.12), (0.05, 0.17), (0.045, 0.2)],
                         thickness=0.005, sectors=8, bands=4, base=0.03, wall_lift=0.002)
    write_usda(root / "vase" / "vase.usda", vase)
    for ch in GLYPHS:
        folder = "letter_block" if ch.isalpha() else "number_block"
        write_obj(root / folder / "glyphs" / f"{ch.lower()}.obj", glyph_parts(ch))


if __name__ == "__main__":
    main()
