"""The codec's fast path (msgpack's C extension) gives exactly what the Python decoder gives, or defers to it.

Differential: generated payloads (valid and malformed, every dtype, boundary ints, shared-memory references,
nesting around the depth limit) and the malformed inputs of the other tests go through both paths; the outcome
must be the same value (types, dtypes, shapes, read-only flags included) or the same refusal.
"""

from __future__ import annotations

import collections
import math
import random
import struct
from typing import Any

import msgpack
import msgpack_numpy
import numpy as np
import pytest
from openpi_client import msgpack_numpy as openpi_msgpack
from test_xpl_codec import REFUSED, SAMPLE
from test_xpl_server import MALFORMED

from xpolicylab import codec
from xpolicylab.errors import ProtocolError
from xpolicylab.transport import fragments

DTYPES = [np.dtype(order + code) for code in ("i2", "i4", "i8", "u2", "u4", "u8", "f2", "f4", "f8")
          for order in "<>"] + [np.dtype(t) for t in ("|b1", "|i1", "|u1")]
SHAPES = [(), (0,), (3,), (2, 0), (2, 3), (1, 1, 4), (0, 0, 0)]
INTS = [0, 1, 127, 128, 255, 256, 65535, 65536, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**63 - 1, 2**63, 2**64 - 1,
        -1, -32, -33, -128, -129, -32768, -32769, -2**31, -2**31 - 1, -2**63]
FLOATS = [0.0, -0.0, 1.5, -2.25e300, 5e-324, math.inf, -math.inf, math.nan]
STRINGS = ["", "x", "pick up the mug", "é漢字🙂", "a" * 31, "a" * 32, "b" * 255, "c" * 256, "d" * 70000]
BYTES = [b"", b"\x00", b"\xff" * 255, b"\x01" * 256, b"\x02" * (codec.LARGE_BIN - 1), b"\x03" * codec.LARGE_BIN]


def outcome(decoder, data: Any, shared_refs: bool = False) -> tuple[str, Any]:
    """``("ok", value)`` or ``("error", (exception type, code, message))``."""
    try:
        return "ok", decoder(data, shared_refs)
    except ProtocolError as exc:
        return "error", (ProtocolError, exc.code, exc.message)
    except Exception as exc:  # noqa: BLE001 - compared between the two paths
        return "error", (type(exc), None, str(exc))


def exact(data: Any, shared_refs: bool = False) -> Any:
    return codec._decode_exact(codec._fragment_list(data), shared_refs)


def fast(data: Any, shared_refs: bool = False) -> Any:
    return codec._fast_decode(codec._fragment_list(data), shared_refs)


def assert_identical(a: Any, b: Any, where: str = "") -> None:
    """Same value and same types all the way down, arrays' dtype, shape, flags and buffer type included."""
    assert type(a) is type(b), (where, type(a), type(b))
    if isinstance(a, dict):
        assert [(type(k), k) for k in a] == [(type(k), k) for k in b], where
        for key in a:
            assert_identical(a[key], b[key], f"{where}/{key!r}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_identical(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert (a.dtype, a.shape, a.strides) == (b.dtype, b.shape, b.strides), where
        assert (a.flags.writeable, a.flags.c_contiguous, a.flags.owndata) == (
            b.flags.writeable, b.flags.c_contiguous, b.flags.owndata), where
        assert type(a.base) is type(b.base) and a.tobytes() == b.tobytes(), where
    elif isinstance(a, np.generic):
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), where
    elif isinstance(a, float):
        assert struct.pack(">d", a) == struct.pack(">d", b), where
    elif isinstance(a, memoryview):
        assert a.tobytes() == b.tobytes(), where
    else:
        assert a == b, where


