"""`dojo bench render`: camera throughput of the batched renderer and of MuJoCo's CPU renderer, in one run.

`bench_render(cfg)` returns one flat-enough dict (the CLI prints it as one JSON line) with, for three cameras at
640x480 and at 224x224 (plus the configured `width`x`height` when it is neither), RGB only and RGB + depth:

- `batched`: the mjx engine (warp physics) stepping a heterogeneous mix of task scenes (every bucket of the mix
  in one jitted tick), then one jitted observation call rendering every bucket's cameras, converting to uint8 and
  uint16 millimetres on the device and evaluating the plans' success programs. `interactions_per_s` is
  environment control steps per second of that whole loop (physics + rendering + predicates + conversion; the
  images stay on the device, as they would for a policy served on the same GPU); `frames_per_s` is camera images
  per second of the same loop; `render_frames_per_s` times the observation call alone. `device_mib_per_env` is the
  growth of the GPU's used memory (nvidia-smi, JAX preallocation off) over the engine, render contexts and first
  observations, divided by the number of environments. When no NVIDIA GPU or warp is present the section says
  why and nothing is measured there.
- `cpu`: MuJoCo's renderer (OSMesa or EGL, as MUJOCO_GL says) on the host: `frames_per_s` of one reused renderer
  on one thread, and `interactions_per_s` of the mujoco backend asked for the three cameras (its own loop:
  physics on a thread pool, then observations with images).

Config keys (dojo/cli/config/bench.yaml): num_envs, steps, tasks (null = every built-in task), width, height,
depth, backend.impl; optional `plans` (a folder of plan files to use instead of compiling seed 0 of every task in
both settings), `settings`, `physics` (false: arms moved by kinematics instead of the engine), `cpu_envs` and
`cpu_steps` (the CPU figures take seconds per frame set, so they use few environments), and `alternatives` (also time a depth-only ray caster written in JAX, `mjx.ray` over pixels).
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

STANDARD_SIZES = ((640, 480), (224, 224))
WARMUP_TICKS = 3


def _get(cfg: Any, key: str, default: Any = None) -> Any:
    value = cfg.get(key, default) if hasattr(cfg, "get") else getattr(cfg, key, default)
    return default if value is None else value


def bench_plans(cfg: Any) -> list[Any]:
    """The plans of the mix: the `plans` folder's (`plan_files`: a folder of plan files or `dojo compile`'s output),
    or seed 0 of each task in each setting."""
    from dojo.compiler.plan import Plan, compile_plan
    from dojo.compiler.spec_library import SpecLibrary
    from dojo.compiler.suite_compile import plan_files

    tasks = _get(cfg, "tasks")
    settings = list(_get(cfg, "settings", ("standard", "random")))
    if _get(cfg, "plans"):
        plans = [Plan.load(p) for p in plan_files(Path(_get(cfg, "plans")))]
        return [p for p in plans if (not tasks or p.task in set(tasks)) and p.setting in settings]
    library = SpecLibrary.load()
    ids = list(tasks) if tasks else sorted(t.id for t in library.of_kind("task"))
    return [compile_plan(library, library.get("task", t), s, 0) for t in ids for s in settings]


def render_grid(cfg: Any) -> list[tuple[int, int, bool]]:
    """(width, height, depth) of every measured configuration: the standard sizes and the configured one, RGB
    first (a run cut short keeps the figures the bars are about)."""
    sizes = list(STANDARD_SIZES)
    own = (int(_get(cfg, "width", 640)), int(_get(cfg, "height", 480)))
    if own not in sizes:
        sizes.append(own)
    return [(w, h, d) for d in (False, True) for w, h in sizes]


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    import jax

    info = {"host": platform.node(), "cpus": os.cpu_count(), "jax_backend": jax.default_backend(),
            "devices": sorted({d.device_kind for d in jax.devices()}), "mujoco_gl": os.environ.get("MUJOCO_GL")}
    return info


def _gpu_used_mib() -> float | None:
    """Used memory of GPU 0 by nvidia-smi (covers JAX's and warp's allocators alike), None without it."""
    if shutil.which("nvidia-smi") is None:
        return None
    out = subprocess.run(["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits", "-i", "0"],
                         capture_output=True, text=True, check=False)
    return float(out.stdout.strip()) if out.returncode == 0 and out.stdout.strip() else None


# ---- the batched renderer, end to end ----


def _split(total: int, parts: int) -> list[int]:
    """`total` environments over `parts` buckets, as evenly as possible (each at least 1)."""
    base, extra = divmod(max(total, parts), parts)
    return [base + (k < extra) for k in range(parts)]


class _Programs:
    """The success programs of one bucket's members, batched: layout and state index shared, params stacked."""

    def __init__(self, bucket: Any) -> None:
        import jax.numpy as jnp
        from dojo.backends.predicate_program import compile_program, stack_params

        programs = [compile_program(m.plan, m.model) for m in bucket.members]
        self.layout, self.index = programs[0].layout, programs[0].index
        odd = [m.plan.task for m, p in zip(bucket.members, programs)
               if p.layout != self.layout or p.index != self.index]
        if odd:
            raise ValueError(f"bucket {bucket.key}: members with other program layouts ({odd})")
        self.params = {k: jnp.asarray(v) for k, v in stack_params([p.params for p in programs]).items()}

    def step(self, d: Any, member: Any, memory: dict[str, Any], step: Any) -> tuple[dict[str, Any], Any]:
        """One program step of the batch `d` (traced)."""
        import jax.numpy as jnp
        from dojo.backends.predicate_program import program_step
        from dojo.backends.predicate_state import gather_state

        params = {k: v[member] for k, v in self.params.items()}
        n = d.qpos.shape[0]
        none = jnp.zeros((n, 0), jnp.int32)
        state = gather_state(jnp, self.index, params["const_pos"], d.xpos, d.xmat, d.site_xpos, d.site_xmat, d.qpos,
                             none, none, none.astype(jnp.float32))
        state["contact"] = contact_atoms(d, self.index, n)
        memory, out = program_step(jnp, self.layout, state, params, memory, step)
        return memory, out.score


