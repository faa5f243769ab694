"""`dojo bench ray`: how one `dojo run` scales over Ray workers, measured in one go; prints one JSON line.

It starts one local Ray cluster (every core of this machine) and runs the same `dojo run` command (the overrides
given) once per worker count, `launcher=ray launcher.workers=N`, each into a fresh results store, in turn
(`repeats` times over, interleaved, so that a machine that gets busier part-way affects every count alike). A
run's time is its own progress summary's `elapsed_s`: the evaluation, workers' start included, without Python's
start-up and plan compilation, which do not change with the worker count. It reports episodes and environment
steps per second per count (the best of its repeats), the speedup over the first count, and whether every run
recorded the same episodes (CPU runs are deterministic: anything else is a bug).

    dojo bench ray workers=1,2 repeats=1 policy=oracle num_envs=2
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any, TextIO

from dojo.evaluation.results_store import ResultsStore

USAGE = "usage: dojo bench ray [workers=1,2] [repeats=1] [dojo run overrides ...]"
OWN_KEYS = ("workers", "repeats")


def bench_ray_main(argv: list[str]) -> int:
    """The command line: our two keys, and everything else for `dojo run`."""
    if {"-h", "--help"} & set(argv):
        print(__doc__.strip() + "\n\n" + USAGE)
        return 0
    own, overrides = split_arguments(argv)
    try:
        workers = [int(w) for w in own.get("workers", "1,2").strip("[]").split(",")]
        repeats = int(own.get("repeats", "1"))
    except ValueError:
        print(f"dojo bench ray: workers is a list of counts and repeats a count\n{USAGE}", file=sys.stderr)
        return 2
    print(json.dumps(bench_ray(overrides, workers, repeats)))
    return 0


def split_arguments(argv: list[str], keys: tuple[str, ...] = OWN_KEYS) -> tuple[dict[str, str], list[str]]:
    """A bench's own keys (here `workers`, `repeats`), and the `dojo run` overrides."""
    own = {a.split("=", 1)[0]: a.split("=", 1)[1] for a in argv if a.split("=", 1)[0] in keys and "=" in a}
    return own, [a for a in argv if a.split("=", 1)[0] not in keys]


def bench_ray(overrides: list[str], workers: list[int], repeats: int = 1) -> dict[str, Any]:
    """Run `dojo run <overrides>` on a local cluster once per worker count (and repeat); the figures."""
    import ray

    from dojo.launch.ray_launcher import start_local_cluster

    start_local_cluster()
    try:
        address = ray.get_runtime_context().gcs_address
        cpus = int(ray.cluster_resources().get("CPU", 0))
        with tempfile.TemporaryDirectory(prefix="dojo-bench-ray-") as tmp:
            runs = [_timed_run(overrides, count, address, Path(tmp) / f"w{count}-{rep}.sqlite")
                    for rep in range(repeats) for count in workers]
    finally:
        ray.shutdown()
    per_count = []
    for count in workers:
        mine = [r for r in runs if r["workers"] == count]
        best = min(mine, key=lambda r: r["eval_s"])
        per_count.append({"workers": count, "eval_s": [r["eval_s"] for r in mine],
                          "episodes_per_s": round(best["episodes"] / best["eval_s"], 4),
                          "interactions_per_s": round(best["interactions"] / best["eval_s"], 2)})
    base = per_count[0]["episodes_per_s"]
    return {"benchmark": "ray", "command": " ".join(["dojo", "run", *overrides]), "cluster_cpus": cpus,
            "episodes": runs[0]["episodes"], "runs": per_count,
            "speedup": {str(r["workers"]): round(r["episodes_per_s"] / base, 3) for r in per_count},
            "same_results": all(r["rows"] == runs[0]["rows"] for r in runs)}


def dojo_run(args: list[str]) -> subprocess.CompletedProcess[str]:
    """`dojo run <args> progress=jsonl` in a process of its own (as a user starts it), its stdout kept and its stderr
    both kept and passed on line by line as it comes; raises when it fails (its messages, passed on, say why).

    Why pass stderr on: on a GPU a run's engine build and first tick take minutes (the protocol's: 144 s and 91 s
    on an H200, 2026-12-03), and a bench that kept its runs' messages until they ended said nothing for all that
    time (one was stopped after 200 s of silence, not knowing how far it was)."""
    cmd = [sys.executable, "-m", "dojo.cli.main", "run", *args, "progress=jsonl"]
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        said: list[str] = []
        relay = threading.Thread(target=_relay, args=(proc.stderr, said), daemon=True)
        relay.start()
        out = proc.stdout.read()
        proc.wait()
        relay.join()
    done = subprocess.CompletedProcess(cmd, proc.returncode, out, "".join(said))
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited with {done.returncode} (its messages are above)")
    return done


def _relay(stream: TextIO, said: list[str]) -> None:
    """Each line of `stream` onto this process's stderr as it comes, and into `said`."""
    for line in stream:
        said.append(line)
        sys.stderr.write(line)
        sys.stderr.flush()


def _timed_run(overrides: list[str], workers: int, address: str, store: Path) -> dict[str, Any]:
    """One `dojo run` on the cluster at `address`: its summary and its episodes."""
    done = dojo_run([*overrides, "launcher=ray", f"launcher.address={address}", f"launcher.workers={workers}",
                     f"results={store}"])
    summary = next(json.loads(line) for line in done.stdout.splitlines() if line.startswith('{"event": "summary"'))
    with ResultsStore(store, readonly=True) as results:
        rows = {r.key: (r.success, r.score, r.steps, r.stage_times, r.failure_reason) for r in results.rows()}
    return {"workers": workers, "eval_s": summary["elapsed_s"], "episodes": summary["done"] - summary["resumed"],
            "interactions": summary["interactions"], "rows": rows}
