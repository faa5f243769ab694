"""The loop addresses the policy by `env_id_base + slot`: loops that share one policy server (a launcher's workers)
give it disjoint ids (tests/scale/test_ray_launcher.py runs that on a real cluster)."""

from __future__ import annotations

from pathlib import Path

from dojo.backends.registry import BackendOptions, make_backend
from dojo.compiler.spec_library import SpecLibrary
from dojo.compiler.suite_compile import compile_suite
from dojo.evaluation.evaluate import evaluate
from dojo.evaluation.policy_link import open_policy
from dojo.evaluation.progress import Progress
from dojo.evaluation.results_store import ResultsStore

PACK = Path(__file__).resolve().parents[1] / "recording" / "pack"


def test_the_policy_sees_each_slot_under_the_base_plus_its_index(tmp_path: Path) -> None:
    library = SpecLibrary.load([PACK], strict=False)
    queue = list(compile_suite(library, library.get("suite", "short_suite"), tmp_path / "plans").episodes)
    link = open_policy({"name": "zero", "url": None, "chunk_size": 4}, "arx_x5_bimanual")
    reset, asked = [], []
    link.reset = lambda ids, reset_=link.reset: reset.extend(ids) or reset_(ids)
    link.act = lambda obs, ids, act=link.act: asked.extend(ids) or act(obs, ids)
    factory = lambda: make_backend("mujoco", BackendOptions(settings={"threads": 1}, action_modes=("joint",)))
    with ResultsStore(":memory:") as store:
        assert evaluate(queue, factory, link, store, "run", num_envs=1, progress=Progress(len(queue), mode="quiet"),
                        env_id_base=7) == 2
    assert reset == [7, 7] and set(asked) == {7}  # one slot, refilled once: two episodes, both as environment 7
