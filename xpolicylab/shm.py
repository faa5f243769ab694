"""Shared memory for large arrays when client and server share a host.

On loopback the socket is the bottleneck: every image byte is framed, copied through the kernel twice and
parsed. A client on the server's host instead writes each large array (``THRESHOLD`` bytes or more) of an
``infer`` request into a segment of its own (``SegmentPool``) and sends a small reference in its place
(``codec.SharedArray``); the server copies the array out of the segment (``SegmentCache``) before the model sees
it, so the model owns what it keeps and the client may reuse the segment as soon as the reply arrives. A model that
keeps no array it is given (``Model.borrows_observations``) is handed read-only views of the segment instead.
Both copies of a large request are spread over a few threads (``COPY_THREADS``): one core of the H200 host copies
5.6 GB/s, eight 21 GB/s.

Lent buffers: a client can lend its caller a buffer in a segment of its own (``SegmentPool.lend``). An array that
lies in one piece inside a lent buffer goes as a reference to where it already is, with no copy: a batched
simulator that copies its images from the GPU straight into such a buffer hands them to a policy on the same host
without the host ever copying them (at 2,048 environments' three 224x224 images, 925 MB per request, gathering and
placing a request took 47.8 ms with that copy and 11.3 ms without on the H200 host, 2026-11-29). The caller writes a lent buffer again only once the request that carried it has had
its reply, as with any array it sends.

Negotiation: a native server advertises ``capabilities.shared_memory`` (its ``shared_memory`` option) and accepts
references only from a loopback peer; the client (``shared_memory`` = ``auto`` | ``on`` | ``off``) uses them when
the URL's host is loopback, the server advertises them and one probe at connect time went through (a server in
a container may share the loopback interface but not ``/dev/shm``). Everything else travels as before.

Safety: segment names carry ``PREFIX`` and the server opens no other; a reference must lie within its segment
and name a bool, integer or float dtype; every fault is an ``invalid_frame`` error naming what was wrong, for
that request only. Segments are unlinked when the client closes, when it is collected or exits, and by
``multiprocessing``'s resource tracker if it is killed; the server unregisters the segments it merely opens, or
its own tracker would unlink the client's segments when the server exits.
"""

from __future__ import annotations

import atexit
import ipaddress
import logging
import mmap
import os
import re
import secrets
import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from contextlib import contextmanager
from multiprocessing import resource_tracker
from multiprocessing.shared_memory import SharedMemory
from typing import Any

import numpy as np

from xpolicylab import codec, columns
from xpolicylab.errors import ErrorCode, ProtocolError

