"""Page-locking host memory that was not allocated by CUDA (a shared-memory segment), so that GPU copies into it
run at full speed.

Why. Camera images go from the GPU into a buffer the policy link lends (`dojo.backends.base.HostBuffers`, a
segment of the client's shared memory), and from there to the policy server without another copy. CUDA copies
into ordinary pageable memory through a staging buffer: on the H200 (2026-11-29, `.dw/hr.py`) 925 MB went into an
unregistered segment at 16.3 GB/s, into the same segment once registered at 55.0 GB/s, as fast as Warp's own
page-locked buffer. Neither Warp nor JAX offers registering memory they did not allocate, so this calls the CUDA
driver's `cuMemHostRegister` itself, in the context of the Warp device the copies come from; the driver is
loaded wherever such a device exists. Where anything fails the memory stays pageable: slower, still correct.
"""

from __future__ import annotations

import ctypes
import logging
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

PORTABLE = 1
"""`CU_MEMHOSTREGISTER_PORTABLE`: page-locked for every CUDA context, not only the one current at registration."""

_driver: ctypes.CDLL | None = None


def _cuda() -> ctypes.CDLL:
    global _driver
    if _driver is None:
        _driver = ctypes.CDLL("libcuda.so.1")
    return _driver


def lock(buffer: np.ndarray, device: Any) -> bool:
    """Page-lock `buffer`'s memory for copies from Warp `device` (a CUDA device); False, with a warning, where it
    could not be (the buffer then stays pageable)."""
    try:
        cuda = _cuda()
        cuda.cuCtxPushCurrent_v2(ctypes.c_void_p(device.context))
        try:
            status = cuda.cuMemHostRegister_v2(ctypes.c_void_p(buffer.ctypes.data), ctypes.c_size_t(buffer.nbytes),
                                               ctypes.c_uint(PORTABLE))
        finally:
            cuda.cuCtxPopCurrent_v2(ctypes.byref(ctypes.c_void_p()))
    except (OSError, AttributeError) as exc:
        log.warning("images are copied off the GPU into pageable memory (about a third of the speed): %s", exc)
        return False
    if status != 0:
        log.warning("cuMemHostRegister failed (CUresult %d): images are copied off the GPU into pageable memory "
                    "(about a third of the speed)", status)
        return False
    return True


def unlock(buffer: np.ndarray) -> None:
    """Undo `lock` (before the memory is unmapped)."""
    _cuda().cuMemHostUnregister(ctypes.c_void_p(buffer.ctypes.data))
