"""`dojo report`: score one or more runs and write a JSON report and a self-contained HTML page.

Several runs make a leaderboard: rows are grouped into entries by policy name, each entry is scored with
`scoring.score_episodes` (public rows) and checked with `verification.verify` (public vs hidden rows).
Real-robot trials (backend `real`) are not scored by the robot but by raters: they are left out of the
leaderboard and shown beside it with the raters' verdicts, read from the same stores by `dojo.realeval.scores`
(settled trials' success rate and score per policy and task, the trials flagged for adjudication, appeals).

The page itself is rendered by `html_page` (charts by `svg_charts`). Hidden verification layouts stay
private: the JSON and the page give only the hidden split's aggregate counts, never its plan hashes, videos
or per-episode data, so a report can be published without revealing the private seed set.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import sqlite3
import sys
from collections import Counter, defaultdict
from collections.abc import Collection, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from dojo.compiler.taxonomy import Taxonomy, builtin_taxonomy
from dojo.evaluation.episode import EpisodeResult
from dojo.evaluation.policy_link import PRIVILEGED_NOTE, is_privileged
from dojo.report.html_page import is_url, render_html
from dojo.evaluation.results_store import STORE_FILENAME, ResultsStore, StoreError, store_paths
from dojo.evaluation.run_dir import results_root
from dojo.realeval.ratings import DISAGREEMENT, RATERS_PER_TRIAL
from dojo.realeval.scores import REAL_BACKEND, JudgedTrial, judged_trials, task_scores
from dojo.report.scoring import STD_DDOF, score_episodes
from dojo.evaluation.verification import ALPHA, verify

REPORT_FORMAT = "robodojo-report/1"
HISTOGRAM_BINS = 10  # score distribution bins of width 10 over 0-100


class ReportError(Exception):
    """The report cannot be produced from what was given (shown to the user without a traceback)."""


# ---------------------------------------------------------------------------------------------------------
# Loading and building the report data
# ---------------------------------------------------------------------------------------------------------

def load_rows(sources: Sequence[str | Path], run_ids: Collection[str] | None = None) -> list[EpisodeResult]:
    """Read the episodes of every source (a .sqlite store, a run folder or a folder of runs), optionally only some
    run ids.

    Relative video paths are resolved against their store's folder, so links work wherever the report is
    written. The same episode named twice (the same store given twice) is kept once.
    """
    rows: dict[tuple[str, str, int, int], EpisodeResult] = {}
    for path in (p for source in sources for p in store_paths(source)):
        with ResultsStore(path, readonly=True) as store:
            for row in store.rows():
                if run_ids is not None and row.run_id not in run_ids:
                    continue
                if row.video_path and not is_url(row.video_path) and not os.path.isabs(row.video_path):
                    row = replace(row, video_path=str((path.parent / row.video_path).resolve()))
                rows.setdefault((row.run_id, *row.key), row)
    return list(rows.values())


def load_real_trials(sources: Sequence[str | Path], run_ids: Collection[str] | None = None) -> list[JudgedTrial]:
    """The real trials of every source with their raters' verdicts and appeals (each store read with its own
    ratings), optionally only some run ids; the same trial named twice is kept once."""
    trials: dict[tuple[str, str, int, int], JudgedTrial] = {}
    for path in (p for source in sources for p in store_paths(source)):
        for trial in judged_trials(path):
            if run_ids is None or trial.row.run_id in run_ids:
                trials.setdefault((trial.row.run_id, *trial.row.key), trial)
    return list(trials.values())


def real_section(trials: Sequence[JudgedTrial]) -> dict[str, Any]:
    """The report's real-robot part: verdicts by policy and task, the flagged trials and the appeals."""
    def where(t: JudgedTrial) -> dict[str, Any]:
        return {"policy": t.row.policy_name, "task": t.row.task, "run_id": t.row.run_id,
                "eval_seed": t.row.eval_seed, "episode": t.row.episode}

    ordered = sorted(trials, key=lambda t: (t.row.policy_name, t.row.task, t.row.run_id, *t.row.key))
    return {
        "tasks": [vars(s) for s in task_scores(ordered)],
        "flagged": [{**where(t), "reason": t.verdict.reason, "raters": [r.rater for r in t.verdict.ratings]}
                    for t in ordered if t.verdict.flagged],
        "appeals": [{**where(t), "reason": a["reason"], "outcome": a["outcome"], "filed_at": a["filed_at"]}
                    for t in ordered for a in t.appeals],
    }


