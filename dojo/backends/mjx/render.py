"""Batched camera images for the mjx backend: RGB uint8 and depth uint16 millimetres, per environment and camera.

Choice. Images come from the batched ray tracer that `mujoco.mjx` exposes on MuJoCo Warp (`create_render_context`,
`refit_bvh`, `render`): it reads the simulation arrays where they already are (device memory), takes the
per-environment model fields of a bucket (colours, materials, texture ids, lights) through the same `vmap`
`in_axes` as the physics, and returns packed pixels that this module converts to uint8 / uint16 millimetres on the
device, so only finished observations cross to the host. Alternatives measured (figures in the lead's README and
in `dojo bench render`): MuJoCo's OpenGL renderer, through EGL on the GPU machine or on the CPU here, renders one
camera of one environment per call (its scene is rebuilt on the host from MjData) and reached 27 frames/s at
640x480 per core on the CI machine, hundreds of times below the batched tracer; a ray caster written in JAX
(`mjx.ray` vmapped over pixels) computes depth only, no shading, and is bounded by per-ray geom loops that XLA
cannot prune with a BVH. Without an NVIDIA GPU or warp, `CpuRenderer` renders the same batch with MuJoCo's renderer
(`make_renderer` picks it and says why); asked for by name, the tracer also runs on Warp's CPU device.

What matches MuJoCo and what does not. Cameras: the plan's intrinsics (fovy, resolution from the config) and
poses; poses are recomputed here from body poses for fixed cameras (and fixed lights, whose positions may differ
per environment) because a warp physics step leaves `cam_xpos` one sub-step behind the bodies (its `kinematics`
does not run `camlight`); a state moved by `kinematics` alone renders correctly, with no physics kernels involved.
Lights, materials, textures, the skybox background and the headlight come from each environment's model. Depth is planar (distance
along the optical axis, as MuJoCo's depth buffer); a pixel that hits nothing (the skybox) is 0, the usual "no
reading" of depth cameras, on both paths. MuJoCo's near plane hides geoms that sit right at a camera (a wrist camera's housing); a ray tracer has no near
plane, so such geoms are left out of that camera's context (`near_clipped_geoms`). The ray tracer draws no
reflections and, unless `shadows`, no shadows;
`render_parity` states how close the pictures are.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from dojo.backends.mujoco.render import ensure_headless_gl, open_renderer
from dojo.backends.mjx.cache import warp_installed

log = logging.getLogger(__name__)
Array = Any

CAMERAS = ("head", "left_wrist", "right_wrist")
VISIBLE_GROUPS = (0, 1, 2)
"""Geom groups drawn, as in MuJoCo's default visualisation options."""
HIDDEN_GROUP = 5
MAX_DEPTH_MM = 65535
"""uint16 saturates here (65.5 m), far beyond any scene; misses are 0."""


@dataclass(frozen=True)
class RenderConfig:
    """What to render: which cameras (subset of the robot's, in this order), at what size, and depth or not."""

    cameras: tuple[str, ...] = CAMERAS
    width: int = 640
    height: int = 480
    depth: bool = False
    shadows: bool = False

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if len(set(self.cameras)) != len(self.cameras):
            raise ValueError(f"cameras repeat: {list(self.cameras)}")


class Frames(NamedTuple):
    """Images of a batch: `rgb` uint8 [B, C, H, W, 3], `depth` uint16 millimetres [B, C, H, W] or None."""

    rgb: Array
    depth: Array | None


@dataclass(frozen=True)
class PixelLayout:
    """Where each rendered camera's pixels start in the packed per-world buffers (one entry per camera)."""

    width: int
    height: int
    rgb_adr: tuple[int, ...]
    depth_adr: tuple[int, ...]

    @classmethod
    def contiguous(cls, ncam: int, width: int, height: int, depth: bool) -> PixelLayout:
        """The layout the warp renderer uses when every camera has the same size and outputs."""
        adr = tuple(k * width * height for k in range(ncam))
        return cls(width, height, adr, adr if depth else ())


