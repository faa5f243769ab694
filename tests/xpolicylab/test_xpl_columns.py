"""Columnar batches: gathering observations into columns and back, the rows a batched simulator rendered into one
buffer travelling without a copy, the server's checks, and the same actions as the list form end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
from websockets.sync.client import connect

from xpolicylab import codec, columns, shm
from xpolicylab.cli import bench_main
from xpolicylab.client import PolicyClient, batch_spans, column_entry_bytes, observation_bytes
from xpolicylab.embodiments import get_embodiment
from xpolicylab.errors import ErrorCode
from xpolicylab.model import Model, PolicyMetadata
from xpolicylab.observations import synthetic_batch
from xpolicylab.policies import ZeroPolicy
from xpolicylab.protocol import Frame, MessageType, decode_frame, encode_frame

from conftest import serving, small_obs

EMB = get_embodiment("arx_x5_bimanual")


def stacked_batch(n: int, width: int = 64, height: int = 48) -> list[dict]:
    """Observations whose images are rows of one array per camera, the instruction differing per environment."""
    obs_list = synthetic_batch(EMB, n, width=width, height=height, stacked=True)
    for i, obs in enumerate(obs_list):
        obs["instruction"] = f"task {i}" * (i + 1)
    return obs_list


def same(a, b) -> bool:
    """Deep equality of observations (arrays by value, shape and dtype)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b)
    return a == b


def test_gather_then_split_gives_back_every_observation():
    obs_list = stacked_batch(5)
    obs_list[2]["state"]["joint_pos"] = obs_list[2]["state"]["joint_pos"].copy()  # one row from elsewhere
    batch = columns.gather(obs_list)
    assert isinstance(batch["images"]["head"], columns.Rows) and batch["images"]["head"].shape == (5, 48, 64, 3)
    assert batch["instruction"] == [o["instruction"] for o in obs_list]  # strings: one entry per environment
    assert batch["meta"]["episode"] == [0, 1, 2, 3, 4]
    wire = columns.joined(batch)
    columns.check(wire, 5)
    back = columns.split(wire, 5)
    assert all(same(a, b) for a, b in zip(obs_list, back, strict=True))


def test_observations_of_other_layouts_are_not_columns():
    a, b = small_obs(seed=0), small_obs(seed=1)
    del b["meta"]["task"]
    assert columns.gather([a, b]) is None  # a key missing
    b = small_obs(seed=1)
    b["meta"]["spare"] = 1
    a["meta"]["other"] = 2
    assert columns.gather([a, b]) is None  # as many keys, other names
    b = small_obs(seed=1)
    b["state"] = [1.0, 2.0]
    assert columns.gather([a, small_obs(seed=2), b]) is None  # a map in some environments only
    c = small_obs(seed=2)
    c["images"]["head"] = c["images"]["head"][:10]  # another shape: a list column, not a stacked one
    batch = columns.gather([small_obs(seed=3), c])
    assert isinstance(batch["images"]["head"], list) and isinstance(batch["images"]["left_wrist"], columns.Rows)


def test_rows_of_one_buffer_travel_as_that_buffer(monkeypatch):
    monkeypatch.setattr(columns, "STACKED_ROW_BYTES", 0)  # rows this small are stacked otherwise (the test below)
    buffer = np.arange(6 * 4 * 3, dtype=np.uint8).reshape(6, 4, 3)
    rows = columns.Rows([buffer[i] for i in range(6)])
    (start, run), = rows.runs()
    assert start == 0 and np.shares_memory(run, buffer) and np.array_equal(run, buffer)
    assert np.shares_memory(rows.joined(), buffer)
    other = buffer.copy()
    mixed = columns.Rows([buffer[0], buffer[1], other[2], other[3], buffer[5], buffer[4]])
    runs = list(mixed.runs())
    assert [s for s, _ in runs] == [0, 2, 4, 5]  # two runs of two, then two rows out of order
    assert np.array_equal(mixed.joined(), np.stack(mixed.arrays))
    assert np.array_equal(columns.Rows([buffer[0]] * 3).joined(), np.stack([buffer[0]] * 3))  # one row, 3 times


def test_one_camera_of_a_batch_with_a_camera_axis_is_one_strided_run(monkeypatch):
    """A batched renderer's ``[B, cameras, H, W, 3]``: one camera's rows are a camera's size apart."""
    monkeypatch.setattr(columns, "STACKED_ROW_BYTES", 0)
    batch = np.random.default_rng(0).integers(0, 256, (5, 3, 4, 6, 3), dtype=np.uint8)
    rows = columns.Rows([batch[i, 1] for i in range(5)])
    (start, run), = rows.runs()
    assert start == 0 and np.shares_memory(run, batch) and np.array_equal(run, batch[:, 1])
    joined = rows.joined()
    assert joined.flags.c_contiguous and np.array_equal(joined, batch[:, 1])
    backwards = columns.Rows([batch[i, 1] for i in (4, 3, 2)])  # later rows first: no run
    assert len(list(backwards.runs())) == 3 and np.array_equal(backwards.joined(), batch[[4, 3, 2], 1])


