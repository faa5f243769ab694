"""The loop reads a step's observations only where the policy will look next (a slot whose action chunk ran out),
or all of them when it records every step: a batched backend builds each observation when it is read
(`dojo.backends.mjx.observations`), so what the loop does not read costs nothing."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dojo.backends.registry import BackendOptions, make_backend
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.suite_compile import compile_suite
from dojo.evaluation.evaluate import evaluate
from dojo.evaluation.policy_link import open_policy
from dojo.evaluation.progress import Progress
from dojo.evaluation.results_store import ResultsStore

PACK = Path(__file__).resolve().parents[1] / "recording" / "pack"


class _Counted(Sequence):
    """A step's observations that note which positions were read."""

    def __init__(self, obs: Sequence[dict], reads: list[int]) -> None:
        self._obs, self._reads = obs, reads

    def __len__(self) -> int:
        return len(self._obs)

    def __getitem__(self, at: Any) -> Any:
        self._reads.append(at)
        return self._obs[at]


class _Watched:
    """A real backend whose steps say which observations were asked for (`observe`) and which were read."""

    def __init__(self, backend: Any, log: list[tuple[list[int], list[int], list[int]]]) -> None:
        self._backend, self._log = backend, log

    def __getattr__(self, name: str) -> Any:
        return getattr(self._backend, name)

    def step(self, actions: Any, env_ids: Any = None, mode: str = "joint", observe: Any = None) -> Any:
        result = self._backend.step(actions, env_ids, mode=mode, observe=observe)
        reads: list[int] = []
        self._log.append((list(env_ids), list(observe), reads))
        return dataclasses.replace(result, obs=_Counted(result.obs, reads))


def _run(tmp_path: Path, chunk: int) -> tuple[list, list[dict]]:
    library = SpecLibrary.load([PACK], strict=False)
    queue = list(compile_suite(library, library.get("suite", "short_suite"), tmp_path / "plans").episodes)
    link = open_policy({"name": "zero", "url": None, "chunk_size": chunk}, "arx_x5_bimanual")
    asked: list[dict] = []
    link.act = lambda obs, ids, act=link.act: asked.extend(obs) or act(obs, ids)
    log: list = []
    factory = lambda: _Watched(make_backend("mujoco", BackendOptions(settings={"threads": 1},
                                                                     action_modes=("joint",))), log)
    with ResultsStore(":memory:") as store:
        assert evaluate(queue, factory, link, store, "run", num_envs=2, progress=Progress(len(queue), mode="quiet")) == 2
    return log, asked


def test_only_the_observations_the_policy_will_see_are_read(tmp_path: Path) -> None:
    log, asked = _run(tmp_path, chunk=4)
    assert len(log) >= 5
    for ids, observe, reads in log:
        assert sorted(ids[k] for k in reads) == sorted(observe)  # each asked-for one read once, nothing else
    assert any(not observe for _, observe, _ in log) and any(observe for _, observe, _ in log)
    # the policy is asked at the start and then every 4th step, with that step's observation
    assert sorted(o["meta"]["step"] for o in asked) == [0, 0, 4, 4]
