"""Process-wide JAX settings of the mjx backend: the persistent compilation cache and the choice of MJX impl.

Compiling one tick of a real scene takes minutes on a CPU and tens of seconds on a GPU; the persistent cache
turns every later run with the same buckets (same structures, batch sizes and JAX/MJX versions) into a cache
hit. MJX has two implementations: `jax` (XLA, runs everywhere) and `warp` (MuJoCo Warp kernels, built for NVIDIA
GPUs and several times faster there at large batches, see /work/shared/gpu/README.md; on request also on Warp's
CPU device).
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

DEFAULT_CACHE_DIR = Path(os.environ.get("DOJO_JAX_CACHE", Path.home() / ".cache" / "dojo" / "jax"))
IMPLS = ("jax", "warp")
GRAPH_MODES = ("none", "jax", "warp", "warp_staged", "warp_staged_ex")
"""How MJX's Warp calls are captured in CUDA graphs (`warp.JaxCallableGraphMode`, lower-cased): `warp` (MJX's own
default: Warp captures each call's kernels and replays the graph for the same buffer addresses, capturing again
for new ones), `warp_staged` / `warp_staged_ex` (one capture per call over staging buffers; each later call copies
its inputs in and outputs out, inside the graph or beside it), `jax` (the calls join the CUDA graph XLA builds of
the jitted program), `none` (plain kernel launches, no capture). On the H100 (2026-11-27/28): `warp` failed where
anything freed memory while a call captured (a second engine, an engine left to the garbage collector); `none`
stepped the same physics and survived both, launching every kernel from Python; `jax` was refused by CUDA ("Failed
to create a child graph node"); `warp_staged` and `warp_staged_ex` stepped the same physics as `warp` and
`warp_staged` ran `dojo run` on the mini suite (13 episodes, three calls of ~9 minutes) without a capture error."""
DEFAULT_GRAPH_MODE = "warp_staged"
"""What `dojo run` and `dojo bench` use (backend/mjx.yaml and `MjxBackend`): one capture per Warp call, so a run
captures during its first tick only (`capture.run_settled` keeps the host quiet then)."""


def enable_compilation_cache(path: str | Path | None = None) -> Path:
    """Cache every compiled program on disk (also the quick ones: a tick is one program per run anyway)."""
    path = Path(path or DEFAULT_CACHE_DIR)
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def warp_installed() -> bool:
    """MuJoCo Warp can run here: MJX finds the warp-lang package (on an NVIDIA GPU, or on Warp's CPU device)."""
    try:
        from mujoco.mjx.warp import WARP_INSTALLED
    except ImportError:
        return False
    return bool(WARP_INSTALLED)


def warp_available() -> bool:
    """MuJoCo Warp is importable and JAX sees an NVIDIA GPU: where `impl=auto` chooses it."""
    return warp_installed() and any(d.platform == "gpu" for d in jax.devices())


def choose_impl(requested: str | None = None) -> str:
    """`requested` if given (checked), else `warp` on an NVIDIA GPU with MuJoCo Warp installed, else `jax`.

    `warp` asked for on a machine without an NVIDIA GPU runs MuJoCo Warp's kernels on Warp's CPU device: the same
    engine, cameras and contact pool as on the GPU, so that their code paths (and render parity with MuJoCo) can be
    checked on any machine; `auto` never picks it there. Choosing `warp` also quiets Warp's per-module "load on
    device ... took" lines, which it prints to stdout by default: `dojo bench` prints exactly one JSON line there
    (our own log says how long compilation took).
    """
    if requested in (None, "", "auto"):
        chosen = "warp" if warp_available() else "jax"
    elif requested not in IMPLS:
        raise ValueError(f"unknown MJX impl {requested!r}; choose one of {IMPLS} or 'auto'")
    elif requested == "warp" and not warp_installed():
        raise RuntimeError("impl 'warp' needs the warp-lang package (pip install 'robodojo[warp]'), which runs "
                           "MuJoCo Warp on an NVIDIA GPU or, slowly, on the CPU")
    else:
        chosen = requested
    if chosen == "warp":
        quiet_warp()
    return chosen


def choose_streams(requested: bool | str, impl: str, on_gpu: bool, cameras: bool) -> tuple[bool, str]:
    """Whether the tick's physics runs on streams (`backend.streams`), and why, for the log: as asked when true or
    false; `auto` turns them on for MuJoCo Warp on a GPU without cameras (cameras on streams are checked bit for
    bit on Warp's CPU device only), where they were measured faster (`dojo.backends.mjx.streams_may_run`). On
    Warp's CPU device there is nothing to overlap, so auto leaves them off there."""
    if requested != "auto":
        return bool(requested), "as set"
    if impl != "warp" or not on_gpu:
        return False, "auto: MuJoCo Warp is not on a GPU here"
    if cameras:
        return False, "auto: cameras on streams are not yet checked on a GPU"
    return True, "auto: MuJoCo Warp on a GPU, no cameras"


def graph_mode(name: str | None, impl: str) -> object | None:
    """`backend.graph_mode` as the `GraphMode` MJX's `put_model` takes: None for MJX's default, and under `impl`
    `jax` (no Warp calls to capture); `none` on Warp's CPU device, whatever was asked (no CUDA there). The name is
    checked first, so that a typo fails on any machine."""
    if name not in (None, "") and str(name).lower() not in GRAPH_MODES:
        raise ValueError(f"unknown backend.graph_mode {name!r}; choose one of {GRAPH_MODES} or null (MJX's default)")
    if impl != "warp":
        return None
    import warp as wp

    if jax.default_backend() == "cpu":  # Warp's CPU device: JAX's CPU FFI takes no graph mode but `none`
        return wp.JaxCallableGraphMode.NONE
    if name in (None, ""):
        return None
    return getattr(wp.JaxCallableGraphMode, str(name).upper())


def graph_mode_name(mode: object | None) -> str | None:
    """The `backend.graph_mode` name of a `graph_mode` result, for logs (None: MJX's default)."""
    return None if mode is None else str(getattr(mode, "name", mode)).lower()


def quiet_warp() -> None:
    """Warp logs at WARNING and above only, and prints no start-up banner (both go to stdout, where `dojo bench`
    and the parity script print their one JSON line)."""
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.config.quiet = True


def describe_impl(impl: str) -> str:
    """One line naming the implementation and the device it runs on, for logs and reports."""
    device = jax.devices()[0]
    if impl == "warp" and device.platform == "cpu":
        return "impl=warp (MuJoCo Warp kernels on Warp's CPU device: for checks, far slower than on a GPU)"
    engine = "MuJoCo Warp kernels" if impl == "warp" else "XLA"
    return f"impl={impl} ({engine} on {device.platform} {device.device_kind})"
