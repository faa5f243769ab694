"""Device-to-host copies of large arrays (camera images) through a reused pinned host buffer.

Why. `np.asarray` of a JAX array on an NVIDIA GPU copies into pageable host memory: on an H200 (2026-11-28) it
moved a batch of 512 environments' three 640x480 RGB images (1.4 GB of uint8) at 1.6 GB/s, and in `dojo run` with
three cameras those copies were most of a control step's time (12.6 of 15.3 s of backend steps, under cProfile).
The same copy into page-locked memory through Warp ran at 47 GB/s, and a host copy out of it at several GB/s more.
Page-locked memory is slow to allocate, so one buffer is kept per copier and grown when a larger batch comes.
Warp is already loaded wherever images are rendered on a GPU (MuJoCo Warp's tracer); elsewhere (JAX on a CPU,
Warp's CPU device) `np.asarray` is already a host copy and is used as is.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


class PinnedCopier:
    """Copies device arrays to fresh host arrays, staged in one page-locked buffer that it keeps between calls."""

    def __init__(self, everywhere: bool = False) -> None:
        self.everywhere = everywhere  # stage off the GPU too (Warp's CPU device; what CI can check of this path)
        self._buffer: Any = None  # a warp.array of uint8 on the host, page-locked, or None until the first copy

    def to_host(self, array: jax.Array) -> np.ndarray:
        """`array` as a NumPy array of its own (the caller may keep it: the staging buffer is reused)."""
        if not (self.everywhere or _on_gpu(array)) or array.size == 0:
            return np.asarray(array)
        import warp as wp

        wp.init()  # once per process; later calls return at once
        flat = jax.lax.bitcast_convert_type(array, jnp.uint8).reshape(-1)  # bytes: one buffer serves every dtype
        flat = jax.block_until_ready(flat)  # Warp's copy runs on its own stream, after what made the bytes
        nbytes, source = int(flat.size), wp.from_jax(flat)
        if self._buffer is None or self._buffer.size < nbytes:
            self._buffer = None  # free the old buffer before allocating the larger one
            self._buffer = wp.empty(nbytes, dtype=wp.uint8, device="cpu", pinned=source.device.is_cuda)
        wp.copy(self._buffer, source, count=nbytes)
        wp.synchronize_device(source.device)
        return self._buffer.numpy()[:nbytes].view(array.dtype).reshape(array.shape).copy()


def _on_gpu(array: jax.Array) -> bool:
    """Whether `array` lives on an NVIDIA GPU (where pageable copies are the slow path)."""
    devices = getattr(array, "devices", None)
    return bool(devices) and all(d.platform == "gpu" for d in devices())
