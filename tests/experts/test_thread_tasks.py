"""Smoke tests of fasten_screws (threads, `tightened`, the skill `screw`): the plan compiles with its threads and
`zero` does nothing in it (CI); the expert solves the first scene seed, and the 50-seed table (expert >= 95%, zero
and random 0%, the expert aiming its sockets 3 mm off failing on most seeds) are `-m slow` (about 15 s and 20 min
on one core: `python -m dojo.experts.validity --tasks fasten_screws --seeds 50`, README)."""

from __future__ import annotations

import os

import pytest
from dojo.compiler.plan import Plan
from dojo.experts.validity import SUCCESS_BAR, plan_files, policies, run_episodes, run_policy, summarize

TASK = "fasten_screws"


def test_plan_has_its_threads_and_zero_scores_nothing(library, plan_cache):
    files = plan_files(library, [TASK], 1, plan_cache)[TASK]
    assert "equality:joint" in Plan.load(files[0]).requires  # MJX runs these rows too
    outcomes = run_policy(policies()["zero"], files, max_steps=60)
    assert [(o.success, o.score) for o in outcomes] == [(False, 0.0)]


@pytest.mark.slow
def test_expert_solves_the_first_seed(library, plan_cache):
    files = plan_files(library, [TASK], 1, plan_cache)[TASK]
    outcomes = run_policy(policies()["expert"], files, num_envs=1)
    assert [o.success for o in outcomes] == [True], outcomes


@pytest.mark.slow
def test_validity_table(library, plan_cache):
    jobs = max(2, os.cpu_count() or 1)
    files = plan_files(library, [TASK], 50, plan_cache, jobs=jobs)[TASK]
    rates = {name: summarize(run_episodes(name, files, jobs)) for name in ("expert", "perturbed", "zero", "random")}
    print(f"\n{TASK}: " + ", ".join(f"{n} {100 * r:.0f}% (score {s:.1f})" for n, (r, s) in rates.items()))
    assert rates["zero"][0] == 0.0 and rates["random"][0] == 0.0
    assert rates["expert"][0] >= SUCCESS_BAR
    assert rates["perturbed"][0] < 0.5
