"""Smoke tests of the Precision tasks built on new mechanisms (strikes, towers, granular contents, keyed
insertion): the expert solves the first scene seed and `zero` does nothing. The 50-seed table (expert >= 95%, zero
and random 0%) is `-m slow`."""

from __future__ import annotations

import os

import pytest
from dojo.experts.validity import SUCCESS_BAR, plan_files, policies, run_episodes, run_policy, summarize

TASKS = ["build_tower", "insert_key", "play_xylophone", "plug_in_charger", "pour_balls_into_vase"]


@pytest.mark.parametrize("task", TASKS)
def test_expert_solves_the_first_seed(library, plan_cache, task):
    files = plan_files(library, [task], 1, plan_cache)[task]
    outcomes = run_policy(policies()["expert"], files, num_envs=1)
    assert [o.success for o in outcomes] == [True], outcomes


def test_zero_policy_scores_nothing(library, plan_cache):
    files = plan_files(library, TASKS, 1, plan_cache)
    outcomes = run_policy(policies()["zero"], [f for t in TASKS for f in files[t]], max_steps=60)
    assert sorted(o.task for o in outcomes) == TASKS
    assert not any(o.success or o.score for o in outcomes), outcomes


@pytest.mark.slow
@pytest.mark.parametrize("task", TASKS)
def test_validity_table(library, plan_cache, task):
    jobs = max(2, os.cpu_count() or 1)
    files = plan_files(library, [task], 50, plan_cache, jobs=jobs)[task]
    rates = {name: summarize(run_episodes(name, files, jobs)) for name in policies()}
    print(f"\n{task}: " + ", ".join(f"{n} {100 * r:.0f}% (score {s:.1f})" for n, (r, s) in rates.items()))
    assert rates["zero"][0] == 0.0 and rates["random"][0] == 0.0
    assert rates["expert"][0] >= SUCCESS_BAR
