"""MessagePack codec with numpy arrays, in the two array dialects our peers use.

* ``xpolicylab``: arrays as the ``msgpack-numpy`` package writes them,
  ``{b"nd": True, b"type": dtype.str, b"kind": b"", b"shape": [...], b"data": <bin>}``.
* ``openpi``: arrays as ``openpi_client.msgpack_numpy`` writes them,
  ``{b"__ndarray__": True, b"data": <bin>, b"dtype": dtype.str, b"shape": [...]}``.

The decoder accepts both spellings (keys as bin or str) whatever the dialect, so a peer that mixes them still
interoperates. Decoded arrays are read-only views, as with both reference packages: copy one before
modifying it in place. It is strict about everything that could hurt the receiver: object, structured and string
dtypes are refused (msgpack-numpy would unpickle object arrays), the data length must match the shape, ext
types and deep nesting are refused, and trailing bytes are an error.

Why a hand-written codec rather than ``msgpack.packb(default=...)``: an observation batch is ~180 MB, and the
stock path copies it several times into freshly mapped memory (page faults dominate on loopback). Encoding
returns a list of chunks in which large array buffers are zero-copy ``memoryview``s, so the transport can send
them as WebSocket fragments, one per array; decoding walks the received fragments and returns a view of each
array where it arrived in one fragment (no copy), else copies it once into a recycled buffer. The bytes on the
wire are exactly what ``msgpack`` would write.

The other way round, a batch of small observations (arrays in shared memory) is tens of thousands of small
items, where a Python loop costs ~3 us each: such messages go through msgpack's C extension first
(``_fast_encode``, ``_fast_decode``), which take only what they can write or read exactly as the paths above
(same bytes, same values and types) and hand everything else to them, every error included.

A third map, ``{b"xpl_shm": True, b"segment": name, b"offset": n, b"type": dtype.str, b"shape": [...]}``, stands
for an array that a client on the server's host placed in shared memory (``SharedArray``, see ``xpolicylab.shm``);
only a decoder asked for it (``shared_refs=True``) accepts one, and nothing else writes one.
"""

from __future__ import annotations

import enum
import functools
import math
import struct
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from xpolicylab.errors import ErrorCode, ProtocolError


class Dialect(str, enum.Enum):
    """Which array encoding to write."""

    XPOLICYLAB = "xpolicylab"
    OPENPI = "openpi"


#: Arrays at least this large travel as their own zero-copy chunk (and decode into their own buffer).
LARGE_BIN = 64 * 1024
#: Deepest container nesting accepted by the decoder; real observations are 3-4 levels deep.
MAX_DEPTH = 32
#: Most dimensions an array may declare.
MAX_NDIM = 16
#: dtype kinds allowed on the wire: bool, signed, unsigned, float.
SAFE_KINDS = frozenset("biuf")

_packb = msgpack.Packer(use_bin_type=True, autoreset=True).pack
_ND_KEYS = (b"nd", "nd")
_OPENPI_KEYS = (b"__ndarray__", "__ndarray__")
_OPENPI_GENERIC_KEYS = (b"__npgeneric__", "__npgeneric__")
_SHARED_KEYS = (b"xpl_shm", "xpl_shm")
_MARKER_KEYS = frozenset(_ND_KEYS + _OPENPI_KEYS + _OPENPI_GENERIC_KEYS + _SHARED_KEYS)


@dataclass(frozen=True)
class SharedArray:
    """An array placed in a shared-memory segment, as it travels in place of the array itself: which segment,
    where in it, and what it holds. The receiver checks all of it before reading (``xpolicylab.shm``)."""

    segment: str
    offset: int
    dtype: np.dtype
    shape: tuple[int, ...]

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize


def _bin_header(n: int) -> bytes:
    if n < 0x100:
        return b"\xc4" + bytes((n,))
    if n < 0x10000:
        return b"\xc5" + struct.pack(">H", n)
    return b"\xc6" + struct.pack(">I", n)