def test_small_rows_are_stacked_into_one_run_whatever_their_addresses():
    state = np.arange(8 * 14, dtype=np.float32).reshape(8, 14)
    rows = columns.Rows([state[i] for i in (3, 1, 2, 0, 4, 5, 7, 6)])  # out of order: no run to find
    (start, run), = rows.runs()
    assert start == 0 and not np.shares_memory(run, state) and np.array_equal(run, state[[3, 1, 2, 0, 4, 5, 7, 6]])
    assert rows.runs() is rows.runs()  # found once


@pytest.mark.parametrize(("bad", "field", "words"), [
    ({"state": {"joint_pos": np.zeros((3, 14), np.float32)}}, "columns.state.joint_pos", "first axis"),
    ({"instruction": ["a", "b"]}, "columns.instruction", "holds 2 values for 4"),
    ({"step": 3}, "columns.step", "must be an array, a list or a map"),
    ({"step": np.float32(3)}, "columns.step", "must be an array, a list or a map"),
    ({"x": np.zeros((), np.float32)}, "columns.x", "first axis"),
])
def test_check_names_the_bad_column(bad, field, words):
    with pytest.raises(columns.ProtocolError) as err:
        columns.check(bad, 4)
    assert err.value.code is ErrorCode.INVALID_FRAME and err.value.details["field"] == field
    assert words in err.value.message


class Stacked(ZeroPolicy):
    """Takes columns as they come, and records the shapes of the images it was given."""

    def __init__(self) -> None:
        super().__init__({"chunk_size": 2})
        self.seen: list[tuple[int, ...]] = []

    def update_obs_columns(self, batch, env_ids):
        self.seen.append(batch["images"]["head"].shape)
        super().update_obs_columns(batch, env_ids)


@pytest.mark.parametrize("shared_memory", ["off", "on"])
def test_columns_and_list_give_the_same_actions(shared_memory):
    obs_list = stacked_batch(6, width=192, height=128)  # 73.7 kB images: past the shared-memory threshold
    model = Stacked()
    with serving(model) as srv:
        with PolicyClient(srv.url, shared_memory=shared_memory) as client:
            assert client.sends_columns
            by_columns = client.infer_batch(obs_list, [f"e{i}" for i in range(6)])
        with PolicyClient(srv.url, shared_memory=shared_memory, columnar=False) as client:
            assert not client.sends_columns
            by_list = client.infer_batch(obs_list, [f"e{i}" for i in range(6)])
    assert model.seen == [(6, 128, 192, 3)]  # one call, the images stacked; the list form never came here
    np.testing.assert_array_equal(by_columns, by_list)
    for obs, chunk in zip(obs_list, by_columns, strict=True):
        assert np.array_equal(chunk[0], obs["state"]["joint_pos"])


def test_default_model_gets_each_environment_from_the_columns():
    class Plain(Model):
        metadata = PolicyMetadata(name="plain", chunk_size=1)

        def update_obs(self, obs):
            self.obs = obs

        def get_action(self):
            return np.asarray(self.obs["state"]["joint_pos"])[None]

    obs_list = stacked_batch(3)
    model = Plain()
    model.update_obs_columns(columns.joined(columns.gather(obs_list)), ["a", "b", "c"])
    actions = model.get_action_batch(["a", "b", "c"])
    assert np.array_equal(actions[:, 0], np.stack([o["state"]["joint_pos"] for o in obs_list]))


def test_a_batch_over_the_frame_limit_goes_as_several_columnar_requests():
    obs_list = stacked_batch(8)
    model = Stacked()
    with serving(model, max_frame_mb=0.1) as srv, PolicyClient(srv.url, shared_memory="off") as client:
        actions = client.infer_batch(obs_list, list(range(8)))
        spans = batch_spans([observation_bytes(o) for o in obs_list], client.frame_budget())
    assert len(spans) > 1 and sorted(s[0] for s in model.seen) == sorted(b - a for a, b in spans)
    for obs, chunk in zip(obs_list, actions, strict=True):
        assert np.array_equal(chunk[0], obs["state"]["joint_pos"])


def test_entry_bytes_match_what_each_observation_takes():
    obs_list = stacked_batch(4, width=192, height=128)
    batch = columns.gather(obs_list)
    assert column_entry_bytes(batch, 4) == [observation_bytes(o) for o in obs_list]
    # Through shared memory an image column is one reference for the batch; the joint state (4 x 56 bytes) is
    # too small for one and stays in the frame.
    shared = column_entry_bytes(batch, 4, shared=True)
    assert shared == [observation_bytes(o) - 3 * 128 * 192 * 3 for o in obs_list]