def camera_ids(model: mujoco.MjModel, cameras: Sequence[str]) -> np.ndarray:
    """Camera ids of `cameras` in `model`; an unknown name raises with the model's camera names."""
    ids = np.asarray([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, c) for c in cameras], dtype=np.int32)
    missing = [c for c, i in zip(cameras, ids) if i < 0]
    if missing:
        known = [model.camera(i).name for i in range(model.ncam)]
        raise ValueError(f"cameras {missing} are not in the model (it has {known})")
    return ids


def _per_camera(flat: Array, adr: Sequence[int], width: int, height: int) -> Array:
    """[..., P] packed pixels -> [..., C, H, W], one slice per camera address."""
    size = width * height
    if tuple(adr) == tuple(k * size for k in range(len(adr))):  # one reshape, no copies, in the usual case
        cut = flat[..., :len(adr) * size]
        return cut.reshape(flat.shape[:-1] + (len(adr), height, width))
    parts = [flat[..., a:a + size].reshape(flat.shape[:-1] + (height, width)) for a in adr]
    return jnp.stack(parts, axis=-3)


def unpack_rgb(packed: Array, layout: PixelLayout) -> Array:
    """uint32 pixels packed as the warp renderer writes them (blue in the low byte, then green, red, alpha)
    -> uint8 [..., C, H, W, 3], by reinterpreting the bytes (no float round trip)."""
    pixels = _per_camera(jnp.asarray(packed, dtype=jnp.uint32), layout.rgb_adr, layout.width, layout.height)
    channels = jax.lax.bitcast_convert_type(pixels, jnp.uint8)  # little endian: [b, g, r, a]
    return channels[..., 2::-1]


def depth_to_mm(metres: Array) -> Array:
    """Depth in metres -> uint16 millimetres, rounded; 0 (no hit) stays 0, far values saturate."""
    mm = jnp.round(jnp.asarray(metres, dtype=jnp.float32) * 1000.0)
    return jnp.clip(mm, 0, MAX_DEPTH_MM).astype(jnp.uint16)


def unpack_depth(flat: Array, layout: PixelLayout) -> Array:
    """float32 planar depth in metres, packed per world -> uint16 millimetres [..., C, H, W]."""
    return depth_to_mm(_per_camera(flat, layout.depth_adr, layout.width, layout.height))


def quat_to_mat(q: Array) -> Array:
    """Unit quaternions [..., 4] (w, x, y, z) -> rotation matrices [..., 3, 3]."""
    w, x, y, z = (q[..., i] for i in range(4))
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def fixed_camera_poses(xpos: Array, xmat: Array, cam_bodyid: np.ndarray, cam_pos: Array, cam_quat: Array
                       ) -> tuple[Array, Array]:
    """World poses of cameras fixed to their bodies (one world): `xpos [nbody, 3]`, `xmat [nbody, 3, 3]` or
    `[nbody, 9]`, the cameras' local `cam_pos [ncam, 3]` and `cam_quat [ncam, 4]` -> `([ncam, 3], [ncam, 3, 3])`.
    What MuJoCo's `mj_camlight` computes for `mjCAMLIGHT_FIXED` cameras."""
    body_mat = jnp.reshape(xmat, (-1, 3, 3))[cam_bodyid]
    pos = xpos[cam_bodyid] + jnp.einsum("cij,cj->ci", body_mat, cam_pos)
    return pos, body_mat @ quat_to_mat(cam_quat)


def fixed_light_poses(xpos: Array, xmat: Array, light_bodyid: np.ndarray, light_pos: Array, light_dir: Array
                      ) -> tuple[Array, Array]:
    """World positions and directions of lights fixed to their bodies (one world), as `mj_camlight` computes them
    for `mjCAMLIGHT_FIXED` lights: `([nlight, 3], [nlight, 3])`."""
    body_mat = jnp.reshape(xmat, (-1, 3, 3))[light_bodyid]
    pos = xpos[light_bodyid] + jnp.einsum("lij,lj->li", body_mat, light_pos)
    return pos, jnp.einsum("lij,lj->li", body_mat, light_dir)


