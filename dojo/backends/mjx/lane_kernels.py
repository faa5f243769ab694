"""Warp kernels a lane's CUDA graph runs besides MuJoCo Warp's own (`streams`). Imported only where warp-lang is
installed: the module compiles its kernels on import's first launch and caches them like MuJoCo Warp's."""

from __future__ import annotations

import warp as wp


@wp.kernel
def keep_unstepped(stepping: wp.array(dtype=wp.int32), width: int, field: wp.array(dtype=wp.float32),
                   saved: wp.array(dtype=wp.float32)):
    """Word i of a per-world state field (`width` words a world) back to its value before the sub-steps in the
    worlds whose environment does not step this tick: a lane steps every world, an environment that waits (idle
    slot, paused) must keep its state."""
    i = wp.tid()
    if stepping[i // width] == 0:
        field[i] = saved[i]
