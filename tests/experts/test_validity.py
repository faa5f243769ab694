"""Task validity (DESIGN section 7): the scripted expert solves every task, `zero` and `random` do not.

CI runs a reduced check: the expert on the first seeds of every task outside the default suite (the README quick
start's plain `dojo run` in CI has the oracle solve the default suite's two episodes per task), and `zero` on every
task over a short horizon. The full table (50 seeds, expert / zero / random) is `-m slow`; it prints the table that
`python -m dojo.experts.validity` prints too. No timing is asserted anywhere.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml
from dojo.experts.validity import (
    SUCCESS_BAR,
    plan_files,
    policies,
    run_episodes,
    run_policy,
    runs,
    summarize,
)
from dojo.experts.memoryless import chance_level

TASKS = ["classify_objects", "cover_blocks", "deposit_coin", "general_pickup", "imitate_sorting_sequence",
         "insert_tubes", "match_and_pick_from_conveyor", "pick_from_conveyor_by_image", "play_tic_tac_toe",
         "press_by_number", "push_t", "put_bottles_into_dustbin", "stack_blocks", "stack_blocks_by_language",
         "stack_bowls", "swap_blocks", "swap_t"]
CI_SEEDS = 2
ZERO_STEPS = 40
# The default suite's tasks are CI's quick start's: its plain `dojo run` has their experts (the oracle) solve two
# episodes of each (tests/test_readme.py), so this file's smoke test runs only the others.
DEFAULT_SUITE = yaml.safe_load((Path(__file__).resolve().parents[2] / "specs" / "suites" / "robodojo_sim_mini.yaml")
                               .read_text())["tasks"]


@pytest.mark.parametrize("task", [t for t in TASKS if t not in DEFAULT_SUITE])
def test_expert_solves_the_first_seeds(library, plan_cache, task):
    files = plan_files(library, [task], CI_SEEDS, plan_cache, jobs="auto")[task]
    outcomes = run_policy(policies()["expert"], files, num_envs=CI_SEEDS)
    assert [o.success for o in outcomes] == [True] * CI_SEEDS, outcomes


def test_zero_policy_never_succeeds(library, plan_cache):
    files = plan_files(library, TASKS, 1, plan_cache, jobs="auto")
    outcomes = run_policy(policies()["zero"], [f for t in TASKS for f in files[t]], max_steps=ZERO_STEPS)
    assert sorted(o.task for o in outcomes) == TASKS
    assert not any(o.success for o in outcomes), outcomes
    assert all(o.score == 0.0 for o in outcomes), outcomes


@pytest.mark.slow
@pytest.mark.parametrize("task", TASKS)
def test_validity_table(library, plan_cache, task):
    """50 seeds per task: expert >= 95%, zero 0% and low score, random near zero, and for a Memory task the expert
    denied the history at most at chance level, give or take two standard errors of 50 episodes (one episode per
    process, as `python -m dojo.experts.validity --jobs N` runs the README's table)."""
    jobs = max(2, os.cpu_count() or 1)
    files = plan_files(library, [task], 50, plan_cache, jobs=jobs)[task]
    spec = library.get("task", task)
    rates = {name: summarize(run_episodes(name, files, jobs)) for name in policies() if runs(name, spec)}
    print(f"\n{task}: " + ", ".join(f"{n} {100 * r:.0f}% (score {s:.1f})" for n, (r, s) in rates.items()))
    assert rates["zero"][0] == 0.0 and rates["zero"][1] < 10.0
    assert rates["random"][0] <= 0.04
    assert rates["expert"][0] >= SUCCESS_BAR
    if "memoryless" in rates:
        chance = chance_level(library, spec)
        assert rates["memoryless"][0] <= chance + 2 * (chance * (1 - chance) / len(files)) ** 0.5 + 1 / len(files)


def test_episodes_in_processes_score_as_in_one(library, plan_cache):
    """`--jobs N` runs one episode per process: the same outcomes as the episodes batched in one backend, and
    the random policy's do not depend on how many processes share the work."""
    files = plan_files(library, ["deposit_coin"], 2, plan_cache, jobs="auto")["deposit_coin"]
    assert run_episodes("expert", files, 2) == run_policy(policies()["expert"], files, num_envs=2)
    assert run_episodes("random", files, 2) == run_episodes("random", files[::-1], 2)[::-1]
