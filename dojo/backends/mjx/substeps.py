"""A control step's physics sub-steps as one call: `n` `mjx.step`s, one Warp call under MuJoCo Warp.

Under `impl='warp'` every `mjx.step` is one XLA custom call into Warp, and each call runs a Python callback on the
host that wraps several hundred model and data buffers as Warp arrays before it launches (or replays) the
kernels. On the H200 (2026-11-28, `dojo run backend=mjx policy=zero`, one bucket of 512 `insert_tubes`
environments, 20 sub-steps) that callback, ~1.3-2.4 ms each, 21 times per tick, was the tick: 28 ms under
`graph_mode=warp`, 42 ms under `warp_staged`, with the GPU mostly idle. A `fori_loop` over `mjx.step` keeps one
callback per sub-step. Here the callback runs MuJoCo Warp's step `n` times on the same buffers instead, so a tick
costs one callback and, under a graph mode, one captured graph of all `n` sub-steps.

MJX builds its step's Warp call from the module-level shim `mujoco.mjx.warp.forward._step_shim` (which fills
MuJoCo Warp's Model and Data from the call's buffers and calls `mujoco_warp.step`); `_step_jax_impl` looks the
shim up when it is traced. `multi_step(n)` traces it with a shim that calls the original `n` times, so the
buffer marshalling stays MJX's own. Every data buffer of that call is in-out, so the `n` steps chain exactly as
`n` separate calls would: `tests/backends_mjx/test_substeps.py` checks bit-equality on Warp's CPU device.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from typing import Any

import jax
from mujoco import mjx

Tree = Any

_SHIM_LOCK = threading.Lock()
"""Tracing swaps a module global of MJX for the duration of one `_step_jax_impl` call: one trace at a time."""


def substeps(impl: str, n: int, in_axes: Tree) -> Callable[[Tree, Tree], Tree]:
    """`(m, d) -> d` after `n` physics steps of a batch (`in_axes`: the model's batched fields, as for
    `jax.vmap`). Under `warp` one Warp call; under `jax` a `fori_loop` over the batched `mjx.step`."""
    if n < 1:
        raise ValueError(f"a control step needs at least one physics step, got {n}")
    if impl == "warp":
        return jax.vmap(_warp_multi_step(n), in_axes=(in_axes, 0))
    step = jax.vmap(mjx.step, in_axes=(in_axes, 0))
    return lambda m, d: jax.lax.fori_loop(0, n, lambda _, x: step(m, x), d)


@functools.cache
def _looped_shim(n: int) -> Callable[..., None]:
    """MJX's step shim, run `n` times per call. Cached: Warp registers one FFI target per shim function, so each
    `n` must map to one function for retraces to reuse it. `functools.wraps` keeps the shim's signature, from
    which MJX and Warp read the buffers' types."""
    from mujoco.mjx.warp import forward

    base = forward._step_shim

    @functools.wraps(base)
    def shim(*args: Any, **kwargs: Any) -> None:
        for _ in range(n):
            base(*args, **kwargs)

    return shim


@functools.cache
def _warp_multi_step(n: int) -> Callable[[Tree, Tree], Tree]:
    """`mjx.step` under Warp (MJX's `forward.step`: a batching rule that hands the whole batch to one call),
    with the looped shim."""
    from mujoco.mjx.warp import ffi, forward

    shim = _looped_shim(n)

    @jax.custom_batching.custom_vmap
    @ffi.marshal_jax_warp_callable
    def multi_step(m: Tree, d: Tree) -> Tree:
        with _SHIM_LOCK:
            original, forward._step_shim = forward._step_shim, shim
            try:
                return forward._step_jax_impl(m, d)
            finally:
                forward._step_shim = original

    @multi_step.def_vmap
    @ffi.marshal_custom_vmap
    def multi_step_vmap(axis_size: int, is_batched: Tree, m: Tree, d: Tree) -> tuple[Tree, Tree]:
        return multi_step(m, d), is_batched[1]

    return multi_step
