"""Upstream XPolicyLab's wire format, both ways: its frames through our server, its replies through our client.

Upstream's facts (its ``client_server/ws`` package: ``protocol/schemas.py``, ``codec.py``, ``model_server.py``)
are written here as data, never imported: the wire map has ``message_type, message_id, evaluation_id,
action_case_id, trial_id, repeat_index, step, sent_at, payload``; ``message_id`` and ``evaluation_id`` are
required strings; ``sent_at`` is an ISO-8601 UTC string; arrays are msgpack-numpy maps (the ``msgpack_numpy``
package encodes them here, as upstream does); acks carry ``{"ok": true, "result": ...}``; ``infer_result``
carries ``actions`` and ``latency_ms``; errors carry ``code``, ``message``, ``details``; upstream's server sends
no metadata and answers only single-observation ``infer``.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import datetime

import msgpack
import msgpack_numpy
import numpy as np
import pytest
from websockets.asyncio.server import serve
from websockets.sync.client import connect

from xpolicylab.checker import CheckConfig, run_check
from xpolicylab.client import PolicyClient
from xpolicylab.errors import ErrorCode, ProtocolError

from conftest import free_port, serving, small_obs

ISO = "2026-11-25T00:16:02.910061+00:00"
UPSTREAM_FIELDS = ("message_type", "message_id", "evaluation_id", "action_case_id", "trial_id", "repeat_index",
                   "step", "sent_at", "payload")


def upstream_frame(message_type: str, payload: dict, message_id: str = "req-1", **fields) -> dict:
    """A request exactly as upstream's client writes it."""
    wire = {"message_type": message_type, "message_id": message_id, "evaluation_id": "eval-1",
            "action_case_id": "case-1", "trial_id": "trial-1", "repeat_index": 0, "step": 3, "sent_at": ISO,
            "payload": payload}
    wire.update(fields)
    return wire


def pack(wire: dict) -> bytes:
    """Upstream's encoder: msgpack with msgpack-numpy arrays."""
    return msgpack.packb(wire, default=msgpack_numpy.encode, use_bin_type=True)


def unpack(data: bytes) -> dict:
    """Upstream's decoder."""
    return msgpack.unpackb(data, raw=False, object_hook=msgpack_numpy.decode)


def upstream_reads(reply: dict) -> None:
    """What upstream's ``Frame.from_wire_dict`` (pydantic, ``extra=forbid``) demands of every frame it receives."""
    assert set(reply) == set(UPSTREAM_FIELDS)
    assert isinstance(reply["message_id"], str) and isinstance(reply["evaluation_id"], str)
    assert all(reply[k] is None or isinstance(reply[k], str) for k in ("action_case_id", "trial_id"))
    assert isinstance(reply["step"], int) and isinstance(reply["payload"], dict)
    datetime.fromisoformat(reply["sent_at"])


def _upstream_obs() -> dict:
    rng = np.random.default_rng(0)
    return {"instruction": "stack the blocks",
            "images": {cam: rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
                       for cam in ("head", "left_wrist", "right_wrist")},
            "state": {"joint_pos": np.zeros(14, np.float32), "joint_vel": np.zeros(14, np.float32)}}


def test_upstream_request_sequence_through_our_server():
    with serving() as srv, connect(srv.url, compression=None, max_size=None) as ws:
        def ask(message_type: str, payload: dict, message_id: str) -> dict:
            ws.send(pack(upstream_frame(message_type, payload, message_id)))
            reply = unpack(ws.recv(timeout=30))
            upstream_reads(reply)
            assert reply["message_id"] == message_id and reply["evaluation_id"] == "eval-1"
            assert (reply["action_case_id"], reply["trial_id"], reply["repeat_index"], reply["step"]) == \
                ("case-1", "trial-1", 0, 3)
            return reply

        assert ask("hello", {}, "h")["message_type"] == "hello_ack"
        for request, answer, body in (("prepare_case", "prepare_case_ack", {"action_case_id": "case-1", "task": "x"}),
                                      ("reset", "reset_result", {"trial_id": "trial-1"})):
            reply = ask(request, body, request)
            assert reply["message_type"] == answer and reply["payload"]["ok"] is True
            assert reply["payload"].get("result") is None  # upstream's client reads payload["result"]
        reply = ask("infer", {"observation": _upstream_obs()}, "i")
        assert reply["message_type"] == "infer_result"
        actions = reply["payload"]["actions"]
        assert isinstance(actions, np.ndarray) and actions.dtype == np.float32 and actions.shape == (4, 14)
        assert reply["payload"]["latency_ms"] >= 0
        reply = ask("trial_end", {"trial_id": "trial-1", "success": False}, "t")
        assert reply["message_type"] == "trial_end_ack" and reply["payload"]["ok"] is True


