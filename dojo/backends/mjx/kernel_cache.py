"""MuJoCo Warp's kernels compiled ahead of time, on any machine, into the kernel cache a GPU machine reads.

Why. On an empty Warp kernel cache an engine compiles every module its buckets launch, one after another, before
its first tick: the protocol's 1,150 plans (222 buckets) had not finished after 560 s on an H200 (2026-12-02), and
compiling on threads or in worker processes on the GPU machines did not help (README, speed). Warp's CUDA compiler
(NVRTC, inside `warp.so`) needs no GPU, though, and the modules a bucket needs are known without one
(`warp_launches.recorded_tick`). So the compiling can happen anywhere, earlier: on a CPU node, in CI, while the GPU
is still queued; the GPU machine then finds every module in its cache and loads it.

How. Each recorded (module, block size) is compiled for `sm_<arch>` by Warp's own compile step, under the name and
in the folder `Module.load` looks for on a device of that architecture: `<cache>/<module id>/<module id>.sm<arch>
.cubin`, with the module's metadata beside it. The module id carries a hash of the module's source and options, so
a cache compiled for other versions of warp-lang or MuJoCo Warp, or for other models, is simply not found and the
GPU compiles as before: stale entries cost nothing but disk. Warp's public `compile_aot_module` compiles a module
for its default block size only, and MuJoCo Warp launches many with their own, so this calls the step beneath it
(`Module._compile`, named by `_get_compile_output_name`); `tests/backends_mjx/test_kernel_cache.py` checks that
the file it writes is the one the public call names.

Measured (2026-12-02): `dojo bench kernels plans=DIR arch=90 jobs=2` compiled the 97 modules of the bench's 48
plans (29 buckets) on the 2-core CI machine in 279.5 s beside other work (76 MB with their sources); an H200 given
that cache set up the 29 lanes in 24.2 s, compiling 2 modules itself, where an empty cache takes 128-178 s there.

Scope. Warp writes CUBIN for a GPU whose driver is older than Warp's CUDA toolkit (warp-lang 1.19: CUDA 13.4) and
PTX otherwise; these are CUBIN, so a machine with a newer driver compiles its own PTX. A sparse-solver kernel whose
block size follows the device under elliptic cones is chosen at run time from what a recording on Warp's CPU
device cannot see, and the GPU still compiles it. The N-squared broadphase of a bucket whose members differ in geom
bounds, which MuJoCo Warp specialises on the number of worlds holding them, is found where the recording is of a
lane of the run's size (`dojo bench kernels` with the run's `num_envs`); the variant its occupancy query loads, at
the module's default block size, where the recorder records that query (`warp_launches`: 10 such modules were
compiled on an H200 at the start of the protocol's run, 2026-12-03, before it did). The buckets themselves must be
the run's, and so must the plans: a plan is named by its compiler, MuJoCo's version included, and a GPU host with
MuJoCo 4.0.0 compiled the 4.0.1 plans folder again under new names, which bucketed into 46 where the folder's own
plans make 47 (2026-12-03); with the same MuJoCo on both, the GPU made the same 47 buckets and compiled 11 modules
(the 10 broadphase variants and the sparse-solver kernel) where it had compiled 24. Buckets now follow task,
setting and seed where plans tie (`Plan.sort_key`), so plans named by another install bucket alike; and with the
occupancy query recorded, an H200 given the protocol's 148 modules compiled one itself, the sparse-solver kernel
(2026-12-04, `load 128.5 s`).
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from dojo.backends.mjx.warp_launches import Launches


BINARY_SUFFIXES = (".cubin", ".ptx", ".o")
"""How Warp names a module compiled for a device: `<id>.sm90.cubin`, `<id>.sm90.ptx` (a GPU), `<id>.cpu<hash>.o`."""


def kernel_cache_dir() -> str:
    """Warp's kernel cache folder (`WARP_CACHE_PATH`, else Warp's default), Warp initialised."""
    import warp as wp

    wp.init()
    return wp.config.kernel_cache_dir


def cached_binaries() -> set[str]:
    """Every compiled module in Warp's kernel cache, as paths relative to it: the difference of two readings is what
    was compiled between them. Why: a GPU machine given kernels compiled ahead should compile next to nothing, and
    whether it did is otherwise visible only as a slow set-up (`MjxBackend.load` says how many)."""
    root = kernel_cache_dir()
    return {os.path.relpath(os.path.join(folder, name), root) for folder, _, files in os.walk(root)
            for name in files if name.endswith(BINARY_SUFFIXES)}


def compile_ahead(launches: Launches, arch: int, jobs: int = 1) -> dict[str, Any]:
    """Compile every recorded module variant for `sm_<arch>` into Warp's kernel cache (`WARP_CACHE_PATH`), `jobs` at
    a time (NVRTC lets go of the GIL); return where, how many were compiled or found cached, the seconds, the cache's
    bytes and the slowest compiles."""
    cache = kernel_cache_dir()
    todo: dict[str, tuple[Any, str, str, int]] = {}
    for (_, block_dim), module in launches.items():
        size = module.options["block_dim"] if block_dim is None else block_dim
        module.get_module_hash(size)  # resolves this block size's options, which its id and its compile use
        ident = module.get_module_identifier(size)
        name = module._get_compile_output_name(None, output_arch=arch, use_ptx=False, block_dim=size)
        todo.setdefault(f"{ident}/{name}", (module, ident, name, size))
    cached = [key for key in todo if os.path.exists(os.path.join(cache, key))]

    def build(key: str) -> tuple[str, float]:
        module, ident, name, size = todo[key]
        start = time.perf_counter()
        module._compile(None, os.path.join(cache, ident), name, arch, use_ptx=False,
                        options=module.resolved_options[size])
        return key, time.perf_counter() - start

    start = time.perf_counter()
    missing = sorted(set(todo) - set(cached))
    with ThreadPoolExecutor(max(1, jobs)) as pool:
        took = dict(pool.map(build, missing))
    size = sum(os.path.getsize(os.path.join(root, f)) for key in todo
               for root, _, files in os.walk(os.path.join(cache, key.split("/")[0])) for f in files)
    slowest = sorted(took.items(), key=lambda kv: -kv[1])[:5]
    return {"arch": f"sm_{arch}", "format": "cubin", "cache": cache, "modules": len(todo), "compiled": len(took),
            "cached": len(cached), "seconds": time.perf_counter() - start, "bytes": size,
            "slowest": [{"module": key.split("/")[0], "s": round(s, 2)} for key, s in slowest]}