def warp_renderer_available() -> tuple[bool, str]:
    """Whether the batched renderer can run here, and if not, why (for the fallback's log line)."""
    if not warp_installed():
        return False, "warp-lang is not installed"
    gpus = [d for d in jax.devices() if d.platform in ("gpu", "cuda")]
    if not gpus:
        return False, f"JAX sees no NVIDIA GPU (platform {jax.default_backend()})"
    return True, f"warp on {gpus[0].device_kind}"


def near_clipped_geoms(model: mujoco.MjModel, cam_id: int) -> tuple[int, ...]:
    """Geoms on a fixed camera's own body that lie wholly nearer than MuJoCo's near plane.

    OpenGL clips them away, so MuJoCo's images never show them (a wrist camera mounted on its housing looks past
    it); a ray tracer starts rays at the camera and would see them filling the view. Judged once from the model,
    since camera and geom are rigid on one body: every corner of the geom's bounding box must be nearer than
    `znear` along the optical axis.
    """
    if model.cam_mode[cam_id] != mujoco.mjtCamLight.mjCAMLIGHT_FIXED:
        return ()
    znear = model.vis.map.znear * model.stat.extent
    cam_rot = np.zeros(9)
    mujoco.mju_quat2Mat(cam_rot, model.cam_quat[cam_id])
    axis = -cam_rot.reshape(3, 3)[:, 2]
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    hidden = []
    for g in np.flatnonzero(model.geom_bodyid == model.cam_bodyid[cam_id]):
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, model.geom_quat[g])
        center, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        corners = model.geom_pos[g] + (center + signs * half) @ rot.reshape(3, 3).T
        if np.all((corners - model.cam_pos[cam_id]) @ axis < znear):
            hidden.append(int(g))
    return tuple(hidden)


class _Context:
    """One warp render context: the cameras it renders (positions in the config's order) and its pixel layout."""

    def __init__(self, model: mujoco.MjModel, nworld: int, config: RenderConfig, cameras: list[int],
                 hidden: tuple[int, ...]) -> None:
        from mujoco import mjx

        self.slots = cameras
        ids = camera_ids(model, [config.cameras[k] for k in cameras])
        if hidden:  # the context draws the enabled groups of its own model copy; the dynamics model is untouched
            model = copy.copy(model)
            model.geom_group[list(hidden)] = HIDDEN_GROUP
        self.context = mjx.create_render_context(
            model, nworld, cam_res=(config.width, config.height), cam_active=[int(i) for i in ids],
            render_rgb=True, render_depth=config.depth, use_textures=True, use_shadows=config.shadows,
            render_skybox=bool(np.any(model.tex_type == mujoco.mjtTexture.mjTEXTURE_SKYBOX)),
            enabled_geom_groups=list(VISIBLE_GROUPS),
        )
        self.layout = PixelLayout(
            config.width, config.height, tuple(int(a) for a in self.context.rgb_adr.numpy()),
            tuple(int(a) for a in self.context.depth_adr.numpy()) if config.depth else ())
        self.handle = self.context.pytree()