def build_report(rows: Sequence[EpisodeResult], sources: Sequence[str | Path] = (),
                 taxonomy: Taxonomy | None = None, real_trials: Sequence[JudgedTrial] = ()) -> dict[str, Any]:
    """The report as plain data: one entry per policy, sorted into a leaderboard by overall score, over the scored
    dimensions of `taxonomy` (RoboDojo's when None), from the simulation rows; the real trials (`real_trials`,
    judged by raters) beside it."""
    taxonomy = taxonomy or builtin_taxonomy()
    by_policy: dict[str, list[EpisodeResult]] = defaultdict(list)
    for row in rows:
        if row.backend != REAL_BACKEND:  # a robot reports no score: raters give it (`real_trials`)
            by_policy[row.policy_name].append(row)
    entries = []
    for policy, policy_rows in by_policy.items():
        public = [r for r in policy_rows if r.split == "public"]
        if not public:
            entries.append(_entry_without_public(policy, policy_rows))
            continue
        scores = score_episodes(public, taxonomy=taxonomy)
        meta = _policy_meta(policy_rows)
        entries.append({
            "policy": policy,
            "policy_meta": meta,
            "privileged": any(is_privileged(m) for m in meta.values()),
            "runs": sorted({r.run_id for r in policy_rows}),
            "public_episodes": len(public),
            "hidden_episodes": len(policy_rows) - len(public),
            "scores": scores.to_dict(),
            "verification": verify(policy_rows).to_dict(),
            "plan_hashes": _plan_hashes(public),
            "score_histograms": _histograms(public, taxonomy),
            "failure_reasons": _failure_reasons(public),
            "unmet_conditions": _unmet_terms(public),
            "videos": [
                {"task": r.task, "setting": r.setting, "run_id": r.run_id, "eval_seed": r.eval_seed,
                 "episode": r.episode, "success": r.success, "score": r.score, "path": r.video_path}
                for r in public if r.video_path
            ],
        })
    entries.sort(key=_leaderboard_order)
    return {
        "format": REPORT_FORMAT,
        "generated_at": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "sources": [str(s) for s in sources],
        "method": {
            "task": "success rate (% of episodes) and mean score (0-100) per task",
            "dimension": "mean over the dimension's tasks",
            "overall": "mean of the dimension means (not of tasks); partial when a dimension has no tasks",
            "std": f"sample standard deviation (ddof={STD_DDOF}) over seed replicates (run id, eval seed)",
            "relative_drop": "(standard - random) / standard of the Generalization means",
            "verification": f"public vs hidden success: pooled two-proportion z-test, two-sided, alpha={ALPHA}; "
                            "Fisher exact test when an expected cell count is below 5",
            "real": f"real-robot trials are scored by {RATERS_PER_TRIAL} raters from their videos; a trial is settled "
                    f"(mean score, their common success mark) unless the scores differ by more than "
                    f"{DISAGREEMENT:.0f} points or they split on success, which flags it for adjudication; success "
                    "rate and score are over the settled trials",
        },
        "notes": _comparability_notes(entries),
        "dimensions": [{"id": d, "label": taxonomy.label(d)} for d in taxonomy.scored],
        "entries": entries,
        "real": real_section(real_trials),
    }


