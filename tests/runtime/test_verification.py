"""The hidden-layout statistics against known values, and the verdict from store rows."""

from __future__ import annotations

import math

import pytest

from dojo.evaluation.verification import (
    ALPHA,
    NOT_EVALUATED,
    UNVERIFIED,
    VERIFIED,
    compare_success,
    fisher_exact_test,
    two_proportion_z_test,
    verify,
)


def test_z_test_hand_computed():
    # 50/100 vs 30/100: pooled p = 0.4, se = sqrt(0.4 * 0.6 * (1/100 + 1/100)) = 0.0692820, z = 0.2 / se = 2.886751;
    # two-sided p = erfc(z / sqrt 2) = 0.0038924 (normal table: 2 * (1 - Phi(2.8868)) = 0.00389).
    result = two_proportion_z_test(50, 100, 30, 100)
    assert result.statistic == pytest.approx(0.2 / math.sqrt(0.4 * 0.6 * 0.02))
    assert result.statistic == pytest.approx(2.886751, abs=1e-6)
    assert result.p_value == pytest.approx(0.0038924, abs=1e-6)
    assert two_proportion_z_test(30, 100, 50, 100).p_value == pytest.approx(result.p_value)  # two-sided


def test_z_test_equal_rates_gives_p_one():
    assert two_proportion_z_test(10, 100, 20, 200).p_value == pytest.approx(1.0)


def test_fisher_lady_tasting_tea():
    # Fisher's tea-tasting table [[3, 1], [1, 3]]: two-sided p = 17/70 * 2 = 34/70 = 0.485714.
    assert fisher_exact_test(3, 4, 1, 4).p_value == pytest.approx(34 / 70)


def test_fisher_textbook_example():
    # [[1, 9], [11, 3]] (the classic dieting example): two-sided p = 0.0027594 (R: fisher.test -> 0.002759).
    assert fisher_exact_test(1, 10, 11, 14).p_value == pytest.approx(0.0027594, abs=1e-6)


def test_fisher_exhaustive_small_table():
    """Check against a direct sum with exact binomial coefficients."""
    s1, n1, s2, n2 = 2, 9, 7, 11
    k, n = s1 + s2, n1 + n2
    pmf = {x: math.comb(n1, x) * math.comb(n2, k - x) / math.comb(n, k) for x in range(max(0, k - n2), min(k, n1) + 1)}
    expected = sum(p for p in pmf.values() if p <= pmf[s1] * (1 + 1e-9))
    assert fisher_exact_test(s1, n1, s2, n2).p_value == pytest.approx(expected)


def test_small_counts_switch_to_fisher():
    assert compare_success(2, 300, 0, 300).test.startswith("Fisher")  # expected successes 1 < 5
    assert compare_success(0, 300, 0, 300).p_value == pytest.approx(1.0)  # z-test would be undefined
    assert compare_success(60, 300, 50, 300).test.startswith("two-proportion z-test")


def test_invalid_counts_raise():
    with pytest.raises(ValueError):
        compare_success(5, 4, 1, 4)
    with pytest.raises(ValueError):
        compare_success(0, 0, 1, 4)


def _rows(make_row, split, successes, episodes, start=0):
    return [make_row(split=split, episode=start + i, success=i < successes, score=100.0 if i < successes else 0.0)
            for i in range(episodes)]


def test_verdict_verified_when_rates_agree(make_row):
    rows = _rows(make_row, "public", 40, 150) + _rows(make_row, "hidden", 12, 50, start=1000)
    result = verify(rows)
    assert result.verdict == VERIFIED
    assert (result.public_successes, result.public_episodes, result.hidden_successes, result.hidden_episodes) == (
        40, 150, 12, 50)
    assert result.alpha == ALPHA == 0.01
    assert result.test.p_value >= ALPHA


def test_verdict_unverified_when_public_is_much_better(make_row):
    # 60 % on the public layouts, 10 % on the hidden ones: an overfitted submission.
    rows = _rows(make_row, "public", 90, 150) + _rows(make_row, "hidden", 5, 50, start=1000)
    result = verify(rows)
    assert result.verdict == UNVERIFIED
    assert result.test.p_value < 1e-6
    assert "differ significantly" in result.reason


def test_verdict_not_evaluated_without_hidden_rows(make_row):
    result = verify(_rows(make_row, "public", 3, 10))
    assert result.verdict == NOT_EVALUATED
    assert result.test is None and "no hidden" in result.reason
