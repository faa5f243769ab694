"""Device-to-host copies into the kept staging buffers: the same bytes as `np.asarray`, and a buffer is written
again only once nothing handed out of it is held."""

import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("warp")

from dojo.backends.mjx import host_copy  # noqa: E402
from dojo.backends.mjx.host_copy import RING, PinnedCopier  # noqa: E402


def _images(seed: int) -> jnp.ndarray:
    return (jnp.arange(2 * 3 * 5 * 7 * 3, dtype=jnp.int32).reshape(2, 3, 5, 7, 3) * (seed + 1)).astype(jnp.uint8)


def test_staged_copies_give_the_arrays_bytes_for_every_dtype() -> None:
    copier = PinnedCopier(everywhere=True)
    rgb = _images(0)
    depth = (jnp.arange(2 * 3 * 5 * 7, dtype=jnp.int32).reshape(2, 3, 5, 7) * 997).astype(jnp.uint16)
    first = copier.to_host(rgb)
    assert first.dtype == np.uint8 and first.shape == rgb.shape and not first.flags.writeable
    np.testing.assert_array_equal(first, np.asarray(rgb))
    second = copier.to_host(depth)  # uint16 travels as its bytes
    assert second.dtype == np.uint16
    np.testing.assert_array_equal(second, np.asarray(depth))


def test_a_buffer_is_reused_only_once_nothing_handed_out_of_it_is_held() -> None:
    copier = PinnedCopier(everywhere=True)
    held = [copier.to_host(_images(k))[1, 2] for k in range(RING)]  # a slice of each, as observations hold them
    assert len(copier._ring) == RING
    beyond = copier.to_host(_images(RING))  # every buffer held: a copy of its own, the held ones untouched
    np.testing.assert_array_equal(beyond, np.asarray(_images(RING)))
    for k, image in enumerate(held):
        np.testing.assert_array_equal(image, np.asarray(_images(k))[1, 2])
    del held[0], beyond
    again = copier.to_host(_images(7))  # the buffer let go of is written again; the others are not
    np.testing.assert_array_equal(again, np.asarray(_images(7)))
    for k, image in enumerate(held, start=1):
        np.testing.assert_array_equal(image, np.asarray(_images(k))[1, 2])
    assert len(copier._ring) == RING


def test_a_free_buffer_too_small_is_replaced_and_a_held_one_is_kept(monkeypatch) -> None:
    monkeypatch.setattr(host_copy, "ROW", 8)  # buffers in rows of 8 bytes, so that the first one is small
    copier = PinnedCopier(everywhere=True)
    small = copier.to_host(jnp.ones((4,), jnp.uint8))
    big = copier.to_host(_images(1))  # the small buffer is held: a second buffer
    assert len(copier._ring) == 2
    del small
    bigger = copier.to_host(jnp.zeros((3, *_images(1).shape), jnp.uint8))  # the free small one is replaced
    assert sorted(k.buffer.size for k in copier._ring) == [632, 1896]  # 630 and 1,890 bytes in rows of 8
    np.testing.assert_array_equal(big, np.asarray(_images(1)))
    np.testing.assert_array_equal(bigger, 0)


def test_a_batch_larger_than_one_copy_goes_in_pieces(monkeypatch) -> None:
    """Warp's dimensions are 32-bit: a batch over 2 GiB is copied `CHUNK` bytes at a time into a buffer of `ROW`-byte
    rows. Small figures here: 630 bytes in 7 pieces of at most 100 (the last one short), 10 rows of 64."""
    monkeypatch.setattr(host_copy, "CHUNK", 100)
    monkeypatch.setattr(host_copy, "ROW", 64)
    copier = PinnedCopier(everywhere=True)
    rgb = _images(3)
    np.testing.assert_array_equal(copier.to_host(rgb), np.asarray(rgb))
    assert copier._ring[0].buffer.shape == (10, 64)


def test_off_the_gpu_the_copier_uses_numpy_and_leaves_warp_alone() -> None:
    copier = PinnedCopier()
    out = copier.to_host(jnp.ones((3, 2), jnp.float32))
    np.testing.assert_array_equal(out, np.ones((3, 2), np.float32))
    assert copier._ring == []


class _Lender:
    """`HostBuffers` over a real shared-memory pool (the policy client's), counting what it lent and got back."""

    def __init__(self) -> None:
        from xpolicylab.shm import SegmentPool

        self.pool, self.lent, self.returned = SegmentPool(), 0, 0

    def lend(self, nbytes: int) -> np.ndarray:
        self.lent += 1
        return self.pool.lend(nbytes)

    def give_back(self, buffer: np.ndarray) -> None:
        self.returned += 1
        self.pool.give_back(buffer)


def test_lent_buffers_take_the_copies_and_are_given_back(monkeypatch) -> None:
    """With buffers lent (the policy link's shared memory), the images land in them, so the link finds them where
    they lie; a free one too small is given back when replaced, and the rest when the copier closes."""
    monkeypatch.setattr(host_copy, "ROW", 8)
    lender = _Lender()
    copier = PinnedCopier(everywhere=True, buffers=lender)
    try:
        small = copier.to_host(jnp.ones((4,), jnp.uint8))
        assert lender.lent == 1 and lender.pool.lent_at(small) is not None
        del small
        rgb = _images(2)
        out = copier.to_host(rgb)  # the free small buffer is replaced by a larger lent one
        np.testing.assert_array_equal(out, np.asarray(rgb))
        assert lender.pool.lent_at(out) is not None and (lender.lent, lender.returned) == (2, 1)
        copier.close()
        assert lender.returned == 2 and copier._ring == []
        np.testing.assert_array_equal(out, np.asarray(rgb))  # what was handed out stays readable
    finally:
        lender.pool.close()


def test_a_lender_with_nothing_to_lend_leaves_the_copier_its_own_buffers(caplog) -> None:
    class Full:
        asked = 0

        def lend(self, nbytes: int) -> np.ndarray:
            Full.asked += 1
            raise MemoryError("/dev/shm has no room")

        def give_back(self, buffer: np.ndarray) -> None:
            raise AssertionError("nothing was lent")

    copier = PinnedCopier(everywhere=True, buffers=Full())
    rgb = _images(4)
    np.testing.assert_array_equal(copier.to_host(rgb), np.asarray(rgb))
    np.testing.assert_array_equal(copier.to_host(_images(5)), np.asarray(_images(5)))
    assert Full.asked == 1 and copier.buffers is None and "no room" in caplog.text
    copier.close()