def test_epoch_sent_at_from_older_clients_is_still_read():
    with serving() as srv, connect(srv.url, compression=None, max_size=None) as ws:
        ws.send(pack(upstream_frame("heartbeat", {}, sent_at=1764030962.5)))
        assert unpack(ws.recv(timeout=30))["message_type"] == "heartbeat_ack"


@pytest.mark.parametrize("wire, message_id, evaluation_id", [
    (pack(upstream_frame("infer", {"observation": {}}, sent_at={"when": "now"})), "req-1", "eval-1"),
    (pack(upstream_frame("infer", {"observation": {}}, sent_at="yesterday")), "req-1", "eval-1"),
    (pack(upstream_frame("teleport", {})), "req-1", "eval-1"),
    (pack(upstream_frame("infer", {}, step="three")), "req-1", "eval-1"),
    (pack(upstream_frame("infer", {"observation": {}}, message_id=[1])), "", "eval-1"),
    (pack({"message_type": "infer", "payload": []}), "", ""),
    (b"\xc1", "", ""),
])
def test_every_error_frame_decodes_in_an_upstream_client(wire, message_id, evaluation_id):
    """The error carries the ids readable from the raw map (else placeholders), and the connection stays up."""
    with serving() as srv, connect(srv.url, compression=None, max_size=None) as ws:
        ws.send(wire)
        reply = unpack(ws.recv(timeout=30))
        upstream_reads(reply)
        assert reply["message_type"] == "error"
        assert (reply["message_id"], reply["evaluation_id"]) == (message_id, evaluation_id)
        assert set(reply["payload"]) == {"code", "message", "details"} and reply["payload"]["message"]
        ws.send(pack(upstream_frame("heartbeat", {}, "after")))
        assert unpack(ws.recv(timeout=30))["message_id"] == "after"


# ------------------------------------------------------------------------------------------------- our client
def _ack(payload: dict | None = None) -> dict:
    return {"ok": True, **(payload or {})}


#: Upstream's server's reply to each request type (its ``model_server.py``), as data.
UPSTREAM_REPLIES: dict[str, tuple[str, Callable[[dict], dict]]] = {
    "hello": ("hello_ack", lambda request: {"ok": True, "server": "demo_policy_server"}),
    "prepare_case": ("prepare_case_ack", lambda request: _ack()),
    "reset": ("reset_result", lambda request: _ack()),
    "infer": ("infer_result", lambda request: {"actions": np.zeros((10, 14), np.float32), "latency_ms": 0.4}),
    "trial_end": ("trial_end_ack", lambda request: _ack({"result": {"logged": True}})),
    "heartbeat": ("heartbeat_ack", lambda request: {"ok": True}),
}


@contextmanager
def upstream_style_server(tamper: Callable[[str, dict], dict] = lambda kind, reply: reply) -> Iterator[dict]:
    """A server that answers as upstream's does; ``tamper(request_type, reply)`` may break a reply."""
    port = free_port()
    seen: dict = {"requests": [], "url": f"ws://127.0.0.1:{port}"}
    loop = asyncio.new_event_loop()
    ready = threading.Event()

    async def handle(ws) -> None:
        async for raw in ws:
            request = unpack(raw)
            kind = request["message_type"]
            seen["requests"].append(request)
            if kind == "close":
                return
            answer, build = UPSTREAM_REPLIES[kind]
            reply = {k: request.get(k) for k in UPSTREAM_FIELDS}
            reply.update(message_type=answer, sent_at=ISO, payload=build(request))
            await ws.send(pack(tamper(kind, reply)))

    async def main() -> None:
        async with serve(handle, "127.0.0.1", port, max_size=None):
            ready.set()
            await stop
    stop = loop.create_future()
    thread = threading.Thread(target=loop.run_until_complete, args=(main(),), daemon=True)
    thread.start()
    ready.wait(10)
    try:
        yield seen
    finally:
        loop.call_soon_threadsafe(stop.set_result, None)
        thread.join(10)


