"""Shared memory for large arrays when client and server share a host: negotiation, the wire, the server's checks,
segment lifetimes (client, server and resource tracker), and the bench comparing it with the socket."""

from __future__ import annotations

import concurrent.futures.thread
import json
import os
import signal
import subprocess
import sys
import threading
import time
from multiprocessing.shared_memory import SharedMemory

import numpy as np
import pytest
from websockets.asyncio.server import ServerConnection
from websockets.sync.client import connect

from xpolicylab import codec, shm, transport
from xpolicylab.bench import spawned_server
from xpolicylab.cli import bench_main
from xpolicylab.client import PolicyClient, observation_bytes
from xpolicylab.embodiments import get_embodiment
from xpolicylab.errors import ErrorCode, ProtocolError
from xpolicylab.observations import synthetic_observation
from xpolicylab.model import Model
from xpolicylab.policies import ZeroPolicy
from xpolicylab.protocol import Frame, MessageType, decode_frame, encode_frame

from conftest import serving

#: 192x128x3 uint8 images: 73.7 kB each, over the 64 KiB threshold, three per observation.
WIDTH, HEIGHT = 192, 128


def big_obs(seed: int) -> dict:
    return synthetic_observation(get_embodiment("arx_x5_bimanual"), width=WIDTH, height=HEIGHT, seed=seed)


def checksum(obs: dict) -> float:
    """A number that depends on every pixel of an observation's images (exact in float32)."""
    return float(sum(int(img.sum()) for img in obs["images"].values()) % (1 << 20))


def mine(pid: int | None = None) -> set[str]:
    """The segments in /dev/shm that process ``pid`` (default: this one) created."""
    return {n for n in os.listdir("/dev/shm") if n.startswith(f"{shm.PREFIX}{pid or os.getpid()}_")}


class Keeper(ZeroPolicy):
    """Keeps every observation it is given (as a policy with a history would); its first action column is the
    checksum of the environment's images, so a reply says which images reached the model."""

    borrows_observations = False  # it keeps them

    def __init__(self) -> None:
        super().__init__({"chunk_size": 2})
        self.kept: list[dict] = []
        self.batches: list[int] = []

    def update_obs(self, obs):
        self.kept.append(obs)
        self.last = {None: obs}
        super().update_obs(obs)

    def update_obs_batch(self, obs_list, env_ids):
        self.kept.extend(obs_list)
        self.batches.append(len(obs_list))
        self.last = dict(zip(env_ids, obs_list))
        super().update_obs_batch(obs_list, env_ids)

    update_obs_columns = Model.update_obs_columns  # environment by environment, through update_obs_batch

    def get_action_batch(self, env_ids):
        actions = super().get_action_batch(env_ids)
        actions[:, :, 0] = np.array([checksum(self.last[e]) for e in env_ids])[:, None]
        return actions


@pytest.fixture
def client_bytes(monkeypatch) -> list[int]:
    """Bytes of every message a client sends through its socket (the server's replies are not counted)."""
    sent: list[int] = []
    original = transport.send_chunks

    async def spy(ws, chunks):
        total = await original(ws, chunks)
        if not isinstance(ws, ServerConnection):
            sent.append(total)
        return total

    monkeypatch.setattr(transport, "send_chunks", spy)
    return sent


def test_round_trip_hands_the_model_copies_it_owns(client_bytes):
    model = Keeper()
    with serving(model) as srv, PolicyClient(srv.url, shared_memory="on") as client:
        assert client.uses_shared_memory and client.server_info["capabilities"]["shared_memory"] is True
        first, second = big_obs(1), big_obs(2)
        client_bytes.clear()
        assert client.infer(first)[0, 0] == checksum(first)
        assert sum(client_bytes) < 4096  # the 221 kB of images did not go through the socket
        assert len(mine()) == 1  # so the second request overwrites the segment the first one used
        assert client.infer(second)[0, 0] == checksum(second)
    kept_first, kept_second = model.kept
    for cam, image in first["images"].items():  # what the model kept from the first request is still the first's
        assert np.array_equal(kept_first["images"][cam], image) and kept_first["images"][cam].dtype == np.uint8
        assert not kept_first["images"][cam].flags.writeable  # read-only, as arrays from the socket are
    for cam, image in second["images"].items():
        assert np.array_equal(kept_second["images"][cam], image)
    assert np.array_equal(kept_first["state"]["joint_pos"], first["state"]["joint_pos"])  # small: the socket