def contact_atoms(d: Any, index: Any, n: int) -> Any:
    """bool [n, A, A]: which predicate atoms touch, per world, from a batch's contacts (traced).

    Under the jax implementation every world has its own fixed-size contact rows. Under warp the contacts of the
    whole batch share one buffer (`contact__worldid` says whose, the first `nacon` rows are live), so the atoms are
    scattered per world instead of compared row by row.
    """
    import jax.numpy as jnp
    from dojo.backends.predicates import TOUCH_DISTANCE, contact_matrix

    atom = jnp.asarray(index.arrays["geom_atom"])
    impl = d._impl
    if not hasattr(impl, "contact__geom"):
        c = impl.contact
        return contact_matrix(jnp, atom, c.geom1, c.geom2, c.dist, index.n_atoms)
    geom, world = impl.contact__geom, impl.contact__worldid
    live = (jnp.arange(geom.shape[0]) < jnp.reshape(impl.nacon, (-1,))[0]) & (impl.contact__dist <= TOUCH_DISTANCE)
    a1, a2 = atom[geom[:, 0]], atom[geom[:, 1]]
    hits = jnp.zeros((n, index.n_atoms + 1, index.n_atoms + 1), bool)
    hits = hits.at[jnp.where(live, world, n), a1, a2].set(True, mode="drop")
    hits = hits | jnp.swapaxes(hits, -1, -2)
    return hits[:, :index.n_atoms, :index.n_atoms]


def _observe(renderers: Sequence[Any], programs: Sequence[_Programs], arrays: Sequence[Any], mxs: tuple,
             tables: tuple, data: tuple, members: tuple, memories: tuple, step: Any) -> tuple:
    """Images, program memory and scores of every bucket (jitted with renderers and programs bound)."""
    out = []
    for renderer, program, arr, mx, table, d, member, memory in zip(renderers, programs, arrays, mxs, tables, data,
                                                                   members, memories):
        m = mx.tree_replace({name: table[name][member] for name in arr.bucket.varying})
        frames = renderer(m, d, arr.in_axes)
        memory, score = program.step(d, member, memory, step)
        out.append((frames, memory, score))
    return tuple(out)


def _block(tree: Any) -> None:
    import jax

    jax.block_until_ready(tree)


