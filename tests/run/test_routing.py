"""A plan goes to a backend that can run what it requires, and the run says so: never a silent fallback."""

from __future__ import annotations

from pathlib import Path

import pytest

from dojo.backends.registry import available, unsupported_features
from dojo.compiler.episodes import PlannedEpisode
from dojo.evaluation.routing import Unroutable, route


def _episode(task: str, index: int) -> PlannedEpisode:
    return PlannedEpisode(plan_path=Path(f"/plans/{task}-{index}.json"), plan_hash=f"{task}{index}", task=task,
                         dimension="precision", setting="standard", eval_seed=0, episode=index, scene_seed=index)


NEEDS = {"stack": ["contact:box-box"], "cloth": ["contact:box-plane", "flex"], "conveyor": ["actors"]}


def _requires(item: PlannedEpisode) -> list[str]:
    return NEEDS[item.task]


def test_every_backend_answers_which_features_it_cannot_run():
    assert set(available()) >= {"mujoco", "mjx", "real"}
    assert unsupported_features("mujoco", ["flex", "actors", "contact:box-cylinder"], {}) == {}
    mjx = unsupported_features("mjx", ["flex", "actors", "contact:box-cylinder", "contact:box-mesh"], {})
    assert set(mjx) == {"flex", "actors", "contact:box-cylinder"}  # MJX collides box with mesh, not cylinder
    assert "cylinder" in mjx["contact:box-cylinder"]
    assert set(unsupported_features("real", ["flex", "actors", "events", "contact:box-box"], {})) == {"actors",
                                                                                                       "events"}
    with pytest.raises(ValueError, match="unknown backend"):
        unsupported_features("isaac", ["flex"], {})


def test_plans_a_backend_lacks_go_to_the_reference_backend_with_a_reason():
    queue = [_episode("stack", 0), _episode("cloth", 0), _episode("stack", 1), _episode("cloth", 1)]
    routes, detours = route(queue, "mjx", {"impl": "jax"}, requires=_requires)
    assert [(r.backend, [e.plan_hash for e in r.episodes]) for r in routes] == [
        ("mjx", ["stack0", "stack1"]), ("mujoco", ["cloth0", "cloth1"])]
    assert routes[0].settings == {"impl": "jax"}
    [detour] = detours
    assert (detour.task, detour.episodes, detour.backend, detour.to) == ("cloth", 2, "mjx", "mujoco")
    assert detour.message().startswith("cloth: 2 episodes run on backend mujoco, not mjx (flex: MJX does not")


def test_a_backend_that_runs_everything_keeps_every_episode():
    queue = [_episode(t, 0) for t in NEEDS]
    routes, detours = route(queue, "mujoco", {"threads": 1}, requires=_requires)
    assert detours == [] and [r.backend for r in routes] == ["mujoco"] and routes[0].episodes == queue


def test_a_plan_no_backend_can_run_stops_the_run_before_it_starts():
    with pytest.raises(Unroutable, match="conveyor .*actors: a robot's world has no scripted actors"):
        route([_episode("conveyor", 0)], "real", {}, fallback="real", requires=_requires)


def test_routing_reads_the_plan_files(tmp_path):
    path = tmp_path / "p.json"
    path.write_text('{"requires": ["flex"], "model_xml": "<mujoco/>"}')
    item = PlannedEpisode(plan_path=path, plan_hash="h", task="cloth", dimension="precision", setting="standard",
                         eval_seed=0, episode=0, scene_seed=0)
    routes, detours = route([item], "mjx", {})
    assert [r.backend for r in routes] == ["mujoco"] and detours[0].reasons.keys() == {"flex"}