def test_batched_infer_splits_into_concurrent_requests_each_with_its_own_segment():
    model = Keeper()
    obs_list = [big_obs(i) for i in range(32)]
    with serving(model, max_frame_mb=0.01) as srv, PolicyClient(srv.url) as client:  # ~11 observations a frame
        assert client.uses_shared_memory
        actions = client.infer_batch(obs_list, [f"env{i}" for i in range(32)])
        segments = mine()
    assert [chunk[0, 0] for chunk in actions] == [checksum(o) for o in obs_list]  # each env its own, in order
    assert len(model.batches) > 1 and sum(model.batches) == 32
    assert len(segments) >= len(model.batches)  # requests in flight together never share a region


def test_frame_budget_counts_only_what_travels_through_the_socket():
    obs = big_obs(0)
    assert observation_bytes(obs) > 3 * WIDTH * HEIGHT * 3
    assert observation_bytes(obs, shared=True) < 2048


def _ref_frame(ref: codec.SharedArray, message_id: str) -> bytes:
    obs = dict(big_obs(0), images={"head": ref})
    return b"".join(encode_frame(Frame(MessageType.INFER, {"observation": obs}, message_id=message_id)))


@pytest.fixture
def test_segment():
    """A segment of 4096 bytes made by hand, named like a client's, holding 0..255 repeated."""
    segment = SharedMemory(f"{shm.PREFIX}{os.getpid()}_test", create=True, size=4096)
    segment.buf[:4096] = bytes(range(256)) * 16
    yield segment
    segment.close()
    segment.unlink()


def test_bad_references_get_errors_naming_the_fault_and_the_connection_keeps_working(test_segment):
    u8 = np.dtype(np.uint8)
    name = test_segment.name
    bad = {
        "not ours": (codec.SharedArray("psm_123", 0, u8, (16,)), "is refused"),
        "path in the name": (codec.SharedArray("xpl_/../etc/passwd", 0, u8, (16,)), "is refused"),
        "missing segment": (codec.SharedArray("xpl_0_nosuchsegment", 0, u8, (16,)), "no shared-memory segment"),
        "past the end": (codec.SharedArray(name, 4000, u8, (200,)), "out of bounds"),
        "huge shape": (codec.SharedArray(name, 0, np.dtype("<f8"), (1 << 40, 1 << 40)), "out of bounds"),
    }
    unreadable = {  # refused by the decoder: the error cannot name the request, but it decodes
        "object dtype": codec.SharedArray(name, 0, np.dtype(object), (4,)),
        "negative offset": codec.SharedArray(name, -64, u8, (16,)),
    }
    model = Keeper()
    with serving(model) as srv, connect(srv.url, compression=None, max_size=None) as ws:
        for label, (ref, words) in bad.items():
            ws.send(_ref_frame(ref, f"m-{label}"))
            reply = decode_frame(ws.recv(timeout=10))
            assert reply.message_type is MessageType.ERROR and reply.message_id == f"m-{label}", label
            assert reply.payload["code"] == ErrorCode.INVALID_FRAME.value and words in reply.payload["message"], label
            assert reply.payload["details"]["field"] == "shared_memory", label
        for label, ref in unreadable.items():
            ws.send(_ref_frame(ref, f"m-{label}"))
            reply = decode_frame(ws.recv(timeout=10))
            assert reply.message_type is MessageType.ERROR, label
            assert reply.payload["code"] == ErrorCode.INVALID_FRAME.value and reply.payload["message"], label
        ws.send(_ref_frame(codec.SharedArray(name, 256, u8, (4, 4)), "m-good"))  # and a good one is still read
        reply = decode_frame(ws.recv(timeout=10))
    assert reply.message_type is MessageType.INFER_RESULT and reply.message_id == "m-good"
    assert np.array_equal(model.kept[-1]["images"]["head"], np.arange(16, dtype=np.uint8).reshape(4, 4))


