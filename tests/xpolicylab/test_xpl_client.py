"""The client: retry with backoff, receive deadline, reconnect-and-resume, latency statistics."""

from __future__ import annotations

import asyncio
import threading

import pytest
from websockets.asyncio.server import serve

from xpolicylab.client import PolicyClient
from xpolicylab.errors import ErrorCode, ProtocolError
from xpolicylab.policies import ZeroPolicy
from xpolicylab.server import ServerConfig, ServerThread

from conftest import free_port, serving, small_obs


class CaseRecorder(ZeroPolicy):
    def __init__(self):
        super().__init__({"chunk_size": 2})
        self.cases: list[dict] = []

    def prepare_case(self, meta):
        self.cases.append(meta)


def test_connect_retries_until_the_server_is_up():
    port = free_port()
    started: list[ServerThread] = []

    def start_later():
        thread = ServerThread(ZeroPolicy(), ServerConfig(host="127.0.0.1", port=port))
        thread.__enter__()
        started.append(thread)

    timer = threading.Timer(0.5, start_later)
    timer.start()
    try:
        with PolicyClient(f"ws://127.0.0.1:{port}", max_connect_attempts=20, backoff_s=0.05,
                          backoff_max_s=0.2) as client:
            assert client.infer(small_obs()).shape == (8, 14)
    finally:
        timer.join()
        for thread in started:
            thread.__exit__(None, None, None)


def test_gives_up_after_bounded_attempts():
    client = PolicyClient(f"ws://127.0.0.1:{free_port()}", max_connect_attempts=3, backoff_s=0.01)
    try:
        with pytest.raises(ConnectionError, match="after 3 attempts"):
            client.connect()
    finally:
        client.close()


class Silent:
    """A WebSocket server that accepts and reads but never answers."""

    def __init__(self):
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)

    async def _handler(self, ws):
        async for _ in ws:
            pass

    async def _start(self):
        return await serve(self._handler, "127.0.0.1", 0)

    def __enter__(self):
        self.thread.start()
        self.server = asyncio.run_coroutine_threadsafe(self._start(), self.loop).result(timeout=10)
        return self

    def __exit__(self, *exc):
        self.server.close()
        asyncio.run_coroutine_threadsafe(self.server.wait_closed(), self.loop).result(timeout=10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=10)

    @property
    def url(self):
        return f"ws://127.0.0.1:{self.server.sockets[0].getsockname()[1]}"


@pytest.mark.parametrize("protocol", ["xpolicylab", "openpi"])
def test_silent_server_hits_the_receive_deadline(protocol):
    with Silent() as silent:
        client = PolicyClient(silent.url, protocol, recv_timeout_s=0.3)
        try:
            with pytest.raises(ProtocolError) as info:
                client.connect()
            assert info.value.code is ErrorCode.TIMEOUT
        finally:
            client.close()


def test_reconnects_and_resumes_the_current_trial():
    model = CaseRecorder()
    with serving(model) as srv, PolicyClient(srv.url) as client:
        client.prepare_case({"task": "stack_bowls"}, "case-7")
        client.reset("trial-3", repeat_index=1)
        client.infer(small_obs())

        async def drop_all():
            for connection in list(srv.server._server.connections):
                await connection.close()

        asyncio.run_coroutine_threadsafe(drop_all(), srv._loop).result(timeout=10)
        obs = small_obs(step=1)
        actions = client.infer_raw(obs, step=1)["actions"]
        assert (actions[0] == obs["state"]["joint_pos"]).all()
        assert client.reconnects == 1
        assert [c["task"] for c in model.cases] == ["stack_bowls", "stack_bowls"]
        assert model.cases[-1]["action_case_id"] == "case-7"
        assert len(client.stats) == 2
        summary = client.stats.summary()
        assert summary["count"] == 2 and summary["p50_ms"] <= summary["p99_ms"] <= summary["max_ms"]


@pytest.mark.parametrize("protocol", ["xpolicylab", "openpi"])
def test_connecting_again_closes_the_first_connection(protocol):
    with serving(protocol=protocol) as srv, PolicyClient(srv.url, protocol=protocol) as client:
        first = client._client._ws
        client.connect()
        assert first.state.name == "CLOSED" and client._client._ws is not first
        assert client.infer(small_obs()).shape[-1] == 14
