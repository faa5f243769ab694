"""Buckets kept across runs (`bucket_cache`): read back bit for bit, found only by the same plans, settings and code,
and a damaged entry logged, removed and bucketed again."""

from __future__ import annotations

import dataclasses
import json
import logging
import lzma
import math
import os
import random
from pathlib import Path

import pytest
from conftest import toy_plan
from test_bucket import _fingerprint
from test_padding_groups import mesh_plan

from dojo.backends.mjx import bucket_cache
from dojo.backends.mjx.bucket import make_buckets
from dojo.backends.mjx.bucket_cache import cached_buckets, entry_key
from dojo.compiler.plan import Plan


def _plans() -> list[Plan]:
    """Tasks that merge, random clutter padded into slots, and meshes of one name with other vertices per plan."""
    plans = [toy_plan(task=task, seed=s, items=items, block_size=0.03 + 0.005 * k)
             for k, (task, items) in enumerate((("toy", ()), ("pair", ("ball", "box")), ("twin", ("ball", "ball"))))
             for s in range(2)]
    plans += [toy_plan(setting="random", seed=s, clutter=c) for s, c in enumerate([("ball",), ("box", "ball"), ()])]
    return plans + [mesh_plan(0, (1.0,)), mesh_plan(1, (1.5,))]


def _fresh(plans: list[Plan]) -> list[Plan]:
    """The same plans as new objects, none of their models compiled: as a later run loads them."""
    return [dataclasses.replace(plan) for plan in plans]


def _entries(folder: Path) -> list[Path]:
    return sorted(folder.glob("*.json.xz"))


@pytest.mark.parametrize("merge", [False, True])
def test_a_second_run_reads_the_buckets_back_bit_for_bit(tmp_path, merge):
    """The first call buckets and stores one entry; a second, with the plans loaded again and listed in another
    order, reads it, and its buckets are the plain `make_buckets` ones of the plans in `Plan.sort_key` order: keys,
    varying fields, members, paddings, initial states, models."""
    plans = _plans()
    made, entry = cached_buckets(plans, merge, math.inf, tmp_path)
    assert entry is None and len(_entries(tmp_path)) == 1
    again, entry = cached_buckets(random.Random(0).sample(_fresh(plans), len(plans)), merge, math.inf, tmp_path)
    assert entry == _entries(tmp_path)[0]
    in_order = sorted(_fresh(plans), key=lambda plan: plan.sort_key)
    assert _fingerprint(again) == _fingerprint(made) == _fingerprint(make_buckets(in_order, merge, math.inf))


def test_an_entry_is_found_only_by_the_same_plans_settings_and_code(monkeypatch):
    """Everything that bucketing reads names the entry: the merge and its growth, each plan (in the order given:
    `cached_buckets` sorts them first) and its MJCF, and the package's source."""
    plans = _plans()
    key = entry_key(plans, True, 1.0)
    assert entry_key(_fresh(plans), True, 1.0) == key
    edited = [dataclasses.replace(plans[0], model_xml=plans[0].model_xml.replace("0.8 0.1 0.1 1", "0.1 0.8 0.1 1"))]
    others = [entry_key(plans, False, 1.0), entry_key(plans, True, 0.5), entry_key(plans[::-1], True, 1.0),
              entry_key(edited + plans[1:], True, 1.0), entry_key(plans[:-1], True, 1.0)]
    monkeypatch.setattr(bucket_cache, "code_digest", lambda: "another version of the code")
    others.append(entry_key(plans, True, 1.0))
    assert len({key, *others}) == 1 + len(others)


def _damaged(path: Path, how: str) -> None:
    """Damage an entry: cut short, with a plan it does not list, or a member whose MJCF is another structure."""
    if how == "cut":
        path.write_bytes(path.read_bytes()[:100])
        return
    entry = json.loads(lzma.decompress(path.read_bytes()))
    member = entry["buckets"][0]["members"][0]
    if how == "plan":
        member["plan"] = "0" * 64
    else:
        member["xml"] = member["xml"].replace("</worldbody>", '<geom type="sphere" size="0.01"/></worldbody>', 1)
    path.write_bytes(lzma.compress(json.dumps(entry).encode()))


@pytest.mark.parametrize("how", ["cut", "plan", "structure"])
def test_a_damaged_entry_is_logged_removed_and_the_plans_bucketed_again(tmp_path, caplog, how):
    plans = _plans()
    made, _ = cached_buckets(plans, True, math.inf, tmp_path)
    [path] = _entries(tmp_path)
    _damaged(path, how)
    with caplog.at_level(logging.WARNING, logger=bucket_cache.__name__):
        again, entry = cached_buckets(_fresh(plans), True, math.inf, tmp_path)
    assert entry is None and f"bucket cache entry {path} not used" in caplog.text
    assert _fingerprint(again) == _fingerprint(made)
    assert cached_buckets(_fresh(plans), True, math.inf, tmp_path)[1] == path  # stored again, sound


def test_the_least_recently_used_entries_go_first(tmp_path, monkeypatch):
    """At most `KEPT_ENTRIES` entries stay; one read since it was written counts as used."""
    monkeypatch.setattr(bucket_cache, "KEPT_ENTRIES", 2)
    plans = [toy_plan(seed=s) for s in range(3)]
    paths = []
    for k, plan in enumerate(plans):
        cached_buckets([plan], False, 0.5, tmp_path)
        paths.append(tmp_path / f"{entry_key([plan], False, 0.5)}.json.xz")
        os.utime(paths[-1], (k, k))  # written in turn, a second apart
        if k == 1:
            assert cached_buckets(_fresh([plans[0]]), False, 0.5, tmp_path)[1] == paths[0]  # read: now the newest
    assert _entries(tmp_path) == sorted([paths[0], paths[2]])


def test_plans_sharing_a_hash_are_bucketed_without_the_cache(tmp_path):
    """An entry names its members by plan hash, so plans that share one are bucketed as they are, nothing stored."""
    plan = toy_plan()
    buckets, entry = cached_buckets([plan, dataclasses.replace(plan)], False, 0.5, tmp_path)
    assert entry is None and _entries(tmp_path) == [] and len(buckets[0].members) == 2