class _Kinematic:
    """The state source when physics is off: each tick moves every arm joint along a wave from the member's
    initial qpos and runs `kinematics` only (no collision or solver kernels to compile). Same interface as the
    engine's tick: batched data per bucket in `data`, device model and member table per bucket in `arrays`."""

    def __init__(self, buckets: Sequence[Any], sizes: Sequence[int], impl: str) -> None:
        import jax
        import jax.numpy as jnp
        from dojo.backends.mjx.batch import _prepare
        from dojo.backends.mjx.sharding import Placement
        from mujoco import mjx

        self.arrays = [_prepare(b, n, impl, Placement.over(None, impl)) for b, n in zip(buckets, sizes)]
        self._arm = [jnp.asarray(_arm_mask(b)) for b in buckets]
        self.data = tuple(jax.vmap(lambda q, m=b.model: mjx.make_data(m, impl=impl, naconmax=1, njmax=1)
                                   .replace(qpos=q))(jnp.asarray(a.table["qpos"][jnp.zeros(n, jnp.int32)],
                                                                 jnp.float32))
                          for b, a, n in zip(buckets, self.arrays, sizes))
        self._model, self._model_def = jax.tree.flatten((tuple(a.mx for a in self.arrays),
                                                         tuple(a.table for a in self.arrays)))  # once: `Engine._flat`
        self._step = jax.jit(self._step_all)

    def _step_all(self, model: list, data: tuple, members: tuple, wave: Any) -> tuple:
        import jax
        from mujoco import mjx

        models, tables = jax.tree.unflatten(self._model_def, model)
        out = []
        for arr, arm, mx, table, d, member in zip(self.arrays, self._arm, models, tables, data, members):
            m = mx.tree_replace({name: table[name][member] for name in arr.bucket.varying})
            d = d.replace(qpos=(table["qpos"][member] + wave * arm).astype(d.qpos.dtype))
            out.append(jax.vmap(mjx.kinematics, in_axes=(arr.in_axes, 0))(m, d))
        return tuple(out)

    def tick(self, members: Sequence[Any], resets: Any, stepping: Any, ctrls: Sequence[Any], wave: float) -> None:
        self.data = self._step(self._model, self.data, tuple(members), wave)


def _arm_mask(bucket: Any) -> np.ndarray:
    """1.0 at the qpos entries of the robot's arm joints, 0.0 elsewhere."""
    model = bucket.model
    mask = np.zeros(model.nq, np.float32)
    for name in bucket.members[0].plan.robot["arm_joints"]:
        mask[model.joint(name).qposadr[0]] = 1.0
    return mask


