"""Task validity (DESIGN section 7): the scripted expert solves every task, `zero` and `random` do not.

CI runs a reduced check: the expert on the first seeds of the tasks it solves reliably, and `zero` on every task
over a short horizon. The full table (50 seeds, expert / zero / random) is `-m slow`; it prints the table that
`python -m dojo.runtime.expert_validity` prints too. No timing is asserted anywhere.
"""

from __future__ import annotations

import pytest
from dojo.runtime.expert_validity import (
    SUCCESS_BAR,
    plan_files,
    policies,
    run_policy,
    summarize,
)

TASKS = ["classify_objects", "cover_blocks", "deposit_coin", "general_pickup", "insert_tubes", "push_t",
         "put_bottles_into_dustbin", "stack_blocks", "stack_blocks_by_language", "stack_bowls", "swap_blocks"]
BELOW_BAR = {
    "classify_objects": "88% (score 94.0; 96% before the tilted-grasp and dustbin changes of 2026-11-24): on 6 of "
                        "50 seeds a fruit or can is knocked off the table or a block is not grasped",
}
"""Tasks whose expert is below the 95% bar in the full table, and why (the README's validity table)."""
CI_SEEDS = 3
ZERO_HORIZON = 40


@pytest.mark.parametrize("task", TASKS)
def test_expert_solves_the_first_seeds(library, plan_cache, task):
    files = plan_files(library, [task], CI_SEEDS, plan_cache, jobs=2)[task]
    outcomes = run_policy(policies()["expert"], files, num_envs=CI_SEEDS)
    assert [o.success for o in outcomes] == [True] * CI_SEEDS, outcomes


def test_zero_policy_never_succeeds(library, plan_cache):
    files = plan_files(library, TASKS, 1, plan_cache, jobs=2)
    outcomes = run_policy(policies()["zero"], [f for t in TASKS for f in files[t]], horizon=ZERO_HORIZON)
    assert sorted(o.task for o in outcomes) == TASKS
    assert not any(o.success for o in outcomes), outcomes
    assert all(o.score == 0.0 for o in outcomes), outcomes


@pytest.mark.slow
@pytest.mark.parametrize("task", TASKS)
def test_validity_table(library, plan_cache, task):
    """50 seeds per task: expert >= 95% (tasks in BELOW_BAR xfail, with their reason), zero 0% and low score,
    random near zero."""
    files = plan_files(library, [task], 50, plan_cache, jobs=2)[task]
    table = policies()
    rates = {name: summarize(run_policy(model, files)) for name, model in table.items()}
    print(f"\n{task}: " + ", ".join(f"{n} {100 * r:.0f}% (score {s:.1f})" for n, (r, s) in rates.items()))
    assert rates["zero"][0] == 0.0 and rates["zero"][1] < 10.0
    assert rates["random"][0] <= 0.04
    if task in BELOW_BAR:
        pytest.xfail(f"expert {100 * rates['expert'][0]:.0f}%: {BELOW_BAR[task]}")
    assert rates["expert"][0] >= SUCCESS_BAR