def _falls_back_to_the_socket(url: str, client_bytes: list[int], why: str) -> None:
    """`auto` connects and sends the images through the socket; `on` refuses to connect, saying `why`."""
    with PolicyClient(url) as client:
        assert not client.uses_shared_memory
        client_bytes.clear()
        assert client.infer(big_obs(0)).shape == (4, 14)
        assert sum(client_bytes) > 3 * WIDTH * HEIGHT * 3
    client = PolicyClient(url, shared_memory="on")
    with pytest.raises(ConnectionError, match=why):
        client.connect()
    client.close()


def test_a_peer_that_is_not_loopback_is_refused_and_clients_fall_back(monkeypatch, test_segment, client_bytes):
    monkeypatch.setattr(ServerConnection, "remote_address", property(lambda self: ("10.1.2.3", 40000)))
    with serving() as srv:
        with connect(srv.url, compression=None, max_size=None) as ws:
            ws.send(_ref_frame(codec.SharedArray(test_segment.name, 0, np.dtype(np.uint8), (16,)), "m-1"))
            reply = decode_frame(ws.recv(timeout=10))
            assert reply.message_type is MessageType.ERROR and reply.message_id == "m-1"
            assert "only from a loopback peer, not from 10.1.2.3" in reply.payload["message"]
            ws.send(b"".join(encode_frame(Frame(MessageType.INFER, {"observation": big_obs(0)}))))
            assert decode_frame(ws.recv(timeout=10)).message_type is MessageType.INFER_RESULT
        _falls_back_to_the_socket(srv.url, client_bytes, "loopback peer")  # the probe failed


def test_auto_uses_the_socket_with_a_server_that_does_not_advertise_it(client_bytes):
    with serving(shared_memory=False) as srv:
        with PolicyClient(srv.url, shared_memory="off") as client:
            assert "shared_memory" not in client.server_info["capabilities"]  # as before the option existed
        _falls_back_to_the_socket(srv.url, client_bytes, "does not advertise capabilities.shared_memory")
        with connect(srv.url, compression=None, max_size=None) as ws:  # and references sent anyway are refused
            ws.send(_ref_frame(codec.SharedArray("xpl_0_x", 0, np.dtype(np.uint8), (16,)), "m-1"))
            assert "shared_memory=false" in decode_frame(ws.recv(timeout=10)).payload["message"]
    assert not mine()


def test_off_sends_exactly_what_it_sent_before(client_bytes):
    obs = big_obs(0)
    with serving() as srv, PolicyClient(srv.url, shared_memory="off", evaluation_id="ev-1") as client:
        client_bytes.clear()
        client.infer(obs)
    expected = len(b"".join(encode_frame(Frame(MessageType.INFER, {"observation": obs}, evaluation_id="ev-1"))))
    assert client_bytes == [expected] and not mine()  # no probe, no segment, the whole frame


def test_no_segment_is_left_after_the_client_closes():
    with serving() as srv:
        client = PolicyClient(srv.url)
        client.infer_batch([big_obs(i) for i in range(4)], [0, 1, 2, 3])
        assert mine()
        client.close()
    assert not mine()


CHILD = r"""
import os, sys
from xpolicylab.client import PolicyClient
from xpolicylab.embodiments import get_embodiment
from xpolicylab.observations import synthetic_observation
client = PolicyClient(sys.argv[1], shared_memory="on")
client.infer(synthetic_observation(get_embodiment("arx_x5_bimanual"), width=192, height=128))
print(os.getpid(), flush=True)
sys.stdin.readline()  # the test has seen the segment (or kills us meanwhile)
raise KeyboardInterrupt  # Ctrl-C: the client is never closed
"""


