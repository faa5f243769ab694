"""How far a peer's frames depart from upstream XPolicyLab's wire format (``protocol.UPSTREAM_FORMAT``).

One rule set, two users. The client fails a request at once on a *fatal* departure of its reply (a field it
cannot use: ``actions`` that are not a numeric array, an ``error`` without a message), naming the field, rather
than waiting for a deadline. ``xpolicylab check`` lists every departure, fatal or not (an epoch-number
``sent_at``, a missing ``latency_ms``, arrays in openpi's spelling), so a third-party server learns everything
that an upstream client would trip over in one run.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import msgpack
import numpy as np

from xpolicylab.errors import ErrorCode
from xpolicylab.protocol import REPLY_TO, Frame, MessageType

#: Replies whose payload upstream clients read as ``{"ok": true, "result": ...}``.
ACK_REPLIES = frozenset({MessageType.PREPARE_CASE_ACK, MessageType.RESET_RESULT, MessageType.TRIAL_END_ACK})
_REQUIRED_IDS = ("message_id", "evaluation_id")
_ECHOED = ("message_id", "evaluation_id", "action_case_id", "trial_id", "repeat_index", "step")


@dataclass(frozen=True)
class Departure:
    """One way a frame departs from the format; ``fatal`` when a client cannot use the frame at all."""

    field: str
    message: str
    fatal: bool = False

    def __str__(self) -> str:
        return f"{self.field}: {self.message}"


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def envelope_departures(wire: dict[str, Any], request: Frame | None = None) -> list[Departure]:
    """Departures of a reply's envelope, and of its echo of ``request``'s identifiers."""
    out = []
    for key in _REQUIRED_IDS:
        if wire.get(key) is None:
            out.append(Departure(key, "missing; upstream clients drop a frame without it"))
        elif not isinstance(wire[key], str):
            out.append(Departure(key, f"must be a string, got {type(wire[key]).__name__}"))
    for key in ("action_case_id", "trial_id"):
        if wire.get(key) is not None and not isinstance(wire[key], str):
            out.append(Departure(key, f"must be a string or nil, got {type(wire[key]).__name__}"))
    if wire.get("repeat_index") is not None and not _is_int(wire["repeat_index"]):
        out.append(Departure("repeat_index", "must be an integer or nil"))
    if not _is_int(wire.get("step")):
        out.append(Departure("step", f"must be an integer, got {wire.get('step')!r}"))
    sent_at = wire.get("sent_at")
    if not isinstance(sent_at, str):
        out.append(Departure("sent_at", f"must be an ISO-8601 string, got {type(sent_at).__name__}"))
    else:
        try:
            datetime.fromisoformat(sent_at)
        except ValueError:
            out.append(Departure("sent_at", f"{sent_at!r} is not an ISO-8601 time"))
    if not isinstance(wire.get("payload", {}), dict):
        out.append(Departure("payload", "must be a map", fatal=True))
    if request is not None:
        sent = request.to_wire()
        out += [Departure(key, f"does not echo the request's {sent[key]!r} (got {wire.get(key)!r})",
                          fatal=key == "message_id")
                for key in _ECHOED if wire.get(key) != sent[key]]
        expected = REPLY_TO.get(request.message_type)
        if expected is not None and wire.get("message_type") not in (expected.value, MessageType.ERROR.value):
            out.append(Departure("message_type", f"a {request.message_type.value} is answered by "
                                 f"{expected.value} or error, got {wire.get('message_type')!r}", fatal=True))
    return out


def _actions_departures(actions: Any, batched: bool) -> list[Departure]:
    if actions is None:
        return [Departure("payload.actions", "missing", fatal=True)]
    try:
        array = np.asarray(actions, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        return [Departure("payload.actions", f"not a numeric array ({exc})", fatal=True)]
    want = 3 if batched else 2
    if array.ndim != want:
        shape = "[B, K, D]" if batched else "[K, D]"
        return [Departure("payload.actions", f"must be {shape}, got shape {list(array.shape)}", fatal=True)]
    if not isinstance(actions, np.ndarray):
        return [Departure("payload.actions", "sent as nested lists; upstream sends a msgpack-numpy array")]
    return []


def payload_departures(frame: Frame, batched: bool = False) -> list[Departure]:
    """Departures of a reply's payload, as upstream clients (and ours) read it."""
    kind, payload = frame.message_type, frame.payload
    out: list[Departure] = []
    if kind is MessageType.ERROR:
        try:
            ErrorCode(payload.get("code"))
        except ValueError:
            out.append(Departure("payload.code", f"{payload.get('code')!r} is not one of "
                                 f"{sorted(c.value for c in ErrorCode)}"))
        if not isinstance(payload.get("message"), str):
            out.append(Departure("payload.message", "must be a string", fatal=True))
        if not isinstance(payload.get("details", {}), dict):
            out.append(Departure("payload.details", "must be a map"))
        return out
    if "ok" in payload and not isinstance(payload["ok"], bool):
        out.append(Departure("payload.ok", f"must be true or false, got {payload['ok']!r}", fatal=True))
    if kind in ACK_REPLIES and payload.get("ok") is not True:
        out.append(Departure("payload.ok", "upstream acknowledges with ok: true", fatal=payload.get("ok") is False))
    if kind is MessageType.INFER_RESULT:
        out += _actions_departures(payload.get("actions"), batched)
        latency = payload.get("latency_ms")
        if latency is None:
            out.append(Departure("payload.latency_ms", "missing"))
        elif not isinstance(latency, (int, float)) or isinstance(latency, bool):
            out.append(Departure("payload.latency_ms", f"must be a number, got {latency!r}", fatal=True))
        if "action_mode" in payload and not isinstance(payload["action_mode"], str):
            out.append(Departure("payload.action_mode", "must be a string", fatal=True))
    if kind is MessageType.HELLO_ACK:
        for key in ("metadata", "capabilities"):
            if key in payload and not isinstance(payload[key], dict):
                out.append(Departure(f"payload.{key}", "must be a map", fatal=True))
    return out


def fatal_problem(frame: Frame, batched: bool = False) -> Departure | None:
    """The first departure that makes a reply unusable, if any."""
    return next((d for d in payload_departures(frame, batched) if d.fatal), None)


def _maps(obj: Any, path: str) -> Iterator[tuple[str, dict]]:
    if isinstance(obj, dict):
        yield path, obj
        for key, value in obj.items():
            name = key.decode(errors="replace") if isinstance(key, bytes) else str(key)
            yield from _maps(value, f"{path}.{name}")
    elif isinstance(obj, list):
        for i, value in enumerate(obj):
            yield from _maps(value, f"{path}[{i}]")


def array_departures(raw: bytes) -> list[Departure]:
    """Arrays not written as msgpack-numpy maps with bin keys (upstream's decoder would not turn them back)."""
    try:
        wire = msgpack.unpackb(raw, raw=False, strict_map_key=False)
    except Exception as exc:  # the checker reports undecodable frames elsewhere; nothing more to say here
        return [Departure("frame", f"not MessagePack: {exc}", fatal=True)]
    out = []
    for path, node in _maps(wire.get("payload") if isinstance(wire, dict) else None, "payload"):
        if b"__ndarray__" in node or "__ndarray__" in node:
            out.append(Departure(path, "array in openpi's spelling ({__ndarray__, data, dtype, shape}); "
                                 "upstream sends msgpack-numpy maps ({nd, type, kind, shape, data})"))
        elif "nd" in node and b"nd" not in node:
            out.append(Departure(path, "msgpack-numpy keys written as strings; upstream reads bin keys (b'nd')"))
    return out
