"""Render the asset library laid out on the table, to look at it: ``python assets/tools/render_gallery.py [ids...]``.

Writes /tmp/assets_<k>.png, one image per table of assets (after 1 s of settling), with the presets named by
--texture, --background and --lighting. Needs an OpenGL backend (MUJOCO_GL=egl or osmesa when headless).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import yaml  # noqa: E402
from PIL import Image  # noqa: E402

from dojo.compiler.asset_emit import apply_background, apply_lighting, apply_table_texture  # noqa: E402
from dojo.compiler.asset_gallery import Item, pack, table_scene  # noqa: E402

LIBRARY = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("ids", nargs="*", help="asset ids or categories to show (default: every physical asset)")
    ap.add_argument("--texture", default="wood_light")
    ap.add_argument("--background", default="studio_grey")
    ap.add_argument("--lighting", default="bright_studio")
    ap.add_argument("--size", type=int, nargs=2, default=(960, 720))
    ap.add_argument("--out", default="/tmp/assets")
    args = ap.parse_args()
    items = {}
    for path in sorted(LIBRARY.rglob("*.yaml")):
        asset = yaml.safe_load(path.read_text())
        items[asset["id"]] = Item(asset, path.parent)
    physical = [it for it in items.values() if it.asset["class"] in ("rigid", "articulated", "cloth")
                and it.asset["id"] != "table"]
    if args.ids:
        physical = [it for it in physical if it.asset["id"] in args.ids or it.asset["category"] in args.ids]
    for k, placed in enumerate(pack(physical)):
        spec, _ = table_scene(items["table"], placed)
        spec.delete(spec.geom("floor"))
        apply_table_texture(spec, items[args.texture].asset, base_dir=items[args.texture].base_dir)
        apply_background(spec, items[args.background].asset, base_dir=items[args.background].base_dir)
        apply_lighting(spec, items[args.lighting].asset)
        spec.visual.global_.offwidth, spec.visual.global_.offheight = args.size
        model = spec.compile()
        data = mujoco.MjData(model)
        for _ in range(int(1.0 / model.opt.timestep)):
            mujoco.mj_step(model, data)
        cam = mujoco.MjvCamera()
        cam.lookat[:] = (0.05, 0.0, 0.78)
        cam.distance, cam.azimuth, cam.elevation = 1.5, 0.0, -50.0
        with mujoco.Renderer(model, height=args.size[1], width=args.size[0]) as renderer:
            renderer.update_scene(data, camera=cam)
            pixels = renderer.render()
        out = Path(f"{args.out}_{k}.png")
        Image.fromarray(pixels).save(out)
        print(out, ", ".join(it.asset["id"] for it, _ in placed))


if __name__ == "__main__":
    main()
