"""The progress display in JSON-lines, quiet and rich modes, with a fake clock (no timing assumptions)."""

from __future__ import annotations

import io
import json

import pytest

from dojo.evaluation.progress import FLUSH_S, HEARTBEAT_S, RATE_WINDOW_S, Progress


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_jsonl_lines_and_summary(make_row):
    clock, out = FakeClock(), io.StringIO()
    progress = Progress(4, mode="jsonl", stream=out, clock=clock)
    clock.now += 10
    progress.interactions(250)
    progress.episode_finished(make_row(dimension="memory", task="swap_T", success=True, score=100.0))
    clock.now += 10
    progress.interactions(250)
    progress.episode_finished(make_row(dimension="memory", task="swap_T", episode=1))
    progress.close()
    progress.close()  # a second close writes nothing more
    lines = [json.loads(line) for line in out.getvalue().splitlines()]
    assert [line["event"] for line in lines] == ["progress", "episode", "progress", "episode", "summary"]
    first, second, summary = [line for line in lines if line["event"] != "progress"]
    assert first["done"] == 1 and first["total"] == 4
    assert first["eta_s"] == pytest.approx(30.0)  # 10 s per episode, 3 to go
    assert first["interactions_per_s"] == pytest.approx(25.0)
    assert first["episode"]["task"] == "swap_T" and first["episode"]["success"] is True
    assert second["success_by_dimension"] == {"memory": {"successes": 1, "episodes": 2, "success_pct": 50.0}}
    assert second["eta_s"] == pytest.approx(20.0)
    assert summary["done"] == 2 and summary["interactions"] == 500


class Flushes(io.StringIO):
    """A stream that counts its flushes and the lines written by each."""

    def __init__(self) -> None:
        super().__init__()
        self.flushed: list[int] = []

    def flush(self) -> None:
        self.flushed.append(self.getvalue().count("\n"))


def test_episode_lines_that_end_together_are_flushed_together(make_row):
    """A batch ends thousands of episodes at once: their lines go out in one flush, at most `FLUSH_S` late, and at
    the next step or the end at the latest."""
    clock, out = FakeClock(), Flushes()
    progress = Progress(10, mode="jsonl", stream=out, clock=clock)
    for k in range(3):
        progress.episode_finished(make_row(episode=k))
    assert out.getvalue().count("\n") == 3 and out.flushed == []  # written, not yet flushed
    progress.interactions(8)  # the next step
    assert out.flushed == [3]
    progress.episode_finished(make_row(episode=3))
    clock.now += FLUSH_S
    progress.episode_finished(make_row(episode=4))  # FLUSH_S after the last flush: both go out
    assert out.flushed == [3, 5]
    progress.episode_finished(make_row(episode=5))
    progress.close()
    assert out.flushed[-1] == 7  # the sixth episode and the summary


def test_the_recent_speed_leaves_start_up_out_and_falls_when_the_run_stalls():
    clock, out = FakeClock(), io.StringIO()
    progress = Progress(4, mode="jsonl", stream=out, clock=clock)
    clock.now += 300  # compiling
    progress.interactions(100)
    assert progress.snapshot()["recent_interactions_per_s"] is None  # one step: no speed yet
    for _ in range(5):
        clock.now += 2
        progress.interactions(100)
    snap = progress.snapshot()
    assert snap["recent_interactions_per_s"] == pytest.approx(50.0)  # 500 in the 10 s after the first step
    assert snap["interactions_per_s"] == pytest.approx(600 / 310, abs=0.01)  # start-up included
    clock.now += 10  # nothing stepped since: the recent speed counts the wait
    assert progress.snapshot()["recent_interactions_per_s"] == pytest.approx(25.0)
    clock.now += RATE_WINDOW_S
    assert progress.snapshot()["recent_interactions_per_s"] is None