class WarpRenderer:
    """The batched renderer of one bucket: MuJoCo Warp render contexts for `nworld` environments.

    Contexts are built from the bucket's reference model (meshes, textures and skybox are shared structure in a
    bucket; per-environment values arrive through the model passed to `__call__`). Cameras share one context
    unless `near_clipped_geoms` hides different geoms from them (wrist cameras on their housings): each such set
    gets its own context. Keep the object alive while its images are used: a context's destructor frees its
    device buffers.
    """

    def __init__(self, model: mujoco.MjModel, nworld: int, config: RenderConfig) -> None:
        self.config, self.nworld = config, nworld
        ids = camera_ids(model, config.cameras)
        self.camera_ids = ids
        self._fixed = ids[model.cam_mode[ids] == mujoco.mjtCamLight.mjCAMLIGHT_FIXED]
        self._fixed_body = model.cam_bodyid[self._fixed]
        self._fixed_lights = np.flatnonzero(model.light_mode == mujoco.mjtCamLight.mjCAMLIGHT_FIXED)
        self._light_body = model.light_bodyid[self._fixed_lights]
        groups: dict[tuple[int, ...], list[int]] = {}
        for k, cam in enumerate(ids):
            groups.setdefault(near_clipped_geoms(model, int(cam)), []).append(k)
        self.contexts = [_Context(model, nworld, config, cams, hidden) for hidden, cams in groups.items()]

    def _with_poses(self, m: Any, d: Any) -> Any:
        """`d` with fixed cameras and lights placed from the current body poses (see the module docstring)."""
        fixed = self._fixed
        if fixed.size:
            pos, mat = fixed_camera_poses(d.xpos, d.xmat, self._fixed_body, m.cam_pos[fixed], m.cam_quat[fixed])
            d = d.replace(cam_xpos=d.cam_xpos.at[fixed].set(pos.astype(d.cam_xpos.dtype)),
                          cam_xmat=d.cam_xmat.at[fixed].set(mat.reshape(d.cam_xmat[fixed].shape)
                                                            .astype(d.cam_xmat.dtype)))
        lights = self._fixed_lights
        if lights.size:
            pos, direction = fixed_light_poses(d.xpos, d.xmat, self._light_body, m.light_pos[lights],
                                               m.light_dir[lights])
            impl = d._impl
            d = d.tree_replace({"_impl.light_xpos": impl.light_xpos.at[lights].set(pos.astype(impl.light_xpos.dtype)),
                                "_impl.light_xdir": impl.light_xdir.at[lights].set(
                                    direction.astype(impl.light_xdir.dtype))})
        return d

    def __call__(self, m: Any, data: Any, in_axes: Any = None) -> Frames:
        """Images of a batch (traceable; call inside jit): `m` an mjx.Model (warp) whose per-environment fields
        are batched as `in_axes` says (None: shared), `data` the batch of `nworld` mjx.Data at the current state."""
        from mujoco import mjx

        def one(mw: Any, dw: Any) -> tuple[tuple[Array, Array], ...]:
            dw = self._with_poses(mw, dw)
            out = []
            for ctx in self.contexts:
                dw = mjx.refit_bvh(mw, dw, ctx.handle)
                rgb, depth, dw = mjx.render(mw, dw, ctx.handle)
                out.append((rgb, depth))
            return tuple(out)

        packed = jax.vmap(one, in_axes=(in_axes, 0))(m, data)
        rgb: list[Array] = [None] * len(self.config.cameras)
        depth: list[Array] = [None] * len(self.config.cameras)
        for ctx, (flat_rgb, flat_depth) in zip(self.contexts, packed):
            images = unpack_rgb(flat_rgb, ctx.layout)
            ranges = unpack_depth(flat_depth, ctx.layout) if self.config.depth else None
            for j, k in enumerate(ctx.slots):
                rgb[k] = images[:, j]
                depth[k] = None if ranges is None else ranges[:, j]
        return Frames(jnp.stack(rgb, axis=1), jnp.stack(depth, axis=1) if self.config.depth else None)


