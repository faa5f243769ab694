"""Write the letter and digit block specs (assets/letter_block, assets/number_block) from the stroke font.

Run after make_meshes.py (which writes the glyph meshes): ``python assets/tools/make_glyph_blocks.py``.
Each block is a 4 cm cube with its glyph printed (visual geoms) on the top face and on the -x face, both
reading upright for a viewer at -x.
"""

from __future__ import annotations

from pathlib import Path

from make_meshes import GLYPHS

ROOT = Path(__file__).resolve().parents[1]
TOP_QUAT = "[0.7071068, 0, 0, -0.7071068]"  # glyph x -> -y and glyph up -> +x (away from a viewer at -x)
FRONT_QUAT = "[0.5, 0.5, -0.5, -0.5]"  # glyph x -> -y and glyph up -> +z and glyph normal -> -x

TEMPLATE = """kind: asset
version: 1
id: {id}
class: rigid
category: {category}
names: [{kind} {ch} block, block with the {kind} {ch}, "{ch}"]
description: A 4 cm {kind} block printed with "{ch}" on its top and -x faces. {tasks}
tags: [graspable, stackable, {kind}]
scale_range: [0.95, 1.05]
mass: 0.04
friction: 0.9
rgba: [0.93, 0.85, 0.68, 1]
colors:
  - {{name: natural, rgba: [0.93, 0.85, 0.68, 1]}}
  - {{name: white, rgba: [0.95, 0.95, 0.95, 1]}}
  - {{name: yellow, rgba: [0.98, 0.85, 0.35, 1]}}
geoms:
  - {{name: cube, type: box, size: [0.02, 0.02, 0.02], pos: [0, 0, 0.02]}}
  - {{name: glyph_top, type: mesh, mesh: glyphs/{file}.obj, pos: [0, 0, 0.04], quat: {top},
      rgba: [0.1, 0.1, 0.12, 1], visual: true}}
  - {{name: glyph_front, type: mesh, mesh: glyphs/{file}.obj, pos: [-0.02, 0, 0.02], quat: {front},
      rgba: [0.1, 0.1, 0.12, 1], visual: true}}
annotations:
  - {{name: grasp, kind: grasp, pos: [0, 0, 0.02], size: [0.02, 0.02, 0.02]}}
  - {{name: top, kind: frame, pos: [0, 0, 0.04]}}
  - {{name: front, kind: frame, pos: [-0.02, 0, 0.02], description: Face the glyph reads from.}}
"""


def main() -> None:
    for ch in GLYPHS:
        is_letter = ch.isalpha()
        category = "letter_block" if is_letter else "number_block"
        spec = TEMPLATE.format(
            id=f"{category}_{ch.lower()}", category=category, kind="letter" if is_letter else "number", ch=ch,
            file=ch.lower(), top=TOP_QUAT, front=FRONT_QUAT,
            tasks="Spelling words (dlc) and stack_blocks_by_language." if is_letter
            else "arrange_largest_number and solve_equation and press_by_number.",
        )
        (ROOT / category / f"{category}_{ch.lower()}.yaml").write_text(spec)


if __name__ == "__main__":
    main()
