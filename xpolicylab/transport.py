"""Moving encoded messages over a ``websockets`` asyncio connection, for both server and client.

Large messages go out as WebSocket fragments built from the codec's zero-copy chunks (each large array in
its own fragment, at most ``FRAGMENT`` bytes), and come in through ``recv_streaming`` so no 180 MB buffer is
ever joined: every copy the library makes (masking, framing, socket buffers) stays array-sized, and the
receiver can decode each array as a view of its fragment. Fragmentation is plain RFC 6455, so peers that
read whole messages (openpi's client, XPolicyLab's server) see an ordinary binary message.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

from websockets.asyncio.connection import Connection

#: Largest WebSocket frame we write: a 1280x720 RGB image (2.8 MB) still travels in one fragment.
FRAGMENT = 4 << 20
#: Messages up to this size are sent as one frame (one join is cheaper than several frames).
SINGLE_FRAME = 1 << 20

#: Connection options shared by our server and client: no compression (images do not compress cheaply and
#: deflate would cap throughput at a few tens of MB/s).
CONNECTION_OPTIONS: dict[str, Any] = {"compression": None}


def fragments(chunks: Sequence[bytes | memoryview], size: int = FRAGMENT) -> Iterator[bytes | memoryview]:
    """One fragment per codec chunk (split only above ``size`` bytes), without copying any of them."""
    for chunk in chunks:
        view = memoryview(chunk).cast("B")
        for start in range(0, len(view), size):
            yield view[start:start + size]


async def send_chunks(ws: Connection, chunks: Sequence[bytes | memoryview]) -> int:
    """Send one binary message made of ``chunks``; returns its size in bytes."""
    total = sum(len(c) if isinstance(c, bytes) else c.nbytes for c in chunks)
    if total <= SINGLE_FRAME:
        await ws.send(b"".join(chunks))
    else:
        await ws.send(fragments(chunks))
    return total


async def recv_message(ws: Connection) -> tuple[bool, list[bytes | str]]:
    """Receive one message as ``(is_text, fragments)`` without joining its fragments."""
    parts: list[bytes | str] = []
    async for part in ws.recv_streaming():
        parts.append(part)
    return bool(parts) and isinstance(parts[0], str), parts