def check(data: Any, shared_refs: bool = False) -> bool:
    """Both paths agree on ``data`` (and ``decode`` gives the exact outcome); returns whether the fast path took it."""
    want = outcome(exact, data, shared_refs)
    got = outcome(fast, data, shared_refs)
    if got[0] == "ok":
        assert want[0] == "ok", (data[:200] if isinstance(data, bytes) else data, want)
        assert_identical(want[1], got[1])
    final = outcome(lambda d, s: codec.decode(d, s), data, shared_refs)
    assert final[0] == want[0]
    if want[0] == "ok":
        assert_identical(want[1], final[1])
    else:
        assert final[1] == want[1]
    return got[0] == "ok"


def random_array(rng: random.Random) -> np.ndarray:
    dtype, shape = rng.choice(DTYPES), rng.choice(SHAPES)
    raw = bytes(rng.getrandbits(8) for _ in range(math.prod(shape) * dtype.itemsize))
    arr = np.frombuffer(raw, np.uint8).view(dtype).reshape(shape) if raw else np.zeros(shape, dtype)
    return arr.astype(bool) if dtype.kind == "b" else arr


def random_ref(rng: random.Random) -> codec.SharedArray:
    return codec.SharedArray(f"xpl_{rng.randrange(99)}_s", rng.choice([0, 64, 2**40]), rng.choice(DTYPES),
                             rng.choice(SHAPES))


def random_leaf(rng: random.Random, refs: bool) -> Any:
    pick = rng.randrange(9 if refs else 8)
    return [lambda: rng.choice(INTS), lambda: rng.choice(FLOATS), lambda: rng.choice(STRINGS[:-1]),
            lambda: rng.choice(BYTES[:-2]), lambda: rng.choice([True, False, None]), lambda: random_array(rng),
            lambda: random_array(rng), lambda: np.dtype(rng.choice(DTYPES)).type(1), lambda: random_ref(rng)][pick]()


def random_value(rng: random.Random, depth: int, refs: bool) -> Any:
    if depth <= 0 or rng.random() < 0.3:
        return random_leaf(rng, refs)
    n = rng.randrange(6)
    if rng.random() < 0.5:
        return [random_value(rng, depth - 1, refs) for _ in range(n)]
    names = [rng.choice(["a", "state", "é", "nd", "data", "shape", "type", "xpl_shm"]) for _ in range(n)]
    keys = [name if rng.random() < 0.2 else f"{name}{i}" for i, name in enumerate(names)]
    return {(k.encode() if rng.random() < 0.3 else k): random_value(rng, depth - 1, refs) for k in keys}


def nested(depth: int, leaf: bytes = b"\xc0", header: bytes = b"\x91") -> bytes:
    return header * depth + leaf


def array_map(keys: str, **fields: Any) -> dict:
    """A msgpack-numpy map with bin (``keys="bin"``) or str keys, fields overridden or dropped (None)."""
    base = {"nd": True, "type": "<f4", "kind": b"", "shape": [2], "data": b"\x00" * 8}
    base.update(fields)
    return {(k.encode() if keys == "bin" else k): v for k, v in base.items() if v is not None}


@pytest.mark.parametrize("dialect", list(codec.Dialect))
def test_generated_payloads_decode_identically(dialect):
    rng = random.Random(20261128)
    taken = 0
    for i in range(600):
        refs = i % 3 == 0
        payload = {"observations": [random_value(rng, 5, refs) for _ in range(rng.randrange(4))], "i": i}
        wire = codec.encode(payload, dialect)
        if check(wire, shared_refs=refs):
            taken += 1
        else:  # random keys ("nd", "xpl_shm") made a bad array map: the exact decoder refuses it too
            assert outcome(exact, wire, refs)[0] == "error"
        if refs:
            check(wire, shared_refs=False)  # references without permission: refused the same way
        chunks = codec.encode_chunks(payload, dialect)
        check(chunks, refs)
        check(list(fragments(chunks, size=97)), refs)
    assert taken > 500  # every valid message this size went through the fast path


