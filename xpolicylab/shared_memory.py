"""Large arrays through shared memory when client and server are on the same machine.

Why. Over loopback TCP an observation batch is copied by the client into the socket, by the kernel, and out of
the socket by the server: on the 2-core CI machine `xpolicylab bench batch=512 width=224 height=224` moved
423 MB/s, 0.54 s per request of 512 environments with three cameras; a policy asked every 8th control step then
caps a run at about 7,500 interactions/s, and 640x480 images at a fifth of that. Through shared memory the client
copies each image once into a segment and the server once out of it.

How (the native dialect only; an extension that peers without it never see):
- The server's `hello_ack` lists `capabilities.shared_memory: true` when the peer's address is a loopback one.
- The client then keeps one segment (`multiprocessing.shared_memory`, named `xpl_` + 32 hex digits, its room in
  /dev/shm reserved with `posix_fallocate`), sized to the largest request so far. A request whose large arrays
  (`codec.LARGE_BIN` and up) fit names the segment in its payload (`shm`) and carries, instead of each large
  array's bytes, its place in the segment: the array map holds `shm: [offset, nbytes]` where `data` would be.
- The server opens the segment by that name (same-host peers only, names of that form only) and reads each array
  with `preadv` into its own buffer before the model sees them, so a model may keep what it is given. It never
  maps the segment: a client that shrinks it gets a short read and an error reply, where a mapping would kill the
  server (SIGBUS). One such request per connection at a time, and no more than the server's `max_frame_mb`.
- The client sends one such request at a time and writes the segment again only after the reply; after a timeout
  (the server may still be reading) the next request gets a new segment.
- Anything the client cannot do falls back to sending the bytes, as before: too little room in /dev/shm, a
  server that cannot open the segment (both on loopback but not one /dev/shm: a container, a tunnel, another
  user), a server without the capability, a remote server.
"""

from __future__ import annotations

import asyncio
import ipaddress
import os
import re
import secrets
import shutil
from collections.abc import Callable, Iterator
from multiprocessing.shared_memory import SharedMemory
from typing import Any
from urllib.parse import urlsplit

import numpy as np

from xpolicylab.codec import LARGE_BIN, ShmRef, recycled_buffer
from xpolicylab.errors import ErrorCode, ProtocolError

NAME = re.compile(r"^xpl_[0-9a-f]{32}$")
"""The only segment names a server attaches to: ours, never another program's."""
UNREADABLE = "unreadable"
"""The `reason` of the error a server sends when it cannot open the segment named (it sees another /dev/shm): the
client then sends the bytes in the message instead."""
SHM_DIR = "/dev/shm"
"""Where Linux keeps POSIX shared memory (a tmpfs; its size is the room for segments)."""
ALIGN = 64
"""Arrays start at multiples of this many bytes in the segment (cache lines; numpy views stay aligned)."""


def is_loopback_host(host: str | None) -> bool:
    """Whether `host` (a name or an address, as in a URL or a socket's peer) is this machine's loopback."""
    if not host:
        return False
    if host.lower() == "localhost":
        return True
    try:
        address = ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        return False
    mapped = getattr(address, "ipv4_mapped", None)  # ::ffff:127.0.0.1, a server bound to :: sees IPv4 peers so
    return (mapped or address).is_loopback


def is_loopback_url(url: str) -> bool:
    return is_loopback_host(urlsplit(url).hostname)


def shared_memory_free() -> int:
    """Bytes free for new segments (0 where POSIX shared memory is not the `SHM_DIR` file system)."""
    try:
        return shutil.disk_usage(SHM_DIR).free
    except OSError:
        return 0


