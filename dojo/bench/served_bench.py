"""`dojo bench served`: `dojo run` end to end against a policy served on this host, its images through the socket
and through shared memory (and batches as columns or as a list), measured in one go; prints one JSON line.

It starts `xpolicylab serve policy=zero` with the cameras and image size asked for (in its own process, as a
policy server is) once per `shared_memory` mode and batch layout (`layouts`: `columns`, the default, and `list`,
`policy.columnar`), and runs the same `dojo run` command (the overrides given, with `policy=remote` pointed at that
server) into a fresh results store, reading the run's `progress=jsonl` lines. The
figure is environment steps per second between the first and the last episode ends: the steady rate, without
start-up, plan compilation and the compiling first tick, so give a run several waves of episodes (`episodes` a few
times `num_envs`). It also reports each run's overall rate, first episode end and where its loop's time went
(load, policy, backend steps, resets), and whether every run recorded the same episodes (the zero policy and the
backends are deterministic: a difference is a bug).

    dojo bench served backend=mujoco tasks=[insert_tubes] episodes=6 num_envs=2 width=64 height=64
    dojo bench served backend=mjx tasks=[insert_tubes] episodes=1536 num_envs=512 width=224 height=224  # GPU
"""

from __future__ import annotations

import json
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from xpolicylab.bench import spawned_server

from dojo.bench.ray_bench import dojo_run, split_arguments
from dojo.evaluation.results_store import ResultsStore

USAGE = ("usage: dojo bench served [shared_memory=off,on] [layouts=columns] [width=224] [height=224] "
         "[cameras=head,left_wrist,right_wrist] [dojo run overrides ...]")
OWN_KEYS = ("shared_memory", "layouts", "width", "height", "cameras")
LAYOUTS = {"columns": "true", "list": "false"}
"""Batch layouts and the `policy.columnar` that asks for each."""


def bench_served_main(argv: list[str]) -> int:
    """The command line: our keys, and everything else for `dojo run`."""
    if {"-h", "--help"} & set(argv):
        print(__doc__.strip() + "\n\n" + USAGE)
        return 0
    own, overrides = split_arguments(argv, OWN_KEYS)
    try:
        modes = _words(own.get("shared_memory", "off,on"))
        width, height = int(own.get("width", "224")), int(own.get("height", "224"))
    except ValueError:
        print(f"dojo bench served: width and height are pixel counts\n{USAGE}", file=sys.stderr)
        return 2
    if not set(modes) <= {"off", "on", "auto"}:
        print(f"dojo bench served: shared_memory takes off, on or auto\n{USAGE}", file=sys.stderr)
        return 2
    layouts = _words(own.get("layouts", "columns"))
    if not layouts or not set(layouts) <= set(LAYOUTS):
        print(f"dojo bench served: layouts takes columns, list or both\n{USAGE}", file=sys.stderr)
        return 2
    cameras = _words(own.get("cameras", "head,left_wrist,right_wrist"))
    print(json.dumps(bench_served(overrides, modes, cameras, width, height, layouts)))
    return 0


def _words(value: str) -> list[str]:
    """`a,b` or `[a,b]` as a list of words."""
    return [w.strip() for w in value.strip("[]").split(",") if w.strip()]


def bench_served(overrides: list[str], modes: list[str], cameras: list[str], width: int, height: int,
                 layouts: Sequence[str] = ("columns",)) -> dict[str, Any]:
    """`dojo run <overrides>` against a served zero policy once per shared-memory mode and batch layout; the
    figures, each run's under its mode (and `<mode>_<layout>` when several layouts are measured)."""
    serve = [f"cameras=[{','.join(cameras)}]", f"width={width}", f"height={height}"]
    figures, rows = {}, []
    with tempfile.TemporaryDirectory(prefix="dojo-bench-served-") as tmp:
        for mode in modes:
            for layout in layouts:
                key = mode if len(layouts) == 1 else f"{mode}_{layout}"
                with spawned_server("xpolicylab", options=serve) as url:
                    run = served_run(overrides, url, mode, layout, Path(tmp) / f"{key}.sqlite")
                rows.append(run.pop("rows"))
                figures[key] = run
    report: dict[str, Any] = {
        "benchmark": "served", "command": " ".join(["dojo", "run", *overrides]), "policy": "zero",
        "images": f"{len(cameras)}x{width}x{height}", "runs": figures, "same_results": all(r == rows[0] for r in rows)}
    rate = {k: f.get("steady_interactions_per_s") for k, f in figures.items()}
    if len(layouts) == 1 and rate.get("off") and rate.get("on"):
        report["shared_over_socket"] = round(rate["on"] / rate["off"], 3)
    mode = "on" if "on" in modes else modes[0]
    if len(layouts) > 1 and rate.get(f"{mode}_columns") and rate.get(f"{mode}_list"):
        report["columns_over_list"] = round(rate[f"{mode}_columns"] / rate[f"{mode}_list"], 3)
    return report


def served_run(overrides: list[str], url: str, mode: str, layout: str, store: Path) -> dict[str, Any]:
    """One `dojo run` against the server at `url` with `policy.shared_memory=mode` and the batch `layout`: its
    rates and its episodes (`rows`)."""
    done = dojo_run([*overrides, "policy=remote", f"policy.url={url}", f"policy.shared_memory={mode}",
                     f"policy.columnar={LAYOUTS[layout]}", f"results={store}"])
    events = [json.loads(line) for line in done.stdout.splitlines() if line.startswith('{"event"')]
    with ResultsStore(store, readonly=True) as results:
        rows = {r.key: (r.success, r.score, r.steps, r.failure_reason) for r in results.rows()}
    return {"shared_memory": mode, "layout": layout, "link": _line(done.stderr, "policy link:"),
            **steady_rates(events), "time_split": _line(done.stderr, "where the loop's"), "rows": rows}


def steady_rates(events: list[dict[str, Any]]) -> dict[str, Any]:
    """From a run's progress events: episodes, the overall rate, the wait for the first episode end, and the steady
    rate between the first and the last episode ends (None when they all ended together)."""
    ends = [e for e in events if e.get("event") == "episode"]
    summary = next(e for e in events if e.get("event") == "summary")
    first, last = (ends[0], ends[-1]) if ends else (summary, summary)
    span = last["elapsed_s"] - first["elapsed_s"]
    steady = (last["interactions"] - first["interactions"]) / span if span > 0 else None
    return {"episodes": summary["done"] - summary["resumed"], "interactions": summary["interactions"],
            "elapsed_s": summary["elapsed_s"], "first_episode_end_s": first["elapsed_s"],
            "interactions_per_s": summary["interactions_per_s"],
            "steady_interactions_per_s": None if steady is None else round(steady, 2)}


def _line(stderr: str, start: str) -> str | None:
    """The run's log line that starts so: its policy link (socket or shared memory, to show the mode took effect)
    and where its loop's time went."""
    return next((line.strip() for line in stderr.splitlines() if line.startswith(start)), None)