@pytest.mark.parametrize("value", [*INTS, *FLOATS, *STRINGS, *BYTES, True, False, None, [], {}, [[]], {"a": {}}])
def test_scalars_and_boundaries(value):
    small = not isinstance(value, bytes) or len(value) < codec.LARGE_BIN  # a large bin decodes as a view
    assert check(msgpack.packb(value)) == small
    assert check(msgpack.packb({"v": [value, value]})) == small


@pytest.mark.parametrize("bits", [0, 0x80000000, 1, 0x3FC00000, 0x7F7FFFFF, 0x7F800000, 0x7FC00000, 0x7F800001,
                                  0xFFC00001])
def test_float32_on_the_wire(bits):
    assert check(b"\xca" + struct.pack(">I", bits))


def test_every_dtype_shape_and_spelling():
    for dtype in DTYPES:
        for shape in SHAPES:
            arr = np.ones(shape, dtype)
            for wire in (codec.encode({"a": arr}), codec.encode({"a": arr}, codec.Dialect.OPENPI),
                         msgpack.packb({"a": arr}, default=msgpack_numpy.encode), openpi_msgpack.packb({"a": arr}),
                         codec.encode(arr), codec.encode({"s": dtype.type(3)}),
                         codec.encode({"s": dtype.type(3)}, codec.Dialect.OPENPI)):
                assert check(wire)
            for keys in ("bin", "str"):
                fields = {"type": dtype.str, "shape": list(shape), "data": arr.tobytes()}
                assert check(msgpack.packb({"x": array_map(keys, **fields)}))


ODD_MAPS = {  # refused, or accepted in ways that must match exactly
    "kind V": {"kind": b"V"}, "kind str empty": {"kind": ""}, "kind absent": {"kind": None},
    "kind not bytes": {"kind": 3}, "nd 1 not True": {"nd": 1}, "nd False": {"nd": False, "data": b"\0" * 4},
    "nd False short": {"nd": False}, "dtype bytes": {"type": b"<f4"}, "dtype int": {"type": 4},
    "dtype object": {"type": "|O"}, "dtype unicode": {"type": "<U2"}, "dtype junk": {"type": "<zz"},
    "shape tuple-ish": {"shape": {"a": 1}}, "shape bool": {"shape": [True, True]}, "shape float": {"shape": [2.0]},
    "shape negative": {"shape": [-2]}, "shape 17 dims": {"shape": [1] * 17, "data": b"\0" * 4},
    "shape wraps": {"shape": [1 << 32, 1 << 32], "data": b""}, "data str": {"data": "\0" * 8},
    "data short": {"data": b"\0" * 7}, "data missing": {"data": None}, "data a list": {"data": [0] * 8},
    "extra key nested": {"extra": [[[1]]]}, "extra key array": {"extra": {"nd": True, "type": "<f4", "kind": b"",
                                                                          "shape": [1], "data": b"\0" * 4}},
    "extra key map": {"extra": {"a": 1}}, "extra key flat": {"extra": [1, 2, "x"]},
}


@pytest.mark.parametrize("name", sorted(ODD_MAPS))
@pytest.mark.parametrize("keys", ["bin", "str"])
def test_odd_array_maps(name, keys):
    check(msgpack.packb({"x": array_map(keys, **ODD_MAPS[name])}))


