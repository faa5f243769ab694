"""Parity of the batched renderer with MuJoCo's own renderer, on compiled scenes of every built-in task.

`python -m dojo.backends.mjx.render_parity [--width 640 --height 480] [--out DIR] [PLAN.json ...]` (GPU machine)
compiles seed 0 of every built-in task in both settings (or loads the given plans), and for each plan renders two
environments with the batched renderer: the plan's initial state, and the arms moved away from home (so the wrist
cameras look elsewhere). The batched path gets its state from `kinematics` alone (no physics kernels to
compile), leaving cameras and lights to `WarpRenderer`'s own pose update, as after a warp physics step. The same
states are rendered with `mujoco.Renderer` and compared per camera:

- RGB against MuJoCo with shadows and reflections off (what the tracer draws): mean absolute error in 0-255
  units and structural similarity (grey levels, 7x7 window) must be within `RGB_MAE_MAX` and `SSIM_MIN`; the same
  figures against MuJoCo's default look (shadows, reflective table) are reported, not judged.
- Depth in millimetres: over pixels that both renderers hit, the median absolute difference must be at most
  `DEPTH_MEDIAN_MM_MAX` and at least `DEPTH_WITHIN_FRACTION_MIN` of them within `DEPTH_WITHIN_MM` (object
  silhouettes, where one renderer hits the object and the other the table behind, make up the rest).

It prints one JSON object (per plan and camera, worst cases, pass/fail), writes one picture per plan
(MuJoCo | batched, every camera of both states) when `--out` is given, and exits 1 when a threshold is missed.
A GPU machine without EGL or OSMesa cannot run MuJoCo's renderer: the script then saves the batched images, exits
2, and `--against DIR` finishes the comparison on a machine with GL. The metric helpers need no GPU and are tested
in CI.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

RGB_MAE_MAX = 10.0
SSIM_MIN = 0.85
DEPTH_MEDIAN_MM_MAX = 2.0
DEPTH_WITHIN_MM = 10.0
DEPTH_WITHIN_FRACTION_MIN = 0.95
ARM_OFFSET_RAD = 0.35
"""How far each arm joint is turned from home for the second environment."""


def rgb_mae(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two uint8 images, in 0-255 units."""
    return float(np.mean(np.abs(a.astype(np.float64) - b.astype(np.float64))))


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio of two images in 0-255 units, in dB (capped at 99 for identical images)."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 99.0 if mse == 0 else min(99.0, 10.0 * float(np.log10(255.0 ** 2 / mse)))


def block_mean(image: np.ndarray, k: int = 4) -> np.ndarray:
    """`image [H, W, C]` averaged over k x k blocks (edges cropped): what is left once texture grain finer than k
    pixels is gone, to tell sampling differences (a tracer's texture lookup against OpenGL's filtered one) from
    shading or geometry differences, which survive it."""
    h, w = image.shape[0] // k * k, image.shape[1] // k * k
    x = image[:h, :w].astype(np.float64)
    return x.reshape(h // k, k, w // k, k, -1).mean(axis=(1, 3))


def _box_mean(x: np.ndarray, k: int) -> np.ndarray:
    """Mean over every k x k window (valid positions only), by summed-area table."""
    s = np.pad(np.cumsum(np.cumsum(x, axis=0), axis=1), ((1, 0), (1, 0)))
    return (s[k:, k:] - s[:-k, k:] - s[k:, :-k] + s[:-k, :-k]) / (k * k)


def ssim(a: np.ndarray, b: np.ndarray, window: int = 7) -> float:
    """Structural similarity of two uint8 RGB images on their grey levels (uniform window, the usual constants)."""
    weights = np.array([0.299, 0.587, 0.114])
    x, y = a.astype(np.float64) @ weights, b.astype(np.float64) @ weights
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    mx, my = _box_mean(x, window), _box_mean(y, window)
    vx = _box_mean(x * x, window) - mx * mx
    vy = _box_mean(y * y, window) - my * my
    cxy = _box_mean(x * y, window) - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2))
    return float(np.mean(s))