class CpuRenderer:
    """The fallback: MuJoCo's renderer (EGL or OSMesa, headless) on the host, one environment at a time.

    Environments name the model they simulate by index into `models` (a bucket's member models); each model gets
    one `mujoco.Renderer`, created on first use and reused, since creating a GL context costs far more than a frame.
    Depth follows the batched renderer's convention: planar millimetres, 0 where the ray meets no geom.
    """

    def __init__(self, models: Sequence[mujoco.MjModel], config: RenderConfig) -> None:
        ensure_headless_gl()
        self.models, self.config = list(models), config
        for model in self.models:
            camera_ids(model, config.cameras)
        self._renderers: dict[int, mujoco.Renderer] = {}
        self._data: dict[int, mujoco.MjData] = {}

    def _renderer(self, k: int) -> mujoco.Renderer:
        if k not in self._renderers:
            r = open_renderer(self.models[k], self.config.height, self.config.width)
            r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.config.shadows
            self._renderers[k] = r
        return self._renderers[k]

    def render(self, members: Sequence[int], qpos: Sequence[np.ndarray]) -> Frames:
        """Images of a batch: `members[i]` indexes the model of environment i, `qpos[i]` its state (a batched
        `[B, nq]` array within a bucket; a list when the models differ)."""
        cfg = self.config
        b, c = len(members), len(cfg.cameras)
        rgb = np.zeros((b, c, cfg.height, cfg.width, 3), np.uint8)
        depth = np.zeros((b, c, cfg.height, cfg.width), np.uint16) if cfg.depth else None
        for i, k in enumerate(int(m) for m in members):
            model = self.models[k]
            if k not in self._data:
                self._data[k] = mujoco.MjData(model)
            data = self._data[k]
            data.qpos[:] = qpos[i]
            mujoco.mj_kinematics(model, data)
            mujoco.mj_camlight(model, data)
            renderer = self._renderer(k)
            for j, cam in enumerate(cfg.cameras):
                renderer.update_scene(data, camera=cam)
                rgb[i, j] = renderer.render()
                if depth is not None:
                    renderer.enable_depth_rendering()
                    renderer.update_scene(data, camera=cam)
                    depth[i, j] = cpu_depth_mm(renderer.render(), model)
                    renderer.disable_depth_rendering()
        return Frames(rgb, depth)

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()


def cpu_depth_mm(metres: np.ndarray, model: mujoco.MjModel) -> np.ndarray:
    """MuJoCo's depth buffer (metres, far plane where nothing was drawn) -> uint16 mm with 0 for no hit."""
    far = model.vis.map.zfar * model.stat.extent
    mm = np.clip(np.round(metres * 1000.0), 0, MAX_DEPTH_MM)
    return np.where(metres >= 0.999 * far, 0, mm).astype(np.uint16)


def make_renderer(models: Sequence[mujoco.MjModel], nworld: int, config: RenderConfig,
                  impl: str = "auto") -> WarpRenderer | CpuRenderer:
    """The batched renderer for a bucket when it can run here (impl `auto` or `warp`), else the CPU fallback.

    `models` are the bucket's member models, the first being the reference. `impl="warp"` never falls back: without
    warp-lang it raises, so that a run which asked for the batched renderer never silently measures MuJoCo's, and
    without a GPU it renders on Warp's CPU device (the same ray tracer, for checks).
    """
    if impl == "warp":
        if not warp_installed():
            raise RuntimeError("the warp renderer was asked for but cannot run: warp-lang is not installed")
        return WarpRenderer(models[0], nworld, config)
    ok, why = warp_renderer_available()
    if impl == "jax" or not ok:
        log.info("rendering on the CPU with MuJoCo's renderer (%s)", why if not ok else "impl=jax")
        return CpuRenderer(models, config)
    return WarpRenderer(models[0], nworld, config)


def observation_images(frames: Frames, cameras: Sequence[str]) -> list[dict[str, dict[str, np.ndarray]]]:
    """Per environment `{"images": {camera: uint8[H, W, 3]}, "depth": {...}}` (DESIGN section 4) from one batch,
    with a single device-to-host copy per array."""
    rgb = np.asarray(frames.rgb)
    depth = None if frames.depth is None else np.asarray(frames.depth)
    out = []
    for i in range(rgb.shape[0]):
        obs: dict[str, dict[str, np.ndarray]] = {"images": {c: rgb[i, k] for k, c in enumerate(cameras)}}
        if depth is not None:
            obs["depth"] = {c: depth[i, k] for k, c in enumerate(cameras)}
        out.append(obs)
    return out