OTHER_MAPS = [
    {b"__ndarray__": True, b"data": b"", b"dtype": "|O", b"shape": [0]},
    {"__ndarray__": True, "data": b"\0" * 4, "dtype": "<i4", "shape": [1]},
    {b"__npgeneric__": True, b"data": 1.5, b"dtype": "<f4"}, {b"__npgeneric__": True, b"data": [1, 2], b"dtype": "<f4"},
    {b"__npgeneric__": True, b"data": "x", b"dtype": "<f4"}, {"__npgeneric__": True, "data": 2**64 - 1, "dtype": "<i8"},
    {b"xpl_shm": True, b"segment": "xpl_1", b"offset": 0, b"type": "<f4", b"shape": [2]},
    {"xpl_shm": True, "segment": "xpl_1", "offset": -1, "type": "<f4", "shape": [2]},
    {b"xpl_shm": True, b"segment": b"xpl_1", b"offset": 0, b"type": "<f4", b"shape": [2]},
    {b"xpl_shm": True, b"segment": "xpl_1", b"offset": True, b"type": "<f4", b"shape": [2]},
    {b"xpl_shm": True, b"segment": "xpl_1", b"offset": 0, b"type": "|O", b"shape": [2]},
    {b"xpl_shm": 1, b"segment": "xpl_1"}, {b"nd": True, "nd": False}, {"nd": None, b"__ndarray__": True},
]


@pytest.mark.parametrize("index", range(len(OTHER_MAPS)))
@pytest.mark.parametrize("refs", [False, True])
def test_other_marker_maps(index, refs):
    check(msgpack.packb({"x": OTHER_MAPS[index], "y": [OTHER_MAPS[index]]}), shared_refs=refs)


def test_nesting_around_the_depth_limit():
    arr = codec.encode(np.zeros(2, np.float32))
    for depth in range(codec.MAX_DEPTH - 5, codec.MAX_DEPTH + 3):
        for leaf in (b"\xc0", b"\x90", b"\x80", arr, b"\x81\xa1a" + arr):
            for header in (b"\x91", b"\x81\xa1k"):
                wire = nested(depth, leaf, header)
                taken = check(wire)
                assert taken or depth >= codec.FAST_MAX_DEPTH - 1
    assert not check(nested(200)) and not check(nested(2000))  # the nesting bombs of the other tests, and deeper


def test_malformed_inputs_of_the_other_tests():
    cases = [*REFUSED.values(), *(data for data, _ in MALFORMED.values())]
    assert len(cases) > 40
    for data in cases:
        check(data)
        check(data, shared_refs=True)


def test_mutations_of_a_valid_message():
    wire = codec.encode({**SAMPLE, "image": np.zeros((2, 3), np.uint8), "ref": codec.SharedArray(
        "xpl_1_x", 8, np.dtype("<u2"), (4,))})
    rng = random.Random(7)
    for end in range(len(wire) + 1):
        check(wire[:end], shared_refs=True)  # every truncation
    check(wire + b"\x00")
    for _ in range(1500):
        data = bytearray(wire)
        for _ in range(rng.randrange(1, 4)):
            data[rng.randrange(len(data))] = rng.randrange(256)
        check(bytes(data), shared_refs=rng.random() < 0.5)


RAW = {
    "duplicate keys": b"\x82\xa1a\x01\xa1a\x02",
    "duplicate keys, first one bad": b"\x82\xa1x" + msgpack.packb(array_map("bin", kind=b"V")) + b"\xa1x\x01",
    "int key": b"\x81\x01\x02", "nil key": b"\x81\xc0\x02", "map key": b"\x81\x80\x02", "list key": b"\x81\x90\x02",
    "large bin key": b"\x81\xc6\x00\x01\x00\x00" + b"k" * 65536 + b"\x01",
    "timestamp ext": b"\xd6\xff\x00\x00\x00\x00", "empty ext": b"\xc7\x00\x05", "empty timestamp": b"\xc7\x00\xff",
    "fixext": b"\xd4\x01\x00", "surrogate": b"\xa3\xed\xa0\x80", "overlong utf-8": b"\xa2\xc0\x80",
    "huge list header": b"\xdd\xff\xff\xff\xff", "huge map header": b"\xdf\xff\xff\xff\xff",
    "huge str header": b"\xdb\xff\xff\xff\xff", "huge bin header": b"\xc6\xff\xff\xff\xff",
    "stacked list headers": b"\xdd\x00\x00\x10\x00" * 1000, "stacked map headers": b"\xdf\x00\x00\x10\x00" * 1000,
    "long list": msgpack.packb(list(range(codec.FAST_MAX_LEN + 1))),
    "long map": msgpack.packb({str(i): i for i in range(codec.FAST_MAX_LEN + 1)}),
    "just long enough": msgpack.packb([{str(i): i for i in range(codec.FAST_MAX_LEN)}]),
    "uint64 in shape": msgpack.packb({"x": array_map("bin", shape=[2**64 - 1])}),
}


