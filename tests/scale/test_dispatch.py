"""The Ray launcher's parts that need no cluster: the dispatcher's bookkeeping (pulls, reports, a dead worker's
episodes re-queued, every episode reported exactly once whatever the order of events), plans for workers on other
machines, one policy server per worker, worker resources."""

from __future__ import annotations

from pathlib import Path

import pytest

from dojo.launch.dispatch import EpisodeDispatcher, episode_key, longest_first
from dojo.evaluation.episode import EpisodeResult
from dojo.compiler.episodes import PlannedEpisode
from dojo.launch.ray_launcher import RayOptions, local_plan_paths, worker_count
from dojo.evaluation.policy_link import policy_config_for
from dojo.evaluation.run_dir import run_key


def item(i: int) -> PlannedEpisode:
    return PlannedEpisode(plan_path=Path(f"/plans/p{i}.json"), plan_hash=f"p{i}", task="stack_blocks",
                         dimension="generalization", setting="standard", eval_seed=0, episode=i, scene_seed=i)


def row(q: PlannedEpisode) -> EpisodeResult:
    return EpisodeResult(run_id="r", split="public", plan_hash=q.plan_hash, task=q.task, dimension=q.dimension,
                         setting=q.setting, eval_seed=q.eval_seed, episode=q.episode, scene_seed=q.scene_seed,
                         policy_name="zero", success=False, score=0.0, steps=10, wall_time_s=0.1)


def test_workers_pull_only_what_they_ask_and_the_run_ends_when_all_are_reported() -> None:
    d = EpisodeDispatcher([item(i) for i in range(5)])
    a, b = d.pull(0, 2), d.pull(1, 2)
    assert [q.episode for q in a + b] == [0, 1, 2, 3]
    assert d.left() == 5 and d.drain().queued == 1
    d.report([row(q) for q in a], interactions=20)
    drained = d.drain()
    assert [r.episode for r in drained.rows] == [0, 1] and drained.interactions == 20 and drained.left == 3
    assert d.drain().rows == []  # each row is handed to the driver once
    d.report([row(q) for q in b + d.pull(0, 5)])
    assert d.drain().left == 0


def test_a_dead_workers_unreported_episodes_go_to_the_others_first() -> None:
    d = EpisodeDispatcher([item(i) for i in range(4)])
    a, b = d.pull(0, 2), d.pull(1, 1)
    d.report([row(a[0])])
    assert d.requeue(0) == 1  # a[1] was pulled and not reported; a[0] is done
    assert d.pull(0, 4) == []  # a dead worker gets nothing more
    assert [q.episode for q in d.pull(1, 4)] == [1, 3]  # the re-queued episode before the never-pulled one
    d.report([row(q) for q in [b[0], item(1), item(3)]])
    assert sorted(r.episode for r in d.drain().rows) == [0, 1, 2, 3] and d.left() == 0


@pytest.mark.parametrize("pulled_again", [False, True])
def test_a_late_report_of_a_requeued_episode_counts_once(pulled_again: bool) -> None:
    d = EpisodeDispatcher([item(0), item(1)])
    (lost,) = d.pull(0, 1)
    d.requeue(0)  # the worker was declared dead, but its last report was on its way
    if pulled_again:
        assert d.pull(1, 1) == [lost]
    d.report([row(lost)])  # the late report: accepted, the episode did end
    d.report([row(lost)])  # the same episode reported again (by the worker that pulled it again)
    rows = d.drain().rows
    assert [episode_key(q) for q in [lost]] == [(r.plan_hash, r.eval_seed, r.episode) for r in rows]
    assert [q.episode for q in d.pull(1, 2)] == [1]  # not queued twice
    assert d.left() == 1


def test_the_longest_episodes_are_handed_out_first() -> None:
    items = [item(i) for i in range(4)]
    ordered = longest_first(items, {"p0": 300, "p1": 2200, "p2": 300, "p3": 700})
    assert [q.episode for q in ordered] == [1, 3, 0, 2]  # equals keep their queue order


def test_policy_url_list_gives_each_worker_its_server() -> None:
    cfg = {"name": "remote", "url": ["ws://a:1", "ws://b:2"], "protocol": "xpolicylab"}
    assert [policy_config_for(cfg, i)["url"] for i in range(3)] == ["ws://a:1", "ws://b:2", "ws://a:1"]
    assert policy_config_for({"name": "remote", "url": "ws://a:1"}, 5)["url"] == "ws://a:1"
    with pytest.raises(ValueError, match="empty list"):
        policy_config_for({"name": "remote", "url": []}, 0)


def test_workers_on_another_machine_get_the_plans_from_the_driver(tmp_path: Path) -> None:
    seen = tmp_path / "seen.json"
    seen.write_text("{}")
    fetched: list[int] = []

    def fetch() -> dict[str, bytes]:
        fetched.append(1)
        return {"a": b"{}", "b": b'{"b": 1}'}

    paths = {"a": str(seen), "b": str(tmp_path / "driver-only" / "b.json")}
    local = local_plan_paths(paths, fetch, tmp_path / "cache")
    assert local["a"] == str(seen)  # visible here (one machine, a shared file system): used as it is
    assert Path(local["b"]).read_bytes() == b'{"b": 1}' and Path(local["b"]).parent == tmp_path / "cache"
    assert local_plan_paths({"a": str(seen)}, fetch, tmp_path / "cache") == {"a": str(seen)}
    assert fetched == [1]  # fetched only when a plan was missing


def test_worker_options() -> None:
    assert RayOptions.of({"name": "ray"}, "mjx").gpus_per_worker == 1
    assert RayOptions.of({"name": "ray", "gpus_per_worker": 0}, "mjx").gpus_per_worker == 0
    options = RayOptions.of({"name": "ray", "cpus_per_worker": 2}, "mujoco")
    assert options.gpus_per_worker == 0 and options.backend_settings({"name": "mujoco", "threads": 0})["threads"] == 2
    assert options.backend_settings({"name": "mujoco", "threads": 3})["threads"] == 3
    assert "threads" not in options.backend_settings({"name": "mjx", "impl": "auto"})


def test_worker_count_fits_the_cluster() -> None:
    cpus = RayOptions.of({"name": "ray"}, "mujoco")
    assert worker_count(cpus, {"CPU": 16.0}, episodes=22) == 16
    assert worker_count(cpus, {"CPU": 16.0}, episodes=3) == 3  # never more workers than episodes
    gpus = RayOptions.of({"name": "ray"}, "mjx")
    assert worker_count(gpus, {"CPU": 64.0, "GPU": 4.0}, episodes=100) == 4  # one GPU each
    with pytest.raises(ValueError, match="GPU"):  # MJX on a cluster without GPUs would wait forever
        worker_count(gpus, {"CPU": 2.0}, episodes=10)
    assert worker_count(RayOptions(workers=8), {"CPU": 2.0}, episodes=10) == 8  # asked for: waits for resources


def test_where_a_run_executes_is_not_part_of_its_folder() -> None:
    assert run_key(["launcher=ray", "launcher.workers=4", "launcher.address=auto"]) == "default"
