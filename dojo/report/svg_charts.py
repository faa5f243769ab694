"""Inline SVG charts for the HTML report: grouped bars with error bars, and score histograms.

Plain SVG strings, no plotting library and no script, so that the page stays self-contained and renders the same
offline. Every label is HTML-escaped (policy and task names may come from untrusted packs); full names that do
not fit are cut and kept in a native `<title>` tooltip.
"""

from __future__ import annotations

import html
from typing import Any


_LEGEND_COLUMNS = 3
_PALETTE = ("#3b6fb6", "#e07b39", "#3a9a5b", "#c0392b", "#8e6bbf", "#8c564b", "#d35fa7", "#7f7f7f",
            "#b5b026", "#17a2b8", "#9ec1e8", "#f4b183", "#9fd6a9", "#eea39b", "#c9b6e4", "#c8a99f", "#f1b6da",
            "#c7c7c7", "#dbdb8d", "#9edae5")  # 20 distinguishable colours (the tab20 idea), reused beyond that


def _e(value: Any) -> str:
    return html.escape(str(value), quote=True)


def percent(fraction: float | None) -> str:
    """A fraction as a percentage with one decimal (the paper's relative drops), or a dash when undefined."""
    return "—" if fraction is None else f"{100 * fraction:.1f}%"


def _nice_max(value: float) -> float:
    """The y-axis top: the value rounded up to a multiple of 10 (at least 10, at most 100)."""
    return min(100.0, max(10.0, 10.0 * -(-value // 10)))


def _bar_chart(groups: list[str], series: list[tuple[str, list[float | None], list[float | None]]],
               *, width: int = 600, plot_h: int = 220, sublabels: list[str] | None = None) -> str:
    """Grouped bars with error bars and value labels where they fit. series: (name, value per group, std per
    group); a None value draws no bar. `sublabels` adds a second line under each group's label."""
    extra = 14 if sublabels else 0
    left, right, top, bottom = 44, 12, 14, 40 + extra + 18 * -(-len(series) // _LEGEND_COLUMNS)
    plot_w, height = width - left - right, top + plot_h + bottom
    tops = [v + (s or 0) for _, vals, stds in series for v, s in zip(vals, stds, strict=True) if v is not None]
    tallest = max(tops, default=0.0)
    ymax = _nice_max(tallest)
    y = lambda v: top + plot_h * (1 - v / ymax)  # noqa: E731
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" viewBox="0 0 {width} {height}" '
           f'role="img" class="chart">']
    for k in range(6):
        v = ymax * k / 5
        out.append(f'<line x1="{left}" x2="{width - right}" y1="{y(v):.1f}" y2="{y(v):.1f}" stroke="#e6e9ee"/>'
                   f'<text x="{left - 6}" y="{y(v) + 4:.1f}" font-size="11" text-anchor="end" '
                   f'fill="#5b6474">{v:g}</text>')
    group_w = plot_w / max(len(groups), 1)
    bar_w = min(38.0, group_w * 0.8 / max(len(series), 1))
    labels, whiskers = bar_w >= 22, bar_w >= 6  # value labels and error bars only where they fit
    fits = max(int(group_w / 6.2), 4)  # characters of a group label at 12 px
    for g, group in enumerate(groups):
        gx, mid = left + g * group_w + (group_w - bar_w * len(series)) / 2, left + (g + 0.5) * group_w
        shown = group if len(group) <= fits else group[: fits - 1] + "…"
        out.append(f'<text x="{mid:.1f}" y="{top + plot_h + 16}" font-size="12" text-anchor="middle">'
                   f'<title>{_e(group)}</title>{_e(shown)}</text>')
        if sublabels:
            out.append(f'<text x="{mid:.1f}" y="{top + plot_h + 30}" font-size="11" text-anchor="middle" '
                       f'fill="#5b6474">{_e(sublabels[g])}</text>')
        for s, (name, values, stds) in enumerate(series):
            value, std = values[g], stds[g]
            if value is None:
                continue
            x, color = gx + s * bar_w, _PALETTE[s % len(_PALETTE)]
            tip = f"{name} · {group}: {value:.2f}" + ("" if std is None else f" ± {std:.2f}")
            out.append(f'<rect x="{x + 1:.1f}" y="{y(value):.1f}" width="{bar_w - 2:.1f}" '
                       f'height="{max(y(0) - y(value), 0):.1f}" fill="{color}"><title>{_e(tip)}</title></rect>')
            if std and whiskers:
                cx, lo, hi = x + bar_w / 2, y(max(value - std, 0)), y(min(value + std, ymax))
                out.append(f'<path d="M{cx:.1f} {lo:.1f}V{hi:.1f}M{cx - 4:.1f} {hi:.1f}h8M{cx - 4:.1f} {lo:.1f}h8" '
                           'stroke="#1d2330" stroke-width="1"/>')
            if labels:
                ly = y(min(value + (std or 0), ymax)) - 4
                out.append(f'<text x="{x + bar_w / 2:.1f}" y="{ly:.1f}" font-size="10" text-anchor="middle" '
                           f'fill="#1d2330">{value:.1f}</text>')
    out.append(f'<line x1="{left}" x2="{width - right}" y1="{y(0):.1f}" y2="{y(0):.1f}" stroke="#5b6474"/>')
    out.append(_legend([name for name, _, _ in series], top + plot_h + 34 + extra, left, width - left - right))
    out.append("</svg>")
    return "".join(out)


def _legend(names: list[str], y0: float, x0: float, width: float) -> str:
    """Colour keys in up to three columns; names cut to what fits a column (the full name is in the tooltip)."""
    columns = _LEGEND_COLUMNS
    col_w = width / columns
    fits = max(int((col_w - 24) / 7), 4)  # ~7 px per character at 12 px
    out = []
    for i, name in enumerate(names):
        x, y = x0 + (i % columns) * col_w, y0 + (i // columns) * 18
        shown = name if len(name) <= fits else name[: fits - 1] + "…"
        out.append(f'<g><title>{_e(name)}</title><rect x="{x:.1f}" y="{y - 10:.1f}" width="12" height="12" '
                   f'fill="{_PALETTE[i % len(_PALETTE)]}"/><text x="{x + 17:.1f}" y="{y:.1f}" font-size="12">'
                   f'{_e(shown)}</text></g>')
    return "".join(out)


def _stat_of(metrics: dict[str, Any] | None, metric: str) -> tuple[float | None, float | None]:
    if metrics is None:
        return None, None
    return metrics[metric]["mean"], metrics[metric]["std"]


def dimension_chart(entries: list[dict[str, Any]], metric: str, dims: dict[str, str]) -> str:
    """Per dimension and the average, one bar per leaderboard entry (`metric`: "score" or "success")."""
    groups = list(dims.values()) + ["Average"]
    series = []
    for e in entries:
        pairs = [_stat_of(e["scores"]["dimensions"].get(d, {}).get("metrics"), metric) for d in dims]
        pairs.append(_stat_of(e["scores"]["overall"], metric))
        series.append((e["policy"], [p[0] for p in pairs], [p[1] for p in pairs]))
    return _bar_chart(groups, series)


def standard_random_chart(entries: list[dict[str, Any]]) -> str:
    """Per entry, the Generalization standard and random scores, with the relative drop under each pair."""
    gens = [e["scores"]["generalization"] for e in entries]
    series = [
        ("standard", [g["standard"]["score"]["mean"] for g in gens], [g["standard"]["score"]["std"] for g in gens]),
        ("random", [g["random"]["score"]["mean"] for g in gens], [g["random"]["score"]["std"] for g in gens]),
    ]
    return _bar_chart([e["policy"] for e in entries], series, width=min(1240, max(360, 140 + 100 * len(entries))),
                      sublabels=[f"drop {percent(g['relative_drop_score'])}" for g in gens])


def histogram_chart(hist: dict[str, list[int]], dims: dict[str, str]) -> str:
    """Small multiples, one panel per dimension: the share of episodes in each score bin (full height = 100 %)."""
    panel_w, panel_h, gap, top, bottom = 200, 110, 16, 18, 22
    shown = [d for d in dims if d in hist]
    width = len(shown) * (panel_w + gap)
    base, half = top + panel_h, top + panel_h / 2
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{base + bottom}" '
           f'role="img" class="chart histogram">']
    for i, d in enumerate(shown):
        counts, x0 = hist[d], i * (panel_w + gap)
        total = sum(counts)
        bar_w = panel_w / len(counts)
        colour = _PALETTE[list(dims).index(d) % len(_PALETTE)]
        out.append(f'<text x="{x0 + panel_w / 2:.1f}" y="12" font-size="12" text-anchor="middle">'
                   f'{_e(dims[d])} (n={total})</text>'
                   f'<line x1="{x0}" x2="{x0 + panel_w}" y1="{half}" y2="{half}" stroke="#e6e9ee"/>'
                   f'<text x="{x0 + panel_w}" y="{half - 3}" font-size="9" text-anchor="end" fill="#5b6474">50%</text>')
        for b, c in enumerate(counts):
            h = panel_h * c / total
            lo, hi = b * 100 // len(counts), (b + 1) * 100 // len(counts)
            out.append(f'<rect x="{x0 + b * bar_w + 0.5:.1f}" y="{base - h:.1f}" width="{bar_w - 1:.1f}" '
                       f'height="{h:.1f}" fill="{colour}"><title>score {lo}-{hi}: {c} '
                       f'episodes ({100 * c / total:.1f}%)</title></rect>')
        out.append(f'<line x1="{x0}" x2="{x0 + panel_w}" y1="{base}" y2="{base}" stroke="#5b6474"/>'
                   f'<text x="{x0}" y="{base + 14}" font-size="10" fill="#5b6474">0</text>'
                   f'<text x="{x0 + panel_w}" y="{base + 14}" font-size="10" text-anchor="end" '
                   f'fill="#5b6474">100</text>')
    out.append("</svg>")
    return "".join(out)
