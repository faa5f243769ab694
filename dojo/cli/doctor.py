"""`dojo doctor`: what this installation is and what it can use, the first thing to paste into a bug report.

Versions (RoboDojo, Python, the simulation and learning libraries), the devices found (CPU cores, NVIDIA GPUs,
the JAX backend, MuJoCo Warp, whether MuJoCo can render headless), and where dojo keeps things (the results
root, the plan, bucket and JAX compilation caches) with their sizes. Every probe that fails says why in its line
instead of stopping the report: a broken GL or GPU set-up is what a user runs this to find out about.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
from collections.abc import Callable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

PACKAGES = ("robodojo", "mujoco", "mujoco-mjx", "mujoco-warp", "warp-lang", "jax", "jaxlib", "numpy", "hydra-core",
            "websockets", "msgpack", "openpi-client")


def _version(package: str) -> str:
    try:
        return version(package)
    except PackageNotFoundError:
        return "not installed"


def _probe(check: Callable[[], str]) -> str:
    """A probe's answer, or why it failed (one line)."""
    try:
        return check()
    except Exception as err:  # noqa: BLE001 - any failure is the answer the user needs
        return f"unavailable ({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})"


def _gpus() -> str:
    if not shutil.which("nvidia-smi"):
        return "none (no nvidia-smi)"
    out = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total,driver_version", "--format=csv,noheader"],
                         capture_output=True, text=True, timeout=30)
    lines = [line.strip() for line in out.stdout.splitlines() if line.strip()]
    return "; ".join(lines) if out.returncode == 0 and lines else f"none (nvidia-smi: {out.stderr.strip()[:80]})"


def _jax() -> str:
    import jax

    devices = jax.devices()
    return f"{jax.default_backend()} ({', '.join(sorted({d.device_kind for d in devices}))}, {len(devices)} device(s))"


def _warp() -> str:
    from dojo.backends.mjx.cache import warp_available, warp_installed

    if warp_available():
        return "available (backend=mjx runs it: impl=auto)"
    if warp_installed():
        return ("on Warp's CPU device only, when asked for (backend.impl=warp: for checks); impl=auto runs MJX's jax "
                "implementation without an NVIDIA GPU")
    return "not available (needs warp-lang, pip install 'robodojo[warp]'; backend=mjx runs MJX's jax implementation)"


def _render() -> str:
    from dojo.backends.mujoco.render import ensure_headless_gl

    ensure_headless_gl()
    import mujoco

    model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><light/><geom size='1'/></worldbody></mujoco>")
    with mujoco.Renderer(model, 16, 16) as renderer:
        renderer.update_scene(mujoco.MjData(model))
        renderer.render()
    return f"ok (MUJOCO_GL={os.environ.get('MUJOCO_GL')})"


def _folder(path: Path) -> dict[str, Any]:
    """A folder's absolute path, whether it exists, and the bytes of the files below it."""
    size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else 0
    return {"path": str(path.resolve()), "exists": path.is_dir(), "bytes": size}


def facts() -> dict[str, Any]:
    """Everything the report shows, as plain data (`--format json`)."""
    from dojo.backends.mjx.bucket_cache import cache_dir as bucket_cache_dir
    from dojo.backends.mjx.cache import DEFAULT_CACHE_DIR
    from dojo.evaluation.results_store import STORE_FILENAME
    from dojo.cli.run_cmd import DEFAULT_PLAN_CACHE
    from dojo.evaluation.run_dir import results_root

    root = results_root()
    return {
        "versions": {"python": platform.python_version(), **{p: _version(p) for p in PACKAGES}},
        "system": {"platform": platform.platform(), "machine": platform.machine(), "cpu_cores": os.cpu_count()},
        "devices": {"gpus": _probe(_gpus), "jax_backend": _probe(_jax), "mujoco_warp": _probe(_warp),
                    "rendering": _probe(_render)},
        "folders": {"results_root": {**_folder(root), "runs": len(list(root.rglob(STORE_FILENAME))) if root.is_dir()
                                     else 0},
                    "plan_cache": _folder(DEFAULT_PLAN_CACHE), "bucket_cache": _folder(bucket_cache_dir()),
                    "jax_cache": _folder(DEFAULT_CACHE_DIR)},
    }


def _size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


def render_text(data: dict[str, Any]) -> str:
    lines = []
    for section, values in data.items():
        lines.append(f"{section}:")
        for key, value in values.items():
            if isinstance(value, dict):
                extra = f", {value['runs']} run(s)" if "runs" in value else ""
                value = (f"{value['path']} ({_size(value['bytes'])}{extra})" if value["exists"]
                         else f"{value['path']} (not created yet)")
            lines.append(f"  {key:<14} {value}")
    return "\n".join(lines)


def doctor_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="dojo doctor", description="Print versions, the devices found, and where dojo keeps results and caches "
                                        "(paste it into a bug report).",
        epilog="example:\n  dojo doctor\n  dojo doctor --format json", formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--format", choices=("text", "json"), default="text", help="output format (default: text)")
    try:
        args = parser.parse_args(argv)
    except SystemExit as stop:
        return 0 if stop.code == 0 else 2
    data = facts()
    print(json.dumps(data) if args.format == "json" else render_text(data))
    return 0