def _map_header(n: int) -> bytes:
    if n < 16:
        return bytes((0x80 | n,))
    if n < 0x10000:
        return b"\xde" + struct.pack(">H", n)
    return b"\xdf" + struct.pack(">I", n)


def _array_header(n: int) -> bytes:
    if n < 16:
        return bytes((0x90 | n,))
    if n < 0x10000:
        return b"\xdc" + struct.pack(">H", n)
    return b"\xdd" + struct.pack(">I", n)


def _check_dtype(dtype: np.dtype) -> None:
    if dtype.kind not in SAFE_KINDS:
        raise TypeError(f"arrays of dtype {dtype} cannot be sent; use bool, integer or float arrays")


class _Encoder:
    """Writes one object as a list of chunks; small items are coalesced, large array buffers are not copied."""

    def __init__(self, dialect: Dialect) -> None:
        self.dialect = dialect
        self.chunks: list[bytes | memoryview] = []
        self.buf = bytearray()

    def finish(self) -> list[bytes | memoryview]:
        if self.buf:
            self.chunks.append(bytes(self.buf))
            self.buf = bytearray()
        return self.chunks

    def _data(self, arr: np.ndarray) -> None:
        arr = np.ascontiguousarray(arr)
        view = memoryview(arr).cast("B") if arr.nbytes else memoryview(b"")
        self.buf += _bin_header(arr.nbytes)
        if arr.nbytes >= LARGE_BIN:
            self.chunks.append(bytes(self.buf))
            self.buf = bytearray()
            self.chunks.append(view)
        else:
            self.buf += view

    def _ndarray(self, arr: np.ndarray) -> None:
        _check_dtype(arr.dtype)
        shape = list(arr.shape)
        if self.dialect is Dialect.OPENPI:
            self.buf += b"\x84" + _packb(b"__ndarray__") + b"\xc3" + _packb(b"data")
            self._data(arr)
            self.buf += _packb(b"dtype") + _packb(arr.dtype.str) + _packb(b"shape") + _packb(shape)
        else:
            self.buf += (
                b"\x85" + _packb(b"nd") + b"\xc3" + _packb(b"type") + _packb(arr.dtype.str)
                + _packb(b"kind") + _packb(b"") + _packb(b"shape") + _packb(shape) + _packb(b"data")
            )
            self._data(arr)

    def _generic(self, value: np.generic) -> None:
        _check_dtype(value.dtype)
        if self.dialect is Dialect.OPENPI:
            self.buf += _packb({b"__npgeneric__": True, b"data": value.item(), b"dtype": value.dtype.str})
        else:
            self.buf += _packb({b"nd": False, b"type": value.dtype.str, b"data": value.tobytes()})

    def _shared(self, ref: SharedArray) -> None:
        self.buf += (
            b"\x85" + _packb(b"xpl_shm") + b"\xc3" + _packb(b"segment") + _packb(ref.segment) + _packb(b"offset")
            + _packb(ref.offset) + _packb(b"type") + _packb(ref.dtype.str) + _packb(b"shape") + _packb(list(ref.shape))
        )

    def write(self, obj: Any, depth: int = 0) -> None:
        if depth > MAX_DEPTH:
            raise ValueError(f"object nested deeper than {MAX_DEPTH} levels")
        if isinstance(obj, np.ndarray):
            self._ndarray(obj)
        elif isinstance(obj, dict):
            self.buf += _map_header(len(obj))
            for key, value in obj.items():
                if not isinstance(key, (str, bytes)):
                    raise TypeError(f"map keys must be str or bytes, not {type(key).__name__}")
                self.buf += _packb(key)
                self.write(value, depth + 1)
        elif isinstance(obj, (list, tuple)):
            self.buf += _array_header(len(obj))
            for value in obj:
                self.write(value, depth + 1)
        elif isinstance(obj, np.generic):
            self._generic(obj)
        elif obj is None or isinstance(obj, (bool, int, float, str, bytes)):
            self.buf += _packb(obj)
        elif isinstance(obj, (bytearray, memoryview)):
            self.buf += _packb(bytes(obj))
        elif isinstance(obj, SharedArray):
            self._shared(obj)
        else:
            raise TypeError(f"cannot encode {type(obj).__name__} in a frame")


