"""`dojo bench served`: `dojo run` against a served zero policy, socket and shared memory, in one JSON line."""

from __future__ import annotations

import json
import subprocess
import sys
from contextlib import contextmanager

import pytest

from dojo.bench import served_bench
from dojo.bench.served_bench import steady_rates
from dojo.evaluation.evaluate import TimeSplit


def test_steady_rate_runs_between_the_first_and_last_episode_ends():
    events = [{"event": "progress", "elapsed_s": 1.0, "interactions": 10},
              {"event": "episode", "elapsed_s": 4.0, "interactions": 100},
              {"event": "episode", "elapsed_s": 6.0, "interactions": 300},
              {"event": "summary", "done": 2, "resumed": 0, "elapsed_s": 6.5, "interactions": 300,
               "interactions_per_s": 46.15}]
    rates = steady_rates(events)
    assert rates["steady_interactions_per_s"] == 100.0 and rates["first_episode_end_s"] == 4.0
    assert rates["episodes"] == 2 and rates["interactions_per_s"] == 46.15
    together = [events[1], {**events[1], "interactions": 150}, events[3]]  # one wave: no span to time
    assert steady_rates(together)["steady_interactions_per_s"] is None


def test_a_benchs_dojo_run_passes_its_messages_on_and_a_failure_points_at_them(capsys):
    """A bench's `dojo run` can take minutes before its first result on a GPU: its messages reach the bench's
    stderr as they come rather than when it ends, and a failed run raises saying so, its own message shown once."""
    from dojo.bench.ray_bench import dojo_run

    with pytest.raises(RuntimeError, match=r"exited with 1 \(its messages are above\)"):
        dojo_run(["tasks=[no_such_task]"])
    said = capsys.readouterr().err
    assert said.count("has no task 'no_such_task'") == 1 and said.startswith("dojo run: error: KeyError")


def test_time_split_adds_phases_and_leaves_the_rest():
    split = TimeSplit()
    with split.phase("policy"):
        pass
    with split.phase("policy"):
        pass
    line = split.line("mujoco")
    assert line.startswith("where the loop's ") and " on backend mujoco went: " in line and "policy 0.0 s" in line
    assert line.endswith("s")
    assert set(split.seconds) == {"policy"}


def test_both_modes_run_the_same_episodes_and_say_which_link_they_used(tmp_path):
    """160x160 images (75 KiB) are over the 64 KiB from which arrays go through shared memory."""
    horizons = tmp_path / "horizons.json"
    horizons.write_text(json.dumps({"format": "robodojo-horizons/1", "tasks": {"insert_tubes": {"demo_lengths": [8]}}}))
    done = subprocess.run(
        [sys.executable, "-m", "dojo.cli.main", "bench", "served", "width=160", "height=160", "backend=mujoco",
         "suite=robodojo_sim_mini", "tasks=[insert_tubes]", "episodes=4", "num_envs=2", f"horizons={horizons}",
         f"plans={tmp_path / 'plans'}"], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["benchmark"] == "served" and report["images"] == "3x160x160" and report["same_results"] is True
    off, on = report["runs"]["off"], report["runs"]["on"]
    assert "through the socket" in off["link"] and "through shared memory" in on["link"]
    assert all(f"{phase} " in off["time_split"] for phase in ("policy", "backend steps", "resets and records"))
    assert off["episodes"] == on["episodes"] == 4 and off["interactions"] == on["interactions"] > 0
    assert report["shared_over_socket"] > 0


def test_layouts_each_get_their_run_and_their_ratio(monkeypatch):
    """The runs a layout list makes, their keys and `columns_over_list` (each `dojo run` stood in for: the real
    one with columns is the test above, and `policy.columnar=false` reaching the client is test_policy_link's)."""
    asked = []

    @contextmanager
    def server(protocol, options=()):
        yield "ws://127.0.0.1:1"

    def run(overrides, url, mode, layout, store):
        asked.append((mode, layout))
        return {"shared_memory": mode, "layout": layout, "steady_interactions_per_s": 30.0 if layout == "columns"
                else 20.0, "rows": {"episode": (True, 1.0, 5, None)}}

    monkeypatch.setattr(served_bench, "spawned_server", server)
    monkeypatch.setattr(served_bench, "served_run", run)
    report = served_bench.bench_served(["backend=mujoco"], ["on"], ["head"], 32, 24, ["list", "columns"])
    assert asked == [("on", "list"), ("on", "columns")] and set(report["runs"]) == {"on_list", "on_columns"}
    assert report["columns_over_list"] == 1.5 and report["same_results"] and "shared_over_socket" not in report
    report = served_bench.bench_served([], ["off", "on"], ["head"], 32, 24)
    assert set(report["runs"]) == {"off", "on"} and report["shared_over_socket"] == 1.0


@pytest.mark.parametrize("argument", ["shared_memory=maybe", "layouts=rows"])
def test_bad_arguments_exit_2_with_the_usage(argument):
    done = subprocess.run([sys.executable, "-m", "dojo.cli.main", "bench", "served", argument],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "usage: dojo bench served" in done.stderr