def test_bad_columnar_requests_get_an_error_and_the_connection_keeps_working():
    good = {columns.KEY: columns.joined(columns.gather([small_obs(seed=i) for i in range(2)])), "env_ids": [0, 1]}
    cases = [
        ({**good, "env_ids": [0]}, "columns.instruction"),
        ({**good, "env_ids": []}, "env_ids"),
        ({**good, "env_ids": [0, 0]}, "env_ids"),
        ({**good, "observations": [small_obs()]}, "columns"),
        ({columns.KEY: [1, 2], "env_ids": [0, 1]}, "columns"),
    ]
    with serving(ZeroPolicy({"chunk_size": 2})) as srv, connect(srv.url, compression=None, max_size=None) as ws:
        for payload, field in cases:
            ws.send(b"".join(encode_frame(Frame(MessageType.INFER, payload, message_id=field))))
            reply = decode_frame(ws.recv())
            assert reply.message_type is MessageType.ERROR and reply.message_id == field
            assert reply.payload["code"] == "invalid_frame" and reply.payload["details"]["field"] == field
        ws.send(b"".join(encode_frame(Frame(MessageType.INFER, good))))
        reply = decode_frame(ws.recv())
        assert reply.message_type is MessageType.INFER_RESULT and reply.payload["actions"].shape == (2, 2, 14)


def test_rows_placed_in_shared_memory_arrive_whole(monkeypatch):
    """Runs of rows and single rows each copied into their place in the segment; big columns cut over threads."""
    monkeypatch.setattr(shm, "COPY_THREADS", 3)
    monkeypatch.setattr(shm, "BYTES_PER_COPY_THREAD", shm.THRESHOLD)
    obs_list = stacked_batch(9, width=192, height=128)
    rendered = np.random.default_rng(1).integers(0, 256, (9, 2, 128, 192, 3), dtype=np.uint8)
    for i, obs in enumerate(obs_list):  # one camera from a batch with a camera axis: a strided run
        obs["images"]["head"] = rendered[i, 1]
    for i in (3, 7):  # rows from elsewhere between runs
        obs_list[i]["images"] = {k: v.copy() + i for k, v in obs_list[i]["images"].items()}
    payload = {columns.KEY: columns.gather(obs_list), "env_ids": list(range(9))}
    pool, cache = shm.SegmentPool(), shm.SegmentCache()
    with pool.lease(payload) as wire:
        assert isinstance(wire[columns.KEY]["images"]["head"], codec.SharedArray)
        received = codec.decode(encode_frame(Frame(MessageType.INFER, wire)), shared_refs=True)["payload"]
        cache.resolve(received)
    cache.close()
    pool.close()
    for cam in obs_list[0]["images"]:
        got = received[columns.KEY]["images"][cam]
        assert not got.flags.writeable and np.array_equal(got, np.stack([o["images"][cam] for o in obs_list]))


def test_checker_checks_both_forms(zero_server):
    from xpolicylab.checker import CheckConfig, run_check

    report = run_check(CheckConfig(url=zero_server.url, cameras=("head",), width=64, height=48, n=2))
    assert report.passed, report.format()
    assert "infer_columns" in report.format() and "as columns" in report.format()


def test_bench_compares_the_layouts_in_one_run(capsys):
    assert bench_main(["batch=4", "width=64", "height=48", "n=2", "warmup=1", "single_n=2",
                       "protocols=[xpolicylab]", "layouts=[list,columns]"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["xpolicylab_list"]["columns"] is False and figures["xpolicylab_columns"]["columns"] is True
    assert bench_main(["layouts=[rows]"]) == 2


def test_copies_cut_over_threads_cover_every_row_once():
    """`_pieces` cuts a large array along its first axis so that threads share it; every byte lands once, in its
    place, whatever the array's strides; an empty array is nothing to copy."""
    source = np.random.default_rng(2).integers(0, 256, (10, 3, 8, 5), dtype=np.uint8)[:, 1]  # strided rows
    small = np.arange(7, dtype=np.uint8)
    segment = bytearray(source.nbytes + 64 + small.nbytes)
    jobs = [(memoryview(segment), 0, source, True), (memoryview(segment), 0, np.zeros((0, 4), np.uint8), True),
            (memoryview(segment), source.nbytes + 64, small, True)]
    groups = shm._pieces(jobs, 3)
    assert len(groups) == 3 and sum(p[2].nbytes for g in groups for p in g) == source.nbytes + small.nbytes
    for group in groups:
        shm._copy_group(group)
    got = np.frombuffer(segment, np.uint8)
    assert np.array_equal(got[:source.nbytes].reshape(source.shape), source)
    assert np.array_equal(got[source.nbytes + 64:], small)