#: Values of the client's ``shared_memory`` option.
MODES = ("auto", "on", "off")
#: Every segment name starts with this; the server refuses any other name.
PREFIX = "xpl_"
#: Arrays at least this large travel through shared memory (smaller ones cost less on the socket than a reference).
THRESHOLD = codec.LARGE_BIN
#: About what one reference takes in a frame, for the client's frame budget.
REFERENCE_BYTES = 96
#: Offsets of arrays in a segment are multiples of this (cache lines; any dtype's alignment).
ALIGN = 64
#: Segments one server connection keeps open; older ones are closed (a client that grew a segment unlinked it).
OPEN_PER_CONNECTION = 16
#: Threads that copy arrays into and out of segments, each given at least ``BYTES_PER_COPY_THREAD``: 177 MB of
#: 640x480 images took 32 ms on one core of the H200 host, 8 ms on eight; less than that per thread is not worth
#: handing over. Half the cores, as the other process of the pair copies at other times but also runs.
COPY_THREADS = max(1, min(8, (os.cpu_count() or 1) // 2))
BYTES_PER_COPY_THREAD = 8 << 20

logger = logging.getLogger(__name__)
_NAME = re.compile(rf"{PREFIX}[A-Za-z0-9_]{{1,60}}\Z")
#: Names of the segments this process created: a server in the same process (tests, notebooks) must leave their
#: resource-tracker registration alone, since it is the creator's.
_CREATED: set[str] = set()


class NoSharedMemory(RuntimeError):
    """A segment for a request could not be created (``/dev/shm`` full or missing); nothing was sent."""


def mode(value: str | bool) -> str:
    """The ``shared_memory`` option as one of ``MODES``; YAML's booleans (``on`` reads as true there) are accepted."""
    if isinstance(value, bool):
        return "on" if value else "off"
    text = str(value).strip().lower()
    text = {"true": "on", "false": "off"}.get(text, text)
    if text not in MODES:
        raise ValueError(f"shared_memory must be one of {', '.join(MODES)}, got {value!r}")
    return text


def is_loopback_host(host: str | None) -> bool:
    """Whether a URL's host is this machine's loopback (``localhost``, 127.0.0.0/8 or ::1)."""
    return host == "localhost" or is_loopback_address(host)


def is_loopback_address(peer: Any) -> bool:
    """Whether a socket address (``(host, port, ...)`` or a bare host) is loopback, IPv4-mapped IPv6 included."""
    host = peer[0] if isinstance(peer, (tuple, list)) and peer else peer
    try:
        address = ipaddress.ip_address(str(host).split("%")[0])
    except ValueError:
        return False
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        address = address.ipv4_mapped
    return address.is_loopback


def travels_shared(value: Any) -> bool:
    """Whether ``value`` goes through shared memory rather than the socket (a large array of a wire dtype, or a
    column of such arrays, ``columns.Rows``)."""
    return (isinstance(value, (np.ndarray, columns.Rows)) and value.nbytes >= THRESHOLD
            and value.dtype.kind in codec.SAFE_KINDS)


def _aligned(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


#: Where an array lies in a lent buffer: ``(segment name, offset)``, or None when it does not lie in one whole.
_Lent = Callable[[Any], "tuple[str, int] | None"]


def _nothing_lent(value: Any) -> None:
    return None


def _shared_bytes(value: Any, lent: _Lent = _nothing_lent) -> int:
    """Bytes of segment that ``value``'s shared arrays need, each at an aligned offset (none for those already in a
    lent buffer)."""
    if travels_shared(value):
        return 0 if lent(value) is not None else _aligned(value.nbytes)
    if isinstance(value, dict):
        return sum(_shared_bytes(v, lent) for v in value.values())
    if isinstance(value, (list, tuple)):
        return 0 if _plain(value) else sum(_shared_bytes(v, lent) for v in value)
    return 0


_PLAIN = frozenset({str, int, float, bool, bytes, type(None)})


def _plain(values: Sequence[Any]) -> bool:
    """Whether a list holds only values that never travel shared (a columnar batch's instructions, episode
    numbers, ...): nothing in it to look into, for thousands of environments."""
    return all(type(v) in _PLAIN for v in values)


def _one_block(value: np.ndarray | columns.Rows) -> np.ndarray | None:
    """``value`` as one C-contiguous array over memory already there (a ``Rows`` whose rows lie one after another
    in one buffer), or None."""
    if isinstance(value, columns.Rows):
        runs = value.runs()
        value = runs[0][1] if len(runs) == 1 else None
    return value if value is not None and value.flags.c_contiguous else None


#: One copy between an array and a segment: ``(segment's buffer, offset, array, True: into the segment)``.
_Copy = tuple[memoryview, int, np.ndarray, bool]
#: The copying threads and the process they belong to (a forked child has none of them, and makes its own).
_copier: tuple[int, ThreadPoolExecutor] | None = None


def _copy(job: _Copy) -> None:
    """Copy one array into or out of a segment. The view of the segment lives only during the copy: a segment
    cannot be closed while a view of it exists."""
    buf, offset, array, into = job
    view = np.ndarray(array.shape, array.dtype, buf, offset)
    if into:
        np.copyto(view, array)
    else:
        np.copyto(array, view)


def _copy_group(jobs: Sequence[_Copy]) -> None:
    for job in jobs:
        _copy(job)


def _pieces(jobs: list[_Copy], threads: int) -> list[list[_Copy]]:
    """``jobs`` dealt to ``threads`` groups of about equal bytes: an array larger than a group's share is cut
    along its first axis (a columnar batch is a few arrays of hundreds of MB, the list form thousands of small
    ones)."""
    share = -(-sum(job[2].nbytes for job in jobs) // threads)
    groups: list[list[_Copy]] = [[] for _ in range(threads)]
    loads = [0] * threads
    for buf, offset, array, into in jobs:
        rows = array.shape[0] if array.ndim else 1  # the segment holds it C-contiguous, whatever its own strides
        if not rows:
            continue  # an empty array: nothing to copy
        row_bytes = array.nbytes // rows
        step = max(1, share // row_bytes) if row_bytes and array.nbytes > share else rows
        for start in range(0, rows, step):
            piece = array if step >= rows else array[start:start + step]
            target = loads.index(min(loads))
            groups[target].append((buf, offset + start * row_bytes, piece, into))
            loads[target] += piece.nbytes
    return [g for g in groups if g]


def _copy_all(jobs: list[_Copy]) -> None:
    """Run the copies of one request, on several threads when there is enough to copy (numpy lets go of the GIL
    while copying)."""
    global _copier
    threads = min(COPY_THREADS, sum(job[2].nbytes for job in jobs) // BYTES_PER_COPY_THREAD)
    if threads < 2:
        _copy_group(jobs)
        return
    if _copier is None or _copier[0] != os.getpid():
        _copier = os.getpid(), ThreadPoolExecutor(COPY_THREADS, thread_name_prefix="xpolicylab-shm")
    futures = [_copier[1].submit(_copy_group, group) for group in _pieces(jobs, threads)]
    wait(futures)  # all of them, even when one fails: no copy may outlive the request
    for future in futures:
        future.result()


def _place(value: Any, segment: SharedMemory | None, cursor: list[int], jobs: list[_Copy],
           lent: _Lent = _nothing_lent) -> Any:
    """``value`` with each shared array replaced by its reference, and its copy into ``segment`` (from ``cursor[0]``
    on) added to ``jobs``; containers are rebuilt, the caller's are left as they were. A column of arrays
    (``columns.Rows``) is laid out as one array, each run of rows copied in one piece. An array already in a lent
    buffer (``lent``) is referenced where it is, and copied nowhere (``segment`` is None when all of them are)."""
    if travels_shared(value):
        found = lent(value)
        if found is not None:
            return codec.SharedArray(found[0], found[1], value.dtype, value.shape)
        assert segment is not None, "_shared_bytes counted this array"
        offset = cursor[0]
        cursor[0] += _aligned(value.nbytes)
        if isinstance(value, columns.Rows):
            jobs.extend((segment.buf, offset + start * value.row_nbytes, run, True) for start, run in value.runs())
        else:
            jobs.append((segment.buf, offset, value, True))
        return codec.SharedArray(segment.name, offset, value.dtype, value.shape)
    if isinstance(value, columns.Rows):
        return value.joined()  # too small to be worth a reference
    if isinstance(value, dict):
        return {k: _place(v, segment, cursor, jobs, lent) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return list(value) if _plain(value) else [_place(v, segment, cursor, jobs, lent) for v in value]
    return value


def _create(size: int) -> SharedMemory:
    """A new segment of at least ``size`` bytes, its memory reserved now: on a full ``/dev/shm`` (64 MiB in a
    default Docker container) writing into a merely truncated segment would kill the process with SIGBUS."""
    size = -(-size // mmap.PAGESIZE) * mmap.PAGESIZE
    name = f"{PREFIX}{os.getpid()}_{secrets.token_hex(6)}"  # the pid says whose a left-over segment was
    try:
        segment = SharedMemory(name, create=True, size=size)
    except OSError as exc:
        raise NoSharedMemory(f"cannot create a {size / (1 << 20):.1f} MiB shared-memory segment: {exc}") from exc
    _CREATED.add(segment.name)
    if hasattr(os, "posix_fallocate"):  # Linux; macOS has no tmpfs to overfill
        try:
            os.posix_fallocate(segment._fd, 0, size)  # SharedMemory keeps its descriptor there
        except OSError as exc:
            _unlink(segment)
            raise NoSharedMemory(f"/dev/shm has no room for a {size / (1 << 20):.1f} MiB segment: {exc}") from exc
    return segment


def _unlink(segment: SharedMemory) -> None:
    """Remove a segment of ours from ``/dev/shm`` and close it; one whose memory a lent buffer still exports is
    closed once that buffer is let go of (``_LENT``), as a server's borrowed views are."""
    _CREATED.discard(segment.name)
    try:
        segment.unlink()
    except FileNotFoundError:  # someone removed it from /dev/shm by hand
        pass
    _LENT[:] = [s for s in _LENT if not _closed(s)]
    if not _closed(segment):
        _LENT.append(segment)


def _unlink_all(segments: dict[str, SharedMemory]) -> None:
    while segments:
        _unlink(segments.popitem()[1])


class SegmentPool:
    """The client's segments: each leased to one request at a time (requests in flight together each need their
    own), reused once its reply has arrived, grown when a request needs more, all unlinked on ``close``."""

    def __init__(self) -> None:
        self._owned: dict[str, SharedMemory] = {}
        self._free: list[SharedMemory] = []
        self._lent: dict[str, tuple[int, int]] = {}  # segment name -> (address, bytes) of a buffer lent out
        self._lock = threading.Lock()  # lending happens on the caller's thread, leases on the client's loop
        # Unlinks what is left if the pool is collected or the interpreter exits (Ctrl-C) without close().
        self._finalizer = weakref.finalize(self, _unlink_all, self._owned)

    def lend(self, nbytes: int) -> np.ndarray:
        """A writable uint8 buffer of ``nbytes`` in a segment of its own, for the caller to put arrays in that it
        will send: one lying in one piece inside it travels as a reference to it (module docstring). Kept until
        ``give_back`` or ``close``. Raises ``NoSharedMemory`` when no segment can be had."""
        segment = _create(max(1, nbytes))
        buffer = np.frombuffer(segment.buf, np.uint8, count=nbytes)  # an export: the segment outlives the buffer
        with self._lock:
            self._owned[segment.name] = segment
            self._lent[segment.name] = (buffer.ctypes.data, nbytes)
        return buffer

    def give_back(self, buffer: np.ndarray) -> None:
        """Unlink the segment of ``buffer`` (from ``lend``); its memory goes once nothing refers to the buffer."""
        address = buffer.ctypes.data
        with self._lock:
            name = next((n for n, (start, size) in self._lent.items() if start <= address < start + size), None)
            if name is None:
                raise ValueError("give_back of a buffer this pool did not lend")
            del self._lent[name]
            segment = self._owned.pop(name)
        _unlink(segment)

    def lent_at(self, value: np.ndarray | columns.Rows) -> tuple[str, int] | None:
        """``(segment name, offset)`` where ``value`` lies in one piece inside a lent buffer, else None."""
        if not self._lent:
            return None
        block = _one_block(value)
        if block is None:
            return None
        address, nbytes = block.ctypes.data, block.nbytes
        with self._lock:
            for name, (start, size) in self._lent.items():
                if start <= address and address + nbytes <= start + size:
                    return name, address - start
        return None

    @contextmanager
    def lease(self, payload: dict[str, Any]) -> Iterator[dict[str, Any]]:
        """``payload`` as it goes on the wire: its large arrays written into a segment held until the block ends.

        The segment is reused only after a normal exit (the reply arrived); after an exception (a timeout, a lost
        connection) the server may still read it, so it is unlinked instead. Raises ``NoSharedMemory`` before
        anything is written when no segment can be had."""
        need = _shared_bytes(payload, self.lent_at)
        if not need and not self._lent:
            yield columns.joined(payload) if columns.KEY in payload else payload  # small columns: in the frame
            return
        segment = self._acquire(need) if need else None
        try:
            jobs: list[_Copy] = []
            wire = _place(payload, segment, [0], jobs, self.lent_at)
            _copy_all(jobs)
            yield wire
        except BaseException:
            if segment is not None:
                self._drop(segment)
            raise
        if segment is not None and segment.name in self._owned:  # unless the pool was closed meanwhile
            self._free.append(segment)

    def _acquire(self, need: int) -> SharedMemory:
        fitting = [s for s in self._free if s.size >= need]
        if fitting:
            segment = min(fitting, key=lambda s: s.size)
            self._free.remove(segment)
            return segment
        if self._free:  # every free segment is too small: replace the largest by one that fits
            self._drop(max(self._free, key=lambda s: s.size))
        segment = _create(need + need // 8)
        self._owned[segment.name] = segment
        return segment

    def _drop(self, segment: SharedMemory) -> None:
        if segment in self._free:
            self._free.remove(segment)
        if self._owned.pop(segment.name, None) is not None:  # not already unlinked by close()
            _unlink(segment)

    def close(self) -> None:
        """Unlink every segment, lent ones included (the pool can still be used afterwards; it creates new ones)."""
        self._free.clear()
        with self._lock:
            self._lent.clear()
        _unlink_all(self._owned)


def _invalid(message: str, ref: codec.SharedArray) -> ProtocolError:
    return ProtocolError(ErrorCode.INVALID_FRAME, message, {"field": "shared_memory", "segment": ref.segment})


class SegmentCache:
    """The segments one server connection reads from: each opened once, then kept (up to ``OPEN_PER_CONNECTION``)
    so that its pages stay mapped; all closed with the connection.

    ``refusal`` says why this connection may not use shared memory at all (a remote peer, or the server's
    ``shared_memory`` option off); every reference then gets that as its error.
    """

    def __init__(self, refusal: str | None = None) -> None:
        self.refusal = refusal
        self._open: OrderedDict[str, SharedMemory] = OrderedDict()

    def resolve(self, payload: dict[str, Any], borrow: bool = False) -> None:
        """Replace, in place, every reference in a decoded payload by a copy of its array that the server owns:
        every reference is checked before anything is copied. ``borrow``: by a read-only view of the client's
        segment instead, without a copy, for a model that keeps none of the arrays it is given
        (``Model.borrows_observations``): the client writes that segment again once the reply has reached it."""
        jobs: list[_Copy] = []
        try:
            self._collect(payload, jobs, borrow)
            _copy_all(jobs)
            for job in jobs:
                job[2].flags.writeable = False  # like a decoded array
        finally:  # only now: a request's own segments stay open until copied
            self._close_oldest()

    def _collect(self, value: Any, jobs: list[_Copy], borrow: bool) -> None:
        items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
        for key, item in items:
            if isinstance(item, codec.SharedArray):
                value[key] = self._target(item, jobs, borrow)
            else:
                self._collect(item, jobs, borrow)

    def _target(self, ref: codec.SharedArray, jobs: list[_Copy], borrow: bool) -> np.ndarray:
        """The array a checked reference will be copied into (added to ``jobs``), or with ``borrow`` its view."""
        if self.refusal is not None:
            raise _invalid(self.refusal, ref)
        segment = self._segment(ref)
        if ref.offset + ref.nbytes > segment.size:
            raise _invalid(f"shared-memory reference out of bounds: {ref.nbytes} bytes at offset {ref.offset} of "
                           f"segment {ref.segment!r}, which has {segment.size}", ref)
        if borrow:
            # Through a slice of the segment's memoryview, which the array holds as an export: the segment cannot be
            # closed under it (an array made on the memoryview directly holds none, and would read unmapped memory).
            lent = segment.buf[ref.offset:ref.offset + ref.nbytes]
            view = np.frombuffer(lent, ref.dtype).reshape(ref.shape)
            view.flags.writeable = False
            return view
        out = codec.recycled_buffer(ref.nbytes).view(ref.dtype).reshape(ref.shape)
        jobs.append((segment.buf, ref.offset, out, False))
        return out

    def _close_oldest(self) -> None:
        """Close the oldest segments beyond ``OPEN_PER_CONNECTION``. One whose arrays are still lent out (a request
        of this connection is in the model) is closed once they are let go of (``_LENT``); a later reference to it
        opens it again."""
        for name in list(self._open)[:max(0, len(self._open) - OPEN_PER_CONNECTION)]:
            if not _closed(self._open[name]):
                _LENT.append(self._open[name])
            del self._open[name]

    def _segment(self, ref: codec.SharedArray) -> SharedMemory:
        name = ref.segment
        if not _NAME.match(name):
            raise _invalid(f"shared-memory segment name {name!r} is refused: names are {PREFIX!r} followed by up to "
                           "60 letters, digits or underscores", ref)
        segment = self._open.get(name)
        if segment is not None:
            self._open.move_to_end(name)
            return segment
        try:
            segment = SharedMemory(name)
        except FileNotFoundError:
            raise _invalid(f"no shared-memory segment {name!r} on this host (client and server must share "
                           "/dev/shm)", ref) from None
        except (OSError, ValueError) as exc:
            raise _invalid(f"shared-memory segment {name!r} cannot be opened: {exc}", ref) from None
        if name not in _CREATED:
            resource_tracker.unregister(segment._name, "shared_memory")  # the client's to unlink, not our tracker's
        self._open[name] = segment
        return segment

    def close(self) -> None:
        """Close (never unlink) every segment this connection opened. A segment whose arrays a model kept although
        it borrows them (``Model.borrows_observations``) cannot be closed yet: it stays mapped, with a warning,
        until they are let go of (tried again at every later ``close``)."""
        while self._open:
            name, segment = self._open.popitem()
            if not _closed(segment):
                logger.warning("a model kept arrays it borrowed from shared-memory segment %s (it says it borrows "
                               "observations, so it must copy what it keeps): the segment stays mapped until they "
                               "are let go of, and its client may have written other images into it", name)
                _LENT.append(segment)
        _LENT[:] = [s for s in _LENT if not _closed(s)]


#: Segments whose close waits for arrays lent out of them (``SegmentCache.close``, ``_close_oldest``, and a client's
#: lent buffers given back while still referred to), no longer used for new ones; held here so that their
#: finalizer, which would fail the same way, does not run meanwhile.
_LENT: list[SharedMemory] = []


@atexit.register
def _leave_lent() -> None:
    """At exit, a segment still waiting for its arrays is left to the process's end, which unmaps it, rather than
    to its finalizer, which would print a ``BufferError`` it cannot do anything about."""
    for segment in _LENT:
        if not _closed(segment):
            segment.close = lambda: None  # type: ignore[method-assign]


def _closed(segment: SharedMemory) -> bool:
    """Close ``segment``; False while arrays lent out of it are alive (its mapping stays; its ``buf`` may be gone,
    so it must not lend again), True once closed."""
    try:
        segment.close()
    except BufferError:
        return False
    return True
