"""Warp kernels a lane's CUDA graph runs besides MuJoCo Warp's own (`streams`). Imported only where warp-lang is
installed: the module compiles its kernels on import's first launch and caches them like MuJoCo Warp's."""

from __future__ import annotations

import warp as wp


@wp.kernel(enable_backward=False)
def keep_unstepped(stepping: wp.array(dtype=wp.int32), width: int, field: wp.array(dtype=wp.float32),
                   saved: wp.array(dtype=wp.float32)):
    """Word i of a per-world state field (`width` words a world) back to its value before the sub-steps in the
    worlds whose environment does not step this tick: a lane steps every world, an environment that waits (idle
    slot, paused) must keep its state."""
    i = wp.tid()
    if stepping[i // width] == 0:
        field[i] = saved[i]


@wp.kernel(enable_backward=False)
def tendon_velocity(rownnz: wp.array(dtype=int), rowadr: wp.array(dtype=int), colind: wp.array(dtype=int),
                    qvel: wp.array2d(dtype=float), ten_J: wp.array2d(dtype=float),
                    ten_velocity: wp.array2d(dtype=float)):
    """Each tendon's speed in each world, its sparse Jacobian row times the joint velocities (the one velocity a
    lane's refresh brings up to date: the grippers' speeds in the proprioception). The row is summed in MuJoCo
    Warp's order, skipping its zeros as MuJoCo Warp's forward does, so the speed is the forward's to the bit."""
    world, tendon = wp.tid()
    speed = float(0.0)
    for i in range(rownnz[tendon]):
        k = rowadr[tendon] + i
        if ten_J[world, k] != 0.0:
            speed += ten_J[world, k] * qvel[world, colind[k]]
    ten_velocity[world, tendon] = speed