@pytest.mark.parametrize("name", sorted(RAW))
def test_raw_inputs(name):
    check(RAW[name])
    check([RAW[name][:3], RAW[name][3:]])


def test_fragments_and_buffer_types():
    wire = codec.encode(SAMPLE)  # the image is large: views of the fragment, so the Python path keeps it
    assert not check(wire) and not check(codec.encode_chunks(SAMPLE))
    small = codec.encode({k: v for k, v in SAMPLE.items() if k != "image"})
    for data in (small, bytearray(small), memoryview(small), [small]):
        assert check(data)
    assert check([small[:10], small[10:]]) and check([b"", small])  # fragments: joined, the same result
    assert not check(b"\xc0" * (codec.FAST_DECODE_MAX + 1))  # above the size limit: trailing bytes, exact error


def test_a_batch_of_small_observations_split_into_fragments_takes_the_fast_path():
    batch = {"observations": [{"state": {"joint_pos": np.arange(14, dtype=np.float32)}, "instruction": "stack",
                               "meta": {"episode": i, "step": 3}} for i in range(4000)], "env_ids": list(range(4000))}
    wire = list(fragments(codec.encode_chunks(batch), size=64 * 1024))  # as the transport splits a long message
    assert len(wire) > 1 and check(wire)
    assert_identical(codec.decode(wire), exact(wire))


def test_fast_path_bounds_what_it_allocates():
    for data in (RAW["stacked list headers"], RAW["stacked map headers"], RAW["huge list header"]):
        with pytest.raises(ValueError):
            fast(data)
    with pytest.raises(ProtocolError, match="nested deeper"):
        codec.decode(RAW["stacked list headers"])


def encoded(encoder, obj: Any, dialect: codec.Dialect) -> tuple[str, Any]:
    """``("ok", chunks as bytes)`` or ``("error", (exception type, message))``."""
    try:
        return "ok", [bytes(c) for c in encoder(obj, dialect)]
    except Exception as exc:  # noqa: BLE001 - compared between the two paths
        return "error", (type(exc), str(exc))


def exact_chunks(obj: Any, dialect: codec.Dialect) -> list[bytes | memoryview]:
    encoder = codec._Encoder(dialect)
    encoder.write(obj)
    return encoder.finish()


def check_encode(obj: Any) -> bool:
    """``encode_chunks`` gives exactly what ``_Encoder`` gives (chunk for chunk, or the same error) in both dialects;
    returns whether the fast path wrote it."""
    taken = True
    for dialect in codec.Dialect:
        want = encoded(exact_chunks, obj, dialect)
        assert encoded(codec.encode_chunks, obj, dialect) == want
        fast_result = encoded(codec._fast_encode, obj, dialect)
        taken &= fast_result[0] == "ok"
        assert fast_result[0] == "error" or fast_result == want
    return taken


class Key(str):
    pass


class Number(int):
    pass


