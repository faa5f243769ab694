"""The native server: the request sequence, batching, concurrency, limits, auth, and 20+ malformed frames."""

from __future__ import annotations

import asyncio
import threading
import time
import urllib.request

import msgpack
import msgpack_numpy
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from xpolicylab import codec
from xpolicylab.client import AsyncPolicyClient, AuthError, PolicyClient, batch_spans, observation_bytes
from xpolicylab.errors import ErrorCode, ProtocolError
from xpolicylab.model import Model, PolicyMetadata
from xpolicylab.policies import ZeroPolicy
from xpolicylab.protocol import Frame, MessageType, decode_frame, encode_frame

from conftest import serving, small_obs


def _wire(frame: Frame) -> bytes:
    return b"".join(encode_frame(frame))


def _infer_frame(payload=None) -> dict:
    return Frame(MessageType.INFER, payload if payload is not None else {"observation": small_obs()}).to_wire()


class Recorder(ZeroPolicy):
    """Zero policy that records every hook and batched call, to check what the server invoked."""

    def __init__(self, config=None):
        super().__init__({"chunk_size": 2, **(config or {})})
        self.calls: list[str] = []

    def prepare_case(self, meta):
        self.calls.append(f"prepare_case:{meta.get('task')}")

    def on_trial_end(self, result):
        self.calls.append(f"trial_end:{result.get('success')}")

    def reset(self):
        self.calls.append("reset")
        super().reset()

    def get_action_batch(self, env_ids):
        self.calls.append(f"batch:{len(env_ids)}")
        return super().get_action_batch(env_ids)


class Failing(Model):
    """Raises in reset and infer; sleeps on demand (the observation's instruction says how long)."""

    @property
    def metadata(self):
        return PolicyMetadata(name="failing", chunk_size=1)

    def reset(self):
        raise RuntimeError("reset exploded")

    def update_obs(self, obs):
        self.obs = obs

    def get_action(self):
        if self.obs["instruction"].startswith("sleep"):
            time.sleep(float(self.obs["instruction"].split()[1]))
            return np.zeros((1, 14), np.float32)
        raise RuntimeError("infer exploded")


def test_request_sequence_and_hooks():
    model = Recorder()
    with serving(model) as srv, PolicyClient(srv.url) as client:
        info = client.server_info
        assert info["server"] == "xpolicylab_policy_server" and info["capabilities"]["batch_infer"] is True
        assert client.metadata.name == "zero" and client.metadata.chunk_size == 2
        client.prepare_case({"task": "stack_bowls"}, "case-1")
        client.reset("trial-1", repeat_index=0)
        obs = small_obs()
        actions = client.infer(obs, step=3)
        assert actions.shape == (2, 14) and actions.dtype == np.float32
        assert np.array_equal(actions[0], obs["state"]["joint_pos"])
        assert client.heartbeat() >= 0
        client.trial_end({"success": True})
    assert model.calls[:2] == ["prepare_case:stack_bowls", "reset"]
    assert model.calls[-1] == "trial_end:True"


def test_reply_echoes_identifiers():
    with serving() as srv, connect(srv.url, compression=None, max_size=None) as ws:
        request = Frame(MessageType.INFER, {"observation": small_obs()}, message_id="m-42", evaluation_id="ev",
                        action_case_id="case", trial_id="t", repeat_index=2, step=17)
        ws.send(_wire(request))
        reply = decode_frame(ws.recv())
        assert reply.message_type is MessageType.INFER_RESULT
        assert (reply.message_id, reply.evaluation_id, reply.action_case_id, reply.trial_id, reply.repeat_index,
                reply.step) == ("m-42", "ev", "case", "t", 2, 17)
        assert reply.payload["action_mode"] == "joint" and reply.payload["latency_ms"] >= 0


def test_batched_infer_is_one_model_call():
    model = Recorder()
    with serving(model) as srv, PolicyClient(srv.url) as client:
        obs_list = [small_obs(seed=i) for i in range(8)]
        actions = client.infer_batch(obs_list, [f"env{i}" for i in range(8)])
    assert actions.shape == (8, 2, 14)
    for obs, chunk in zip(obs_list, actions, strict=True):
        assert np.array_equal(chunk[0], obs["state"]["joint_pos"])
    assert model.calls.count("batch:8") == 1


def test_batch_over_the_frame_limit_travels_as_several_requests_in_order():
    model = Recorder()
    # About 3 observations a frame (through shared memory, a column of their images would be one reference).
    with serving(model, max_frame_mb=0.1) as srv, PolicyClient(srv.url, shared_memory="off") as client:
        obs_list = [small_obs(seed=i) for i in range(8)]
        assert observation_bytes(obs_list[0]) * 8 > srv.server.config.max_frame_mb * (1 << 20)
        actions = client.infer_batch(obs_list, [f"env{i}" for i in range(8)])
        for obs, chunk in zip(obs_list, actions, strict=True):  # every environment gets its own action, in order
            assert np.array_equal(chunk[0], obs["state"]["joint_pos"])
        batches = sorted(c for c in model.calls if c.startswith("batch:"))
        assert client.infer(small_obs()).shape == (2, 14)  # the connection was never closed for size
        spans = batch_spans([observation_bytes(o) for o in obs_list], client.frame_budget())
    assert len(spans) > 1 and batches == sorted(f"batch:{b - a}" for a, b in spans)