def test_our_client_against_an_upstream_style_server():
    with upstream_style_server() as seen, PolicyClient(seen["url"], evaluation_id="eval-7") as client:
        assert client.metadata.name == "demo_policy_server" and not client.batches
        assert client.prepare_case({"task": "stack_blocks"}, "case-1")["ok"] is True
        assert client.reset("trial-1", repeat_index=0)["ok"] is True
        assert client.infer(small_obs()).shape == (10, 14)
        assert client.infer_batch([small_obs(), small_obs(1)], [0, 1]).shape == (2, 10, 14)
        assert client.trial_end({"success": True})["result"] == {"logged": True}
    requests = seen["requests"]
    for request in requests:
        assert isinstance(request["sent_at"], str) and datetime.fromisoformat(request["sent_at"])
        assert request["evaluation_id"] == "eval-7" and isinstance(request["message_id"], str)
    infers = [r for r in requests if r["message_type"] == "infer"]
    assert len(infers) == 3 and all("observation" in r["payload"] for r in infers)  # no batched infer sent


def _set(path: str, value) -> Callable[[str, dict], dict]:
    """Break one field of every ``infer_result`` (``payload.x`` or a top-level key)."""
    def tamper(kind: str, reply: dict) -> dict:
        if kind == "infer":
            target = reply["payload"] if path.startswith("payload.") else reply
            target[path.removeprefix("payload.")] = value
        return reply
    return tamper


@pytest.mark.parametrize("tamper, field", [
    (_set("payload.actions", "garbage"), "actions"),
    (_set("payload.actions", [1.0, 2.0]), "actions"),
    (_set("payload.latency_ms", "fast"), "latency_ms"),
    (_set("sent_at", {"when": "now"}), "sent_at"),
    (_set("step", "three"), "step"),
    (_set("payload", [1, 2]), "payload"),
    (_set("message_id", [1]), "message_id"),
])
def test_a_malformed_reply_fails_the_request_at_once_naming_the_field(tamper, field):
    """Never a receive deadline: the deadline is 60 s, the error is an invalid frame that names the field."""
    with upstream_style_server(tamper) as seen, PolicyClient(seen["url"], recv_timeout_s=60) as client:
        with pytest.raises(ProtocolError) as info:
            client.infer(small_obs())
        assert info.value.code is ErrorCode.INVALID_FRAME and field in info.value.message
        assert client.heartbeat() >= 0  # the connection is still usable


def test_checker_lists_every_departure_of_a_third_party_server():
    def sloppy(kind: str, reply: dict) -> dict:
        reply["sent_at"] = 1764030962.5
        reply["evaluation_id"] = None
        if kind == "infer":
            del reply["payload"]["latency_ms"]
        return reply

    with upstream_style_server(sloppy) as seen:
        report = run_check(CheckConfig(url=seen["url"], n=2, batch=2, width=64, height=48, timeout_s=10))
    wire = next(item for item in report.items if item.name == "wire format")
    assert not wire.ok
    for words in ("sent_at: must be an ISO-8601 string", "evaluation_id: missing", "latency_ms: missing"):
        assert words in wire.detail, wire.detail


def test_checker_finds_no_departure_in_upstream_or_our_server():
    with upstream_style_server() as seen:
        report = run_check(CheckConfig(url=seen["url"], n=2, batch=2, width=64, height=48, timeout_s=10))
    assert report.passed, report.format()
    with serving() as srv:
        report = run_check(CheckConfig(url=srv.url, n=2, batch=2, width=64, height=48, timeout_s=10))
    assert report.passed and any(item.name == "wire format" for item in report.items), report.format()
