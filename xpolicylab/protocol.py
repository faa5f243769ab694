"""The native dialect: the public XPolicyLab WebSocket protocol, plus a compatible batched ``infer``.

The format follows upstream XPolicyLab's ``client_server/ws`` package (``UPSTREAM_FORMAT``). Every frame is one
binary MessagePack map
``{message_type, message_id, evaluation_id, action_case_id, trial_id, repeat_index, step, sent_at, payload}``:
``message_id`` and ``evaluation_id`` are required strings, ``step`` an integer, ``sent_at`` an ISO-8601 UTC string
(a number of seconds since the epoch is still read, as older clients sent one), numpy arrays are msgpack-numpy
maps. A reply copies the request's identifiers (``message_id`` included, which is how a client matches replies
to requests) and ``step``. Replies to ``prepare_case``/``reset``/``trial_end`` carry ``{"ok": true, "result": ...}``
(``result`` only when the hook returned something); ``infer_result`` carries ``actions`` and ``latency_ms``;
``error`` replaces the paired reply and carries ``{code, message, details}``. An error answering a frame that
could not be read carries whatever ids could be read from its raw map, else ``PLACEHOLDER_ID``, so that every
error frame decodes in every client.

Extension (advertised in ``hello_ack`` as ``capabilities.batch_infer``): an ``infer`` payload
``{observations: [obs, ...], env_ids: [id, ...]}`` is answered by one ``get_action_batch`` call with
``{actions: float32[B, K, D], env_ids, action_mode, latency_ms}``. A single ``infer`` stays
``{observation}`` -> ``{actions: float32[K, D], action_mode, latency_ms}``. Where ``capabilities.columnar_batch``
is advertised too, the batch may come as ``{columns: {...}, env_ids}`` instead, each array stacked over the batch
(``xpolicylab.columns``), and is answered the same way.
"""

from __future__ import annotations

import enum
import math
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any

from xpolicylab import codec, columns
from xpolicylab.errors import ErrorCode, ProtocolError

PROTOCOL_VERSION = "1.0"
SERVER_NAME = "xpolicylab_policy_server"
#: The upstream release whose wire format this module follows (README: "XPolicyLab compatibility").
UPSTREAM_FORMAT = "XPolicyLab client_server/ws at 7198143e (main, 2026-07-22)"
#: Stands in for an id that could not be read from a malformed frame (upstream clients need a string there).
PLACEHOLDER_ID = ""


class MessageType(str, enum.Enum):
    """All message types of the protocol."""

    HELLO = "hello"
    HELLO_ACK = "hello_ack"
    PREPARE_CASE = "prepare_case"
    PREPARE_CASE_ACK = "prepare_case_ack"
    RESET = "reset"
    RESET_RESULT = "reset_result"
    INFER = "infer"
    INFER_RESULT = "infer_result"
    TRIAL_END = "trial_end"
    TRIAL_END_ACK = "trial_end_ack"
    HEARTBEAT = "heartbeat"
    HEARTBEAT_ACK = "heartbeat_ack"
    CLOSE = "close"
    ERROR = "error"


#: Request type -> reply type. ``close`` has no reply.
REPLY_TO: dict[MessageType, MessageType] = {
    MessageType.HELLO: MessageType.HELLO_ACK,
    MessageType.PREPARE_CASE: MessageType.PREPARE_CASE_ACK,
    MessageType.RESET: MessageType.RESET_RESULT,
    MessageType.INFER: MessageType.INFER_RESULT,
    MessageType.TRIAL_END: MessageType.TRIAL_END_ACK,
    MessageType.HEARTBEAT: MessageType.HEARTBEAT_ACK,
}
REQUESTS = frozenset(REPLY_TO) | {MessageType.CLOSE}

_ID_FIELDS = ("evaluation_id", "action_case_id", "trial_id")


def utc_now_iso() -> str:
    """The current time as upstream writes ``sent_at``: ISO-8601 with the UTC offset."""
    return datetime.now(timezone.utc).isoformat()


def _iso_from_epoch(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, timezone.utc).isoformat()


@dataclass
class Frame:
    """One protocol frame."""

    message_type: MessageType
    payload: dict[str, Any] = field(default_factory=dict)
    message_id: str = field(default_factory=lambda: uuid.uuid4().hex)
    evaluation_id: str | None = None
    action_case_id: str | None = None
    trial_id: str | None = None
    repeat_index: int | None = None
    step: int = 0
    sent_at: str = field(default_factory=utc_now_iso)

    def to_wire(self) -> dict[str, Any]:
        """The frame as the map that goes on the wire (the two required ids never ``nil``)."""
        return {
            "message_type": self.message_type.value,
            "message_id": self.message_id if self.message_id is not None else PLACEHOLDER_ID,
            "evaluation_id": self.evaluation_id if self.evaluation_id is not None else PLACEHOLDER_ID,
            "action_case_id": self.action_case_id,
            "trial_id": self.trial_id,
            "repeat_index": self.repeat_index,
            "step": self.step,
            "sent_at": self.sent_at,
            "payload": self.payload,
        }

    def reply(self, message_type: MessageType, payload: dict[str, Any] | None = None) -> Frame:
        """A reply that keeps this request's identifiers and step."""
        return Frame(message_type, payload or {}, self.message_id, self.evaluation_id, self.action_case_id,
                     self.trial_id, self.repeat_index, self.step)

    def error(self, exc: ProtocolError) -> Frame:
        """The ``error`` frame answering this request."""
        return self.reply(MessageType.ERROR, exc.to_payload())


