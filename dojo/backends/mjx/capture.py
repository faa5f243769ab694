"""Keeping the host quiet while Warp captures CUDA graphs.

While a CUDA stream captures a graph, CUDA refuses anything that frees or allocates device or pinned host memory
on that device ("operation not permitted when stream is capturing", then Warp's "CUDA error 901"). A JAX array
freed at that moment (by Python's garbage collector, or because its last reference went away) makes XLA do just
that. Warp captures when a Warp call first runs: MJX's calls inside a jitted program capture during that program's
first execution (`backend.graph_mode` `warp_staged`/`warp_staged_ex` only then; `warp` again for every new set of
buffer addresses), and `StreamEngine` captures its graphs explicitly. Seen on the H100 (2026-11-27): the bench's
streams capture after `homogeneous`'s engines, and `homogeneous` itself on a cold kernel cache.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import jax


@contextmanager
def collector_held() -> Iterator[None]:
    """Python's garbage collector held back for the block (reference counting still frees; callers keep what
    they hold alive until the block ends)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def wait_for(out: Any) -> Any:
    """`out`, the outputs of one jitted call, once they are computed. They become ready together, so one leaf is
    waited for: `jax.block_until_ready` waits leaf by leaf, 2-3.5 ms for the 1,100 leaves a split tick's half
    returns at six buckets (an H200 host), and thousands more at the whole mix."""
    leaves = jax.tree.leaves(out)
    if leaves:
        leaves[0].block_until_ready()
    return out


def run_settled(call: Any, *args: Any) -> Any:
    """`call(*args)` with the collector held and its results waited for, so that the captures its execution makes
    finish before the host frees anything (the arguments stay referenced until then)."""
    with collector_held():
        return wait_for(call(*args))