def _aligned(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def shared_bytes(obj: Any) -> int:
    """Room a request needs in the segment: its large arrays (those sent as their own chunk), each aligned."""
    if isinstance(obj, np.ndarray):
        return _aligned(obj.nbytes) if obj.nbytes >= LARGE_BIN else 0
    if isinstance(obj, dict):
        return sum(shared_bytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(shared_bytes(v) for v in obj)
    return 0


class OutgoingSegment:
    """The client's segment: grown to the largest request, written anew for each (see the module docstring)."""

    def __init__(self) -> None:
        self._shm: SharedMemory | None = None
        self._offset = 0

    @property
    def name(self) -> str:
        assert self._shm is not None
        return self._shm.name

    def ready_for(self, nbytes: int) -> None:
        """A segment of at least `nbytes` (a new, larger one if needed: the old is removed), empty. Raises
        OSError when the machine has no room for it."""
        if self._shm is None or self._shm.size < nbytes:
            self.close()
            size = max(nbytes, 1 << 20)
            free = shared_memory_free()
            if free < size:  # a segment is created sparse: writing past the room left would kill us (SIGBUS)
                raise OSError(f"{SHM_DIR} has {free} bytes free, a request needs {size} (containers often give it "
                              "64 MB: docker run --shm-size)")
            shm = SharedMemory(f"xpl_{secrets.token_hex(16)}", create=True, size=size)
            try:  # reserve its room now: another process may take what the check above saw free
                fd = os.open(os.path.join(SHM_DIR, shm.name), os.O_RDWR | os.O_NOFOLLOW)
                try:
                    os.posix_fallocate(fd, 0, size)
                finally:
                    os.close(fd)
            except OSError:
                shm.close()
                shm.unlink()
                raise
            self._shm = shm
        self.rewind()

    def rewind(self) -> None:
        """Write the next request's arrays from the segment's start (its reply has come, or it is sent again)."""
        self._offset = 0

    def put(self, arr: np.ndarray) -> tuple[int, int]:
        """Copy a C-contiguous array into the segment; its (offset, nbytes)."""
        assert self._shm is not None
        start, n = self._offset, arr.nbytes
        if start + n > self._shm.size:
            raise ValueError(f"the request needs more than the {self._shm.size} bytes its segment was sized for")
        np.frombuffer(self._shm.buf, np.uint8, n, start)[:] = np.frombuffer(memoryview(arr).cast("B"), np.uint8)
        self._offset = _aligned(start + n)
        return start, n

    def close(self) -> None:
        """Remove the segment (the server's mapping, if any, stays valid until it closes it)."""
        if self._shm is not None:
            self._shm.close()
            try:
                self._shm.unlink()
            except FileNotFoundError:
                pass
            self._shm = None


class IncomingSegments:
    """A server connection's view of its client's segment; `allowed` only for a same-host peer.

    The segment is read with `preadv` from a file descriptor, never mapped: a client that shrinks its segment
    then gets a short read (an error reply), where reading a mapping would kill the server (SIGBUS). Requests
    through the segment are served one at a time per connection (`one_at_a_time`): a few bytes of message may
    name hundreds of MB of arrays, and only one such copy is held at once."""

    def __init__(self, allowed: bool, max_bytes: int) -> None:
        """`max_bytes`: the most one request may bring through the segment, the server's limit on a message."""
        self.allowed = allowed
        self.max_bytes = max_bytes
        self.one_at_a_time = asyncio.Lock()
        self._fd: int | None = None
        self._name: str | None = None

    def _open(self, name: Any) -> int:
        if not self.allowed:
            raise ProtocolError(ErrorCode.INVALID_FRAME, "shared memory is offered to clients on this machine only",
                                {"field": "shm"})
        if not isinstance(name, str) or not NAME.match(name):
            raise ProtocolError(ErrorCode.INVALID_FRAME, f"'shm' must name an xpl_ segment, got {name!r}",
                                {"field": "shm"})
        if self._fd is None or self._name != name:
            self.close()
            try:
                self._fd = os.open(os.path.join(SHM_DIR, name), os.O_RDONLY | os.O_NOFOLLOW)
            except OSError as exc:
                raise ProtocolError(ErrorCode.INVALID_FRAME, f"cannot open shared memory {name}: {exc}",
                                    {"field": "shm", "reason": UNREADABLE}) from None
            self._name = name
        return self._fd

    def resolve(self, payload: dict[str, Any]) -> dict[str, Any]:
        """The payload with every array placed in the segment copied out of it (a payload without `shm` must
        hold no such places)."""
        refs = list(_refs(payload))
        if "shm" not in payload:
            if refs:
                raise ProtocolError(ErrorCode.INVALID_FRAME, "an array is placed in shared memory but the request "
                                    "names no segment ('shm')", {"field": "shm"})
            return payload
        payload = dict(payload)
        fd = self._open(payload.pop("shm"))
        total = sum(_aligned(r.nbytes) for r in refs)
        if total > self.max_bytes:
            raise ProtocolError(ErrorCode.INVALID_FRAME, f"the request places {total} bytes in shared memory, more "
                                f"than this server accepts in a message ({self.max_bytes})", {"field": "shm"})
        return _replace(payload, _Copies(fd, total).take)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = self._name = None


def _refs(obj: Any) -> Iterator[ShmRef]:
    """Every array place in a decoded payload."""
    if isinstance(obj, ShmRef):
        yield obj
    elif isinstance(obj, dict):
        for value in obj.values():
            yield from _refs(value)
    elif isinstance(obj, list):
        for value in obj:
            yield from _refs(value)


class _Copies:
    """The arrays of one request read out of the segment into one recycled buffer, as read-only views of it (like
    the arrays the codec decodes from a message)."""

    def __init__(self, fd: int, total: int) -> None:
        self.fd = fd
        self.target = recycled_buffer(total) if total else np.empty(0, np.uint8)
        self.filled = 0

    def take(self, ref: ShmRef) -> np.ndarray:
        start, n = self.filled, ref.nbytes
        view, got = memoryview(self.target[start:start + n]), 0
        while got < n:  # a read returns at most about 2 GB
            step = os.preadv(self.fd, [view[got:]], ref.offset + got)
            if step <= 0:
                break
            got += step
        if got != n:
            raise ProtocolError(ErrorCode.INVALID_FRAME, f"an array at bytes {ref.offset}-{ref.offset + n} lies "
                                f"outside the segment ({got} of its {n} bytes there)", {"field": "shm"})
        self.filled = _aligned(start + n)
        out = self.target[start:start + n].view(ref.dtype).reshape(ref.shape)
        out.flags.writeable = False
        return out


def _replace(obj: Any, place: Callable[[ShmRef], np.ndarray]) -> Any:
    if isinstance(obj, ShmRef):
        return place(obj)
    if isinstance(obj, dict):
        return {k: _replace(v, place) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_replace(v, place) for v in obj]
    return obj