def depth_stats(a_mm: np.ndarray, b_mm: np.ndarray, within_mm: float = DEPTH_WITHIN_MM) -> dict[str, float]:
    """Agreement of two uint16 millimetre depth images over the pixels both hit (0 = no hit)."""
    both = (a_mm > 0) & (b_mm > 0)
    diff = np.abs(a_mm.astype(np.int64) - b_mm.astype(np.int64))[both]
    if diff.size == 0:
        return {"median_mm": 0.0, "within_fraction": 1.0, "hit_fraction": 0.0}
    return {"median_mm": float(np.median(diff)), "within_fraction": float(np.mean(diff <= within_mm)),
            "hit_fraction": float(np.mean(both))}


def judge(row: dict[str, Any]) -> list[str]:
    """The thresholds a row (one plan, environment and camera) misses."""
    misses = []
    if row["rgb_mae"] > RGB_MAE_MAX:
        misses.append(f"rgb_mae {row['rgb_mae']:.1f} > {RGB_MAE_MAX}")
    if row["ssim"] < SSIM_MIN:
        misses.append(f"ssim {row['ssim']:.3f} < {SSIM_MIN}")
    depth = row.get("depth")
    if depth is not None:
        if depth["median_mm"] > DEPTH_MEDIAN_MM_MAX:
            misses.append(f"depth median {depth['median_mm']:.1f} mm > {DEPTH_MEDIAN_MM_MAX}")
        if depth["within_fraction"] < DEPTH_WITHIN_FRACTION_MIN:
            misses.append(f"depth within {DEPTH_WITHIN_MM} mm {depth['within_fraction']:.3f} "
                          f"< {DEPTH_WITHIN_FRACTION_MIN}")
    return misses


def moved_qpos(plan: Any, model: Any) -> np.ndarray:
    """The plan's initial qpos with every arm joint turned by ARM_OFFSET_RAD (alternating sign), within limits."""
    qpos = np.asarray(plan.init_qpos, dtype=np.float64).copy()
    for k, name in enumerate(plan.robot["arm_joints"]):
        joint = model.joint(name)
        adr = joint.qposadr[0]
        value = qpos[adr] + (ARM_OFFSET_RAD if k % 2 == 0 else -ARM_OFFSET_RAD)
        if model.jnt_limited[joint.id]:
            value = float(np.clip(value, *model.jnt_range[joint.id]))
        qpos[adr] = value
    return qpos


def mujoco_images(model: Any, qpos: np.ndarray, cameras: Sequence[str], width: int, height: int,
                  plain: bool) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's RGB [C, H, W, 3] and depth mm [C, H, W] of one state; `plain` turns shadows and reflections off."""
    import mujoco

    from dojo.backends.mujoco.render import open_renderer
    from dojo.backends.mjx.render import cpu_depth_mm

    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    rgb, depth = [], []
    with open_renderer(model, height, width) as renderer:
        if plain:
            renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
            renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        for cam in cameras:
            renderer.update_scene(data, camera=cam)
            rgb.append(renderer.render().copy())
            renderer.enable_depth_rendering()
            renderer.update_scene(data, camera=cam)
            depth.append(cpu_depth_mm(renderer.render(), model))
            renderer.disable_depth_rendering()
    return np.stack(rgb), np.stack(depth)


