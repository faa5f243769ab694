"""The Warp kernels one MuJoCo Warp step of a bucket launches, recorded instead of run.

Why. On an empty kernel cache an engine compiles every Warp module its buckets' steps launch, one module after
another, at the launch that first needs it. Which modules those are (and with which block size, which selects the
compiled variant) is a property of the bucket's model and capacities, and can be known before anything runs:
`dojo bench kernels` counts them this way, to judge how many modules a change of the buckets' structures saves.

How. The bucket's model, as a lane of a given size holds it, steps with `wp.launch` and `wp.launch_tiled` replaced
by a recorder (the module and block size of each kernel launched over a non-empty grid: Warp loads no module for an
empty launch), `wp.capture_while` / `wp.capture_if` running their bodies once, `wp.get_suggested_block_size`
recording the module at its default block size (what that call loads on a GPU) and Warp's native sorts and scans
skipped (`NATIVE_PASSES`); Warp's own functions are back when it returns.
Nothing is compiled and nothing is simulated. MuJoCo Warp's step is capturable in a CUDA graph, so it never reads
the device between launches and the recorded sequence is the real one. Checked against an H100's kernel cache for
the 24 simulation tasks (2026-11-28): 95 of the 96 kernel names recorded on Warp's CPU device were the modules
compiled there; the one apart is a kernel whose block size MuJoCo Warp chooses from the device, which recording on
the GPU itself gets right.
"""

from __future__ import annotations

from contextlib import ExitStack
from typing import Any, Callable
from unittest import mock

import numpy as np

from dojo.backends.mjx.batch import contact_capacity
from dojo.backends.mjx.bucket import Bucket

NATIVE_PASSES = ("segmented_sort_pairs", "radix_sort_pairs", "array_scan")
"""Warp's utilities that MuJoCo Warp calls between its launches (the sweep-and-prune broadphase of models of 1,000
geoms or more sorts and scans): they run Warp's own compiled code, no module, and here they would read arrays that
no recorded launch has filled (a sort of uninitialised segment bounds fails), so they too are skipped."""
Launches = dict[tuple[str, Any], Any]
"""{(module name, block size): Warp module}; block size None is the launch's default."""


def _empty(dim: Any) -> bool:
    if dim is None:
        return False
    return int(np.prod(dim if isinstance(dim, (tuple, list)) else [dim])) == 0


def _recording(wp: Any, launches: Launches, counted: list[Any] | None = None) -> ExitStack:
    """Warp's launch and conditional-capture functions replaced by recorders until the stack closes; with
    `counted`, every launch over a non-empty grid is appended to it too (its kernel), in order."""

    def launch(kernel: Any, *args: Any, **kwargs: Any) -> None:
        if not _empty(kwargs.get("dim", args[0] if args else None)):
            launches[kernel.module.name, kwargs.get("block_dim")] = kernel.module
            if counted is not None:
                counted.append(kernel)

    def suggested_block_size(kernel: Any, device: Any = None) -> tuple[int, int]:
        """On a GPU, Warp answers this by loading the kernel's module at its default block size to ask the driver
        for its occupancy, a variant the launch that follows may not use (the N-squared broadphase launches at
        its model's own block size): recorded, that default variant is compiled ahead too. The answer is the
        CPU's, as Warp's own call here would give."""
        launches[kernel.module.name, None] = kernel.module
        return 1, 1

    def capture_while(condition: Any, while_body: Callable[..., None], **kwargs: Any) -> None:
        while_body(**kwargs)

    def capture_if(condition: Any, on_true: Callable[..., None] | None = None,
                   on_false: Callable[..., None] | None = None, **kwargs: Any) -> None:
        for branch in (on_true, on_false):
            if callable(branch):
                branch(**kwargs)

    stack = ExitStack()
    for name, stand_in in (("launch", launch), ("launch_tiled", launch), ("capture_while", capture_while),
                           ("capture_if", capture_if), ("get_suggested_block_size", suggested_block_size)):
        stack.enter_context(mock.patch.object(wp, name, stand_in))
    for name in NATIVE_PASSES:
        stack.enter_context(mock.patch.object(wp.utils, name, lambda *args, **kwargs: None))
    return stack


def recorded_tick(bucket: Bucket, device: str | None = None, size: int = 1) -> tuple[Launches, dict[str, int]]:
    """On `device` (Warp's current device when None), `bucket`'s model as a lane of `size` worlds holds it (its
    varying fields batched per world, `streams.batchable_fields`) with the engine's contact and row capacities: the
    kernels a physics step, a whole forward and a lane's end-of-tick refresh (`streams.refresh`)
    launch (by module and block size: every module an engine of this bucket loads for its physics), and how many
    kernels (launches over non-empty grids, one solver iteration) each of the three launches, and so a lane's tick:
    its sub-steps and the refresh (besides its ~20 copies in and one restore per state field). One model and data
    serve all three records.

    Why the lane's size: MuJoCo Warp specialises some kernels on how many rows a batched field has (the N-squared
    broadphase of a bucket whose members differ in geom bounds), so a lane of 40 worlds loads another module than
    one world does: recorded at one world, the cache compiled ahead missed 27 modules of the protocol's default run
    on an H200 (2026-12-03), which the GPU compiled in 26.0 s.

    Why the counts: a lane's tick on the GPU is a graph of these launches, and where lanes are small their number
    weighs on its pace beside their arithmetic (README, speed); this counts a change to the tick before a GPU
    runs it."""
    import warp as wp
    from mujoco.mjx.third_party import mujoco_warp as mjw

    from dojo.backends.mjx.streams import batchable_fields, refresh

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.init()
    launches: Launches = {}
    counts = {}
    contacts, rows = contact_capacity(bucket)
    with wp.ScopedDevice(device):
        model = mjw.put_model(bucket.model, batch_sizes={name: size for name in batchable_fields(bucket.varying)[0]})
        data = mjw.make_data(bucket.model, nworld=size, naconmax=contacts * size, njmax=rows)
        for part, run in (("step", lambda: mjw.step(model, data)), ("forward", lambda: mjw.forward(model, data)),
                          ("refresh", lambda: refresh(wp, mjw, model, data))):
            counted: list[Any] = []
            with _recording(wp, launches, counted):
                run()
            counts[part] = len(counted)
    counts["tick"] = bucket.n_substeps * counts["step"] + counts["refresh"]
    return launches, counts