@pytest.mark.parametrize("end", ["interrupt", "kill"])
def test_a_client_that_never_closes_leaves_no_segment(end):
    with serving() as srv:
        proc = subprocess.Popen([sys.executable, "-c", CHILD, srv.url], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        pid = int(proc.stdout.readline())
        assert mine(pid)
        if end == "kill":
            proc.send_signal(signal.SIGKILL)  # the resource tracker, still alive, unlinks what was registered
        _, stderr = proc.communicate("go\n", timeout=30)  # until the tracker, which shares the pipe, is done
    assert not mine(pid)
    if end == "interrupt":  # unlinked by the client itself on the way out, not left to the tracker
        assert "KeyboardInterrupt" in stderr and "leaked shared_memory" not in stderr


def test_a_server_in_another_process_leaves_the_client_segments_alone():
    """Python 3.11's resource tracker unlinks, when a process ends, every segment it opened; the server's must not
    take the client's segments with it."""
    with spawned_server("xpolicylab") as url:
        client = PolicyClient(url, shared_memory="on")
        client.infer(big_obs(0))
        segments = mine()
    time.sleep(1.5)  # the server was terminated: its tracker has cleaned up by now
    assert segments and mine() == segments
    client.close()
    assert not mine()


def test_option_values_and_loopback_addresses():
    assert [shm.mode(v) for v in ("auto", "ON", "off", True, False, "true")] == ["auto", "on", "off", "on", "off", "on"]
    with pytest.raises(ValueError, match="auto, on, off"):
        shm.mode("sometimes")
    with pytest.raises(ValueError, match="xpolicylab dialect"):
        PolicyClient("ws://127.0.0.1:1", "openpi", shared_memory="on")
    for peer in (("127.0.0.1", 1), ("127.8.9.10", 1), ("::1", 1, 0, 0), ("::ffff:127.0.0.1", 1)):
        assert shm.is_loopback_address(peer), peer
    for peer in (("10.0.0.1", 1), ("192.168.1.2", 1), ("::ffff:10.0.0.1", 1), ("2001:db8::1", 1), None, ""):
        assert not shm.is_loopback_address(peer), peer
    assert shm.is_loopback_host("localhost") and shm.is_loopback_host("::1") and shm.is_loopback_host("127.0.0.1")
    assert not shm.is_loopback_host("example.org") and not shm.is_loopback_host(None)


def test_segment_pool_reuses_grows_and_drops_segments():
    pool = shm.SegmentPool()
    small = {"a": np.ones(shm.THRESHOLD, np.uint8)}
    with pool.lease(small) as wire:
        first = wire["a"].segment
    with pool.lease(small) as wire:
        assert wire["a"].segment == first  # reused once its request is over
        with pool.lease(small) as other:
            second = other["a"].segment
            assert second != first  # in flight together: another segment
    with pool.lease({"a": np.ones(4 * shm.THRESHOLD, np.uint8)}) as wire:
        grown = wire["a"].segment
    assert len(mine() & {first, second}) == 1 and grown in mine()  # a free one was replaced by a larger one
    with pytest.raises(RuntimeError), pool.lease(small) as wire:
        dropped = wire["a"].segment
        raise RuntimeError("no reply")
    assert dropped not in mine()  # the server may still read it: never reused
    plain = {"a": np.ones(8, np.uint8)}
    with pool.lease(plain) as wire:
        assert wire is plain  # nothing large: no segment at all
    with pool.lease(small):
        pool.close()  # the client closed while a request was in flight: nothing is left, nothing is reused
    assert not mine()
    with pytest.raises(RuntimeError, match="lost"), pool.lease(small):
        pool.close()
        raise RuntimeError("lost")  # and the request's own error is the one that surfaces
    with pool.lease(small) as wire:
        assert wire["a"].segment in mine()  # a closed pool makes new segments
    pool.close()
    assert not mine()


def test_references_are_refused_outside_the_native_server():
    wire = codec.encode({"a": codec.SharedArray("xpl_1_a", 0, np.dtype("<f4"), (2, 3))})
    assert codec.decode(wire, shared_refs=True)["a"] == codec.SharedArray("xpl_1_a", 0, np.dtype("<f4"), (2, 3))
    with pytest.raises(ProtocolError, match="not accepted here"):
        codec.decode(wire)


def test_bench_compares_socket_and_shared_memory_in_one_run(capsys):
    assert bench_main(["batch=2", "width=192", "height=128", "n=2", "warmup=1", "single_n=2",
                       "protocols=[xpolicylab]", "shared_memory=[off,on]"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["xpolicylab_shm_off"]["shared_memory"] is False
    assert figures["xpolicylab_shm_on"]["shared_memory"] is True
    assert bench_main(["shared_memory=[maybe]"]) == 2


def test_copies_spread_over_threads_give_the_same_arrays(monkeypatch):
    """A large request's copies run on several threads (on the H200 host: 32 ms on one core, 8 ms on eight); the
    arrays must come out the same whoever copied them."""
    monkeypatch.setattr(shm, "COPY_THREADS", 3)
    monkeypatch.setattr(shm, "BYTES_PER_COPY_THREAD", shm.THRESHOLD)
    payload = {"observations": [big_obs(i) for i in range(4)], "env_ids": [0, 1, 2, 3]}
    pool, cache = shm.SegmentPool(), shm.SegmentCache()
    with pool.lease(payload) as wire:
        received = codec.decode(encode_frame(Frame(MessageType.INFER, wire)), shared_refs=True)["payload"]
        cache.resolve(received)
    cache.close()
    pool.close()
    assert any(t.name.startswith("xpolicylab-shm") for t in threading.enumerate())
    for sent, got in zip(payload["observations"], received["observations"], strict=True):
        for cam, image in sent["images"].items():
            assert np.array_equal(got["images"][cam], image) and not got["images"][cam].flags.writeable


class Borrower(ZeroPolicy):
    """Says it borrows observations, and (against that word, to show what it means) keeps the images it is given."""

    def __init__(self) -> None:
        super().__init__({"chunk_size": 2})
        self.images: list[np.ndarray] = []

    def update_obs(self, obs):
        self.images.append(obs["images"]["head"])
        super().update_obs(obs)


def test_a_borrowing_model_reads_the_client_segment_itself(caplog):
    """No copy: the image the model is given is a read-only view of the client's segment, which the client
    writes again for its next request; a model that keeps one anyway gets a warning when the connection closes,
    and the segment is closed once the model lets go."""
    model = Borrower()
    first, second = big_obs(1), big_obs(2)
    with serving(model) as srv, PolicyClient(srv.url, shared_memory="on") as client:
        client.infer(first)
        kept = model.images[0]
        assert isinstance(kept.base, np.ndarray) and type(kept.base.base) is memoryview  # the segment's memory
        assert not kept.flags.writeable
        assert np.array_equal(kept, first["images"]["head"])
        client.infer(second)
        assert np.array_equal(kept, second["images"]["head"])  # the client wrote its next images there
    assert "kept arrays it borrowed" in caplog.text and shm._LENT
    model.images.clear()
    del kept
    shm.SegmentCache().close()  # every later close tries again
    assert not shm._LENT


def test_a_model_that_keeps_nothing_leaves_no_segment_lent_however_late_its_thread_lets_go(monkeypatch, caplog):
    """The model's executor holds the call it ran (and with it the request's borrowed views) a moment after the
    result is handed back; stretched here to 0.3 s, a connection closing in that moment must still close its
    segment, without the warning meant for a model that keeps what it borrowed (CI saw that race on a busy host)."""
    run = concurrent.futures.thread._WorkItem.run

    def lingering(item) -> None:
        run(item)
        time.sleep(0.3)

    monkeypatch.setattr(concurrent.futures.thread._WorkItem, "run", lingering)
    with serving(ZeroPolicy({"chunk_size": 2})) as srv, PolicyClient(srv.url, shared_memory="on") as client:
        client.infer(big_obs(1))
    assert "kept arrays it borrowed" not in caplog.text
    assert not shm._LENT


def test_a_segment_whose_arrays_are_lent_out_stays_open_until_they_are_let_go_of(monkeypatch):
    monkeypatch.setattr(shm, "OPEN_PER_CONNECTION", 1)
    first, second = shm._create(4096), shm._create(4096)  # a client's segments, made in this process
    try:
        cache = shm.SegmentCache()
        lent = {"a": codec.SharedArray(first.name, 0, np.dtype(np.uint8), (16,))}
        cache.resolve(lent, borrow=True)
        cache.resolve({"b": codec.SharedArray(second.name, 0, np.dtype(np.uint8), (16,))}, borrow=True)
        # Over the limit, and an array of it still lent: set aside, to be closed once let go of.
        assert list(cache._open) == [second.name] and [s.name for s in shm._LENT] == [first.name]
        cache.resolve({"c": codec.SharedArray(first.name, 0, np.dtype(np.uint8), (4,))}, borrow=True)
        assert list(cache._open) == [first.name]  # opened again to lend again
        del lent
        cache.close()
        assert not shm._LENT  # closed once nothing of it was lent any more
    finally:
        shm._unlink(first)
        shm._unlink(second)


def _lent_batch(client: PolicyClient, n: int) -> tuple[np.ndarray, list[dict], list[dict]]:
    """A lent buffer holding ``n`` observations' images camera-major (as the mjx backend copies them off the GPU),
    the observations whose images are views of it, and the observations they were copied from."""
    source = [big_obs(i) for i in range(n)]
    cams = list(source[0]["images"])
    shape = source[0]["images"][cams[0]].shape
    buffer = client.lend_shared(len(cams) * n * int(np.prod(shape)))
    images = buffer.reshape(len(cams), n, *shape)
    for c, cam in enumerate(cams):
        for i, obs in enumerate(source):
            images[c, i] = obs["images"][cam]
    lent = [{**obs, "images": {cam: images[c, i] for c, cam in enumerate(cams)}} for i, obs in enumerate(source)]
    return buffer, lent, source


@pytest.mark.parametrize("columnar", [True, False])
def test_images_in_a_lent_buffer_travel_where_they_lie(client_bytes, columnar):
    """No copy on the client: a request whose images lie in a buffer the client lent references them there (one
    array per camera as columns, one per image as a list); no segment is leased for it, and the model is given
    the right images."""
    model = Keeper()
    with serving(model) as srv, PolicyClient(srv.url, shared_memory="on", columnar=columnar) as client:
        assert client.sends_columns is columnar
        buffer, lent, source = _lent_batch(client, 6)
        before = mine()
        client_bytes.clear()
        actions = client.infer_batch(lent, list(range(6)))
        assert mine() == before  # nothing was copied into a segment of the pool's
        assert sum(client_bytes) < 16384  # 1.3 MB of images did not go through the socket either
        assert [chunk[0, 0] for chunk in actions] == [checksum(o) for o in source]
        name = next(n for n in before if os.path.exists(f"/dev/shm/{n}") and
                    os.path.getsize(f"/dev/shm/{n}") >= buffer.nbytes)
        del lent
        client.give_back_shared(buffer)
        assert not os.path.exists(f"/dev/shm/{name}")  # unlinked at once; its memory goes with the buffer
        with pytest.raises(ValueError, match="did not lend"):
            client.give_back_shared(np.zeros(4, np.uint8))
    del buffer
    shm.SegmentCache().close()
    assert not shm._LENT


def test_an_array_only_partly_in_a_lent_buffer_is_copied():
    pool = shm.SegmentPool()
    try:
        buffer = pool.lend(1 << 20)
        inside = buffer[4096:4096 + 300_000]
        assert pool.lent_at(inside) == (pool.lent_at(buffer)[0], 4096)
        assert pool.lent_at(buffer[::2]) is None  # not in one piece
        assert pool.lent_at(np.zeros(1 << 17, np.uint8)) is None
        rows = shm.columns.Rows([buffer[k * 100_000:(k + 1) * 100_000] for k in (0, 1, 3)])  # a gap: two runs
        assert pool.lent_at(rows) is None
        with pool.lease({"a": rows, "b": inside}) as wire:
            assert wire["b"].segment == pool.lent_at(buffer)[0] and wire["b"].offset == 4096
            assert wire["a"].segment != wire["b"].segment  # copied into a leased segment
    finally:
        pool.close()
