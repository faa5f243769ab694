"""The backend agreement report: episode-by-episode success agreement of two results stores."""

from __future__ import annotations

from pathlib import Path

from dojo.bench.backend_agreement import compare, main, overall
from dojo.evaluation.results_store import ResultsStore


def _store(path: Path, make_row, outcomes: dict[tuple[str, int], tuple[bool, float]], run_id: str) -> Path:
    with ResultsStore(path) as store:
        store.ensure_run(run_id, {"backend": path.stem})
        store.add_many([make_row(run_id=run_id, task=task, episode=ep, success=ok, score=score)
                        for (task, ep), (ok, score) in outcomes.items()])
    return path


def test_agreement_counts_only_shared_episodes_per_task(tmp_path, make_row, capsys):
    a = {("stack_bowls", e): (True, 100.0) for e in range(50)} | {("push_t", 0): (True, 100.0)}
    b = {("stack_bowls", e): (e != 7, 100.0 if e != 7 else 50.0) for e in range(50)} | {("push_t", 1): (True, 100.0)}
    cpu = _store(tmp_path / "cpu.sqlite", make_row, a, "run-cpu")
    mjx = _store(tmp_path / "mjx.sqlite", make_row, b, "run-mjx")
    with ResultsStore(cpu, readonly=True) as sa, ResultsStore(mjx, readonly=True) as sb:
        rows = compare({r.key: r for r in sa.rows()}, {r.key: r for r in sb.rows()})
    assert [(r.task, r.episodes, r.same_success, r.success_a, r.success_b) for r in rows] == [
        ("stack_bowls", 50, 49, 50, 49)]
    assert rows[0].mean_abs_score_diff == 1.0 and overall(rows) == 0.98
    assert main([str(cpu), str(mjx)]) == 0  # 98% meets the bar
    assert "stack_bowls" in capsys.readouterr().out
    assert main([str(cpu), str(mjx), "--min-agreement", "0.99"]) == 1


def test_stores_without_shared_episodes_fail(tmp_path, make_row, capsys):
    cpu = _store(tmp_path / "cpu.sqlite", make_row, {("push_t", 0): (True, 100.0)}, "run-cpu")
    mjx = _store(tmp_path / "mjx.sqlite", make_row, {("push_t", 1): (True, 100.0)}, "run-mjx")
    assert main([str(cpu), str(mjx)]) == 1
    assert "share no episode" in capsys.readouterr().err