_FAST_CONTAINER_TYPES = frozenset({dict, list, tuple})
#: numpy scalars whose ``item()`` is a Python bool, int or float (not ``longdouble``).
_NUMPY_SCALAR_TYPES = frozenset(np.dtype(code).type for code in "?bhilqBHILQefd")
#: What ``_fast_encode`` accepts, by exact type: msgpack's packer (``strict_types``) writes the plain ones just as
#: ``_Encoder`` does and hands the others to ``_fast_default``; subclasses, memoryviews and the rest go to
#: ``_Encoder``.
_FAST_ENCODE_TYPES = _FAST_CONTAINER_TYPES | _NUMPY_SCALAR_TYPES | {
    type(None), bool, int, float, str, bytes, bytearray, np.ndarray, SharedArray}
_KEY_TYPES = frozenset({str, bytes})


class _Unpackable(Exception):
    """``_fast_encode`` cannot write this value byte for byte as ``_Encoder`` does; ``_Encoder`` writes it."""


def _fast_encodable(obj: dict | list | tuple, depth: int = 0) -> bool:
    """Whether ``obj`` holds only ``_FAST_ENCODE_TYPES``, with str or bytes keys, no deeper than ``_Encoder``
    writes (msgpack's packer checks neither key types nor ``MAX_DEPTH``). One pass over the values, in C."""
    if depth >= MAX_DEPTH:
        return False
    if type(obj) is dict:
        if not _KEY_TYPES.issuperset(map(type, obj)):
            return False
        items = obj.values()
    else:
        items = obj
    kinds = set(map(type, items))
    if not _FAST_ENCODE_TYPES.issuperset(kinds):
        return False
    return kinds.isdisjoint(_FAST_CONTAINER_TYPES) or all(
        _fast_encodable(v, depth + 1) for v in items if type(v) in _FAST_CONTAINER_TYPES)


def _fast_default(obj: Any, dialect: Dialect) -> Any:
    """msgpack's ``default`` hook: what ``_Encoder`` writes for a tuple, a numpy scalar, a small array or a
    shared-memory reference, as a value the packer writes natively (maps keep their key order)."""
    kind = type(obj)
    if kind is tuple:
        return list(obj)
    if kind in _NUMPY_SCALAR_TYPES:
        if dialect is Dialect.OPENPI:
            return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
        return {b"nd": False, b"type": obj.dtype.str, b"data": obj.tobytes()}
    if kind is SharedArray:
        if not (type(obj.segment) is str and type(obj.offset) is int and all(type(d) is int for d in obj.shape)):
            raise _Unpackable("a reference of other types")  # that _Encoder may refuse, or write otherwise
        return {b"xpl_shm": True, b"segment": obj.segment, b"offset": obj.offset, b"type": obj.dtype.str,
                b"shape": list(obj.shape)}
    if kind is not np.ndarray or obj.nbytes >= LARGE_BIN:  # a large array travels as its own zero-copy chunk
        raise _Unpackable(kind.__name__)
    _check_dtype(obj.dtype)
    if dialect is Dialect.OPENPI:
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": list(obj.shape)}
    return {b"nd": True, b"type": obj.dtype.str, b"kind": b"", b"shape": list(obj.shape), b"data": obj.tobytes()}


_FAST_DEFAULTS = {dialect: functools.partial(_fast_default, dialect=dialect) for dialect in Dialect}


def _fast_encode(obj: Any, dialect: Dialect) -> list[bytes | memoryview]:
    """``encode_chunks`` through msgpack's C packer, byte for byte: one chunk, as ``_Encoder`` makes of a message
    without large arrays. Raises for anything else (see ``_fast_encodable``, ``_fast_default``)."""
    if type(obj) not in _FAST_CONTAINER_TYPES or not _fast_encodable(obj):
        raise _Unpackable(type(obj).__name__)
    # A packer per call: the shared one (``_packb``) must not be re-entered from ``default`` by another thread.
    return [msgpack.packb(obj, use_bin_type=True, strict_types=True, default=_FAST_DEFAULTS[dialect])]


