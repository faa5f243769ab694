"""The report's HTML page: one self-contained file (inline CSS, inline SVG, no script, nothing fetched).

Safety, because the data may come from untrusted task packs and policy servers: every string from the data is
HTML-escaped; a Content-Security-Policy forbids scripts and every external load, so even a missed escape could
neither run code nor phone home; video links are only relative/file paths or http(s) URLs.
"""

from __future__ import annotations

import html
import json
import os
import re
import urllib.parse
from collections import defaultdict
from pathlib import Path
from typing import Any

from dojo.evaluation.policy_link import PRIVILEGED_NOTE
from dojo.report.svg_charts import dimension_chart, histogram_chart, percent, standard_random_chart
from dojo.report.scoring import report_dimensions
from dojo.evaluation.verification import NOT_EVALUATED

_CSS = """
:root { --fg:#1d2330; --muted:#5b6474; --line:#dde1e8; --bg:#ffffff; --head:#f3f5f8; --accent:#3b6fb6; }
* { box-sizing: border-box; }
body { font: 14px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; color: var(--fg);
       background: var(--bg); margin: 0 auto; padding: 24px 32px 64px; max-width: 1320px; }
h1 { font-size: 24px; margin: 0 0 4px; } h3 { font-size: 16px; margin: 22px 0 8px; }
h2 { font-size: 19px; margin: 36px 0 10px; border-bottom: 2px solid var(--line); padding-bottom: 4px; }
.muted { color: var(--muted); } .small { font-size: 12px; }
table { border-collapse: collapse; margin: 8px 0 16px; width: 100%; }
th, td { border-bottom: 1px solid var(--line); padding: 6px 10px; text-align: right; vertical-align: top; }
th { background: var(--head); font-weight: 600; white-space: nowrap; }
th:first-child, td:first-child, td.l, th.l { text-align: left; }
td.num { font-variant-numeric: tabular-nums; white-space: nowrap; }
.pm { color: var(--muted); font-size: 12px; }
.badge { display: inline-block; padding: 1px 8px; border-radius: 10px; font-size: 12px; font-weight: 600; }
.b-verified { background: #dff3e4; color: #1e6b35; } .b-unverified { background: #fbe0dd; color: #9b2218; }
.b-not_evaluated { background: #eceef2; color: #5b6474; } .b-partial { background: #fff1d6; color: #8a5a00; }
.b-privileged { background: #f3e8ff; color: #5b2a86; }
.charts { display: flex; flex-wrap: wrap; gap: 18px; }
figure { margin: 0; } figcaption { font-weight: 600; margin-bottom: 4px; }
svg text { font-family: system-ui, sans-serif; }
details { margin: 6px 0 12px; } summary { cursor: pointer; color: var(--accent); }
code, .hash { font-family: ui-monospace, Menlo, Consolas, monospace; font-size: 12px; word-break: break-all; }
ul.notes, .warn { color: #8a5a00; margin: 4px 0 12px; }
.entry { border-top: 1px solid var(--line); margin-top: 28px; }
table.compact { width: auto; min-width: 420px; }
.leaderboard .score { font-weight: 600; } .leaderboard .succ { color: #3a4150; }
.leaderboard td { padding: 8px 10px; }
"""

_CSP = "default-src 'none'; style-src 'unsafe-inline'; img-src data:"