def batched_images(model: Any, states: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The batched renderer's RGB [B, C, H, W, 3] and depth [B, C, H, W] of `states [B, nq]` (see module doc)."""
    import jax
    import jax.numpy as jnp
    from mujoco import mjx

    from dojo.backends.mjx.cache import quiet_warp
    from dojo.backends.mjx.render import RenderConfig, WarpRenderer

    quiet_warp()
    n = states.shape[0]
    mx = mjx.put_model(model, impl="warp")
    data = jax.vmap(lambda q: mjx.make_data(model, impl="warp", naconmax=n, njmax=1).replace(qpos=q))(
        jnp.asarray(states, dtype=jnp.float32))
    data = jax.jit(jax.vmap(mjx.kinematics, in_axes=(None, 0)))(mx, data)
    renderer = WarpRenderer(model, n, RenderConfig(width=width, height=height, depth=True))
    frames = jax.jit(lambda m, d: renderer(m, d))(mx, data)
    return np.asarray(frames.rgb), np.asarray(frames.depth)


ENVS = ("home", "moved")


def picture(pairs: Sequence[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """One uint8 picture of a plan: a row per (MuJoCo, batched) pair, side by side, at half size."""
    rows = [np.concatenate([a[::2, ::2], b[::2, ::2]], axis=1) for a, b in pairs]
    return np.concatenate(rows, axis=0)


def plan_label(plan: Any) -> str:
    return f"{plan.task}-{plan.setting}-{plan.seed}"


def plan_states(plan: Any) -> np.ndarray:
    """The two compared states of a plan: home and arms moved."""
    return np.stack([np.asarray(plan.init_qpos), moved_qpos(plan, plan.model())])


def save_batched(plan: Any, rgb: np.ndarray, depth: np.ndarray, folder: Path) -> None:
    """The batched renderer's images as PNG (RGB, and depth as 16-bit millimetres), for `--against`."""
    from dojo.backends.mujoco.render import save_png

    from dojo.backends.mjx.render import CAMERAS

    for env in range(rgb.shape[0]):
        for k, cam in enumerate(CAMERAS):
            save_png(rgb[env, k], folder / f"{plan_label(plan)}_{ENVS[env]}_{cam}_batched.png")
            save_png(depth[env, k], folder / f"{plan_label(plan)}_{ENVS[env]}_{cam}_batched_depth.png")


def load_batched(plan: Any, folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """Images written by `save_batched`."""
    from PIL import Image

    from dojo.backends.mjx.render import CAMERAS

    def read(suffix: str) -> np.ndarray:
        return np.stack([np.stack([np.asarray(Image.open(folder / f"{plan_label(plan)}_{env}_{cam}_{suffix}.png"))
                                   for cam in CAMERAS]) for env in ENVS])

    return read("batched"), read("batched_depth").astype(np.uint16)


def compare_plan(plan: Any, rgb: np.ndarray, depth: np.ndarray, width: int, height: int,
                 out: Path | None) -> list[dict[str, Any]]:
    """Rows (one per environment and camera) for one plan's batched images against MuJoCo's; with `out`, one
    picture per plan (rows: home and moved states' cameras; columns: MuJoCo with its default look, batched)."""
    from dojo.backends.mjx.render import CAMERAS

    model = plan.model()
    rows, pairs = [], []
    for env, qpos in enumerate(plan_states(plan)):
        plain_rgb, plain_depth = mujoco_images(model, qpos, CAMERAS, width, height, plain=True)
        look_rgb, _ = mujoco_images(model, qpos, CAMERAS, width, height, plain=False)
        for k, cam in enumerate(CAMERAS):
            row = {"plan": plan_label(plan), "task": plan.task, "setting": plan.setting, "env": ENVS[env],
                   "camera": cam, "rgb_mae": rgb_mae(plain_rgb[k], rgb[env, k]),
                   "psnr_db": psnr(plain_rgb[k], rgb[env, k]),
                   "psnr_db_4x4": psnr(block_mean(plain_rgb[k]), block_mean(rgb[env, k])),
                   "ssim": ssim(plain_rgb[k], rgb[env, k]),
                   "rgb_mae_default_look": rgb_mae(look_rgb[k], rgb[env, k]),
                   "ssim_default_look": ssim(look_rgb[k], rgb[env, k]),
                   "depth": depth_stats(plain_depth[k], depth[env, k])}
            row["misses"] = judge(row)
            rows.append(row)
            pairs.append((look_rgb[k], rgb[env, k]))
    if out is not None:
        from dojo.backends.mujoco.render import save_png

        save_png(picture(pairs), out / f"{plan_label(plan)}.png")
    return rows


def builtin_plans() -> list[Any]:
    """Seed 0 of every built-in task in both settings."""
    from dojo.compiler.plan import compile_plan
    from dojo.compiler.spec_library import SpecLibrary

    library = SpecLibrary.load()
    return [compile_plan(library, task, setting, 0) for task in sorted(library.of_kind("task"), key=lambda t: t.id)
            for setting in ("standard", "random")]


def gl_problem() -> str | None:
    """Why MuJoCo's renderer cannot run here (no EGL/OSMesa), or None when it can."""
    import mujoco

    try:
        with mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 8, 8) as renderer:
            renderer.render()
    except Exception as exc:  # noqa: BLE001  (GL platforms fail with many exception types)
        return f"{type(exc).__name__}: {exc}"
    return None


def summarize(rows: list[dict[str, Any]], plans: int, width: int, height: int) -> dict[str, Any]:
    """The printed summary: thresholds, worst and mean figures, and every row."""
    return {
        "thresholds": {"rgb_mae_max": RGB_MAE_MAX, "ssim_min": SSIM_MIN, "depth_median_mm_max": DEPTH_MEDIAN_MM_MAX,
                       "depth_within_mm": DEPTH_WITHIN_MM, "depth_within_fraction_min": DEPTH_WITHIN_FRACTION_MIN},
        "size": [width, height], "plans": plans, "images": len(rows), "failed": sum(bool(r["misses"]) for r in rows),
        "worst_rgb_mae": max(r["rgb_mae"] for r in rows), "mean_rgb_mae": float(np.mean([r["rgb_mae"] for r in rows])),
        "worst_ssim": min(r["ssim"] for r in rows), "mean_ssim": float(np.mean([r["ssim"] for r in rows])),
        "mean_rgb_mae_default_look": float(np.mean([r["rgb_mae_default_look"] for r in rows])),
        "mean_ssim_default_look": float(np.mean([r["ssim_default_look"] for r in rows])),
        "worst_depth_median_mm": max(r["depth"]["median_mm"] for r in rows),
        "worst_depth_within_fraction": min(r["depth"]["within_fraction"] for r in rows),
        "mean_psnr_db": float(np.mean([r["psnr_db"] for r in rows])),
        "mean_psnr_db_4x4": float(np.mean([r["psnr_db_4x4"] for r in rows])),
        "by_task_setting": by_task_setting(rows),
        "rows": rows,
    }


def by_task_setting(rows: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, float]]]:
    """Mean PSNR, SSIM and RGB error per task and setting (over both states and every camera): the figure to read
    when one task's scene, or its random setting's colours and lights, renders differently."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((row["task"], row["setting"]), []).append(row)
    table: dict[str, dict[str, dict[str, float]]] = {}
    for (task, setting), group in sorted(groups.items()):
        table.setdefault(task, {})[setting] = {
            "psnr_db": round(float(np.mean([r["psnr_db"] for r in group])), 2),
            "psnr_db_4x4": round(float(np.mean([r["psnr_db_4x4"] for r in group])), 2),
            "ssim": round(float(np.mean([r["ssim"] for r in group])), 4),
            "rgb_mae": round(float(np.mean([r["rgb_mae"] for r in group])), 2), "images": len(group)}
    return table


def main(argv: Sequence[str] | None = None) -> int:
    from dojo.backends.mujoco.render import ensure_headless_gl
    from dojo.compiler.plan import Plan

    ensure_headless_gl()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("plans", nargs="*", type=Path, help="plan files; default: compile the built-in tasks")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--out", type=Path, default=None,
                        help="folder for the batched images and side-by-side pictures")
    parser.add_argument("--against", type=Path, default=None,
                        help="compare batched images saved earlier with --out (for a GPU machine without GL)")
    args = parser.parse_args(argv)
    plans = [Plan.load(p) for p in args.plans] if args.plans else builtin_plans()
    batched = {}
    for plan in plans:
        started = time.perf_counter()
        if args.against is not None:
            batched[plan.hash] = load_batched(plan, args.against)
        else:
            batched[plan.hash] = batched_images(plan.model(), plan_states(plan), args.width, args.height)
            if args.out is not None:
                save_batched(plan, *batched[plan.hash], args.out)
        print(f"{plan_label(plan)}: batched images in {time.perf_counter() - started:.1f} s", file=sys.stderr)
    problem = gl_problem()
    if problem is not None:
        print(json.dumps({"mujoco_renderer": f"unavailable: {problem}", "batched_images": str(args.out),
                          "next": "run again with --against on a machine with EGL or OSMesa"}))
        return 2
    rows = [row for plan in plans for row in compare_plan(plan, *batched[plan.hash], args.width, args.height, args.out)]
    print(json.dumps(summarize(rows, len(plans), args.width, args.height)))
    return 1 if any(r["misses"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