def encode_chunks(obj: Any, dialect: Dialect = Dialect.XPOLICYLAB) -> list[bytes | memoryview]:
    """Encode ``obj`` as chunks whose concatenation is the MessagePack message; large arrays are not copied.

    The arrays must not be modified until the chunks have been sent. A message of plain values and small arrays
    is written by ``_fast_encode``; the rest, and every error, by ``_Encoder``.
    """
    dialect = Dialect(dialect)
    try:
        return _fast_encode(obj, dialect)
    except Exception:  # noqa: BLE001 - _Encoder writes (or refuses) whatever the fast path could not
        pass
    enc = _Encoder(dialect)
    enc.write(obj)
    return enc.finish()


def encode(obj: Any, dialect: Dialect = Dialect.XPOLICYLAB) -> bytes:
    """Encode ``obj`` as one MessagePack message (``bytes``)."""
    return b"".join(encode_chunks(obj, dialect))


def _invalid(message: str) -> ProtocolError:
    return ProtocolError(ErrorCode.INVALID_FRAME, message)


class _Reader:
    """Sequential reads over the fragments of one message without joining them."""

    def __init__(self, fragments: Sequence[bytes | bytearray | memoryview], shared_refs: bool = False) -> None:
        self.shared_refs = shared_refs  # whether SharedArray maps are accepted (see ``decode``)
        self.frags = [memoryview(f).cast("B") for f in fragments if len(f)]
        self.total = sum(len(f) for f in self.frags)
        self.index = 0
        self.cur = self.frags[0] if self.frags else memoryview(b"")
        self.offset = 0  # bytes in the fragments before `cur`
        self.pos = 0

    def _advance(self) -> bool:
        if self.index + 1 >= len(self.frags):
            return False
        self.offset += len(self.cur)
        self.index += 1
        self.cur = self.frags[self.index]
        self.pos = 0
        return True

    def byte(self) -> int:
        if self.pos >= len(self.cur) and not self._advance():
            raise _invalid("truncated message")
        value = self.cur[self.pos]
        self.pos += 1
        return value

    def take(self, n: int) -> bytes | memoryview:
        end = self.pos + n
        if end <= len(self.cur):
            out = self.cur[self.pos:end]
            self.pos = end
            return out
        if n > self.remaining():  # before allocating what a forged length (of a string) asks for
            raise _invalid("truncated message")
        out = bytearray(n)
        self.readinto(memoryview(out))
        return out

    def readinto(self, target: memoryview) -> None:
        filled, n = 0, len(target)
        while filled < n:
            if self.pos >= len(self.cur) and not self._advance():
                raise _invalid("truncated message")
            step = min(n - filled, len(self.cur) - self.pos)
            target[filled:filled + step] = self.cur[self.pos:self.pos + step]
            filled += step
            self.pos += step

    def view(self, n: int) -> memoryview | None:
        """A zero-copy view of the next ``n`` bytes if they lie within one fragment, else None."""
        if self.pos == len(self.cur):
            self._advance()
        if self.pos + n > len(self.cur):
            return None
        out = self.cur[self.pos:self.pos + n]
        self.pos += n
        return out

    def remaining(self) -> int:
        return self.total - self.offset - self.pos


_FIXED = {
    0xCA: (4, ">f"), 0xCB: (8, ">d"), 0xCC: (1, ">B"), 0xCD: (2, ">H"), 0xCE: (4, ">I"), 0xCF: (8, ">Q"),
    0xD0: (1, ">b"), 0xD1: (2, ">h"), 0xD2: (4, ">i"), 0xD3: (8, ">q"),
}
_LEN = {0xC4: 1, 0xC5: 2, 0xC6: 4, 0xD9: 1, 0xDA: 2, 0xDB: 4, 0xDC: 2, 0xDD: 4, 0xDE: 2, 0xDF: 4}


