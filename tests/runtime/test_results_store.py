"""The results store: round trip, idempotent writes, resume keys, read-only readers, and SIGKILL mid-run."""

from __future__ import annotations

import json
import signal
import sqlite3
import subprocess
import sys
import textwrap
from contextlib import closing

import pytest

from dojo.evaluation.episode import EpisodeKey, EpisodeResult
from dojo.evaluation.results_store import STORE_FILENAME, ResultsStore, StoreError, resolve_store_path


def test_round_trip_keeps_every_field(tmp_path, make_row):
    row = make_row(success=True, score=87.5, stage_times={"grasp": 12, "place": None},
                   policy_meta={"checkpoint": "c", "chunk": 8, "nested": {"a": [1, 2]}},
                   failure_reason=None, video_path="videos/ep0.mp4")
    other = make_row(episode=1, failure_reason="timeout", dimension="memory", task="swap_T")
    with ResultsStore(tmp_path / "r.sqlite") as store:
        assert store.add(row) and store.add(other)
        assert sorted(store.rows(), key=lambda r: r.episode) == [row, other]
        assert store.run_ids() == ["run-a"]


def test_same_key_is_written_once_and_first_row_wins(tmp_path, make_row):
    first = make_row(success=True, score=100.0)
    again = make_row(success=False, score=0.0)  # same run, plan hash, eval seed and episode index
    with ResultsStore(tmp_path / "r.sqlite") as store:
        assert store.add(first) is True
        assert store.add(again) is False
        assert store.rows() == [first]
        assert store.add(make_row(eval_seed=1)) is True  # another seed is another episode
        assert store.count("run-a") == 2


def test_finished_keys_are_per_run(tmp_path, make_row):
    with ResultsStore(tmp_path / "r.sqlite") as store:
        store.add(make_row(plan_hash="h1", episode=3, eval_seed=2))
        store.add(make_row(run_id="run-b", plan_hash="h2"))
        assert store.finished("run-a") == {EpisodeKey("h1", 2, 3)}
        assert store.finished("run-b") == {EpisodeKey("h2", 0, 0)}
        assert store.finished("run-c") == set()


def test_ensure_run_accepts_the_same_settings_and_refuses_others(tmp_path):
    with ResultsStore(tmp_path / "r.sqlite") as store:
        assert store.ensure_run("run-a", {"suite": "robodojo", "seeds": [0, 1, 2]}) is True
        assert store.ensure_run("run-a", {"seeds": [0, 1, 2], "suite": "robodojo"}) is False
        with pytest.raises(StoreError, match="different settings"):
            store.ensure_run("run-a", {"suite": "other"})
        assert store.run_meta("run-a") == {"suite": "robodojo", "seeds": [0, 1, 2]}
        assert store.run_ids() == ["run-a"]


def test_reader_sees_commits_while_the_writer_is_open(tmp_path, make_row):
    path = tmp_path / "r.sqlite"
    writer = ResultsStore(path)
    writer.add(make_row(episode=0))
    reader = ResultsStore(path, readonly=True)
    assert reader.count() == 1
    writer.add(make_row(episode=1))
    assert reader.count() == 2
    with pytest.raises(StoreError, match="read-only"):
        reader.add(make_row(episode=2))
    reader.close()
    writer.close()


def test_opening_bad_paths_fails_clearly(tmp_path):
    with pytest.raises(StoreError, match="no results store"):
        ResultsStore(tmp_path / "missing.sqlite", readonly=True)
    assert not (tmp_path / "missing.sqlite").exists()
    garbage = tmp_path / "garbage.sqlite"
    garbage.write_bytes(b"this is not a database" * 100)
    with pytest.raises(StoreError, match="not a usable"):
        ResultsStore(garbage, readonly=True)
    other = tmp_path / "other.sqlite"
    with closing(sqlite3.connect(other)) as con:
        con.execute("CREATE TABLE t (x)")
    with pytest.raises(StoreError, match="not a RoboDojo results store"):
        ResultsStore(other, readonly=True)
    with pytest.raises(StoreError, match="not a RoboDojo results store"):
        ResultsStore(other)  # a writer does not add its tables to an unrelated database either
    with closing(sqlite3.connect(other)) as con:
        assert [r[0] for r in con.execute("SELECT name FROM sqlite_master")] == ["t"]


def test_resolve_store_path_accepts_a_run_folder(tmp_path):
    run = tmp_path / "run1"
    ResultsStore(run / STORE_FILENAME).close()
    assert resolve_store_path(run) == run / STORE_FILENAME
    assert resolve_store_path(run / STORE_FILENAME) == run / STORE_FILENAME
    with pytest.raises(StoreError, match="run folder"):
        resolve_store_path(tmp_path / "nowhere")


