"""Large arrays through shared memory between a client and a server on one machine: the arrays the model gets
are the ones sent, the segment follows the largest request and is removed with the client, and a server refuses
(with a reply the client can read, on a connection that stays usable) every place it should not read."""

from __future__ import annotations

from multiprocessing.shared_memory import SharedMemory

import numpy as np
import pytest

from xpolicylab import codec
from xpolicylab.client import PolicyClient
from xpolicylab.embodiments import get_embodiment
from xpolicylab.errors import ErrorCode, ProtocolError
from xpolicylab.observations import synthetic_observation
from xpolicylab.policies import ZeroPolicy
from xpolicylab.protocol import MessageType
from xpolicylab.shared_memory import IncomingSegments, OutgoingSegment, is_loopback_host, is_loopback_url

from conftest import serving

EMBODIMENT = get_embodiment("arx_x5_bimanual")


class Keeper(ZeroPolicy):
    """A zero policy that keeps every batch it was given (a policy may keep its inputs, e.g. a frame history)."""

    def __init__(self) -> None:
        super().__init__({"chunk_size": 1})
        self.batches: list[list[dict]] = []

    def update_obs_batch(self, obs_list, env_ids) -> None:
        super().update_obs_batch(obs_list, env_ids)
        self.batches.append(list(obs_list))


def _batch(n: int, size: int, seed: int = 0) -> list[dict]:
    return [synthetic_observation(EMBODIMENT, width=size, height=size, step=0, seed=seed + i) for i in range(n)]


def _same(sent: list[dict], got: list[dict]) -> None:
    for a, b in zip(sent, got, strict=True):
        assert set(a["images"]) == set(b["images"])
        for cam in a["images"]:
            np.testing.assert_array_equal(a["images"][cam], b["images"][cam])
        np.testing.assert_array_equal(a["state"]["joint_pos"], b["state"]["joint_pos"])


def test_loopback_hosts():
    assert all(is_loopback_host(h) for h in ("127.0.0.1", "127.3.2.1", "::1", "[::1]", "localhost", "::ffff:127.0.0.1"))
    assert not any(is_loopback_host(h) for h in ("10.0.0.2", "::ffff:10.0.0.2", "gpu1", "", None, "0.0.0.0"))
    assert is_loopback_url("ws://127.0.0.1:19000") and not is_loopback_url("ws://gpu1:19000")


def test_the_model_gets_the_arrays_sent_and_may_keep_them():
    model = Keeper()
    first, second = _batch(4, 160), _batch(4, 160, seed=10)
    with serving(model) as srv, PolicyClient(srv.url) as client:
        assert client.server_info["capabilities"]["shared_memory"] is True and client.shares_memory
        client.infer_batch(first, list(range(4)))
        name = client._client._segment.name
        client.infer_batch(second, list(range(4)))
        assert client._client._segment.name == name  # the same segment, written again
    _same(first, model.batches[0])  # what the model kept from the first request was not overwritten
    _same(second, model.batches[1])
    with pytest.raises(FileNotFoundError):
        SharedMemory(name)  # the client removed its segment when it closed


def test_a_larger_request_gets_a_larger_segment_and_the_old_one_goes():
    model = Keeper()
    small, large = _batch(2, 160), _batch(8, 256)
    with serving(model) as srv, PolicyClient(srv.url) as client:
        client.infer_batch(small, [0, 1])
        old = client._client._segment.name
        client.infer_batch(large, list(range(8)))
        assert client._client._segment.name != old
        with pytest.raises(FileNotFoundError):
            SharedMemory(old)
    _same(large, model.batches[1])


def test_without_shared_memory_the_bytes_travel_in_the_message():
    model = Keeper()
    sent = _batch(3, 160)
    with serving(model) as srv, PolicyClient(srv.url, shared_memory=False) as client:
        client.infer_batch(sent, [0, 1, 2])
        assert not client.shares_memory and client._client._segment is None
    _same(sent, model.batches[0])


def _infer(client: PolicyClient, payload: dict):
    return client._call(client._client._request, MessageType.INFER, payload)


class _Placer:
    """Writes large arrays' places without writing them anywhere: a client that lies about its segment."""

    def __init__(self, offset: int) -> None:
        self.offset = offset

    def rewind(self) -> None:
        pass

    def put(self, arr: np.ndarray) -> tuple[int, int]:
        return self.offset, arr.nbytes


def test_the_server_refuses_places_it_should_not_read_and_stays_usable():
    obs = _batch(1, 160)[0]
    segment = OutgoingSegment()
    segment.ready_for(1 << 20)
    try:
        with serving(Keeper()) as srv, PolicyClient(srv.url) as client:
            for payload, shared, words in (
                ({"observation": obs, "shm": "not_ours"}, None, "xpl_ segment"),
                ({"observation": obs, "shm": "xpl_" + "0" * 32}, None, "cannot open"),
                ({"observation": obs}, _Placer(0), "names no segment"),
                ({"observation": obs, "shm": segment.name}, _Placer((1 << 20) - 100), "outside"),
            ):
                with pytest.raises(ProtocolError) as err:
                    client._call(client._client._request, MessageType.INFER, payload, shared=shared)
                assert err.value.code is ErrorCode.INVALID_FRAME and words in err.value.message
            assert client.infer(obs).shape[-1] == 14  # the same connection answers the next request
    finally:
        segment.close()