def _first(obj: dict, keys: tuple[Any, Any]) -> Any:
    """The value under the first of two spellings of a key present (bin, then str), else None."""
    return obj.get(keys[0], obj.get(keys[1]))


def _dtype(spec: Any) -> np.dtype:
    if isinstance(spec, bytes):
        spec = spec.decode("ascii", "replace")
    if not isinstance(spec, str):
        raise _invalid(f"array dtype must be a string, got {type(spec).__name__}")
    return _checked_dtype(spec)


@functools.lru_cache(maxsize=64)
def _checked_dtype(spec: str) -> np.dtype:
    """A dtype named on the wire, parsed once per name (a batch of observations names the same few thousands of
    times; a bad name raises, and errors are not cached)."""
    try:
        dtype = np.dtype(spec)
    except (TypeError, ValueError):
        raise _invalid(f"bad array dtype {spec!r}") from None
    if dtype.kind not in SAFE_KINDS:
        raise _invalid(f"array dtype {spec!r} is not allowed (only bool, integer and float)")
    return dtype


def _shape(spec: Any) -> tuple[int, ...]:
    if not isinstance(spec, (list, tuple)) or len(spec) > MAX_NDIM:
        raise _invalid(f"array shape must be a list of at most {MAX_NDIM} integers")
    if not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in spec):
        raise _invalid(f"array shape {list(spec)} must hold non-negative integers")
    return tuple(spec)


