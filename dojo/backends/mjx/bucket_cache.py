"""Buckets kept across runs: what `make_buckets` found for a set of plans, stored so that the next run over the same
plans compiles their padded models instead of bucketing them again.

Why: bucketing was the part of a GPU run's set-up that no kernel or XLA cache served. The protocol's 850 mjx
plans took 30-34 s to bucket on the H200 host at every run (2026-12-04, session 66) and 40 s on the 2-core CI
machine, most of it padding MJCF in Python and compiling the 3,800 paddings that the merge tries; the buckets it
settles on are 850 padded MJCF, which compile again in 10 s on two threads. An entry is those MJCF with their
names, parked slots and slot keys (0.9 MB as JSON under xz for the protocol), never a pickle or a binary model: the
cache folder is read as data.

An entry is found by everything bucketing depends on (`entry_key`): every plan (its hash, scene and objects), the
merge and its growth, MuJoCo's and MJX's versions and the source of the `dojo` package, so any change to the code
misses. What an entry says is checked as it is read: every plan once, each bucket's members compiling to the one
structure its key names. An entry that fails is logged, removed, and the plans are bucketed again.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import logging
import lzma
import os
import tempfile
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from importlib.metadata import version
from pathlib import Path

import mujoco

import dojo
from dojo.compiler.plan import Plan

from dojo.backends.mjx.bucket import Bucket, Compiling, bucket_members, compile_jobs, make_buckets, varying_fields
from dojo.backends.mjx.pad import PaddedPlan

log = logging.getLogger(__name__)

FORMAT = "robodojo-buckets/1"
KEPT_ENTRIES = 32
"""Entries kept in the folder, the least recently used removed first (the protocol's is 0.9 MB)."""


def cache_dir() -> Path:
    """`$DOJO_BUCKET_CACHE`, else `~/.cache/dojo/buckets` (beside MJX's XLA cache, `~/.cache/dojo/jax`)."""
    return Path(os.environ.get("DOJO_BUCKET_CACHE") or Path.home() / ".cache" / "dojo" / "buckets")


@functools.cache
def code_digest() -> str:
    """SHA-256 over the source of every module of the `dojo` package, by path: bucketing's code is spread over
    padding, merging, plans and their programs, and a stale entry would bucket silently wrong, so every change to
    the package misses (reading the package's files takes some milliseconds)."""
    root = Path(dojo.__file__).parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def entry_key(plans: Sequence[Plan], merge: bool, growth: float) -> str:
    """The name of the entry for these plans, in this order (`cached_buckets` sorts them first), bucketed with
    `merge` and `growth`."""
    h = hashlib.sha256()
    h.update(json.dumps([FORMAT, code_digest(), mujoco.__version__, version("mujoco-mjx"), bool(merge),
                         repr(float(growth))]).encode())
    for plan in plans:
        h.update(json.dumps([plan.hash, plan.task, plan.setting, plan.seed, plan.embodiment, plan.n_substeps,
                             plan.objects], sort_keys=True).encode())
        h.update(hashlib.sha256(plan.model_xml.encode()).digest())
    return h.hexdigest()[:32]


def cached_buckets(plans: Sequence[Plan], merge: bool, growth: float,
                   folder: Path | None = None) -> tuple[list[Bucket], Path | None]:
    """`make_buckets(plans, merge, growth)` over the plans in `Plan.sort_key` order, read from the cache folder
    where an entry for them is there and sound, else made and stored. Returns the buckets and the entry they were
    read from (None when bucketed here).

    In that order, whichever order the caller lists the plans in: which plans share a bucket does not depend on it
    (`make_buckets`), only the members' order within one, and so `dojo bench kernels` on a CPU node and `dojo run`
    on the GPU find one entry for the same plans (a folder carried along with the kernels, as `DOJO_BUCKET_CACHE`)."""
    if len({plan.hash for plan in plans}) != len(plans):  # an entry names its members by plan hash
        return make_buckets(plans, merge=merge, growth=growth), None
    plans = sorted(plans, key=lambda plan: plan.sort_key)
    folder = cache_dir() if folder is None else folder
    path = folder / f"{entry_key(plans, merge, growth)}.json.xz"
    if path.exists():
        try:
            buckets = _read(path, plans)
        except Exception as err:  # whatever a damaged or foreign entry raises, the plans are bucketed again
            log.warning("mjx backend: bucket cache entry %s not used (%s: %s); bucketing again", path,
                        type(err).__name__, err)
            path.unlink(missing_ok=True)
        else:
            with contextlib.suppress(OSError):  # another process may have pruned it meanwhile
                os.utime(path)
            return buckets, path
    buckets = make_buckets(plans, merge=merge, growth=growth)
    try:
        _write(path, buckets)
    except OSError as err:  # a read-only or full disk costs the next run its bucketing, not this run
        log.warning("mjx backend: buckets not kept in %s (%s)", folder, err)
    return buckets, None


def _write(path: Path, buckets: Sequence[Bucket]) -> None:
    """Store the buckets' padded plans as one entry (written whole, then renamed into place), then prune."""
    entry = {"format": FORMAT, "buckets": [
        {"key": b.key, "members": [{"plan": m.plan.hash, "xml": m.padded.xml, "names": m.padded.names,
                                    "parked": m.padded.parked, "slot_keys": m.padded.slot_keys}
                                   for m in b.members]} for b in buckets]}
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, scratch = tempfile.mkstemp(dir=path.parent, suffix=".part")
    try:
        with os.fdopen(fd, "wb") as out:
            out.write(lzma.compress(json.dumps(entry).encode(), preset=1))
        os.replace(scratch, path)
    finally:
        Path(scratch).unlink(missing_ok=True)
    _prune(path.parent)


def _prune(folder: Path) -> None:
    """Keep the `KEPT_ENTRIES` most recently used entries; runs beside this one may be reading or pruning too."""
    used: list[tuple[float, Path]] = []
    for entry in folder.glob("*.json.xz"):
        with contextlib.suppress(FileNotFoundError):
            used.append((entry.stat().st_mtime, entry))
    for _, old in sorted(used, reverse=True)[KEPT_ENTRIES:]:
        old.unlink(missing_ok=True)


def _read(path: Path, plans: Sequence[Plan]) -> list[Bucket]:
    """The buckets an entry describes, their models compiled on threads beside the plans' own (which the members'
    initial states read); raises ValueError where the entry does not fit the plans."""
    entry = json.loads(lzma.decompress(path.read_bytes()))
    if entry.get("format") != FORMAT:
        raise ValueError(f"format {entry.get('format')!r}, not {FORMAT!r}")
    by_hash = {plan.hash: plan for plan in plans}
    padded = [(b["key"], [PaddedPlan(by_hash[m["plan"]], m["xml"], dict(m["names"]), list(m["parked"]),
                                     list(m["slot_keys"])) for m in b["members"]]) for b in entry["buckets"]]
    listed = sorted(pp.plan.hash for _, members in padded for pp in members)
    if listed != sorted(by_hash):
        raise ValueError("it does not list every plan once")
    with ThreadPoolExecutor(os.cpu_count() or 1) as pool:
        jobs = compile_jobs(pool, (pp for _, members in padded for pp in members))
        sources = [pool.submit(plan.model) for plan in plans]
        found = [(key, members, Compiling(members, jobs, {}).result()) for key, members in padded]
        for job in sources:
            job.result()
    buckets = []
    for key, members, compiled in found:
        signatures = {signature for _, signature in compiled}
        if len(signatures) != 1 or not key.endswith(":" + next(iter(signatures))[:16]):
            raise ValueError(f"bucket {key}: its members compile to {len(signatures)} structure(s), not the key's")
        models = [model for model, _ in compiled]
        buckets.append(Bucket(key, bucket_members(list(zip(members, models))), varying_fields(models)))
    return buckets