def test_jsonl_says_how_a_run_goes_while_no_episode_ends():
    clock, out = FakeClock(), io.StringIO()
    progress = Progress(8, mode="jsonl", stream=out, clock=clock)
    for _ in range(30):  # 30 s of steps, every batch of environments mid-episode
        clock.now += 1
        progress.interactions(64)
    lines = [json.loads(line) for line in out.getvalue().splitlines()]
    assert [line["event"] for line in lines] == ["progress"] * int(30 // HEARTBEAT_S)
    assert lines[-1]["interactions"] == 64 * 30 and lines[-1]["recent_interactions_per_s"] == pytest.approx(64.0)


def test_resumed_episodes_count_towards_done_but_not_speed(make_row):
    clock, out = FakeClock(), io.StringIO()
    resumed = [make_row(dimension="precision", task="insert_key", episode=i, success=i == 0) for i in range(6)]
    progress = Progress(10, mode="jsonl", stream=out, clock=clock, finished=resumed)
    clock.now += 5
    progress.episode_finished(make_row(dimension="open", task="align_blocks", episode=6, success=True))
    progress.close()
    line = json.loads(out.getvalue().splitlines()[0])
    assert line["done"] == 7 and line["resumed"] == 6
    assert line["eta_s"] == pytest.approx(15.0)  # 5 s for the one new episode, 3 to go
    assert line["success_by_dimension"]["precision"]["success_pct"] == pytest.approx(100 / 6, abs=0.01)
    assert list(line["success_by_dimension"]) == ["precision", "open"]  # leaderboard order


def test_training_only_episodes_are_shown_after_the_scored_dimensions(make_row):
    """`dojo collect` of a DLC task: its successes are counted and drawn, after the five scored dimensions."""
    clock, out = FakeClock(), io.StringIO()
    progress = Progress(3, mode="rich", stream=out, clock=clock)
    clock.now += 2
    progress.episode_finished(make_row(dimension="dlc", task="dlc", success=True))
    progress.episode_finished(make_row(dimension="memory", task="swap_T", episode=1))
    progress.close()
    assert list(progress.snapshot()["success_by_dimension"]) == ["memory", "dlc"]
    assert "DLC (training only) 100.0% (1/1)" in out.getvalue()


def test_quiet_mode_writes_nothing(make_row):
    out = io.StringIO()
    with Progress(2, mode="quiet", stream=out) as progress:
        progress.interactions(10)
        progress.episode_finished(make_row())
        assert progress.snapshot()["done"] == 1
    assert out.getvalue() == ""


def test_rich_mode_draws_counts_and_dimensions(make_row):
    clock, out = FakeClock(), io.StringIO()
    progress = Progress(3, mode="rich", stream=out, clock=clock)
    clock.now += 4
    progress.interactions(40)
    progress.episode_finished(make_row(dimension="long_horizon", task="make_kong", success=True))
    progress.close()
    text = out.getvalue()
    assert "1/3" in text
    assert "Long-Horizon 100.0% (1/1)" in text
    assert "interactions/s" in text
    assert text.endswith("\n"), "in a log file, what is written next starts on a line of its own"


def test_bad_arguments_are_rejected():
    with pytest.raises(ValueError):
        Progress(3, mode="fancy")
    with pytest.raises(ValueError):
        Progress(3, mode="quiet").interactions(-1)


def test_a_resumed_run_with_nothing_left_shows_no_rate(make_row):
    """A resumed run used to print '0.0 interactions/s': it stepped nothing, so it has no rate to show."""
    clock, out = FakeClock(), io.StringIO()
    done = [make_row(episode=i) for i in range(2)]
    progress = Progress(2, mode="rich", finished=done, stream=out, clock=clock)
    clock.now += 3
    progress.close()
    assert "resumed: 2 already recorded, nothing to run" in out.getvalue()
    assert "0.0 interactions/s" not in out.getvalue()
    assert progress.snapshot()["interactions_per_s"] is None