def _comparability_notes(entries: list[dict[str, Any]]) -> list[str]:
    """Warnings that leaderboard rows are not like for like: plans are content-addressed, so entries scored on
    different plan hashes were not shown the same scenes."""
    plan_sets = {json.dumps(e["plan_hashes"], sort_keys=True) for e in entries if e["scores"] is not None}
    if len(plan_sets) > 1:
        return ["The entries were not evaluated on the same public plans (different tasks, suite versions or "
                "layouts): compare their numbers with care."]
    return []


def _leaderboard_order(entry: dict[str, Any]) -> tuple[int, float, str]:
    """Complete entries by overall score, then partial ones (not comparable), then privileged references (they
    read the simulator state: shown for scale, never ranked), then those with nothing scored."""
    scores = entry["scores"]
    if scores is None:
        return (3, 0.0, entry["policy"])
    group = 2 if entry["privileged"] else int(scores["partial"])
    return (group, -scores["overall"]["score"]["mean"], entry["policy"])


def _entry_without_public(policy: str, rows: list[EpisodeResult]) -> dict[str, Any]:
    meta = _policy_meta(rows)
    return {"policy": policy, "policy_meta": meta, "privileged": any(is_privileged(m) for m in meta.values()),
            "runs": sorted({r.run_id for r in rows}),
            "public_episodes": 0, "hidden_episodes": len(rows), "scores": None,
            "verification": verify(rows).to_dict(), "plan_hashes": {}, "score_histograms": {},
            "failure_reasons": {}, "videos": []}


def _policy_meta(rows: Sequence[EpisodeResult]) -> dict[str, dict[str, Any]]:
    """Per run, the metadata the policy server reported (runs of one entry may be different checkpoints)."""
    meta: dict[str, dict[str, Any]] = {}
    for r in rows:
        meta.setdefault(r.run_id, r.policy_meta)
    return dict(sorted(meta.items()))


def _plan_hashes(rows: Sequence[EpisodeResult]) -> dict[str, list[str]]:
    hashes: dict[str, set[str]] = defaultdict(set)
    for r in rows:
        hashes[r.task].add(r.plan_hash)
    return {task: sorted(hashes[task]) for task in sorted(hashes)}