def test_only_same_host_peers_may_name_a_segment():
    segments = IncomingSegments(allowed=False, max_bytes=1 << 30)
    with pytest.raises(ProtocolError, match="this machine only"):
        segments.resolve({"observation": {}, "shm": "xpl_" + "0" * 32})


def test_the_server_limit_on_a_message_holds_for_shared_memory_too():
    sent = _batch(4, 160)  # 4 x 3 images of 76,800 bytes
    with serving(Keeper(), max_frame_mb=0.5) as srv, PolicyClient(srv.url) as client:
        with pytest.raises(ProtocolError, match="more than this server accepts"):
            client.infer_batch(sent, [0, 1, 2, 3])
        client.infer_batch(sent[:1], [0])  # 230 kB: under the limit


def test_an_array_place_is_checked_like_array_data():
    def wire(place, shape=(4, 4), dtype="|u1"):
        return codec.encode({"a": {"nd": True, "type": dtype, "kind": "", "shape": list(shape), "shm": place}})

    ref = codec.decode(wire([128, 16]))["a"]
    assert isinstance(ref, codec.ShmRef) and (ref.offset, ref.nbytes, ref.shape) == (128, 16, (4, 4))
    for bad in ([0, 15], [-1, 16], [0], "x", [0, True]):
        with pytest.raises(ProtocolError):
            codec.decode(wire(bad))
    with pytest.raises(ProtocolError):
        codec.decode(wire([0, 16], dtype="|O"))


def test_too_little_room_for_a_segment_sends_the_bytes_instead(monkeypatch, caplog):
    """A container's /dev/shm is often 64 MB, and a segment is made sparse: writing past the room left would kill
    the client (SIGBUS), so the room is checked first and the arrays go in the message."""
    from xpolicylab import shared_memory

    monkeypatch.setattr(shared_memory, "shared_memory_free", lambda: 64 << 10)
    model, sent = Keeper(), _batch(2, 160)
    with serving(model) as srv, PolicyClient(srv.url) as client:
        assert client.shares_memory
        client.infer_batch(sent, [0, 1])
        assert not client.shares_memory and client._client._segment is None
    _same(sent, model.batches[0])
    assert "--shm-size" in caplog.text


def test_a_server_that_cannot_read_the_segment_gets_the_bytes_instead(monkeypatch):
    """Both ends on loopback but not one /dev/shm (a container without --ipc=host, an ssh tunnel, another user):
    the server says it cannot open the segment, and the client sends the request again in the message."""
    import os

    from xpolicylab import shared_memory

    made = shared_memory.OutgoingSegment.ready_for

    def made_elsewhere(self, nbytes):  # the segment exists for the client only
        made(self, nbytes)
        os.unlink(os.path.join(shared_memory.SHM_DIR, self.name))

    monkeypatch.setattr(shared_memory.OutgoingSegment, "ready_for", made_elsewhere)
    model, sent = Keeper(), _batch(2, 160)
    with serving(model) as srv, PolicyClient(srv.url) as client:
        client.infer_batch(sent, [0, 1])
        assert not client.shares_memory and client._client._segment is None
    _same(sent, model.batches[0])


def test_a_segment_shrunk_under_the_server_is_an_error_reply_not_a_crash():
    """The server reads the segment from a file descriptor, not a mapping: bytes a client took away read short
    (a mapping would have killed the server with SIGBUS, and this test process with it)."""
    import os

    from xpolicylab.shared_memory import SHM_DIR

    obs = _batch(1, 160)[0]
    with serving(Keeper()) as srv, PolicyClient(srv.url) as client:
        client.infer(obs)  # the server has the segment open now
        name = client._client._segment.name
        os.truncate(os.path.join(SHM_DIR, name), 0)
        with pytest.raises(ProtocolError, match="outside the segment"):
            client._call(client._client._request, MessageType.INFER, {"observation": obs, "shm": name},
                         shared=_Placer(0))
        assert client.heartbeat() > 0  # the server and the connection are still there


class Slow(Keeper):
    def get_action_batch(self, env_ids):
        import time

        time.sleep(1.0)
        return super().get_action_batch(env_ids)


def test_after_a_timeout_the_next_request_gets_a_new_segment():
    """The server may still read a request that timed out: the next one must not overwrite its arrays."""
    sent = _batch(2, 160)
    with serving(Slow()) as srv, PolicyClient(srv.url, recv_timeout_s=0.2) as client:
        with pytest.raises(ProtocolError) as err:
            client.infer_batch(sent, [0, 1])
        assert err.value.code is ErrorCode.TIMEOUT and client._client._segment is None