def measure_batched(plans: Sequence[Any], num_envs: int, steps: int, grid: Sequence[tuple[int, int, bool]],
                    impl: str = "warp", physics: bool = True) -> dict[str, Any]:
    """End-to-end figures of the batched loop, one row per (width, height, depth). With `physics` the mjx engine
    steps the scenes; without, `_Kinematic` moves the arms (a render-side figure: compiling warp's physics kernels
    for every bucket structure takes minutes per bucket on a fresh machine)."""
    import jax
    import jax.numpy as jnp
    from dojo.backends.mjx.batch import Engine
    from dojo.backends.mjx.bucket import make_buckets
    from dojo.backends.predicate_program import init_memory

    from dojo.backends.mjx.render import CAMERAS, RenderConfig, WarpRenderer

    start = time.perf_counter()
    buckets = make_buckets(plans)
    sizes = _split(num_envs, len(buckets))
    used0 = _gpu_used_mib()
    engine = Engine(buckets, sizes, impl) if physics else _Kinematic(buckets, sizes, impl)
    programs = [_Programs(b) for b in buckets]
    members = tuple(jnp.arange(n, dtype=jnp.int32) % len(b.members) for b, n in zip(buckets, sizes))
    ctrl0 = [np.asarray(a.table["ctrl"])[np.asarray(m)] for a, m in zip(engine.arrays, members)]
    ones = [np.ones(n, bool) for n in sizes]
    zeros = [np.zeros(n, bool) for n in sizes]
    # models and tables as leaves taken once: MJX's models flatten in Python per call (`Engine._flat`)
    model, model_def = jax.tree.flatten((tuple(a.mx for a in engine.arrays), tuple(a.table for a in engine.arrays)))

    def tick(t: int) -> None:
        wave = 0.15 * np.sin(0.3 * t)  # every actuator (or arm joint) swings, so arms and wrist cameras move
        if physics:
            engine.tick(members, zeros if t else ones, ones if t else zeros, [c + wave for c in ctrl0])
        else:
            engine.tick(members, None, None, (), wave)

    tick(0)
    _block(engine.data)
    used_engine = _gpu_used_mib()
    result: dict[str, Any] = {"available": True, "impl": impl, "physics": physics, "buckets": len(buckets),
                              "sizes": sizes, "envs": int(sum(sizes)), "cameras": len(CAMERAS),
                              "state_setup_s": time.perf_counter() - start, "rows": []}
    for width, height, depth in grid:
        config = RenderConfig(width=width, height=height, depth=depth)
        t_setup = time.perf_counter()
        renderers = [WarpRenderer(a.bucket.model, a.size, config) for a in engine.arrays]
        bound = partial(_observe, renderers, programs, engine.arrays)

        def observe_leaves(leaves: list, *args: Any, bound: Any = bound) -> tuple:
            return bound(*jax.tree.unflatten(model_def, leaves), *args)

        observe = jax.jit(observe_leaves)
        memories = tuple(init_memory(jnp, p.layout, n) for p, n in zip(programs, sizes))
        out = observe(model, engine.data, members, memories, 1)
        _block(out)
        setup_s = time.perf_counter() - t_setup
        for t in range(1, WARMUP_TICKS + 1):
            tick(t)
            out = observe(model, engine.data, members, tuple(o[1] for o in out), t)
            _block(out)
        used = _gpu_used_mib()
        t0 = time.perf_counter()
        for t in range(WARMUP_TICKS + 1, WARMUP_TICKS + 1 + steps):
            tick(t)
            out = observe(model, engine.data, members, tuple(o[1] for o in out), t)
            _block(tuple(o[0] for o in out) + tuple(o[2] for o in out))
        loop_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for _ in range(steps):
            _block(observe(model, engine.data, members, tuple(o[1] for o in out), 1))
        render_s = time.perf_counter() - t0
        env_steps = sum(sizes) * steps
        row = {"width": width, "height": height, "depth": depth,
               "interactions_per_s": env_steps / loop_s, "frames_per_s": env_steps * len(CAMERAS) / loop_s,
               "render_frames_per_s": env_steps * len(CAMERAS) / render_s, "setup_s": setup_s}
        if used0 is not None and used is not None and used_engine is not None:
            row["device_mib_per_env"] = (used - used0) / sum(sizes)
            row["render_mib_per_env"] = (used - used_engine) / sum(sizes)
        result["rows"].append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
        del observe, renderers, out
    result["setup_s"] = time.perf_counter() - start
    return result


# ---- MuJoCo's renderer on the host ----