def encode_frame(frame: Frame) -> list[bytes | memoryview]:
    """Encode a frame as zero-copy chunks (see ``codec.encode_chunks``)."""
    return codec.encode_chunks(frame.to_wire(), codec.Dialect.XPOLICYLAB)


def is_batch(payload: dict[str, Any]) -> bool:
    """Whether an ``infer`` payload asks for a batch (its reply's actions are ``[B, K, D]``), as a list or as
    columns."""
    return "observations" in payload or columns.KEY in payload


def _optional(wire: dict, key: str, kinds: tuple[type, ...]) -> Any:
    value = wire.get(key)
    if value is not None and (not isinstance(value, kinds) or isinstance(value, bool)):
        raise ProtocolError(ErrorCode.INVALID_FRAME, f"field {key!r} must be {' or '.join(k.__name__ for k in kinds)}",
                            {"field": key})
    return value


def parse_frame(wire: Any) -> Frame:
    """Validate a decoded map as a frame. Unknown types raise ``unknown_message_type``, the rest ``invalid_frame``."""
    if not isinstance(wire, dict):
        raise ProtocolError(ErrorCode.INVALID_FRAME, f"a frame must be a map, got {type(wire).__name__}")
    kind = wire.get("message_type")
    if not isinstance(kind, str):
        raise ProtocolError(ErrorCode.INVALID_FRAME, "frame has no string 'message_type'", {"field": "message_type"})
    try:
        message_type = MessageType(kind)
    except ValueError:
        raise ProtocolError(ErrorCode.UNKNOWN_MESSAGE_TYPE, f"unknown message type {kind!r}",
                            {"message_type": kind, "known": sorted(t.value for t in MessageType)}) from None
    message_id = _optional(wire, "message_id", (str, int))
    payload = wire.get("payload", {})
    if payload is None:
        payload = {}
    if not isinstance(payload, dict):
        raise ProtocolError(ErrorCode.INVALID_FRAME, "field 'payload' must be a map", {"field": "payload"})
    ids = {key: _optional(wire, key, (str, int)) for key in _ID_FIELDS}
    step = _optional(wire, "step", (int,))
    return Frame(
        message_type, payload, message_id if message_id is not None else PLACEHOLDER_ID,
        ids["evaluation_id"], ids["action_case_id"], ids["trial_id"],
        _optional(wire, "repeat_index", (int,)), step or 0, _sent_at(wire),
    )


def _sent_at(wire: dict) -> str:
    """``sent_at`` as an ISO string: upstream writes one; older clients wrote seconds since the epoch."""
    value = _optional(wire, "sent_at", (str, int, float))
    if value is None:
        return ""
    if isinstance(value, str):
        try:
            datetime.fromisoformat(value)
        except ValueError:
            raise ProtocolError(ErrorCode.INVALID_FRAME, f"field 'sent_at' must be an ISO-8601 time, got {value!r}",
                                {"field": "sent_at"}) from None
        return value
    if not math.isfinite(value) or not 0 <= value < 1e11:
        raise ProtocolError(ErrorCode.INVALID_FRAME, f"field 'sent_at' is not a time: {value!r}", {"field": "sent_at"})
    return _iso_from_epoch(float(value))


def readable_ids(wire: Any) -> tuple[str | int, str | int]:
    """``(message_id, evaluation_id)`` of a raw map that failed validation, placeholders where unreadable.

    An error frame answering a malformed request carries them, so the sender can match the error to its request.
    """
    if not isinstance(wire, dict):
        return PLACEHOLDER_ID, PLACEHOLDER_ID

    def read(key: str) -> str | int:
        value = wire.get(key)
        ok = isinstance(value, (str, int)) and not isinstance(value, bool)
        return value if ok else PLACEHOLDER_ID

    return read("message_id"), read("evaluation_id")


def error_for_unreadable(wire: Any, exc: ProtocolError) -> Frame:
    """The ``error`` frame answering a message that is not a valid frame (``wire`` is its decoded map, if any)."""
    message_id, evaluation_id = readable_ids(wire)
    return Frame(MessageType.ERROR, exc.to_payload(), message_id, evaluation_id)


def decode_frame(fragments: Sequence[bytes | bytearray | memoryview] | bytes) -> Frame:
    """Decode and validate one binary message as a frame."""
    return parse_frame(codec.decode(fragments))


def decode_frame_or_error(fragments: Sequence[bytes | bytearray | memoryview] | bytes,
                          shared_refs: bool = False) -> tuple[Frame | None, Frame | None]:
    """``(frame, None)``, or ``(None, error frame)`` when the message is not a valid frame.

    The error frame carries the ids that could be read from the raw map (see ``error_for_unreadable``).
    ``shared_refs``: shared-memory references stay in the payload as ``codec.SharedArray``s (see ``codec.decode``).
    """
    try:
        wire = codec.decode(fragments, shared_refs)
    except ProtocolError as exc:
        return None, error_for_unreadable(None, exc)
    try:
        return parse_frame(wire), None
    except ProtocolError as exc:
        return None, error_for_unreadable(wire, exc)