# A stand-in for `dojo run`: skips finished episodes, "runs" the others, records each as it ends and only then
# prints "<index> <inserted>". Results are a pure function of the episode index, like a deterministic policy.
_WRITER = textwrap.dedent("""
    import sys, time
    from dojo.evaluation.episode import EpisodeResult
    from dojo.evaluation.results_store import ResultsStore

    def result(i):
        return EpisodeResult(
            run_id="run-k", split="hidden" if i % 7 == 0 else "public", plan_hash=f"plan-{i % 10}",
            task=f"task_{i % 10}", dimension="precision", setting="standard", eval_seed=i // 20, episode=i,
            scene_seed=1000 + i, policy_name="p", success=i % 3 == 0, score=float(i % 101),
            steps=i, wall_time_s=0.5 * i, stage_times={"s": i if i % 2 else None}, policy_meta={"v": 1},
            failure_reason=None if i % 3 == 0 else "timeout", video_path=None)

    path, total = sys.argv[1], int(sys.argv[2])
    store = ResultsStore(path)
    store.ensure_run("run-k", {"suite": "demo", "episodes": total})
    done = store.finished("run-k")
    for i in range(total):
        row = result(i)
        if row.key in done:
            continue
        time.sleep(0.002)  # the episode itself
        inserted = store.add(row)
        print(i, inserted, flush=True)
    store.close()
    if len(sys.argv) > 3:  # also print what an uninterrupted run would have recorded
        import json
        print(json.dumps([result(i).to_dict() for i in range(total)]))
""")


def test_sigkill_mid_run_loses_and_repeats_nothing(tmp_path):
    script = tmp_path / "writer.py"
    script.write_text(_WRITER)
    store_path = tmp_path / "run" / STORE_FILENAME
    total = 120
    reported: list[int] = []

    def start(*extra: str) -> subprocess.Popen[str]:
        return subprocess.Popen([sys.executable, str(script), str(store_path), str(total), *extra],
                                stdout=subprocess.PIPE, text=True)

    for kill_after in (7, 25, 30):  # three crashes, each after some more episodes were reported as recorded
        with start() as proc:
            assert proc.stdout is not None
            seen = 0
            for line in proc.stdout:  # ends early if the writer exits by itself
                index, inserted = line.split()
                assert inserted == "True", f"episode {index} was executed again after it had been recorded"
                reported.append(int(index))
                seen += 1
                if seen == kill_after:
                    proc.send_signal(signal.SIGKILL)
                    break
            proc.wait(timeout=60)
        assert proc.returncode == -signal.SIGKILL
        with ResultsStore(store_path, readonly=True) as reader:
            stored = {r.episode for r in reader.rows()}
        assert set(reported) <= stored, "an episode reported as recorded was lost"

    with start("dump") as final:
        out, _ = final.communicate(timeout=60)
    assert final.returncode == 0
    *lines, dump = out.strip().splitlines()
    for line in lines:
        index, inserted = line.split()
        assert inserted == "True"
        reported.append(int(index))
    assert len(reported) == len(set(reported)), "an episode was executed twice"

    expected = sorted((EpisodeResult(**d) for d in json.loads(dump)), key=lambda r: r.episode)
    with ResultsStore(store_path, readonly=True) as reader:
        rows = sorted(reader.rows(), key=lambda r: r.episode)
        assert reader.count() == total
    assert rows == expected  # the same results as an uninterrupted run


def test_add_many_is_one_transaction_and_idempotent(tmp_path, make_row):
    batch = [make_row(episode=i) for i in range(5)]
    with ResultsStore(tmp_path / "r.sqlite") as store:
        assert store.add_many(batch[:3]) == 3
        assert store.add_many(batch) == 2  # the first three are already recorded
        assert store.count() == 5
        broken = make_row(episode=11)
        object.__setattr__(broken, "run_id", None)  # bypass validation to make the database refuse this row
        with pytest.raises(sqlite3.IntegrityError):  # and the whole batch is rolled back
            store.add_many([make_row(episode=10), broken])
        assert store.count() == 5


def test_add_many_keeps_each_rows_values_when_rows_share_objects(tmp_path, make_row):
    """A run's rows share one policy metadata dict (encoded once per batch); other values are each row's own."""
    meta = {"checkpoint": "c", "chunk": 8}
    stages = {"grasp": 3, "place": None}
    batch = [make_row(episode=i, policy_meta=meta, stage_times=stages if i % 2 else {"grasp": i, "place": 7})
             for i in range(4)]
    batch.append(make_row(episode=1, policy_meta={"other": 1}))  # a key twice in one batch: the first row wins
    with ResultsStore(tmp_path / "r.sqlite") as store:
        assert store.add_many(batch) == 4
        stored = sorted(store.rows(), key=lambda r: r.episode)
    assert stored == batch[:4]
    assert [r.stage_times["grasp"] for r in stored] == [0, 3, 2, 3] and stored[1].policy_meta == meta
