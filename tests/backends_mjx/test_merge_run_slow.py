"""`dojo run backend=mjx backend.merge=true` end to end on a two-task mix: the same episodes' success, score,
stages and success terms as `merge=false`. Two compilations of the backend's tick (two arms, IK) on a CPU: tens of
minutes on the 2-core machine, hence slow.

The pack's two tasks have different objects (a block and a plate; two blocks) and different programs (two stages,
none), so the merged run has one bucket with two lanes (against two buckets), parked slots in both tasks, and
outputs padded to the wider lane; horizons of 3 steps keep the CPU run short. `merge_pair` succeeds at its first
step (its blocks stand, within a metre of each other), `merge_place` reaches its first stage and fails.
"""

from __future__ import annotations

import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import write_pack

pytestmark = pytest.mark.slow

PLACE = """kind: task
version: 1
id: merge_place
dimension: generalization
embodiment: arx_x5_bimanual
instruction: Put the block on the plate.
settings: {standard: {clutter: [0, 0]}}
scene:
  regions:
    left: {center: [-0.2, 0.0], size: [0.1, 0.1]}
    right: {center: [0.2, 0.0], size: [0.1, 0.1]}
  objects:
    - {name: block, asset: {category: test_block}, region: left, color: red}
    - {name: plate, asset: test_plate, region: right}
success: {all: [{upright: block}, {on: [block, plate]}]}
stages:
  - {name: standing, when: {upright: block}}
  - {name: placed, when: {on: [block, plate]}, weight: 2}
horizon: 3
"""
PAIR = """kind: task
version: 1
id: merge_pair
dimension: generalization
embodiment: arx_x5_bimanual
instruction: Keep both blocks standing.
settings: {standard: {clutter: [0, 0]}}
scene:
  regions:
    left: {center: [-0.2, 0.05], size: [0.1, 0.1]}
    right: {center: [0.2, -0.05], size: [0.1, 0.1]}
  objects:
    - {name: block_a, asset: {category: test_block}, region: left, color: blue}
    - {name: block_b, asset: {category: test_block}, region: right, color: green}
success: {all: [{near: [block_a, block_b, 1.0]}, {upright: block_b}]}
horizon: 3
"""
SUITE = """kind: suite
version: 1
id: merge_mix
tasks: [merge_place, merge_pair]
episodes: 1
seeds: [0]
generalization_split: {standard: 1.0}
"""
"""Standard scenes only: random ones add clutter slots and lights, a larger model and more buckets to compile."""


def _pack(root: Path) -> Path:
    return write_pack(root, {"merge_place.yaml": PLACE, "merge_pair.yaml": PAIR}, {"merge_mix.yaml": SUITE})


def _run(tmp: Path, pack: Path, merge: bool) -> list[tuple]:
    results = tmp / f"merge-{merge}.sqlite"
    cmd = [sys.executable, "-m", "dojo.cli.main", "run", f"packs=[{pack}]", "suite=merge_mix", "backend=mjx",
           f"backend.merge={str(merge).lower()}", "policy=zero", "num_envs=2", f"results={results}",
           f"plans={tmp / 'plans'}", "progress=quiet", f"hydra.run.dir={tmp / f'out-{merge}'}"]
    done = subprocess.run(cmd, cwd=tmp, capture_output=True, text=True, timeout=7200)
    assert done.returncode == 0, done.stderr[-4000:]
    with sqlite3.connect(results) as db:
        return db.execute("SELECT task, success, score, steps, stage_times, success_terms, eval_seed, episode "
                          "FROM episodes ORDER BY task, eval_seed, episode").fetchall()


def test_merged_run_scores_every_episode_as_separate_buckets(tmp_path):
    pack = _pack(tmp_path)
    separate, merged = _run(tmp_path, pack, False), _run(tmp_path, pack, True)
    assert {row[0] for row in separate} == {"merge_place", "merge_pair"}
    assert merged == separate
    for task, success, score, steps, *_ in merged:
        assert (success, steps) == ((1, 1) if task == "merge_pair" else (0, 3))
        assert score == pytest.approx(100.0 if task == "merge_pair" else 100.0 / 3, abs=1e-3)