def test_batch_spans_keep_each_request_within_budget():
    assert batch_spans([4, 4, 4, 4, 4], 8) == [(0, 2), (2, 4), (4, 5)]
    assert batch_spans([3, 6, 1, 8], 8) == [(0, 1), (1, 3), (3, 4)]
    assert batch_spans([], 8) == [(0, 0)]
    with pytest.raises(ProtocolError, match="over the"):
        batch_spans([4, 9], 8)


def test_batch_default_loops_single_methods():
    with serving(Failing()) as srv, PolicyClient(srv.url) as client:
        obs_list = [dict(small_obs(seed=i), instruction="sleep 0") for i in range(3)]
        assert client.infer_batch(obs_list, [0, 1, 2]).shape == (3, 1, 14)


def test_heartbeat_answered_during_slow_infer():
    async def scenario(url):
        async with AsyncPolicyClient(url) as client:
            infer = asyncio.create_task(client.infer(dict(small_obs(), instruction="sleep 1.0")))
            await asyncio.sleep(0.05)
            await client.heartbeat()
            heartbeat_first = not infer.done()
            await infer
            return heartbeat_first

    with serving(Failing()) as srv:
        assert asyncio.run(scenario(srv.url))


def test_32_concurrent_clients_get_their_own_answers():
    async def one(url, i):
        async with AsyncPolicyClient(url) as client:
            await client.reset(f"trial-{i}")
            for step in range(5):
                obs = small_obs(step=step, seed=1000 * i)
                actions = await client.infer(obs, step)
                assert np.array_equal(actions[0], obs["state"]["joint_pos"])
            return len(client.stats)

    async def many(url):
        return await asyncio.gather(*(one(url, i) for i in range(32)))

    with serving() as srv:
        assert asyncio.run(many(srv.url)) == [5] * 32


def test_model_errors_have_their_codes():
    with serving(Failing(), request_timeout_s=0.3) as srv, PolicyClient(srv.url) as client:
        with pytest.raises(ProtocolError) as info:
            client.reset("t")
        assert info.value.code is ErrorCode.RESET_FAILED and "reset exploded" in info.value.message
        with pytest.raises(ProtocolError) as info:
            client.infer(small_obs())
        assert info.value.code is ErrorCode.INFER_FAILED and "infer exploded" in info.value.message
        with pytest.raises(ProtocolError) as info:
            client.infer(dict(small_obs(), instruction="sleep 1.0"))
        assert info.value.code is ErrorCode.TIMEOUT
        assert client.heartbeat() >= 0  # the connection survives all three


def _frame_bytes(**fields) -> bytes:
    wire = _infer_frame()
    wire.update(fields)
    return codec.encode({k: v for k, v in wire.items() if v is not _DROP})


_DROP = object()
_OBS = small_obs()


def _obs_with(**arrays) -> bytes:
    wire = _infer_frame()
    obs = dict(_OBS)
    obs.update(arrays)
    wire["payload"] = {"observation": obs}
    return msgpack.packb(wire, default=msgpack_numpy.encode)


def _raw_array(spec: dict) -> bytes:
    wire = _infer_frame()
    wire["payload"] = {"observation": {"state": {"joint_pos": spec}}}
    return msgpack.packb(wire)


_VALID = b"".join(encode_frame(Frame(MessageType.INFER, {"observation": _OBS})))

