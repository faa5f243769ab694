"""``xpolicylab bench`` / ``dojo bench policy``: loopback throughput and round-trip latency of the protocol.

The server runs in a separate process (``python -m xpolicylab.serve``), as in a real evaluation: client and
server in one process would share one interpreter lock and measure the GIL instead of the protocol. Each of the
``shared_memory`` modes listed is measured in turn against the same server, so socket and shared memory compare
in one run; ``mb_per_s`` counts the observations' bytes either way. So are the ``layouts`` of a batch: ``columns``
(one array per camera for the batch, to a server that reads them) and ``list`` (one observation per environment).
The observations' images are rows of one array per camera, as a batched simulator renders them.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from typing import Any

from xpolicylab import codec, shm
from xpolicylab.client import PolicyClient
from xpolicylab.embodiments import CAMERAS, get_embodiment
from xpolicylab.observations import synthetic_batch
from xpolicylab.server import READY_LINE
from xpolicylab.stats import LatencyStats


@dataclass
class BenchConfig:
    protocols: tuple[str, ...] = ("xpolicylab", "openpi")
    batch: int = 64
    width: int = 640
    height: int = 480
    cameras: tuple[str, ...] = CAMERAS
    n: int = 20
    warmup: int = 3
    single_n: int = 50
    embodiment: str = "arx_x5_bimanual"
    url: str | None = None
    shared_memory: tuple[str, ...] = ("auto",)
    layouts: tuple[str, ...] = ("columns",)

LAYOUTS = ("columns", "list")


@contextmanager
def spawned_server(protocol: str, timeout_s: float = 60.0, options: Sequence[str] = ()) -> Iterator[str]:
    """Run ``python -m xpolicylab.serve policy=zero`` (and ``options``, ``key=value``) on a free loopback port;
    yield its URL."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "xpolicylab.serve", "policy=zero", f"protocol={protocol}", "host=127.0.0.1",
         "port=0", "log_level=warning", *options], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + timeout_s
        for line in proc.stdout:
            if line.startswith(READY_LINE):
                yield line.rsplit(" ", 1)[-1].strip()
                return
            if time.monotonic() > deadline:
                break
        raise RuntimeError(f"the {protocol} bench server did not start")
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _measure(url: str, protocol: str, cfg: BenchConfig, shared_memory: str, layout: str) -> dict[str, Any]:
    emb = get_embodiment(cfg.embodiment)
    obs_list = synthetic_batch(emb, cfg.batch, cfg.cameras, cfg.width, cfg.height, stacked=True)
    env_ids = list(range(cfg.batch))
    request_bytes = sum(memoryview(c).nbytes for c in codec.encode_chunks(
        {"observations": obs_list, "env_ids": env_ids}, codec.Dialect(protocol)))
    with PolicyClient(url, protocol, recv_timeout_s=120.0, max_connect_attempts=8,
                      shared_memory=shared_memory, columnar=layout == "columns") as client:
        used_shared_memory, used_columns = client.uses_shared_memory, client.sends_columns
        for _ in range(cfg.warmup):
            client.infer_batch(obs_list, env_ids)
        batch = LatencyStats()
        start = time.perf_counter()
        for _ in range(cfg.n):
            t0 = time.perf_counter()
            client.infer_batch(obs_list, env_ids)
            batch.record((time.perf_counter() - t0) * 1e3)
        elapsed = time.perf_counter() - start
        single = LatencyStats()
        for i in range(cfg.warmup + cfg.single_n):
            t0 = time.perf_counter()
            client.infer(obs_list[i % cfg.batch])
            if i >= cfg.warmup:
                single.record((time.perf_counter() - t0) * 1e3)
    return {
        "mb_per_s": round(request_bytes * cfg.n / elapsed / 1e6, 1),
        "batch_rtt_ms_p50": round(batch.percentile(50), 2),
        "batch_rtt_ms_p99": round(batch.percentile(99), 2),
        "single_rtt_ms_p50": round(single.percentile(50), 2),
        "single_rtt_ms_p99": round(single.percentile(99), 2),
        "request_mb": round(request_bytes / 1e6, 2),
        "shared_memory": used_shared_memory,
        "columns": used_columns,
    }


def run_bench(cfg: BenchConfig) -> dict[str, Any]:
    """Measure every dialect in ``cfg.protocols`` (the native one in every ``cfg.shared_memory`` mode and every
    layout of ``cfg.layouts``); returns the figures the bench prints as one JSON line, under the dialect's name,
    followed by ``_shm_<mode>`` when several modes are measured and by ``_<layout>`` when several layouts are."""
    result: dict[str, Any] = {
        "bench": "xpolicylab_loopback", "policy": "zero", "batch": cfg.batch,
        "images": f"{len(cfg.cameras)}x{cfg.width}x{cfg.height}", "n": cfg.n, "single_n": cfg.single_n,
    }
    for protocol in cfg.protocols:
        modes = cfg.shared_memory if protocol == "xpolicylab" else ("off",)
        layouts = cfg.layouts if protocol == "xpolicylab" else ("list",)
        with nullcontext(cfg.url) if cfg.url else spawned_server(protocol) as url:
            for mode in modes:
                for layout in layouts:
                    key = protocol + (f"_shm_{mode}" if len(modes) > 1 else "") + (
                        f"_{layout}" if len(layouts) > 1 else "")
                    result[key] = _measure(url, protocol, cfg, mode, layout)
    return result


def protocols_arg(values: Sequence[str]) -> tuple[str, ...]:
    """Validate the ``protocols`` option."""
    bad = [p for p in values if p not in ("xpolicylab", "openpi")]
    if bad or not values:
        raise ValueError(f"protocols must be a subset of [xpolicylab,openpi], got {list(values)}")
    return tuple(values)


def layouts_arg(values: Sequence[str]) -> tuple[str, ...]:
    """Validate the ``layouts`` option: one or more of columns, list."""
    bad = [v for v in values if v not in LAYOUTS]
    if bad or not values:
        raise ValueError(f"layouts must list one or more of {', '.join(LAYOUTS)}, got {list(values)}")
    return tuple(values)


def shared_memory_arg(values: Sequence[str]) -> tuple[str, ...]:
    """Validate the ``shared_memory`` option: one or more of auto, on, off."""
    if not values:
        raise ValueError(f"shared_memory must list one or more of {', '.join(shm.MODES)}")
    return tuple(shm.mode(v) for v in values)
