"""A policy served on this host through shared memory lends the run's backend the buffers its camera images go
into (`Backend.use_image_buffers`): images a batched backend copies off the GPU there reach the server without
another copy (the GPU path itself: `tests/backends_mjx/test_host_copy.py` and the device's `-m gpu` runs)."""

from __future__ import annotations

from pathlib import Path

import pytest

from dojo.backends.mujoco.backend import MujocoBackend
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.suite_compile import compile_suite
from dojo.evaluation.evaluate import evaluate
from dojo.evaluation.policy_link import open_policy
from dojo.evaluation.progress import Progress
from dojo.evaluation.results_store import ResultsStore
from xpolicylab.policies import ZeroPolicy
from xpolicylab.server import ServerConfig, ServerThread

PACK = Path(__file__).resolve().parents[1] / "recording" / "pack"


class _Lent(MujocoBackend):
    """The CPU backend, keeping what it was lent (it copies no images off a device, so it uses none of it)."""

    lent: list = []

    def use_image_buffers(self, buffers) -> None:
        _Lent.lent.append(buffers)


@pytest.fixture(scope="module")
def queue(tmp_path_factory):
    library = SpecLibrary.load([PACK], strict=False)
    return list(compile_suite(library, library.get("suite", "short_suite"),
                              tmp_path_factory.mktemp("plans")).episodes)


def _run(queue, link) -> None:
    _Lent.lent = []
    with ResultsStore(":memory:") as store:
        evaluate(queue, lambda: _Lent(num_threads=1, cameras=("head",), width=32, height=24), link, store, "run",
                 num_envs=1, progress=Progress(len(queue), mode="quiet"))


@pytest.mark.parametrize("shared_memory", ["on", "off"])
def test_a_served_policy_lends_its_shared_memory_for_images(queue, shared_memory):
    model = ZeroPolicy({"chunk_size": 4, "cameras": ["head"], "width": 32, "height": 24})
    with ServerThread(model, ServerConfig(port=0, host="127.0.0.1")) as srv:
        link = open_policy({"url": srv.url, "shared_memory": shared_memory}, "arx_x5_bimanual")
        try:
            _run(queue, link)
            if shared_memory == "off":
                assert _Lent.lent == []  # nothing to lend through a socket
                return
            (buffers,) = _Lent.lent
            buffer = buffers.lend(1 << 20)
            pool = link.client._client._pool()
            assert pool.lent_at(buffer[4096:8192]) == (pool.lent_at(buffer)[0], 4096)  # sent where it lies
            buffers.give_back(buffer)
        finally:
            link.close()


def test_a_policy_in_this_process_or_without_cameras_is_lent_nothing(queue):
    _run(queue, open_policy({"name": "zero", "url": None, "chunk_size": 4, "cameras": ["head"]}, "arx_x5_bimanual"))
    assert _Lent.lent == []
    with ServerThread(ZeroPolicy({"chunk_size": 4, "cameras": []}), ServerConfig(port=0, host="127.0.0.1")) as srv:
        link = open_policy({"url": srv.url, "shared_memory": "on"}, "arx_x5_bimanual")
        try:
            _run(queue, link)
        finally:
            link.close()
    assert _Lent.lent == []  # it asks for no images