def _e(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _fmt_stat(stat: dict[str, Any], is_percent: bool) -> str:
    unit = "%" if is_percent else ""
    std = "" if stat["std"] is None else f' <span class="pm">± {stat["std"]:.2f}</span>'
    return f'{stat["mean"]:.2f}{unit}{std}'


def _cell(metrics: dict[str, Any] | None) -> str:
    """A leaderboard cell as in the paper (score over success rate), each with its std over seeds."""
    if metrics is None:
        return '<td class="num muted">—</td>'
    return (f'<td class="num"><div class="score">{_fmt_stat(metrics["score"], False)}</div>'
            f'<div class="succ">{_fmt_stat(metrics["success"], True)}</div></td>')


def render_html(report: dict[str, Any], html_dir: Path | None = None) -> str:
    """The whole page as one string (no external resources)."""
    entries = report["entries"]
    dims = report_dimensions(report)
    scored = [e for e in entries if e["scores"] is not None]
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f'<meta http-equiv="Content-Security-Policy" content="{_e(_CSP)}">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        "<title>RoboDojo report</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>RoboDojo evaluation report</h1>",
        f'<p class="muted">Generated {_e(report["generated_at"])} from '
        f'{", ".join(f"<code>{_e(s)}</code>" for s in report["sources"]) or "rows given directly"}.</p>',
        '<h2 id="leaderboard">Leaderboard</h2>',
        "".join(f'<p class="warn">{_e(n)}</p>' for n in report["notes"]),
        _leaderboard_table(entries, dims),
        '<p class="muted small">Each cell: score (top) and success rate (bottom), mean <span class="pm">± std</span> '
        "over seed replicates. Average = mean of the dimension means. Partial entries lack a dimension and "
        "are not ranked; privileged references (the scripted <code>oracle</code>) read the simulator state, show "
        "that the tasks are solvable and are not ranked either.</p>",
        _real_section(report.get("real")),
    ]
    if scored:
        parts += ['<h2 id="plots">Plots</h2>', '<div class="charts">',
                  _figure("Score by dimension", dimension_chart(scored, "score", dims)),
                  _figure("Success rate by dimension (%)", dimension_chart(scored, "success", dims)),
                  ]
        gen = [e for e in scored if e["scores"]["generalization"] is not None]
        if gen:
            parts.append(_figure("Generalization: standard vs random score", standard_random_chart(gen)))
        parts.append("</div>")
        parts.append("<h3>Score distributions (public episodes, share of episodes per score bin)</h3>")
        parts += [_figure(e["policy"], histogram_chart(e["score_histograms"], dims)) for e in scored]
    parts += [_entry_section(i, e, html_dir, dims) for i, e in enumerate(entries)]
    parts.append(_method_section(report["method"]))
    parts.append("</body></html>")
    return "\n".join(parts)


def _leaderboard_table(entries: list[dict[str, Any]], dims: dict[str, str]) -> str:
    head = "".join(f"<th>{_e(label)}</th>" for label in dims.values())
    rows = []
    for index, entry in enumerate(entries):
        scores = entry["scores"]
        policy = f'<a href="#entry-{index}">{_e(entry["policy"])}</a>'
        badges = _verdict_badge(entry["verification"])
        if scores is None:
            rows.append(f'<tr><td class="num">—</td><td class="l">{policy} {badges}</td>'
                        + '<td class="num muted">—</td>' * (len(dims) + 1) + "</tr>")
            continue
        if scores["partial"]:
            badges += ' <span class="badge b-partial" title="missing dimensions: '
            badges += _e(", ".join(dims.get(d, d) for d in scores["missing_dimensions"])) + '">partial</span>'
        if entry.get("privileged"):
            badges += f' <span class="badge b-privileged" title="{_e(PRIVILEGED_NOTE)}">{_e(PRIVILEGED_NOTE)}</span>'
        cells = "".join(_cell(scores["dimensions"].get(d, {}).get("metrics")) for d in dims)
        rank = "—" if scores["partial"] or entry.get("privileged") else str(index + 1)
        rows.append(f'<tr><td class="num">{rank}</td><td class="l">{policy} {badges}</td>{cells}'
                    f'{_cell(scores["overall"])}</tr>')
    return (f'<table class="leaderboard"><thead><tr><th>#</th><th class="l">Policy</th>{head}'
            f"<th><i>Average</i></th></tr></thead><tbody>{''.join(rows)}</tbody></table>")


