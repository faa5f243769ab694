"""Hidden-layout verification: is the success rate on a suite's private seed set consistent with the public one?

The paper (appendix "Hidden verification") marks a submission invalid when "the success rate on the hidden
verification set differs significantly from that on the public evaluation set". We make that concrete:

* Counts: successes and episodes of every `public` row and every `hidden` row of the entry, pooled over
  tasks and seed replicates.
* Test: two-sided two-proportion z-test with the pooled proportion,
  z = (p_pub - p_hid) / sqrt(p (1 - p) (1/n_pub + 1/n_hid)).
  When any expected cell count of the 2x2 table is below 5 the normal approximation is poor (typical here:
  success rates of a few percent), so we use Fisher's exact test instead (two-sided: the summed probability
  of all tables with the same margins that are no more likely than the observed one).
* Level: alpha = 0.01. The verdict is `verified` when p >= alpha, `unverified` when p < alpha. A 1 % level
  keeps the chance of wrongly flagging an honest submission at 1 in 100 per check.
* Without hidden rows the verdict is `not_evaluated`; a run is never called verified without evidence.

Pooling over tasks ignores that tasks have different success rates. When the hidden set covers the same tasks
in the same proportions as the public one (as a suite's hidden seed set does), that heterogeneity makes the
real variance of the difference smaller than the binomial one, so the test errs towards `verified`: it flags
only gaps that are large by any standard.

Only math and the standard library are used (no scipy), so the check runs wherever the runtime does.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from typing import Any

from dojo.evaluation.episode import EpisodeResult

ALPHA = 0.01
MIN_EXPECTED = 5.0  # below this expected cell count, use Fisher's exact test
# Relative tolerance when comparing table probabilities in Fisher's test, so that tables exactly as likely as
# the observed one are counted despite floating-point noise (R's fisher.test uses the same 1e-7).
_FISHER_RELATIVE_TOLERANCE = 1e-7

VERIFIED, UNVERIFIED, NOT_EVALUATED = "verified", "unverified", "not_evaluated"


@dataclass(frozen=True)
class TestResult:
    test: str  # "two-proportion z-test (pooled, two-sided)" or "Fisher exact test (two-sided)"
    statistic: float | None  # z for the z-test, the odds ratio for Fisher (None where undefined)
    p_value: float


@dataclass(frozen=True)
class Verification:
    verdict: str  # VERIFIED | UNVERIFIED | NOT_EVALUATED
    alpha: float
    public_successes: int
    public_episodes: int
    hidden_successes: int
    hidden_episodes: int
    test: TestResult | None
    reason: str

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def two_proportion_z_test(s1: int, n1: int, s2: int, n2: int) -> TestResult:
    """Pooled two-proportion z-test, two-sided. Requires 0 < pooled proportion < 1."""
    _check_counts(s1, n1, s2, n2)
    pooled = (s1 + s2) / (n1 + n2)
    if pooled in (0.0, 1.0):
        raise ValueError("the z-test is undefined when every episode failed or every episode succeeded")
    z = (s1 / n1 - s2 / n2) / math.sqrt(pooled * (1 - pooled) * (1 / n1 + 1 / n2))
    return TestResult(test="two-proportion z-test (pooled, two-sided)", statistic=z,
                      p_value=math.erfc(abs(z) / math.sqrt(2)))


def fisher_exact_test(s1: int, n1: int, s2: int, n2: int) -> TestResult:
    """Fisher's exact test on the table [[s1, n1 - s1], [s2, n2 - s2]], two-sided."""
    _check_counts(s1, n1, s2, n2)
    successes, total = s1 + s2, n1 + n2
    lo, hi = max(0, successes - n2), min(successes, n1)

    def log_pmf(x: int) -> float:  # hypergeometric: x successes among the n1 draws of group 1
        return _log_comb(n1, x) + _log_comb(n2, successes - x) - _log_comb(total, successes)

    observed = log_pmf(s1)
    threshold = observed + math.log1p(_FISHER_RELATIVE_TOLERANCE)
    p = math.fsum(math.exp(lp) for lp in map(log_pmf, range(lo, hi + 1)) if lp <= threshold)
    f1, f2 = n1 - s1, n2 - s2
    odds_ratio = None if s2 * f1 == 0 else (s1 * f2) / (s2 * f1)
    return TestResult(test="Fisher exact test (two-sided)", statistic=odds_ratio, p_value=min(1.0, p))


def compare_success(s1: int, n1: int, s2: int, n2: int) -> TestResult:
    """The z-test when every expected cell count is at least MIN_EXPECTED, otherwise Fisher's exact test."""
    _check_counts(s1, n1, s2, n2)
    successes, failures, total = s1 + s2, (n1 - s1) + (n2 - s2), n1 + n2
    expected = [n * k / total for n in (n1, n2) for k in (successes, failures)]
    if min(expected) < MIN_EXPECTED:
        return fisher_exact_test(s1, n1, s2, n2)
    return two_proportion_z_test(s1, n1, s2, n2)


def verify(rows: Iterable[EpisodeResult], alpha: float = ALPHA) -> Verification:
    """The hidden-layout verdict for one leaderboard entry, from its public and hidden rows."""
    counts = {"public": [0, 0], "hidden": [0, 0]}
    for r in rows:
        counts[r.split][0] += int(r.success)
        counts[r.split][1] += 1
    (s_pub, n_pub), (s_hid, n_hid) = counts["public"], counts["hidden"]
    base = dict(alpha=alpha, public_successes=s_pub, public_episodes=n_pub, hidden_successes=s_hid,
                hidden_episodes=n_hid)
    if n_hid == 0 or n_pub == 0:
        missing = "hidden" if n_hid == 0 else "public"
        return Verification(verdict=NOT_EVALUATED, test=None, reason=f"no {missing} episodes", **base)
    result = compare_success(s_pub, n_pub, s_hid, n_hid)
    rates = f"public {100 * s_pub / n_pub:.1f}% of {n_pub}, hidden {100 * s_hid / n_hid:.1f}% of {n_hid}"
    p = result.p_value
    if p < alpha:
        verdict, reason = UNVERIFIED, f"success rates differ significantly ({rates}; p = {p:.3g} < {alpha})"
    else:
        verdict, reason = VERIFIED, f"no significant difference ({rates}; p = {p:.3g} >= {alpha})"
    return Verification(verdict=verdict, test=result, reason=reason, **base)


def _log_comb(n: int, k: int) -> float:
    return math.lgamma(n + 1) - math.lgamma(k + 1) - math.lgamma(n - k + 1)


def _check_counts(s1: int, n1: int, s2: int, n2: int) -> None:
    if n1 <= 0 or n2 <= 0 or not (0 <= s1 <= n1 and 0 <= s2 <= n2):
        raise ValueError(f"invalid counts: {s1}/{n1} and {s2}/{n2}")
