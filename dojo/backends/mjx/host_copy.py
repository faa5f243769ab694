"""Device-to-host copies of large arrays (camera images) into reused page-locked host buffers.

Why. `np.asarray` of a JAX array on an NVIDIA GPU copies into pageable host memory: on an H200 (2026-11-28) it
moved a batch of 512 environments' three 640x480 RGB images (1.4 GB of uint8) at 1.6 GB/s, and in `dojo run` with
three cameras those copies were most of a control step's time (12.6 of 15.3 s of backend steps, under cProfile).
The same copy into page-locked memory through Warp ran at 47 GB/s. Copying the result once more into an array of
the caller's own costs about as much again on the host (a fresh 1.4 GB array fills at about 4 GB/s), so the caller
gets a view of the page-locked buffer itself, and a buffer is written again only once nothing refers to what was
handed out of it (every view of it keeps its NumPy array alive; the policy server's decode buffers are recycled the
same way, `xpolicylab.codec._BufferPool`).

Lent buffers (`buffers`, the policy link's shared memory, `dojo.backends.base.HostBuffers`): the buffers are
taken from there instead and page-locked (`page_lock`), so that images copied into them reach a policy server on
this host as they lie, without the client copying them into shared memory (about 36 ms a request at 2,048
environments' three 224x224 images on the H200 host); the GPU's copy into them runs as fast as into Warp's own.

Page-locked memory is slow to allocate, so the buffers are kept (at most `RING`; a caller that holds on to more
generations of images than that gets pageable copies). A buffer is dropped, to be replaced by a larger one, only
while nothing refers to it, so it is freed at once, here: memory freed while Warp captures a CUDA graph breaks the
capture (`capture.py`). Warp is already loaded wherever images are rendered on a GPU (MuJoCo Warp's tracer);
elsewhere (JAX on a CPU, Warp's CPU device) `np.asarray` is already a host copy and is used as is.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

from dojo.backends.base import HostBuffers
from dojo.backends.mjx import page_lock

log = logging.getLogger(__name__)

CHUNK = 1 << 30
"""Bytes per Warp copy, and ROW bytes per row of the kept buffers: Warp's array dimensions are 32-bit, so a batch
over 2 GiB (1,024 environments' three 640x480 RGB images are 2.8 GB) is copied in pieces into buffers seen as rows;
one array of its size failed (`Array shapes must not exceed ... 32-bit integer`, H200, 2026-11-28)."""
ROW = 1 << 20

RING = 4
"""Buffers a copier keeps: RGB and depth of the images a caller asked for last and of the time before, if it still
holds those (only buffers something holds are added, so a caller that lets go of its images uses one or two)."""


class PinnedCopier:
    """Copies device arrays to the host into reused page-locked buffers (see the module docstring)."""

    def __init__(self, everywhere: bool = False, buffers: HostBuffers | None = None) -> None:
        """`everywhere`: stage off the GPU too (Warp's CPU device; what CI can check of this path). `buffers`:
        where new buffers come from (module docstring); None: Warp's page-locked memory."""
        self.everywhere, self.buffers = everywhere, buffers
        self._ring: list[_Kept] = []

    def to_host(self, array: jax.Array) -> np.ndarray:
        """`array` on the host: a read-only view of one of the copier's buffers, valid for as long as it is held."""
        devices = array.devices()
        if array.size == 0 or len(devices) != 1:
            return np.asarray(array)  # (an array split over several GPUs is copied shard by shard by JAX)
        device = next(iter(devices))
        if not (self.everywhere or device.platform == "gpu"):
            return np.asarray(array)  # off the GPU, already a host copy
        import warp as wp

        wp.init()  # once per process; later calls return at once
        array = jax.block_until_ready(array)  # Warp's copy runs on its own stream, after what made the array
        nbytes, start = int(array.nbytes), array.unsafe_buffer_pointer()
        source_device = wp.device_from_jax(device)
        host = self._free_buffer(nbytes, source_device)
        if host is None:  # every buffer is still held by the caller
            return np.asarray(array)
        buffer, whole = host.buffer, host.view
        for offset in range(0, nbytes, CHUNK):
            # The array's own bytes, as Warp sees them: no reshape or bitcast on the device (each would be a new
            # array of the same size; Warp's arrays have at most four dimensions, images five).
            count = min(CHUNK, nbytes - offset)
            piece = wp.array(ptr=start + offset, dtype=wp.uint8, shape=(count,), device=source_device)
            wp.copy(buffer, piece, dest_offset=offset, count=count)
        wp.synchronize_device(source_device)
        out = whole.reshape(-1)[:nbytes].view(array.dtype).reshape(array.shape)
        out.flags.writeable = False  # the caller reads it; the next copies write here once it is let go of
        return out

    def _free_buffer(self, nbytes: int, device: Any) -> _Kept | None:
        """A kept buffer of at least `nbytes` that nothing else refers to, allocating (or replacing a free but
        smaller one) while fewer than `RING` are kept; None when all are held. `device`: the Warp device the
        copies come from."""
        import warp as wp

        free = [k for k in range(len(self._ring)) if _unreferenced(self._ring, k)]
        for k in free:
            if self._ring[k].buffer.size >= nbytes:
                return self._ring[k]
        if free:  # a free buffer too small for this batch: freed now, replaced below
            self._drop(free[0])
        elif len(self._ring) >= RING:
            return None
        rows = -(-nbytes // ROW)
        host = self._lend(rows * ROW)
        if host is not None:
            locked = device.is_cuda and page_lock.lock(host, device)
            buffer = wp.array(ptr=host.ctypes.data, dtype=wp.uint8, shape=(rows, ROW), device="cpu")
            self._ring.append(_Kept(buffer, host, self.buffers, locked))
        else:
            buffer = wp.empty((rows, ROW), dtype=wp.uint8, device="cpu", pinned=device.is_cuda)
            self._ring.append(_Kept(buffer, buffer.numpy()))
        return self._ring[-1]

    def _lend(self, nbytes: int) -> np.ndarray | None:
        """A lent buffer, or None without a lender or when it has none to give (`/dev/shm` full: 64 MiB in a
        default Docker container); then this copier stops asking and keeps its own page-locked buffers."""
        if self.buffers is None:
            return None
        try:
            return self.buffers.lend(nbytes)
        except MemoryError as exc:
            log.warning("camera images go into page-locked memory of their own, not the policy link's shared memory "
                        "(each request then copies them there): %s", exc)
            self.buffers = None
            return None

    def _drop(self, k: int) -> None:
        """Forget buffer `k`; a lent one is unlocked and given back (its memory goes once nothing refers to it)."""
        kept = self._ring.pop(k)
        if kept.locked:
            page_lock.unlock(kept.view)
        if kept.lender is not None:
            kept.lender.give_back(kept.view)

    def close(self) -> None:
        """Forget every buffer (lent ones given back)."""
        while self._ring:
            self._drop(len(self._ring) - 1)


@dataclass(frozen=True)
class _Kept:
    """A kept buffer: Warp's array of it (uint8 [rows, ROW] on the host), the NumPy array every view handed out
    refers to, and for a lent one its lender and whether `page_lock` locked it."""

    buffer: Any
    view: np.ndarray
    lender: HostBuffers | None = None
    locked: bool = False


def _unreferenced(ring: list[_Kept], k: int) -> bool:
    """Whether nothing but the ring refers to buffer `k`'s NumPy view: every view taken of it refers to it (NumPy's
    `base`), so two references remain when none is held, the ring's record and `sys.getrefcount`'s argument."""
    return sys.getrefcount(ring[k].view) == 2

