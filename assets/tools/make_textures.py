"""Generate the library's image textures (PNG) from code: ``python assets/tools/make_textures.py``.

Procedural builtins cover most table tops; wood grain needs an image. Output is deterministic.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]


def wood_grain(size: int = 256, seed: int = 7) -> np.ndarray:
    """Planks of wood grain: rings bent by smooth noise, light and dark bands, plank seams every quarter."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    bend = sum(rng.uniform(0.002, 0.006) * np.sin(2 * np.pi * (k * x + rng.uniform())) for k in (1, 2, 3))
    plank = np.floor(y * 4)
    rings = np.sin(2 * np.pi * (40 * (y + bend) + 0.37 * plank + 1.5 * x * (plank % 2 - 0.5)))
    fibre = rng.normal(0, 0.04, (size, 1)).repeat(size, axis=1)
    tone = 0.55 + 0.25 * rings ** 3 + fibre
    light, dark = np.array([0.78, 0.6, 0.4]), np.array([0.55, 0.36, 0.2])
    rgb = dark + (light - dark) * np.clip(tone, 0, 1)[..., None]
    seam = (np.abs(y * 4 - np.round(y * 4)) < 1.5 / size)[..., None]
    rgb = np.where(seam, rgb * 0.55, rgb)
    return (np.clip(rgb, 0, 1) * 255).astype(np.uint8)


def main(root: Path = ROOT) -> None:
    """Write every generated texture under ``root``."""
    (root / "table_texture").mkdir(parents=True, exist_ok=True)
    Image.fromarray(wood_grain()).save(root / "table_texture" / "wood_grain.png", optimize=True)


if __name__ == "__main__":
    main()
