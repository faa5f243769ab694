"""`dojo bench served`: `dojo run` end to end against a policy served on this host, its images through the socket
and through shared memory, measured in one go; prints one JSON line.

It starts `xpolicylab serve policy=zero` with the cameras and image size asked for (in its own process, as a
policy server is) once per `shared_memory` mode, and runs the same `dojo run` command (the overrides given, with
`policy=remote` pointed at that server) into a fresh results store, reading the run's `progress=jsonl` lines. The
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
from pathlib import Path
from typing import Any

from xpolicylab.bench import spawned_server

from dojo.bench.ray_bench import dojo_run, split_arguments
from dojo.evaluation.results_store import ResultsStore

USAGE = ("usage: dojo bench served [shared_memory=off,on] [width=224] [height=224] "
         "[cameras=head,left_wrist,right_wrist] [dojo run overrides ...]")
OWN_KEYS = ("shared_memory", "width", "height", "cameras")


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
    cameras = _words(own.get("cameras", "head,left_wrist,right_wrist"))
    print(json.dumps(bench_served(overrides, modes, cameras, width, height)))
    return 0


def _words(value: str) -> list[str]:
    """`a,b` or `[a,b]` as a list of words."""
    return [w.strip() for w in value.strip("[]").split(",") if w.strip()]


def bench_served(overrides: list[str], modes: list[str], cameras: list[str], width: int,
                 height: int) -> dict[str, Any]:
    """`dojo run <overrides>` against a served zero policy once per shared-memory mode; the figures."""
    serve = [f"cameras=[{','.join(cameras)}]", f"width={width}", f"height={height}"]
    with tempfile.TemporaryDirectory(prefix="dojo-bench-served-") as tmp:
        runs = []
        for mode in modes:
            with spawned_server("xpolicylab", options=serve) as url:
                runs.append(served_run(overrides, url, mode, Path(tmp) / f"{mode}.sqlite"))
    figures = {r["shared_memory"]: {k: v for k, v in r.items() if k not in ("rows", "shared_memory")} for r in runs}
    report: dict[str, Any] = {
        "benchmark": "served", "command": " ".join(["dojo", "run", *overrides]), "policy": "zero",
        "images": f"{len(cameras)}x{width}x{height}", "runs": figures,
        "same_results": all(r["rows"] == runs[0]["rows"] for r in runs)}
    off, on = figures.get("off", {}).get("steady_interactions_per_s"), figures.get("on", {}).get(
        "steady_interactions_per_s")
    if off and on:
        report["shared_over_socket"] = round(on / off, 3)
    return report


def served_run(overrides: list[str], url: str, mode: str, store: Path) -> dict[str, Any]:
    """One `dojo run` against the server at `url` with `policy.shared_memory=mode`: its rates and its episodes."""
    done = dojo_run([*overrides, "policy=remote", f"policy.url={url}", f"policy.shared_memory={mode}",
                     f"results={store}"])
    events = [json.loads(line) for line in done.stdout.splitlines() if line.startswith('{"event"')]
    with ResultsStore(store, readonly=True) as results:
        rows = {r.key: (r.success, r.score, r.steps, r.failure_reason) for r in results.rows()}
    return {"shared_memory": mode, "link": _line(done.stderr, "policy link:"), **steady_rates(events),
            "time_split": _line(done.stderr, "where the loop's"), "rows": rows}


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
