"""Error codes of the XPolicyLab protocol and the exception that carries them.

One exception type crosses every layer (codec, envelope validation, server dispatch, client) so that the
code a peer sees on the wire is decided exactly where the fault is detected.
"""

from __future__ import annotations

import enum
from typing import Any


class ErrorCode(str, enum.Enum):
    """The `code` values of an `error` frame, as in the public XPolicyLab protocol."""

    INVALID_FRAME = "invalid_frame"
    UNKNOWN_MESSAGE_TYPE = "unknown_message_type"
    TIMEOUT = "timeout"
    INFER_FAILED = "infer_failed"
    RESET_FAILED = "reset_failed"
    INTERNAL = "internal"


class ProtocolError(Exception):
    """A protocol-level failure with the code, message and details that go into an `error` frame."""

    def __init__(self, code: ErrorCode, message: str, details: dict[str, Any] | None = None) -> None:
        super().__init__(f"{code.value}: {message}")
        self.code = code
        self.message = message
        self.details = dict(details or {})

    def to_payload(self) -> dict[str, Any]:
        """The `error` frame payload `{code, message, details}`."""
        return {"code": self.code.value, "message": self.message, "details": self.details}
