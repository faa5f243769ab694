"""The codec writes exactly what msgpack-numpy / openpi_client write, reads theirs, and refuses unsafe input."""

from __future__ import annotations

import msgpack
import msgpack_numpy
import numpy as np
import pytest
from openpi_client import msgpack_numpy as openpi_msgpack

from xpolicylab import codec
from xpolicylab.errors import ErrorCode, ProtocolError
from xpolicylab.transport import fragments

SAMPLE = {
    "image": np.arange(480 * 64 * 3, dtype=np.uint8).reshape(480, 64, 3),
    "state": np.linspace(-1, 1, 14, dtype=np.float32),
    "depth": np.full((4, 5), 800, dtype=np.uint16),
    "flags": np.array([True, False]),
    "scalar": np.float64(2.5),
    "text": "pick up the mug",
    "nested": {"list": [1, -2, 3.5, None, True, "x"], "bytes": b"\x00\x01"},
}


def _assert_same(a, b):
    assert type(a) is type(b) or (isinstance(a, np.generic) and isinstance(b, (np.generic, float)))
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            _assert_same(a[key], b[key])
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)
    elif isinstance(a, list):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _assert_same(x, y)
    else:
        assert a == b


def test_native_bytes_equal_msgpack_numpy():
    data = {"a": SAMPLE["state"], "b": SAMPLE["image"]}
    assert codec.encode(data) == msgpack.packb(data, default=msgpack_numpy.encode)


def test_openpi_bytes_equal_openpi_client():
    data = {"a": SAMPLE["state"], "b": SAMPLE["image"], "s": np.float32(1.5)}
    assert codec.encode(data, codec.Dialect.OPENPI) == openpi_msgpack.packb(data)


@pytest.mark.parametrize("dialect", list(codec.Dialect))
def test_roundtrip_whole_and_fragmented(dialect):
    chunks = codec.encode_chunks(SAMPLE, dialect)
    whole = b"".join(chunks)
    _assert_same(SAMPLE, codec.decode(whole))
    _assert_same(SAMPLE, codec.decode(list(fragments(chunks, size=1000))))  # arrays split across fragments
    decoded = codec.decode(chunks)  # each array in its own fragment: decoded as a view
    assert not decoded["image"].flags.writeable and not decoded["state"].flags.writeable


def test_recycled_buffers_are_never_shared_by_live_arrays():
    chunks = list(fragments(codec.encode_chunks(SAMPLE), size=1000))  # forces the copying path
    first, second = codec.decode(chunks), codec.decode(chunks)
    assert not np.shares_memory(first["image"], second["image"])
    del first
    third = codec.decode(chunks)
    assert not np.shares_memory(second["image"], third["image"])
    assert np.array_equal(third["image"], SAMPLE["image"])


def test_reads_what_the_reference_packages_write():
    data = {"a": SAMPLE["state"], "img": SAMPLE["image"]}
    for packed in (msgpack_numpy.packb(data), openpi_msgpack.packb(data)):
        out = codec.decode(packed)
        assert np.array_equal(out["img"], data["img"]) and out["a"].dtype == np.float32


def test_reference_packages_read_what_we_write():
    assert np.array_equal(msgpack_numpy.unpackb(codec.encode(SAMPLE))["image"], SAMPLE["image"])
    assert np.array_equal(openpi_msgpack.unpackb(codec.encode(SAMPLE, "openpi"))["image"], SAMPLE["image"])


def test_encoder_refuses_object_arrays_and_unknown_types():
    with pytest.raises(TypeError):
        codec.encode({"x": np.array([object()], dtype=object)})
    with pytest.raises(TypeError):
        codec.encode({"x": {1, 2}})


def _nd(override: dict) -> bytes:
    base = {b"nd": True, b"type": "<f4", b"kind": b"", b"shape": [2], b"data": b"\x00" * 8}
    base.update(override)
    return msgpack.packb({"x": base})


REFUSED = {
    "object array (pickle)": msgpack.packb({"x": np.array([1, "a"], dtype=object)}, default=msgpack_numpy.encode),
    "structured dtype": _nd({b"kind": b"V"}),
    "unicode dtype": _nd({b"type": "<U2"}),
    "bad dtype": _nd({b"type": "<zz"}),
    "length mismatch": _nd({b"data": b"\x00" * 7}),
    "negative shape": _nd({b"shape": [-2]}),
    "too many dims": _nd({b"shape": [1] * 40, b"data": b"\x00" * 4}),
    "shape whose size wraps in 64 bits": _nd({b"shape": [1 << 32, 1 << 32], b"data": b""}),
    "openpi object dtype": openpi_msgpack.packb({"x": {b"__ndarray__": True, b"data": b"", b"dtype": "|O",
                                                      b"shape": [0]}}),
    "truncated": msgpack.packb({"x": "hello"})[:-2],
    "trailing bytes": msgpack.packb({"x": 1}) + b"\x00",
    "ext type": msgpack.packb({"x": msgpack.ExtType(5, b"abc")}),
    "int map key": msgpack.packb({1: 2}, strict_types=False),
    "invalid utf-8": b"\x81\xa1x\xa2\xff\xfe",
    "too deep": b"\x91" * 100 + b"\xc0",
    "empty": b"",
    "never-used byte": b"\xc1",
}


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_decoder_refuses(name):
    with pytest.raises(ProtocolError) as info:
        codec.decode(REFUSED[name])
    assert info.value.code is ErrorCode.INVALID_FRAME


def test_buffer_pool_hands_a_released_batch_back_in_order_and_keeps_live_buffers_out():
    pool = codec._BufferPool(max_bytes=1 << 20)
    batch = [pool.get(100) for _ in range(40)]
    order = [id(b) for b in batch]
    del batch
    again = [pool.get(100) for _ in range(40)]  # the same buffers, in the same order: one probe each
    assert [id(b) for b in again] == order and len(pool._buffers[100]) == 40
    kept = again[::2]
    del again
    fresh = [pool.get(100) for _ in range(40)]
    assert not {id(b) for b in kept} & {id(b) for b in fresh}  # a buffer still referenced is never handed out
    assert len({id(b) for b in fresh}) == 40


def test_buffer_pool_keeps_no_more_bytes_per_size_than_it_may():
    pool = codec._BufferPool(max_bytes=1000)
    held = [pool.get(100) for _ in range(25)]
    assert len(held) == 25 and len({id(b) for b in held}) == 25
    assert len(pool._buffers[100]) == 10