ODD_VALUES = {  # each is written by _Encoder (or refused by it), whatever the fast path would make of it
    "tuple": (1, (2, "x"), []),
    "numpy scalars": [np.float64(1.5), np.float32(2), np.int64(3), np.bool_(True), np.uint64(2**64 - 1),
                      np.float16(0.5), np.intc(1), np.longlong(2), np.ulonglong(3), np.int8(-1)],
    "odd numpy scalars": [np.longdouble(1.5), np.complex64(1), np.str_("x"), np.bytes_(b"x"), np.void(b"x"),
                          np.datetime64(1, "s")],
    "str subclass key": {Key("a"): 1}, "str subclass value": [Key("a")], "int subclass": [Number(3)],
    "bool key": {True: 1}, "int key": {1: 2}, "None key": {None: 1}, "tuple key": {(1,): 2},
    "memoryview": [memoryview(b"abc")], "memoryview of floats": [memoryview(np.ones(3, np.float32))],
    "non-contiguous memoryview": [memoryview(np.arange(8, dtype=np.uint8))[::2]], "bytearray": [bytearray(b"ab")],
    "ext type": [msgpack.ExtType(1, b"x")], "timestamp": [msgpack.Timestamp(1, 0)], "set": [{1, 2}],
    "huge int": [2**64], "negative huge int": [-2**63 - 1], "surrogate": ["\ud800"],
    "object array": [np.array([1, "x"], dtype=object)], "unicode array": [np.array(["ab"])],
    "complex array": [np.ones(2, np.complex64)], "datetime array": [np.zeros(2, "M8[s]")],
    "non-contiguous array": [np.arange(12, dtype=np.int16).reshape(3, 4)[:, ::2]],
    "fortran array": [np.asfortranarray(np.ones((2, 3)))], "array subclass": [np.ma.masked_array([1, 2])],
    "transposed": [np.arange(6.0).reshape(2, 3).T], "large array": [np.zeros(codec.LARGE_BIN, np.uint8)],
    "just below large": [np.zeros(codec.LARGE_BIN - 1, np.uint8)], "0-d array": np.array(2.5),
    "0-d in a map": {"a": np.array(7, np.int8)}, "empty arrays": [np.zeros((0, 3)), np.zeros(0, bool)],
    "big-endian": [np.arange(3, dtype=">u4")], "shared ref": [codec.SharedArray("xpl_1", 8, np.dtype("<f4"), (2, 3))],
    "shared ref numpy shape": [codec.SharedArray("xpl_1", 8, np.dtype("<f4"), (np.int64(2),))],
    "shared ref numpy offset": [codec.SharedArray("xpl_1", np.int64(8), np.dtype("<f4"), (2,))],
    "shared ref bool offset": [codec.SharedArray("xpl_1", True, np.dtype("<f4"), (2,))],
    "shared ref object dtype": [codec.SharedArray("xpl_1", 8, np.dtype(object), (2,))],
    "dict subclass": [collections.OrderedDict(a=1)], "list subclass": [type("L", (list,), {})([1])],
    "top-level scalar": 5, "top-level str": "x", "top-level None": None, "function": [len],
}


@pytest.mark.parametrize("name", sorted(ODD_VALUES))
def test_encoder_odd_values(name):
    check_encode(ODD_VALUES[name])
    check_encode({"wrapped": [ODD_VALUES[name], 1]})


def test_encoder_nesting_around_the_depth_limit():
    for depth in range(codec.MAX_DEPTH - 3, codec.MAX_DEPTH + 3):
        for leaf in (1, [], {}, np.zeros(2), (1,)):
            value: Any = leaf
            for i in range(depth):
                value = [value] if i % 2 else {"k": value}
            assert check_encode(value) or depth >= codec.MAX_DEPTH - 1


def test_encoder_generated_payloads():
    rng = random.Random(5)
    taken = 0
    for i in range(300):
        payload = {"observations": [random_value(rng, 5, True) for _ in range(rng.randrange(4))], "i": i,
                   "t": tuple(INTS[:rng.randrange(len(INTS))]), "f": FLOATS, "s": STRINGS[:-1]}
        taken += check_encode(payload)
    assert taken == 300
    assert check_encode({"observations": [{**SAMPLE, "image": np.zeros((4, 4, 3), np.uint8)}] * 3,
                         "env_ids": list(range(3))})