def _real_section(real: dict[str, Any] | None) -> str:
    """Real-robot trials beside the simulation leaderboard: the raters' verdicts, flagged trials, appeals."""
    if not real or not real["tasks"]:
        return ""

    def num(value: float | None) -> str:
        return "—" if value is None else f"{value:.1f}"

    def trial(t: dict[str, Any]) -> list[str]:
        return [_e(t["policy"]), _e(t["task"]), f'<code>{_e(t["run_id"])}</code>', f'{t["eval_seed"]}/{t["episode"]}']

    rows = [[_e(t["policy"]), _e(t["task"]), str(t["trials"]), str(t["settled"]), str(t["flagged"]), str(t["open"]),
             num(t["success_rate"]) + ("" if t["success_rate"] is None else "%"), num(t["score"]), str(t["appeals"])]
            for t in real["tasks"]]
    out = ['<h2 id="real">Real robots (RealEval): raters\' verdicts</h2>',
           _table(["Policy", "Task", "Trials", "Settled", "Flagged", "Open", "Success", "Score", "Appeals"], rows,
                  "llnnnnnnn", cls="real"),
           '<p class="muted small">Scored by three raters from each trial\'s videos, blind to the policy. Success '
           "and score are over the settled trials; flagged trials await adjudication; open ones lack ratings.</p>"]
    if real["flagged"]:
        flagged = [trial(t) + [_e(t["reason"]), _e(", ".join(t["raters"]))] for t in real["flagged"]]
        out.append("<h3>Flagged for adjudication</h3>" + _table(
            ["Policy", "Task", "Run", "Seed/trial", "Why", "Raters"], flagged, "lllnll", cls="flagged"))
    if real["appeals"]:
        appeals = [trial(a) + [_e(a["reason"]), _e(a["outcome"] or "pending"), _e(a["filed_at"])]
                   for a in real["appeals"]]
        out.append("<h3>Appeals</h3>" + _table(
            ["Policy", "Task", "Run", "Seed/trial", "Reason", "Outcome", "Filed"], appeals, "lllnlll", cls="appeals"))
    return "\n".join(out)


def _verdict_badge(verification: dict[str, Any]) -> str:
    verdict = verification["verdict"]
    label = {"verified": "verified", "unverified": "unverified", "not_evaluated": "no hidden set"}[verdict]
    return f'<span class="badge b-{_e(verdict)}" title="{_e(verification["reason"])}">{label}</span>'


def _table(headers: list[str], rows: list[list[str]], align: str, *, cls: str = "") -> str:
    """A table; `align` has one letter per column: `l` text (left-aligned), `n` number. Cells are HTML."""
    kinds = {"l": "l", "n": "num"}

    def cells(tag: str, values: list[str]) -> str:
        return "".join(f'<{tag} class="{kinds[a]}">{v}</{tag}>' for a, v in zip(align, values, strict=True))

    body = "".join(f"<tr>{cells('td', row)}</tr>" for row in rows)
    return f'<table class="{cls}"><thead><tr>{cells("th", headers)}</tr></thead><tbody>{body}</tbody></table>'


def _entry_section(index: int, entry: dict[str, Any], html_dir: Path | None, dims: dict[str, str]) -> str:
    scores = entry["scores"]
    runs = ", ".join(f"<code>{_e(r)}</code>" for r in entry["runs"])
    out = [f'<section class="entry" id="entry-{index}">',
           f'<h2>{_e(entry["policy"])} {_verdict_badge(entry["verification"])}</h2>',
           (f'<p class="warn">{_e(entry["policy"])} is a {_e(PRIVILEGED_NOTE)}: it plays each task\'s scripted '
            "expert from the simulator state, which no submitted policy is given.</p>"
            if entry.get("privileged") else ""),
           f'<p class="muted">Runs: {runs}; {entry["public_episodes"]} public and {entry["hidden_episodes"]} '
           "hidden episodes.</p>"]
    if any(entry["policy_meta"].values()):
        meta = json.dumps(entry["policy_meta"], indent=2, sort_keys=True)
        out.append(f"<details><summary>Policy metadata (per run)</summary><pre><code>{_e(meta)}</code></pre></details>")
    out.append(_verification_block(entry["verification"]))
    if scores is None:
        out.append('<p class="muted">No public episodes: nothing to score.</p></section>')
        return "\n".join(out)
    reps = ", ".join(f"{_e(run)}/seed {_e(seed)}" for run, seed in scores["replicates"])
    out.append(f'<p class="small muted">Seed replicates ({len(scores["replicates"])}): {reps}</p>')
    notes = list(scores["notes"])
    if scores["partial"]:
        missing = ", ".join(dims.get(d, d) for d in scores["missing_dimensions"])
        notes.insert(0, f"partial: no tasks of {missing}; the average covers the other dimensions only")
    if notes:
        out.append('<ul class="notes">' + "".join(f"<li>{_e(n)}</li>" for n in notes) + "</ul>")
    gen = scores["generalization"]
    if gen is not None:
        rows = [[setting, _fmt_stat(gen[setting]["score"], False), _fmt_stat(gen[setting]["success"], True)]
                for setting in ("standard", "random")]
        rows.append(["relative drop", percent(gen["relative_drop_score"]), percent(gen["relative_drop_success"])])
        out.append("<h3>Generalization: standard vs random</h3>"
                   + _table(["Setting", "Score", "Success"], rows, "lnn", cls="compact"))
    out.append(_task_table(entry, dims))
    out.append(_videos_block(entry, html_dir))
    hashes = [[_e(task), "<br>".join(_e(h) for h in plan_hashes)] for task, plan_hashes in entry["plan_hashes"].items()]
    out.append("<details><summary>Plan hashes (public)</summary>"
               + _table(["Task", "Plans"], hashes, "ll", cls="hashes") + "</details></section>")
    return "\n".join(out)


