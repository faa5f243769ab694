"""Device-to-host copies through the reused staging buffer: the same bytes as `np.asarray`, arrays of their own."""

import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("warp")

from dojo.backends.mjx.host_copy import PinnedCopier  # noqa: E402


def test_staged_copies_give_the_arrays_bytes_for_every_dtype_and_own_their_memory() -> None:
    copier = PinnedCopier(everywhere=True)
    rgb = jnp.arange(2 * 3 * 5 * 7 * 3, dtype=jnp.int32).reshape(2, 3, 5, 7, 3).astype(jnp.uint8)
    depth = (jnp.arange(2 * 3 * 5 * 7, dtype=jnp.int32).reshape(2, 3, 5, 7) * 997).astype(jnp.uint16)
    first = copier.to_host(rgb)
    assert first.dtype == np.uint8 and first.shape == rgb.shape
    np.testing.assert_array_equal(first, np.asarray(rgb))
    # a larger array grows the buffer; uint16 travels as its bytes
    second = copier.to_host(depth)
    assert second.dtype == np.uint16
    np.testing.assert_array_equal(second, np.asarray(depth))
    # a smaller copy into the same buffer leaves what was handed out before untouched
    third = copier.to_host(jnp.zeros((4,), jnp.uint8))
    np.testing.assert_array_equal(third, np.zeros(4, np.uint8))
    np.testing.assert_array_equal(first, np.asarray(rgb))
    np.testing.assert_array_equal(second, np.asarray(depth))


def test_off_the_gpu_the_copier_uses_numpy_and_leaves_warp_alone() -> None:
    copier = PinnedCopier()
    out = copier.to_host(jnp.ones((3, 2), jnp.float32))
    np.testing.assert_array_equal(out, np.ones((3, 2), np.float32))
    assert copier._buffer is None