MALFORMED: dict[str, tuple[bytes | str, ErrorCode]] = {
    "truncated msgpack": (_VALID[:-100], ErrorCode.INVALID_FRAME),
    "never-used type byte": (b"\xc1", ErrorCode.INVALID_FRAME),
    "empty frame": (b"", ErrorCode.INVALID_FRAME),
    "top level list": (msgpack.packb([1, 2, 3]), ErrorCode.INVALID_FRAME),
    "top level int": (msgpack.packb(7), ErrorCode.INVALID_FRAME),
    "text frame": ("{\"message_type\": \"infer\"}", ErrorCode.INVALID_FRAME),
    "missing message_type": (_frame_bytes(message_type=_DROP), ErrorCode.INVALID_FRAME),
    "message_type not a string": (_frame_bytes(message_type=3), ErrorCode.INVALID_FRAME),
    "unknown message type": (_frame_bytes(message_type="teleport"), ErrorCode.UNKNOWN_MESSAGE_TYPE),
    "reply type sent as request": (_frame_bytes(message_type="infer_result"), ErrorCode.UNKNOWN_MESSAGE_TYPE),
    "payload not a map": (_frame_bytes(payload=[1, 2]), ErrorCode.INVALID_FRAME),
    "infer without observation": (_frame_bytes(payload={}), ErrorCode.INVALID_FRAME),
    "observation not a map": (_frame_bytes(payload={"observation": "hello"}), ErrorCode.INVALID_FRAME),
    "step not an integer": (_frame_bytes(step="three"), ErrorCode.INVALID_FRAME),
    "message_id a list": (_frame_bytes(message_id=[1]), ErrorCode.INVALID_FRAME),
    "sent_at not an ISO-8601 time": (_frame_bytes(sent_at="now"), ErrorCode.INVALID_FRAME),
    "sent_at a map": (_frame_bytes(sent_at={"t": 1}), ErrorCode.INVALID_FRAME),
    "object array": (_obs_with(extra=np.array([1, "x"], dtype=object)), ErrorCode.INVALID_FRAME),
    "bad dtype": (_raw_array({b"nd": True, b"type": "<q9", b"kind": b"", b"shape": [1], b"data": b"\0" * 8}),
                  ErrorCode.INVALID_FRAME),
    "string dtype": (_raw_array({b"nd": True, b"type": "|S4", b"kind": b"", b"shape": [1], b"data": b"abcd"}),
                     ErrorCode.INVALID_FRAME),
    "data shorter than shape": (_raw_array({b"nd": True, b"type": "<f4", b"kind": b"", b"shape": [14],
                                            b"data": b"\0" * 8}), ErrorCode.INVALID_FRAME),
    "negative shape": (_raw_array({b"nd": True, b"type": "<f4", b"kind": b"", b"shape": [-1], b"data": b""}),
                       ErrorCode.INVALID_FRAME),
    "ext type": (msgpack.packb({"message_type": "infer", "payload": msgpack.ExtType(1, b"x")}),
                 ErrorCode.INVALID_FRAME),
    "trailing bytes": (_VALID + b"\x00", ErrorCode.INVALID_FRAME),
    "nesting bomb": (b"\x81\xa7payload" + b"\x91" * 200 + b"\xc0", ErrorCode.INVALID_FRAME),
    "batch env_ids too short": (_frame_bytes(payload={"observations": [_OBS, _OBS], "env_ids": [0]}),
                                ErrorCode.INVALID_FRAME),
    "batch duplicate env_ids": (_frame_bytes(payload={"observations": [_OBS, _OBS], "env_ids": [0, 0]}),
                                ErrorCode.INVALID_FRAME),
    "batch observations not a list": (_frame_bytes(payload={"observations": _OBS, "env_ids": [0]}),
                                      ErrorCode.INVALID_FRAME),
    "reset env_ids not a list": (_frame_bytes(message_type="reset", payload={"env_ids": 5}),
                                 ErrorCode.INVALID_FRAME),
}


def test_malformed_frames_get_error_codes_while_others_are_served():
    assert len(MALFORMED) >= 20
    stop = threading.Event()
    served: list[int] = []
    failures: list[BaseException] = []
    with serving() as srv:
        def bystander():
            try:
                with PolicyClient(srv.url) as client:
                    while not stop.is_set() and len(served) < 10_000:
                        client.infer(small_obs())
                        served.append(1)
            except BaseException as exc:  # surfaced by the assertion below
                failures.append(exc)

        thread = threading.Thread(target=bystander)
        thread.start()
        try:
            with connect(srv.url, compression=None, max_size=None) as ws:
                for name, (data, code) in MALFORMED.items():
                    before = len(served)
                    ws.send(data)
                    reply = decode_frame(ws.recv(timeout=10))
                    assert reply.message_type is MessageType.ERROR, name
                    assert reply.payload["code"] == code.value, (name, reply.payload)
                    assert reply.payload["message"], name
                    deadline = time.monotonic() + 10
                    while len(served) == before and time.monotonic() < deadline and not failures:
                        time.sleep(0.001)
                    assert len(served) > before, f"bystander starved after {name}"
                ws.send(_VALID)  # and the offending connection itself still works
                assert decode_frame(ws.recv(timeout=10)).message_type is MessageType.INFER_RESULT
        finally:
            stop.set()
            thread.join(timeout=30)
    assert not failures


def test_oversized_frame_is_closed_with_1009_and_server_survives():
    with serving(max_frame_mb=1) as srv:
        with connect(srv.url, compression=None, max_size=None) as ws:
            ws.send(b"\x00" * (2 << 20))
            with pytest.raises(ConnectionClosed) as info:
                ws.recv(timeout=10)
            assert info.value.rcvd is not None and info.value.rcvd.code == 1009
        with PolicyClient(srv.url) as client:
            assert client.infer(small_obs()).shape == (4, 14)


def test_token_is_required_and_checked():
    with serving(token="s3cret") as srv:
        for headers in (None, {"Authorization": "Bearer wrong"}, {"Authorization": "s3cret"}):
            with pytest.raises(InvalidStatus) as info:
                connect(srv.url, additional_headers=headers)
            assert info.value.response.status_code == 401
        refused = PolicyClient(srv.url, token="wrong")
        try:
            with pytest.raises(AuthError):
                refused.connect()
        finally:
            refused.close()
        with PolicyClient(srv.url, token="s3cret") as client:
            assert client.infer(small_obs()).shape == (4, 14)
        body = urllib.request.urlopen(f"http://127.0.0.1:{srv.port}/healthz", timeout=10).read()
        assert body == b"ok\n"