def _histograms(rows: Sequence[EpisodeResult], taxonomy: Taxonomy) -> dict[str, list[int]]:
    """Per dimension, episode counts in score bins [0,10), [10,20), ..., [90,100]."""
    hist: dict[str, list[int]] = {}
    for r in rows:
        bins = hist.setdefault(r.dimension, [0] * HISTOGRAM_BINS)
        bins[min(int(r.score // (100 / HISTOGRAM_BINS)), HISTOGRAM_BINS - 1)] += 1
    return {d: hist[d] for d in taxonomy.ids if d in hist}


def _failure_reasons(rows: Sequence[EpisodeResult]) -> dict[str, dict[str, int]]:
    reasons: dict[str, Counter[str]] = defaultdict(Counter)
    for r in rows:
        if not r.success:
            reasons[r.task][r.failure_reason or "unspecified"] += 1
    return {t: dict(c.most_common()) for t, c in sorted(reasons.items())}


def _unmet_terms(rows: Sequence[EpisodeResult]) -> dict[str, dict[str, int]]:
    """Per task, how many failed episodes ended with each success condition unmet (where the backend said)."""
    unmet: dict[str, Counter[str]] = defaultdict(Counter)
    for r in rows:
        if not r.success:
            unmet[r.task].update(term for term, holds in r.success_terms.items() if not holds)
    return {t: dict(c.most_common()) for t, c in sorted(unmet.items()) if c}


def write_report(
    sources: Sequence[str | Path], out_json: str | Path, out_html: str | Path, *,
    run_ids: Collection[str] | None = None, taxonomy: Taxonomy | None = None,
) -> dict[str, Any]:
    """Load the runs, score them, and write both files. Returns the report data."""
    rows = load_rows(sources, run_ids)
    if not rows:
        which = "" if run_ids is None else f" for run ids {sorted(run_ids)}"
        raise ReportError(f"no episodes found in {', '.join(map(str, sources))}{which}")
    report = build_report(rows, sources, taxonomy, load_real_trials(sources, run_ids))
    out_json, out_html = Path(out_json), Path(out_html)
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_html.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(report, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    out_html.write_text(render_html(report, html_dir=out_html.parent), encoding="utf-8")
    return report


# ---------------------------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------------------------

class _ArgumentError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # report usage errors to the caller instead of exiting
        raise _ArgumentError(message)


def _parser() -> _Parser:
    parser = _Parser(
        prog="dojo report",
        description="Score finished runs and write report.json and a self-contained report.html. "
                    "Several runs (or runs of several policies) make a leaderboard, one row per policy.",
        epilog=f"RUN is a results store (.sqlite), a run folder containing {STORE_FILENAME}, or a folder of runs\n"
               f"(every {STORE_FILENAME} below it: outputs/<suite>/<policy> holds each run of that policy).\n\n"
               "example:\n  dojo report outputs/robodojo_sim_mini/zero outputs/robodojo_sim_mini/random\n"
               f"  -> {results_root() / 'report'}/report.json and report.html",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("runs", nargs="+", metavar="RUN", help="results store, run folder or folder of runs")
    parser.add_argument("--out", "-o", metavar="DIR", default=str(results_root() / "report"),
                        help=f"output folder (also accepted as out=DIR; default: {results_root() / 'report'})")
    parser.add_argument("--run-id", action="append", metavar="ID", dest="run_ids",
                        help="only these run ids (repeatable; default: every run in the stores)")
    return parser


def report_main(args: list[str]) -> int:
    """Entry point for `dojo report RUN... [out=DIR]`. Returns the exit status; never raises on bad input."""
    args = [f"--out={a[4:]}" if a.startswith("out=") else a for a in args]
    parser = _parser()
    try:
        ns = parser.parse_args(args)
    except _ArgumentError as exc:
        print(f"dojo report: {exc}\n{parser.format_usage().rstrip()}\n(see: dojo report --help)", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help
        return int(exc.code or 0)
    out = Path(ns.out)
    try:
        report = write_report(ns.runs, out / "report.json", out / "report.html",
                              run_ids=None if ns.run_ids is None else set(ns.run_ids))
    except StoreError as exc:
        print(f"dojo report: {exc}", file=sys.stderr)
        return 2
    except (ReportError, sqlite3.Error, OSError, ValueError) as exc:
        print(f"dojo report: {exc}", file=sys.stderr)
        return 1
    for entry in report["entries"]:
        if entry["scores"] is None:
            print(f"{entry['policy']}: no public episodes ({entry['verification']['verdict']})")
            continue
        overall = entry["scores"]["overall"]
        partial = " (partial)" if entry["scores"]["partial"] else ""
        privileged = f" [{PRIVILEGED_NOTE}]" if entry["privileged"] else ""
        print(f"{entry['policy']}: score {_plain(overall['score'])}, success {_plain(overall['success'])}%"
              f"{partial}, {entry['verification']['verdict']}{privileged}")
    for real in report["real"]["tasks"]:
        judged = "no settled trial" if real["settled"] == 0 else \
            f"success {real['success_rate']:.1f}%, score {real['score']:.1f} over {real['settled']} settled"
        print(f"{real['policy']} on {real['task']} (real): {judged} of {real['trials']} trials, {real['flagged']} "
              f"flagged, {real['appeals']} appeal(s)")
    runs = sum(len(e["runs"]) for e in report["entries"])
    print(f"wrote {out / 'report.json'} and {out / 'report.html'} ({runs} run(s) of {len(report['entries'])} "
          "policies)")
    return 0


def _plain(stat: dict[str, Any]) -> str:
    return f"{stat['mean']:.2f}" + ("" if stat["std"] is None else f" ± {stat['std']:.2f}")
