"""Offscreen rendering with MuJoCo's own renderer, headless.

MuJoCo picks its OpenGL platform from MUJOCO_GL when it is first imported; `ensure_headless_gl` chooses one
(`dojo.backends.gl_platform`: EGL, which needs no display and without a GPU runs on Mesa's software driver, else
OSMesa, else none) unless the user chose, and must run before `mujoco` is imported by anything that will render.
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import numpy as np

from dojo.backends.gl_platform import choose_gl_platform, gl_enabled, gl_unavailable_reason


def ensure_headless_gl() -> None:
    """Choose a headless GL platform for MuJoCo unless one is already chosen (none where no library loads)."""
    choose_gl_platform()


SHADOW_MAP_SIZE = 2048
"""Side of the shadow map in pixels. MuJoCo's default, 4096, cost 38 of the 51 ms of a 224x224 frame on the CI
machine's CPU (Mesa); 2048 halves the frame time and changed a 640x480 head image by 0.08 grey levels on average."""


def open_renderer(model: "mujoco.MjModel", height: int, width: int) -> "mujoco.Renderer":
    """A MuJoCo renderer with our shadow map size (a drawing setting only: `vis` never affects the physics).

    Where no OpenGL platform is available (MUJOCO_GL disabled), the error says so and what to install, instead of
    MuJoCo's `module 'mujoco.gl_context' has no attribute 'GLContext'`."""
    import mujoco

    if not gl_enabled():
        raise RuntimeError(gl_unavailable_reason())
    model.vis.quality.shadowsize = min(int(model.vis.quality.shadowsize), SHADOW_MAP_SIZE)
    return mujoco.Renderer(model, height=height, width=width)


def _render_with(renderer: "mujoco.Renderer", data: "mujoco.MjData", cameras: list[str],
                 depth: bool) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for name in cameras:
        renderer.update_scene(data, camera=name)
        out[name] = renderer.render().copy()
        if depth:
            renderer.enable_depth_rendering()
            renderer.update_scene(data, camera=name)
            metres = renderer.render()
            out[f"{name}_depth"] = np.clip(np.round(metres * 1000.0), 0, 65535).astype(np.uint16)
            renderer.disable_depth_rendering()
    return out


def render_cameras(model: "mujoco.MjModel", data: "mujoco.MjData", cameras: list[str], width: int, height: int,
                   depth: bool = False) -> dict[str, np.ndarray]:
    """RGB uint8[H, W, 3] per named camera (and `<camera>_depth` uint16 millimetres when `depth`), for one-off
    pictures; an evaluation renders every step and keeps its renderers in a `RendererCache`."""
    with open_renderer(model, height, width) as renderer:
        return _render_with(renderer, data, cameras, depth)


class RendererCache:
    """One MuJoCo renderer (GL context, uploaded meshes and textures) per model, kept between calls.

    Creating a renderer costs far more than a frame (it uploads the whole model), so a backend that renders every
    control step must reuse them. The least recently used are closed beyond `capacity` models.
    """

    def __init__(self, width: int, height: int, capacity: int = 8):
        self.width, self.height, self.capacity = width, height, capacity
        self._renderers: OrderedDict[int, tuple["mujoco.MjModel", "mujoco.Renderer"]] = OrderedDict()

    def render(self, model: "mujoco.MjModel", data: "mujoco.MjData", cameras: list[str],
               depth: bool = False) -> dict[str, np.ndarray]:
        key = id(model)
        if key not in self._renderers:
            if len(self._renderers) >= self.capacity:
                _, (_, oldest) = self._renderers.popitem(last=False)
                oldest.close()
            self._renderers[key] = (model, open_renderer(model, self.height, self.width))
        self._renderers.move_to_end(key)
        return _render_with(self._renderers[key][1], data, cameras, depth)

    def close(self) -> None:
        for _, renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()


def overview_camera(model: "mujoco.MjModel") -> "mujoco.MjvCamera":
    """A free camera looking at the table from the front-left, for pictures of a whole scene."""
    import mujoco

    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = (0.0, 0.0, 0.8)
    cam.distance, cam.azimuth, cam.elevation = 2.0, 120.0, -30.0
    return cam


def render_overview(model: "mujoco.MjModel", data: "mujoco.MjData", width: int, height: int) -> np.ndarray:
    """RGB uint8[H, W, 3] of the whole scene from `overview_camera`."""
    with open_renderer(model, height, width) as renderer:
        renderer.update_scene(data, camera=overview_camera(model))
        return renderer.render().copy()


def save_png(image: np.ndarray, path: Path) -> None:
    """Write an RGB (uint8) or depth (uint16) image as PNG."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)
