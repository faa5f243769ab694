"""openpi interoperability, both ways, against the real `openpi-client` package from PyPI.

* The real ``openpi_client.websocket_client_policy.WebsocketClientPolicy`` talks to our server in openpi mode.
* Our client (and the checker) evaluate an openpi-style server. openpi's server lives in the openpi repository,
  not on PyPI, so ``OpenpiStyleServer`` re-implements its loop (metadata first, lock-step infer, traceback as a
  text frame + close 1011, ``/healthz``) on top of the real ``openpi_client.msgpack_numpy``.
"""

from __future__ import annotations

import asyncio
import threading
import traceback

import numpy as np
import pytest
import websockets
from openpi_client import msgpack_numpy
from openpi_client.websocket_client_policy import WebsocketClientPolicy
from websockets.asyncio.server import serve

from xpolicylab.checker import CheckConfig, run_check
from xpolicylab.client import PolicyClient
from xpolicylab.embodiments import get_embodiment
from xpolicylab.errors import ErrorCode, ProtocolError
from xpolicylab.model import Model, PolicyMetadata
from xpolicylab.observations import synthetic_observation

from conftest import serving, small_obs


class Exploding(Model):
    @property
    def metadata(self):
        return PolicyMetadata(name="exploding")

    def update_obs(self, obs):
        pass

    def get_action(self):
        raise ValueError("no weights loaded")


def test_openpi_client_talks_to_our_server():
    with serving(protocol="openpi") as srv:
        policy = WebsocketClientPolicy(host=srv.url)
        try:
            meta = policy.get_server_metadata()
            assert meta["name"] == "zero" and meta["chunk_size"] == 4 and meta["action_mode"] == "joint"
            obs = synthetic_observation(get_embodiment("arx_x5_bimanual"))  # full size: 3 x 640x480
            result = policy.infer(obs)
            assert result["actions"].shape == (4, 14) and result["actions"].dtype == np.float32
            assert np.array_equal(result["actions"][-1], obs["state"]["joint_pos"])
            assert "infer_ms" in result["server_timing"]
        finally:
            policy._ws.close()


def test_openpi_client_api_key_is_accepted():
    with serving(protocol="openpi", token="k3y") as srv:
        policy = WebsocketClientPolicy(host=srv.url, api_key="k3y")
        try:
            assert policy.infer(small_obs())["actions"].shape == (4, 14)
        finally:
            policy._ws.close()


def test_openpi_errors_are_a_text_frame_then_close_1011():
    with serving(Exploding(), protocol="openpi") as srv:
        policy = WebsocketClientPolicy(host=srv.url)
        with pytest.raises(RuntimeError, match="no weights loaded"):
            policy.infer(small_obs())
        with pytest.raises(websockets.ConnectionClosed) as info:
            policy._ws.recv(timeout=10)
        assert info.value.rcvd.code == 1011


class OpenpiStyleServer:
    """openpi's WebsocketPolicyServer loop, in a thread, for a policy with ``infer(obs) -> dict``."""

    def __init__(self, infer, metadata):
        self.infer, self.metadata = infer, metadata
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)

    async def _handler(self, ws):
        packer = msgpack_numpy.Packer()
        await ws.send(packer.pack(self.metadata))
        while True:
            try:
                action = self.infer(msgpack_numpy.unpackb(await ws.recv()))
                action["server_timing"] = {"infer_ms": 0.1}
                await ws.send(packer.pack(action))
            except websockets.ConnectionClosed:
                return
            except Exception:
                await ws.send(traceback.format_exc())
                await ws.close(code=1011, reason="Internal server error")
                return

    async def _start(self):
        return await serve(self._handler, "127.0.0.1", 0, compression=None, max_size=None)

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


def _pi_like(obs):
    """Answers like a pi0 policy: a 10-step chunk, float32, here holding the observed pose."""
    pose = np.asarray(obs["state"]["joint_pos"], dtype=np.float32)
    return {"actions": np.repeat(pose[None], 10, axis=0)}


def test_our_client_evaluates_an_openpi_server():
    with OpenpiStyleServer(_pi_like, {"policy": "pi0_arx"}) as srv, PolicyClient(srv.url, "openpi") as client:
        assert client.server_info == {"policy": "pi0_arx"}
        obs = small_obs()
        assert np.array_equal(client.infer(obs)[0], obs["state"]["joint_pos"])
        batch = client.infer_batch([small_obs(seed=i) for i in range(3)], [0, 1, 2])  # looped: no batch support
        assert batch.shape == (3, 10, 14)
        assert client.reset("trial") == {"ok": True}


def test_checker_passes_an_openpi_server_that_declares_nothing():
    with OpenpiStyleServer(_pi_like, {}) as srv:
        report = run_check(CheckConfig(url=srv.url, protocol="openpi", n=3, width=64, height=48))
    assert report.passed, report.format()


def test_checker_fails_an_openpi_server_sending_float64():
    def float64(obs):
        return {"actions": _pi_like(obs)["actions"].astype(np.float64)}

    with OpenpiStyleServer(float64, {}) as srv:
        report = run_check(CheckConfig(url=srv.url, protocol="openpi", n=2, width=64, height=48))
    assert not report.passed and "float32" in report.format()


def test_our_client_surfaces_openpi_server_errors():
    def broken(obs):
        raise KeyError("observation/image")

    with OpenpiStyleServer(broken, {}) as srv, PolicyClient(srv.url, "openpi") as client:
        with pytest.raises(ProtocolError) as info:
            client.infer(small_obs())
        assert info.value.code is ErrorCode.INFER_FAILED and "observation/image" in info.value.message