def measure_cpu_render(plans: Sequence[Any], grid: Sequence[tuple[int, int, bool]], envs: int,
                       steps: int) -> dict[str, Any]:
    """MuJoCo renderer figures: one reused renderer's frames/s and the mujoco backend's interactions/s."""
    from dojo.backends.actions import action_dim
    from dojo.backends.mujoco.render import ensure_headless_gl
    from dojo.backends.registry import BackendOptions, make_backend

    from dojo.backends.gl_platform import gl_enabled, gl_unavailable_reason
    from dojo.backends.mjx.render import CAMERAS, CpuRenderer, RenderConfig

    ensure_headless_gl()
    if not gl_enabled():  # a GPU server without an EGL loader: the batched figures stand, the baseline is named
        return {"renderer": "mujoco (no OpenGL)", "skipped": gl_unavailable_reason()}
    rows = []
    chosen = [plans[k % len(plans)] for k in range(envs)]
    for width, height, depth in grid:
        config = RenderConfig(width=width, height=height, depth=depth)
        renderer = CpuRenderer([p.model() for p in chosen], config)
        qpos = [np.asarray(p.init_qpos) for p in chosen]
        renderer.render(range(len(chosen)), qpos)  # GL contexts made, textures uploaded
        t0 = time.perf_counter()
        renderer.render(range(len(chosen)), qpos)
        frames_s = time.perf_counter() - t0
        renderer.close()
        options = BackendOptions(cameras=CAMERAS, width=width, height=height, depth=depth)
        with make_backend("mujoco", options) as backend:
            backend.load(chosen)
            backend.reset()
            zero = np.zeros((len(chosen), action_dim("joint", len(chosen[0].robot["arm_joints"]) // 2)))
            t0 = time.perf_counter()
            for _ in range(steps):
                result = backend.step(zero)
                if result.done.any():
                    backend.reset(result.env_ids[result.done])
            loop_s = time.perf_counter() - t0
        rows.append({"width": width, "height": height, "depth": depth,
                     "frames_per_s": len(chosen) * len(CAMERAS) / frames_s,
                     "interactions_per_s": len(chosen) * steps / loop_s})
    return {"renderer": f"mujoco ({os.environ.get('MUJOCO_GL')})", "envs": len(chosen), "steps": steps,
            "frames_per_s_threads": 1, "rows": rows}


# ---- an alternative: a ray caster in JAX ----


def measure_jax_raycast(plan: Any, width: int, height: int, nworld: int, repeats: int = 3) -> dict[str, Any]:
    """Depth-only images of the head camera by `mjx.ray` (impl jax) vmapped over pixels and worlds: the cost of
    the simplest JAX ray caster, before any shading, textures or lights."""
    import jax
    import jax.numpy as jnp
    from mujoco import mjx

    from dojo.backends.mjx.render import camera_ids

    model = plan.model()
    mx = mjx.put_model(model, impl="jax")
    d = mjx.forward(mx, mjx.make_data(model, impl="jax").replace(qpos=jnp.asarray(plan.init_qpos)))
    data = jax.tree.map(lambda x: jnp.broadcast_to(x, (nworld,) + x.shape), d)
    cam = int(camera_ids(model, ["head"])[0])
    fovy = np.deg2rad(model.cam_fovy[cam])
    ys, xs = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    half_h = np.tan(fovy / 2)
    local = np.stack([(2 * (xs + 0.5) / width - 1) * half_h * width / height, (1 - 2 * (ys + 0.5) / height) * half_h,
                      -np.ones_like(xs, dtype=float)], axis=-1).reshape(-1, 3)
    local = jnp.asarray(local / np.linalg.norm(local, axis=-1, keepdims=True), dtype=jnp.float32)

    def image(dw: Any) -> Any:
        rot = dw.cam_xmat[cam].reshape(3, 3)
        dirs = local @ rot.T
        dist, _ = jax.vmap(lambda v: mjx.ray(mx, dw, dw.cam_xpos[cam], v, geomgroup=(1, 1, 1, 0, 0, 0)))(dirs)
        return dist * -local[:, 2]

    fn = jax.jit(jax.vmap(image))
    fn(data).block_until_ready()
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn(data).block_until_ready()
    seconds = (time.perf_counter() - t0) / repeats
    return {"what": "mjx.ray depth, head camera", "plan": plan.task, "width": width, "height": height,
            "worlds": nworld, "frames_per_s": nworld / seconds, "backend": jax.default_backend()}


def bench_render(cfg: Any) -> dict[str, Any]:
    """The figures of `dojo bench render` (see the module docstring for what each one measures)."""
    from dojo.backends.mjx.render import warp_renderer_available

    plans = bench_plans(cfg)
    grid = render_grid(cfg)
    num_envs, steps = int(_get(cfg, "num_envs", 64)), int(_get(cfg, "steps", 50))
    backend = _get(cfg, "backend", {})
    impl = _get(backend, "impl", "auto")
    report: dict[str, Any] = {"what": "render", "machine": machine(), "tasks": sorted({p.task for p in plans}),
                              "plans": len(plans), "num_envs": num_envs, "steps": steps}
    ok, why = warp_renderer_available()
    if impl == "warp" or (ok and impl != "jax"):  # warp asked for without a GPU: Warp's CPU device
        report["batched"] = measure_batched(plans, num_envs, steps, grid, physics=bool(_get(cfg, "physics", True)))
    else:
        report["batched"] = {"available": False, "reason": why if not ok else "backend.impl=jax"}
    cpu_envs = int(_get(cfg, "cpu_envs", min(num_envs, 4)))
    try:
        report["cpu"] = measure_cpu_render(plans, grid, cpu_envs, int(_get(cfg, "cpu_steps", 2)))
    except Exception as exc:  # noqa: BLE001  (no EGL/OSMesa here; GL fails with many exception types)
        report["cpu"] = {"available": False, "reason": f"{type(exc).__name__}: {exc}"}
    if _get(cfg, "alternatives", False):
        report["alternatives"] = [measure_jax_raycast(plans[0], 224, 224, 16)]
    return report