def _array(data: Any, dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise _invalid("array data must be binary")
    expected = math.prod(shape) * dtype.itemsize
    if len(data) != expected:
        raise _invalid(f"array data has {len(data)} bytes, shape {list(shape)} of {dtype.str} needs {expected}")
    arr = np.frombuffer(data, dtype=dtype).reshape(shape)
    arr.flags.writeable = False  # always read-only, like msgpack-numpy and openpi_client (and zero-copy)
    return arr


def _numpy_array(kind: Any, data: Any, dtype: Any, shape: Any) -> np.ndarray:
    """The array of a msgpack-numpy map (``nd`` true), from its fields as they came."""
    if kind not in (None, b"", ""):
        raise _invalid(f"array kind {kind!r} is not allowed (object and structured arrays are refused)")
    return _array(data, _dtype(dtype), _shape(shape))


def _shared_array(obj: dict, accepted: bool) -> SharedArray:
    """A shared-memory reference, checked for form only (the segment and the bounds are the receiver's to check)."""
    if not accepted:
        raise _invalid("shared-memory array references are not accepted here (only by a native server, from a "
                       "client on its host)")
    segment, offset = _first(obj, (b"segment", "segment")), _first(obj, (b"offset", "offset"))
    if not isinstance(segment, str):
        raise _invalid("a shared-memory reference needs 'segment', a string")
    if not isinstance(offset, int) or isinstance(offset, bool) or offset < 0:
        raise _invalid(f"a shared-memory reference needs 'offset', a non-negative integer, got {offset!r}")
    dtype, shape = _dtype(_first(obj, (b"type", "type"))), _shape(_first(obj, (b"shape", "shape")))
    return SharedArray(segment, offset, dtype, shape)


def _decode_map(obj: dict, shared_refs: bool) -> Any:
    """Turn an array map of either dialect (or a shared-memory reference) into its value; leave other maps alone."""
    if obj.keys().isdisjoint(_MARKER_KEYS):  # most maps: one set operation instead of the lookups below
        return obj
    nd = _first(obj, _ND_KEYS)
    if nd is True:
        return _numpy_array(_first(obj, (b"kind", "kind")), _first(obj, (b"data", "data")),
                            _first(obj, (b"type", "type")), _first(obj, (b"shape", "shape")))
    if nd is False:
        dtype = _dtype(_first(obj, (b"type", "type")))
        return _array(_first(obj, (b"data", "data")), dtype, ())[()]
    if _first(obj, _OPENPI_KEYS) is True:
        return _array(_first(obj, (b"data", "data")), _dtype(_first(obj, (b"dtype", "dtype"))),
                      _shape(_first(obj, (b"shape", "shape"))))
    if _first(obj, _OPENPI_GENERIC_KEYS) is True:
        dtype = _dtype(_first(obj, (b"dtype", "dtype")))
        try:
            return dtype.type(_first(obj, (b"data", "data")))
        except (TypeError, ValueError, OverflowError):
            raise _invalid("bad numpy scalar") from None
    if _first(obj, _SHARED_KEYS) is True:
        return _shared_array(obj, shared_refs)
    return obj


def _read(r: _Reader, depth: int) -> Any:
    b = r.byte()
    if b <= 0x7F:
        return b
    if b >= 0xE0:
        return b - 0x100
    if 0xA0 <= b <= 0xBF:
        return _str(r, b & 0x1F)
    if 0x80 <= b <= 0x8F:
        return _map(r, b & 0x0F, depth)
    if 0x90 <= b <= 0x9F:
        return _list(r, b & 0x0F, depth)
    if b == 0xC0:
        return None
    if b == 0xC2:
        return False
    if b == 0xC3:
        return True
    fixed = _FIXED.get(b)
    if fixed is not None:
        return struct.unpack(fixed[1], r.take(fixed[0]))[0]
    width = _LEN.get(b)
    if width is None:
        raise _invalid(f"unsupported MessagePack type byte 0x{b:02x} (ext types are refused)")
    n = int.from_bytes(r.take(width), "big")
    if b in (0xC4, 0xC5, 0xC6):
        return _bin(r, n)
    if b in (0xD9, 0xDA, 0xDB):
        return _str(r, n)
    if b in (0xDC, 0xDD):
        return _list(r, n, depth)
    return _map(r, n, depth)


def _str(r: _Reader, n: int) -> str:
    try:
        return bytes(r.take(n)).decode("utf-8")
    except UnicodeDecodeError:
        raise _invalid("string is not valid UTF-8") from None


class _BufferPool:
    """Recycles large decode buffers once nothing decoded from them is alive any more.

    A policy server decodes the same image sizes over and over; without recycling, the allocator hands back
    freshly mapped pages each time and page faults cost as much as the copy itself. A buffer is free again when
    the pool holds the only reference (every array decoded into it keeps it alive through its memoryview).

    Buffers of one size are handed out in turn from a cursor, which looks at no more than ``PROBES`` of them: a
    request's arrays are decoded in order and let go of together, so the buffer after the last one handed out is
    the one most likely free. (Scanning every buffer from the start made a batch of n arrays cost n^2/2 reference
    counts: 6,144 images of 2,048 environments, 19 million per request.) A size keeps at most ``max_bytes`` of
    buffers; beyond that, buffers are allocated for the request and let go of.
    """

    PROBES = 8

    def __init__(self, max_bytes: int = 4 << 30) -> None:
        self._buffers: dict[int, list[np.ndarray]] = {}
        self._cursor: dict[int, int] = {}
        self._lock = threading.Lock()
        self._max_bytes = max_bytes

    def get(self, n: int) -> np.ndarray:
        with self._lock:
            buffers = self._buffers.setdefault(n, [])
            start = self._cursor.get(n, 0)
            for k in range(min(self.PROBES, len(buffers))):
                i = (start + k) % len(buffers)
                if sys.getrefcount(buffers[i]) == 2:  # the list's reference and getrefcount's argument
                    self._cursor[n] = i + 1
                    return buffers[i]
            buf = np.empty(n, dtype=np.uint8)
            if (len(buffers) + 1) * n <= self._max_bytes:
                buffers.insert(start, buf)  # the cursor's place: the next request finds it in order again
                self._cursor[n] = start + 1
            return buf


_POOL = _BufferPool()


def recycled_buffer(n: int) -> np.ndarray:
    """A ``uint8[n]`` buffer for a decoded array, from the pool that recycles them (see ``_BufferPool``)."""
    return _POOL.get(n)


def _bin(r: _Reader, n: int) -> bytes | memoryview:
    if n > r.remaining():
        raise _invalid("truncated message")
    if n < LARGE_BIN:
        return bytes(r.take(n))
    view = r.view(n)
    if view is not None:  # the sender put this array in its own fragment: no copy at all
        return view
    target = memoryview(_POOL.get(n))
    r.readinto(target)
    return target


def _list(r: _Reader, n: int, depth: int) -> list:
    if depth >= MAX_DEPTH:
        raise _invalid(f"message nested deeper than {MAX_DEPTH} levels")
    if n > r.remaining():
        raise _invalid("truncated message")
    return [_read(r, depth + 1) for _ in range(n)]


def _map(r: _Reader, n: int, depth: int) -> Any:
    if depth >= MAX_DEPTH:
        raise _invalid(f"message nested deeper than {MAX_DEPTH} levels")
    if 2 * n > r.remaining():
        raise _invalid("truncated message")
    out: dict = {}
    for _ in range(n):
        key = _read(r, depth + 1)
        if not isinstance(key, (str, bytes)):
            raise _invalid(f"map keys must be strings, got {type(key).__name__}")
        out[key] = _read(r, depth + 1)
    return _decode_map(out, r.shared_refs)


#: Messages up to this size are decoded by msgpack's C unpacker first (``_fast_decode``): a batch of small
#: observations is ~100 items each, and the Python decoder spends ~3 us per item. A batch of 2,048 observations whose
#: images travel through shared memory is about 5 MB (2.4 s a request in the Python decoder on the CI machine).
FAST_DECODE_MAX = 64 * 1024 * 1024
#: Longest array or map the fast path builds. msgpack allocates a container's slots when it reads the header,
#: before its items arrive, so a chain of nested headers (msgpack stops at 1024 levels) costs at most
#: 1024 * 4096 * 8 bytes (32 MiB) however short the message; longer containers go to the Python decoder.
FAST_MAX_LEN = 4096
#: Deepest plain container the fast path accepts: each of its leaves may be an array map (one level) holding a
#: shape list (one more), and the Python decoder refuses a container at depth ``MAX_DEPTH``.
FAST_MAX_DEPTH = MAX_DEPTH - 3
_SCALAR_TYPES = frozenset({type(None), bool, int, float, str, bytes})
_NUMPY_MAP_KEYS = frozenset({b"nd", b"type", b"kind", b"shape", b"data"})


class _Unsure(Exception):
    """The fast path cannot vouch for its result on this message; the Python decoder decides."""


def _refuse_ext(code: int, data: bytes) -> Any:
    """Ext types are refused (as by ``_read``); raising here hands the message to the Python decoder."""
    raise _Unsure(f"ext type {code}")


def _flat(obj: dict) -> bool:
    """Whether each value of ``obj`` is a scalar or a list of scalars: all an array map may hold for the fast path
    to know how deep it went (a map or a converted array inside an array map would hide its depth)."""
    for value in obj.values():
        kind = type(value)
        if kind not in _SCALAR_TYPES and not (kind is list and _SCALAR_TYPES.issuperset(map(type, value))):
            return False
    return True


def _fast_map(pairs: list[tuple[Any, Any]], shared_refs: bool) -> Any:
    """``object_pairs_hook`` of the fast path: a map as ``_map`` returns it, bottom-up in the same order.

    Duplicate keys are left to the Python decoder, which converts (and may refuse) a value before a later
    duplicate replaces it; so are array maps holding anything but scalars and flat lists (see ``_flat``).
    """
    obj = dict(pairs)
    if len(obj) != len(pairs):
        raise _Unsure("duplicate map keys")
    if obj.keys() == _NUMPY_MAP_KEYS and obj[b"nd"] is True:
        # The map _Encoder writes for an array, as _decode_map would read it; _numpy_array accepts only flat
        # fields (a kind, a dtype name, a list of ints, a bin), so _flat holds.
        return _numpy_array(obj[b"kind"], obj[b"data"], obj[b"type"], obj[b"shape"])
    value = _decode_map(obj, shared_refs)
    if value is not obj and not _flat(obj):
        raise _Unsure("nested values in an array map")
    return value


_FAST_HOOKS = {refs: functools.partial(_fast_map, shared_refs=refs) for refs in (False, True)}


def _shallow(value: Any, depth: int = 0) -> bool:
    """Whether no plain container in ``value`` lies deeper than ``FAST_MAX_DEPTH`` (arrays are already
    converted, and ``_fast_map`` made sure each hides at most two levels)."""
    kind = type(value)
    if kind is not dict and kind is not list:
        return True
    if depth > FAST_MAX_DEPTH:
        return False
    items = value.values() if kind is dict else value
    return all(_shallow(v, depth + 1) for v in items if type(v) is dict or type(v) is list)


def _fast_decode(fragments: Sequence[bytes | bytearray | memoryview], shared_refs: bool) -> Any:
    """``decode`` through msgpack's C unpacker, for a message of at most ``FAST_DECODE_MAX`` bytes.

    Raises (anything) where it cannot vouch for giving exactly ``decode``'s result: large binaries (the Python
    decoder returns them as views, ``_bin``), ext types, non-string keys, invalid UTF-8, long containers,
    nesting near ``MAX_DEPTH``, and every malformed message. A message in several fragments is joined first (our
    transport splits one of more than ``transport.FRAGMENT`` bytes even when it holds no large array: a batch of
    thousands of small observations); its size bounds that copy.
    """
    total = sum(memoryview(f).nbytes for f in fragments)
    if not 0 < total <= FAST_DECODE_MAX:
        raise _Unsure("size")
    data = fragments[0] if len(fragments) == 1 else b"".join(fragments)
    value = msgpack.unpackb(
        data, raw=False, strict_map_key=True, object_pairs_hook=_FAST_HOOKS[shared_refs], ext_hook=_refuse_ext,
        max_bin_len=LARGE_BIN - 1, max_str_len=total, max_array_len=FAST_MAX_LEN, max_map_len=FAST_MAX_LEN,
        max_ext_len=0)
    if not _shallow(value):
        raise _Unsure("deep")
    return value


def _fragment_list(fragments: bytes | bytearray | memoryview | Sequence[bytes | bytearray | memoryview]
                   ) -> Sequence[bytes | bytearray | memoryview]:
    """``decode``'s argument as a list of fragments."""
    return [fragments] if isinstance(fragments, (bytes, bytearray, memoryview)) else fragments


def decode(fragments: bytes | bytearray | memoryview | Sequence[bytes | bytearray | memoryview],
           shared_refs: bool = False) -> Any:
    """Decode one MessagePack message given whole or as the list of its WebSocket fragments.

    Raises ``ProtocolError(invalid_frame)`` for anything malformed, truncated, trailing or unsafe. With
    ``shared_refs``, shared-memory references come out as ``SharedArray``s for the caller to resolve (the native
    server does, once it knows which request they belong to); without, they are refused like any unknown array.

    A message of at most ``FAST_DECODE_MAX`` bytes is first tried by ``_fast_decode``; whatever it cannot vouch
    for (including every malformed message) goes to ``_decode_exact``, so results and errors are that decoder's.
    """
    fragments = _fragment_list(fragments)
    try:
        return _fast_decode(fragments, shared_refs)
    except Exception:  # noqa: BLE001 - anything the fast path refuses is for the exact decoder to judge
        return _decode_exact(fragments, shared_refs)


def _decode_exact(fragments: Sequence[bytes | bytearray | memoryview], shared_refs: bool) -> Any:
    """``decode`` in Python, item by item: large arrays as views of their fragments, every refusal named."""
    reader = _Reader(fragments, shared_refs)
    if reader.remaining() == 0:
        raise _invalid("empty frame")
    value = _read(reader, 0)
    if reader.remaining():
        raise _invalid(f"{reader.remaining()} trailing bytes after the message")
    return value