def _verification_block(v: dict[str, Any]) -> str:
    if v["verdict"] == NOT_EVALUATED:
        return f'<p><b>Hidden-layout verification:</b> not evaluated ({_e(v["reason"])}).</p>'
    return (f'<p><b>Hidden-layout verification:</b> {_e(v["verdict"])}: {_e(v["reason"])}. '
            f'<span class="muted">{_e(v["test"]["test"])}, alpha = {_e(v["alpha"])}.</span></p>')


def _task_table(entry: dict[str, Any], dims: dict[str, str]) -> str:
    rows = []
    for task in entry["scores"]["tasks"]:
        settings = task["settings"]
        split = "—"
        if "standard" in settings and "random" in settings:
            split = f'{settings["standard"]["score"]["mean"]:.2f} / {settings["random"]["score"]["mean"]:.2f}'
        reasons = list(entry["failure_reasons"].get(task["task"], {}).items())[:3]
        top = "; ".join(f"{_e(reason)} ×{count}" for reason, count in reasons) or "—"
        unmet = list(entry.get("unmet_conditions", {}).get(task["task"], {}).items())[:3]
        conditions = "; ".join(f"<code>{_e(term)}</code> ×{count}" for term, count in unmet) or "—"
        rows.append([_e(task["task"]), _e(dims.get(task["dimension"], task["dimension"])), str(task["episodes"]),
                     _fmt_stat(task["metrics"]["score"], False), _fmt_stat(task["metrics"]["success"], True), split,
                     f'<span class="small">{top}</span>', f'<span class="small">{conditions}</span>'])
    headers = ["Task", "Dimension", "Episodes", "Score", "Success", "Standard / random score", "Top failure reasons",
               "Success conditions unmet"]
    return "<h3>Tasks</h3>" + _table(headers, rows, "llnnnnll")


def _videos_block(entry: dict[str, Any], html_dir: Path | None) -> str:
    videos = entry["videos"]
    if not videos:
        return '<p class="muted small">No episode videos recorded.</p>'
    by_task: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for v in videos:
        by_task[v["task"]].append(v)
    items = []
    for task, task_videos in sorted(by_task.items()):
        links = []
        for v in task_videos:
            outcome = "✓" if v["success"] else "✗"
            label = _e(f'{v["setting"]} · seed {v["eval_seed"]} · ep {v["episode"]} · {outcome} {v["score"]:.0f}')
            href = _video_href(v["path"], html_dir)
            links.append(f'<a href="{_e(href)}">{label}</a>' if href else f"<span>{label} ({_e(v['path'])})</span>")
        items.append(f'<li><b>{_e(task)}</b>: {" · ".join(links)}</li>')
    return f"<details><summary>Episode videos ({len(videos)})</summary><ul>{''.join(items)}</ul></details>"


_SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9+.\-]*):")


def is_url(path: str) -> bool:
    """Whether a video path is a URL (has a scheme) rather than a file path."""
    return bool(_SCHEME.match(path)) and not re.match(r"^[A-Za-z]:[\\/]", path)  # not a Windows drive letter


def _video_href(path: str, html_dir: Path | None) -> str | None:
    """A link target that can only be a file or an http(s) URL (never javascript:, data:, ...)."""
    if is_url(path):
        return path if _SCHEME.match(path).group(1).lower() in ("http", "https") else None
    if html_dir is not None and os.path.isabs(path):
        path = os.path.relpath(path, html_dir)
    return urllib.parse.quote(Path(path).as_posix(), safe="/._-~")


def _method_section(method: dict[str, str]) -> str:
    items = "".join(f"<li><b>{_e(k)}</b>: {_e(v)}</li>" for k, v in method.items())
    return f'<h2 id="method">Method</h2><ul class="small">{items}</ul>'


def _figure(caption: str, svg: str) -> str:
    return f"<figure><figcaption>{_e(caption)}</figcaption>{svg}</figure>"
