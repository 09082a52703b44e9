"""kftrack.compare: the comparison of two methods over runs, its verdicts, Holm and sweeps.

Exact values are checked against scipy.stats.ttest_rel / ttest_ind(equal_var=False) and against
numbers worked by hand; statistical properties (coverage, power) against binomial bounds at a
stated level over seeded simulations. Verdict cases use data built so that the t statistic is
known exactly (a standardised pattern ``z`` with mean 0 and sample sd 1), so they do not depend
on a seed.
"""
from __future__ import annotations

import dataclasses
import doctest
import math

import numpy as np
import pytest
from scipy import stats

import kftrack.compare as cmp
from kftrack.compare import ComparisonResult, HolmResult, Sweep, compare_runs, compare_sweep, holm

# Round-off: every quantity is a handful of sums and products of O(1) numbers over n <= 10
# values, so its relative error is below ~100 eps; scipy's t quantiles are accurate to ~1e-14.
RTOL = 1e-12
EPS = float(np.finfo(float).eps)
# Binomial bounds: 99.9 % two-sided (a correct implementation fails one such check in 1000).
BOUND = 0.999


def _standardised(n: int) -> np.ndarray:
    """A fixed pattern with mean exactly 0 and sample sd exactly 1 (up to round-off)."""
    z = np.sin(np.arange(1, n + 1) * 1.3)
    z = z - z.mean()
    return z / z.std(ddof=1)


def _binomial_interval(sims: int, p: float) -> tuple[float, float]:
    lo = stats.binom.ppf((1 - BOUND) / 2, sims, p) / sims
    hi = stats.binom.ppf((1 + BOUND) / 2, sims, p) / sims
    return lo, hi


# ------------------------------------------------------------------------------------------
# exact values
# ------------------------------------------------------------------------------------------
def test_paired_difference_matches_hand_computation_and_ttest_rel():
    b = np.array([10.0, 12.0, 9.0, 11.0, 10.5])
    a = b + np.array([-1.0, 0.0, 1.0, 2.0, 3.0])  # d: mean 1, sample variance 2.5
    r = compare_runs(a, b)
    se = math.sqrt(2.5 / 5)  # 0.70711
    t975, t80 = stats.t.ppf([0.975, 0.8], 4)
    assert (round(t975, 3), round(t80, 3)) == (2.776, 0.941)  # printed t tables, 4 degrees of freedom
    assert r.estimate == pytest.approx(1.0, rel=RTOL) and r.delta == r.estimate
    assert r.se == pytest.approx(se, rel=RTOL)
    assert r.df == 4 and r.n == 5 and (r.n_a, r.n_b) == (5, 5) and r.paired
    assert r.ci == pytest.approx((1 - t975 * se, 1 + t975 * se), rel=RTOL)  # (-0.9632, 2.9632)
    assert r.mde == pytest.approx((t975 + t80) * se, rel=RTOL)
    ref = stats.ttest_rel(a, b)
    assert r.p_value == pytest.approx(ref.pvalue, rel=RTOL)
    assert r.ci == pytest.approx(tuple(ref.confidence_interval(0.95)), rel=RTOL)
    assert r.verdict == "not resolved by 5 runs" and r.kind == "not resolved"
    assert r.margin is None and r.equivalent is None and r.p_equivalence is None
    assert r.tests == 1 and r.p_adjusted == r.p_value


def test_welch_matches_hand_computation_and_ttest_ind():
    a = np.array([1.0, 2.0, 3.0, 4.0])
    b = np.array([2.0, 4.0, 6.0, 8.0, 10.0, 12.0])
    r = compare_runs(a, b, paired=False)
    va, vb = (5 / 3) / 4, 14.0 / 6  # s_a^2 / n_a, s_b^2 / n_b
    df = (va + vb) ** 2 / (va**2 / 3 + vb**2 / 5)  # Welch-Satterthwaite, 6.5946
    assert r.estimate == pytest.approx(-4.5, rel=RTOL)
    assert r.se == pytest.approx(math.sqrt(va + vb), rel=RTOL)
    assert r.df == pytest.approx(df, rel=RTOL)
    ref = stats.ttest_ind(a, b, equal_var=False)
    assert r.p_value == pytest.approx(ref.pvalue, rel=RTOL)
    assert r.ci == pytest.approx(tuple(ref.confidence_interval(0.95)), rel=RTOL)
    assert (r.n_a, r.n_b, r.n, r.paired) == (4, 6, 10, False)
    assert r.verdict == "lower"  # p = 0.034


def test_log_ratio_is_the_t_interval_of_the_mean_log_ratio_reported_as_a_ratio():
    b = np.array([10.0, 12.0, 9.0, 11.0, 10.5])
    logs = 0.01 * np.array([-1.0, 0.0, 1.0, 2.0, 3.0])
    a = b * np.exp(logs)
    r = compare_runs(a, b, scale="log_ratio", level=0.9)
    se = 0.01 * math.sqrt(0.5)
    t95 = stats.t.ppf(0.95, 4)
    assert round(t95, 3) == 2.132  # printed t tables
    assert r.delta == pytest.approx(0.01, rel=1e-10)  # log of a ratio: relative error ~ eps / 0.01
    assert r.estimate == pytest.approx(math.exp(0.01), rel=RTOL)
    assert r.se == pytest.approx(se, rel=1e-10)
    assert r.ci == pytest.approx((math.exp(0.01 - t95 * se), math.exp(0.01 + t95 * se)), rel=RTOL)
    assert r.p_value == pytest.approx(stats.ttest_rel(np.log(a), np.log(b)).pvalue, rel=1e-10)
    unpaired = compare_runs(a, b, scale="log_ratio", paired=False)
    assert unpaired.estimate == pytest.approx(math.exp(np.log(a).mean() - np.log(b).mean()), rel=RTOL)
    assert unpaired.p_value == pytest.approx(stats.ttest_ind(np.log(a), np.log(b), equal_var=False).pvalue, rel=1e-10)


# ------------------------------------------------------------------------------------------
# no spread: every paired difference the same (identical runs, or by chance), exact tests
# ------------------------------------------------------------------------------------------
def test_identical_runs_are_equal_in_each_run_not_a_zero_width_interval():
    for margin in (None, 0.1):
        same = compare_runs([1.0, 2.0, 3.0], [1.0, 2.0, 3.0], margin=margin)
        assert same.exact and same.verdict == "equal" and same.kind == "equal"
        assert same.se == 0 and same.mde == 0 and same.ci == (0.0, 0.0) and same.p_value == 1
        # a statement about these runs, not a population equality: the sentence says "in each of the 3"
        assert str(same) == ("A's value equals B's in each of the 3 paired runs (to round-off; these runs only, "
                             "no interval to compute): equal")
    # equivalence from no difference in 3 runs is a sign-test TOST: one-sided 2^-3 = 0.125, not shown at 0.95
    assert same.p_equivalence == 0.125 and same.equivalent is False
    many = compare_runs(np.arange(1.0, 9.0), np.arange(1.0, 9.0), margin=0.1)  # 2^-8 = 0.0039
    assert many.verdict == "equal" and many.p_equivalence == 2.0**-8 and many.equivalent is True
    ratio = compare_runs([1.0, 2.0, 3.0], [1.0, 2.0, 3.0], scale="log_ratio")
    assert ratio.exact and ratio.verdict == "equal" and ratio.estimate == 1.0 and ratio.ci == (1.0, 1.0)
    unpaired = compare_runs([2.0, 2.0, 2.0], [2.0, 2.0], paired=False)
    assert unpaired.exact and unpaired.verdict == "equal" and unpaired.p_value == 1
    assert "equals B's in each of the 3 + 2 unpaired runs (one value on every run of either method" in str(unpaired)


def test_zero_spread_by_chance_gets_the_exact_sign_test_paired():
    """0/1 data: all-ones against all-zeros in n paired runs is the same difference by chance.
    The exact two-sided sign test gives p = 2^(1-n): 0.25 at n = 3, 0.0625 at n = 5, 0.03125 at n = 6."""
    for n, p, kind in ((3, 0.25, "not resolved"), (5, 0.0625, "not resolved"), (6, 0.03125, "higher")):
        r = compare_runs(np.ones(n), np.zeros(n))
        assert r.exact and r.estimate == 1.0 and r.se == 0 and r.ci == (1.0, 1.0)
        assert r.p_value == p == pytest.approx(stats.binomtest(n, n).pvalue, rel=RTOL)  # scipy's exact sign test
        assert r.kind == kind, (n, r.verdict)
    r = compare_runs(np.ones(3), np.zeros(3))
    assert r.verdict == "not resolved by 3 runs"
    assert str(r) == ("A's value minus B's is 1 (the same difference in each of the 3 paired runs, to round-off; "
                      "exact sign test p = 0.25): not resolved by 3 runs (the sign test needs 6 runs of one sign "
                      "for p < 0.05)")
    assert compare_runs(np.zeros(5), np.ones(5), level=0.9).verdict == "lower"  # 0.0625 < 0.1
    b = np.array([1.0, 1.2, 0.9, 1.1, 1.05, 0.95])
    lower = compare_runs(0.9 * b, b, scale="log_ratio")  # the same ratio on 6 runs: p = 1/32
    assert lower.exact and lower.verdict == "lower" and lower.estimate == pytest.approx(0.9, rel=RTOL)
    assert lower.sentence("A", "B", "RMSE") == ("A's RMSE is 0.9× B's (the same ratio in each of the 6 paired runs, "
                                                "to round-off; exact sign test p = 0.031): lower")
    # TOST from the one-sided sign tests: 2^-6 = 0.016 inside the margin; outside, no equivalence
    inside = compare_runs(np.arange(6.0) + 1.0, np.arange(6.0), margin=1.5)
    outside = compare_runs(np.arange(6.0) + 1.0, np.arange(6.0), margin=0.5)
    assert inside.p_equivalence == 2.0**-6 and inside.equivalent is True
    assert inside.verdict == "higher" and str(inside).endswith("higher, yet equivalent within ±1.5")
    assert outside.p_equivalence == 1 and outside.equivalent is False and str(outside).endswith("): higher")


def test_zero_spread_by_chance_gets_the_exact_permutation_test_unpaired():
    """3 + 3 all-ones against all-zeros: Fisher's exact test (the permutation test of the means for two
    values) gives p = 2 / C(6, 3) = 0.1; 3 + 4: 1 / C(7, 3) = 1/35 (no mirror labelling as extreme)."""
    r = compare_runs(np.ones(3), np.zeros(3), paired=False)
    assert r.exact and r.estimate == 1.0 and r.p_value == pytest.approx(0.1, rel=RTOL)
    assert r.p_value == pytest.approx(stats.fisher_exact([[3, 0], [0, 3]]).pvalue, rel=RTOL)
    assert r.verdict == "not resolved by 3 + 3 runs"
    assert str(r) == ("A's value minus B's is 1 (3 + 3 unpaired runs, each method the same value on every run, "
                      "to round-off; exact permutation test p = 0.1): not resolved by 3 + 3 runs")
    r = compare_runs([2.0, 2.0, 2.0], [1.0, 1.0, 1.0, 1.0], paired=False)
    assert r.p_value == pytest.approx(1 / 35, rel=RTOL)
    assert r.p_value == pytest.approx(stats.fisher_exact([[3, 0], [0, 4]]).pvalue, rel=RTOL)
    assert r.verdict == "higher" and r.estimate == 1.0
    with_margin = compare_runs([2.0, 2.0, 2.0], [1.0, 1.0, 1.0, 1.0], paired=False, margin=1.5)
    assert with_margin.p_equivalence == pytest.approx(1 / 35, rel=RTOL) and with_margin.equivalent


def test_exact_results_enter_holm_with_their_exact_p_values():
    six = compare_runs(np.ones(6), np.zeros(6))  # sign test p = 1/32: "higher" alone
    equal = compare_runs([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])
    noisy = compare_runs([1.0, 2.0, 3.0], [1.5, 2.0, 2.0])
    family = holm([six, equal, noisy])
    # Holm over 3: 3 * 1/32 = 0.094 > 0.05, so the exact result is adjusted like any other
    assert family[0].p_adjusted == pytest.approx(3 / 32, rel=RTOL) and family[0].kind == "not resolved"
    assert [r.kind for r in family[1:]] == ["equal", "not resolved"]
    assert "exact sign test p = 0.031; Holm over 3 tests, adjusted p = 0.094" in str(family[0])
    np.testing.assert_allclose([r.p_adjusted for r in family],
                               holm([r.p_value for r in (six, equal, noisy)]).p_adjusted, rtol=RTOL)
    base = np.arange(1.0, 7.0)
    sw = compare_sweep([0.0, 1.0], lambda s: (base - s, base))
    assert [r.kind for r in sw.results] == ["equal", "lower"] and sw.flips == ((0.0, 1.0),)


def test_round_off_bound_is_per_run():
    b = np.array([0.3, 1.7, 2.9, 10.1, 0.01])
    a = b + 0.1  # d = 0.1 up to the rounding of each sum: run i spreads by ~ eps * s_i
    d, s = a - b, np.maximum(a, b)
    assert 0 < np.ptp(d) and np.max(d - 64 * EPS * s) <= np.min(d + 64 * EPS * s)  # the case meant: real round-off
    r = compare_runs(a, b, level=0.9)  # 5 runs of one sign: sign test p = 1/16 < 0.1
    assert r.exact and r.verdict == "higher" and "is 0.1 (the same difference" in str(r)
    twin = compare_runs(b * (1 + 2 * EPS), b)  # a difference of round-off size is 0
    assert twin.exact and twin.verdict == "equal" and twin.estimate == 0
    # a spread of 1e-9, far above the round-off bound (64 eps * 2 * 10.1 = 2.9e-13), is noise to test against
    noisy = compare_runs(b + 0.1 + 1e-9 * _standardised(5), b)
    assert not noisy.exact and noisy.se > 0 and noisy.verdict == "higher" and "95 % CI" in str(noisy)
    # one run at 1e6 must not hide a real relative spread of 2e-9 in the others: a bound from the largest value
    # over all runs (64 eps * 1e6 = 1.4e-8) would call this "no spread"; run by run it is 64 eps * 2 = 2.8e-14
    n = 8
    big = np.r_[1e6, np.linspace(1.0, 2.0, n - 1)]
    a = big + np.r_[0.0, 2e-9 * (0.3 + _standardised(n - 1))]  # real spread (relative <= 2e-9 * 2.3)
    d = a - big
    assert np.ptp(d) <= 64 * EPS * 1e6  # the global bound would have called it no spread ("equal")
    r = compare_runs(a, big)
    assert not r.exact and r.se > 0
    assert r.p_value == pytest.approx(stats.ttest_rel(a, big).pvalue, rel=1e-9)  # d is exact to ~1e-7 relative
    assert r.verdict == "not resolved by 8 runs"
    # the analogue for log ratios: s_i = max(|log a_i|, |log b_i|, 1), so the 1e6 run (log 13.8) widens only itself
    r = compare_runs(a, big, scale="log_ratio")
    assert not r.exact and r.verdict == "not resolved by 8 runs"


def test_rtol_states_the_round_off_of_recursive_quantities():
    """Joseph against short-form covariance updates (identical in exact arithmetic) give per-run values
    that differ by about 1.4e-10 relative after 500 steps: far above 64 eps, so by default a t test, which
    reads the round-off as a result. rtol=1e-9 states that round-off level: no difference."""
    n = 20
    b = np.linspace(1.0, 2.0, n)  # per-run RMSE of the short form
    t = stats.t.isf(0.015, n - 1)  # the t statistic of two-sided p = 0.03
    w = -t / math.sqrt(n) + _standardised(n)  # mean -t / sqrt(n), sample sd 1
    a = b + 1.4e-10 * w / np.abs(w).max()  # the Joseph form: at most 1.4e-10 (relative, b >= 1) from b
    default = compare_runs(a, b)
    assert not default.exact and default.verdict == "lower"
    # t is scale-free; rounding a (|a| < 2) moves each d_i by at most eps = 2.2e-16, 3e-6 of their sample sd
    # (1.4e-10 / 1.91 = 7.3e-11), so t by ~1e-5 relative and p by < 1e-4 (|d log p / d log t| = 2.4 at t = 2.36)
    assert default.p_value == pytest.approx(0.03, rel=1e-3)
    stated = compare_runs(a, b, rtol=1e-9)
    assert stated.exact and stated.verdict == "equal" and stated.p_value == 1 and stated.rtol == 1e-9
    assert str(stated) == ("A's value equals B's in each of the 20 paired runs (to the stated round-off 1e-09; "
                           "these runs only, no interval to compute): equal")
    assert compare_runs(a, b, scale="log_ratio", rtol=1e-9).verdict == "equal"
    # an rtol below the spread leaves the t test in place
    below = compare_runs(a, b, rtol=1e-11)
    assert not below.exact and below.verdict == "lower" and below.p_value == default.p_value


def test_result_is_immutable():
    r = compare_runs([1.0, 2.0, 3.0], [1.5, 2.0, 2.0])
    assert isinstance(r, ComparisonResult)
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.verdict = "lower"


# ------------------------------------------------------------------------------------------
# verdicts (t statistic fixed by construction: t = mu * sqrt(n) / s)
# ------------------------------------------------------------------------------------------
def test_tiny_effect_few_runs_must_be_not_resolved():
    n = 5
    r = compare_runs(0.01 + _standardised(n), np.zeros(n))  # t = 0.022
    assert r.verdict == "not resolved by 5 runs" and r.kind == "not resolved"
    assert r.ci[0] < 0 < r.ci[1]
    assert r.mde > 100 * abs(r.estimate)  # the runs could only have seen a hundred times the effect


def test_clear_effects_say_lower_and_higher():
    n = 50
    low = compare_runs(-0.5 + _standardised(n), np.zeros(n))  # t = -3.5
    assert low.verdict == "lower" and low.ci[1] < 0
    b = np.linspace(1.0, 2.0, 20)
    high = compare_runs(b * np.exp(0.05 + 0.05 * _standardised(20)), b, scale="log_ratio")  # t = 4.5
    assert high.verdict == "higher" and high.ci[0] > 1


def test_equivalence_within_margin_by_tost():
    n = 100
    r = compare_runs(0.01 + 0.1 * _standardised(n), np.zeros(n), margin=0.1)  # delta 0.01, se 0.01
    assert r.verdict == "equivalent within ±0.1" and r.kind == "equivalent" and r.equivalent
    assert r.ci[0] < 0 < r.ci[1]  # not significant, and
    ref = max(stats.ttest_1samp(0.01 + 0.1 * _standardised(n), -0.1, alternative="greater").pvalue,
              stats.ttest_1samp(0.01 + 0.1 * _standardised(n), 0.1, alternative="less").pvalue)
    assert r.p_equivalence == pytest.approx(ref, rel=1e-9) and r.p_equivalence < 0.05


def test_not_significant_but_too_wide_for_equivalence_is_not_resolved():
    """DESIGN rule 2: a test that fails to reject proves nothing unless it could have rejected."""
    n = 10
    r = compare_runs(0.01 + _standardised(n), np.zeros(n), margin=0.1)  # 90 % CI 0.01 ± 0.58
    assert r.p_value > 0.5
    assert r.equivalent is False and r.verdict == "not resolved by 10 runs"


def test_tost_uses_the_one_minus_two_alpha_interval():
    """With level 0.95, equivalence needs the 90 % interval inside the margin, not the 95 %."""
    n, delta, se = 30, 0.02, 0.01
    d = delta + se * math.sqrt(n) * _standardised(n)
    m = delta + 0.5 * (stats.t.ppf(0.95, n - 1) + stats.t.ppf(0.975, n - 1)) * se  # between the two bounds
    r = compare_runs(d, np.zeros(n), margin=m)
    assert r.ci[1] > m  # the 95 % interval pokes out of the margin ...
    assert r.equivalent and r.kind == "equivalent"  # ... the 90 % one does not: equivalent
    assert compare_runs(d, np.zeros(n), margin=0.99 * (delta + stats.t.ppf(0.95, n - 1) * se)).equivalent is False


def test_ratio_margin_is_the_interval_one_plus_minus_m():
    b = np.linspace(1.0, 2.0, 100)
    r = compare_runs(b * np.exp(0.002 + 0.01 * _standardised(100)), b, scale="log_ratio", margin=0.05)
    assert r.verdict == "higher" and r.equivalent  # significant, and inside (0.95, 1.05)
    assert "higher, yet equivalent within ±5 %" in r.sentence("IMM", "CV", "RMSE")
    # bounds log(0.95) and log(1.05): a ratio of 0.96 is inside, 1.04 too, 0.94 is not
    for ratio, inside in ((0.96, True), (1.04, True), (0.94, False)):
        r = compare_runs(b * ratio * np.exp(1e-4 * _standardised(100)), b, scale="log_ratio", margin=0.05)
        assert r.equivalent is inside, ratio


def test_significant_but_small_difference_is_lower_and_equivalent():
    n = 100
    r = compare_runs(-0.05 + 0.1 * _standardised(n), np.zeros(n), margin=0.1)
    assert r.verdict == "lower" and r.equivalent is True


# ------------------------------------------------------------------------------------------
# statistical properties over seeded simulations
# ------------------------------------------------------------------------------------------
def test_paired_interval_covers_the_true_difference_at_its_level():
    rng = np.random.default_rng(20261203)
    sims, n, true = 2000, 10, 0.3
    scenario = 5.0 * rng.standard_normal((sims, n))  # run-to-run spread shared by both methods
    a = scenario + true + rng.standard_normal((sims, n))
    b = scenario + 0.5 * rng.standard_normal((sims, n))
    covered = sum(r.ci[0] <= true <= r.ci[1] for r in map(compare_runs, a, b))
    lo, hi = _binomial_interval(sims, 0.95)  # [0.934, 0.964]
    assert lo <= covered / sims <= hi, covered / sims


def test_log_ratio_and_welch_intervals_cover_at_their_level():
    rng = np.random.default_rng(7)
    sims = 1000
    lo, hi = _binomial_interval(sims, 0.95)  # [0.927, 0.971]
    b = np.exp(rng.standard_normal((sims, 8)))
    a = b * 0.9 * np.exp(0.05 * rng.standard_normal((sims, 8)))  # geometric-mean ratio 0.9
    covered = np.mean([r.ci[0] <= 0.9 <= r.ci[1] for r in
                       (compare_runs(x, y, scale="log_ratio") for x, y in zip(a, b))])
    assert lo <= covered <= hi, covered
    # Welch with unequal sizes and variances (its interval is approximate: coverage 0.952 here
    # by a 10^5-run check, far inside the bound)
    xa = 1.0 + rng.standard_normal((sims, 6))
    xb = 3.0 * rng.standard_normal((sims, 15))
    covered = np.mean([r.ci[0] <= 1.0 <= r.ci[1] for r in
                       (compare_runs(x, y, paired=False) for x, y in zip(xa, xb))])
    assert lo <= covered <= hi, covered


def test_minimal_detectable_effect_is_detected_four_times_in_five():
    n = 10
    mde = compare_runs(_standardised(n), np.zeros(n)).mde  # sample sd 1: the mde of sd-1 runs
    assert mde == pytest.approx((stats.t.ppf(0.975, 9) + stats.t.ppf(0.8, 9)) / math.sqrt(n), rel=RTOL)
    rng = np.random.default_rng(11)
    sims = 2000
    d = mde + rng.standard_normal((sims, n))
    rejected = np.mean([compare_runs(x, np.zeros(n)).kind != "not resolved" for x in d])
    lo, hi = _binomial_interval(sims, 0.8)  # [0.771, 0.828]; the exact power at n = 10 is 0.799
    assert lo <= rejected <= hi, rejected


@pytest.mark.parametrize("df", [5, 9, 20, 100, 1000])
def test_docstring_claim_exact_power_at_mde_is_080_within_001(df):
    tc = stats.t.ppf(0.975, df)
    lam = tc + stats.t.ppf(0.8, df)  # noncentrality of a true effect equal to the mde
    power = stats.nct.sf(tc, df, lam) + stats.nct.cdf(-tc, df, lam)
    assert abs(power - 0.8) < 0.01, power


# ------------------------------------------------------------------------------------------
# Holm
# ------------------------------------------------------------------------------------------
def test_holm_on_hand_worked_examples():
    # m = 4; sorted 0.005, 0.01, 0.03, 0.04 -> 4*0.005 = 0.02, 3*0.01 = 0.03, 2*0.03 = 0.06,
    # max(0.06, 1*0.04) = 0.06; step-down stops at 0.03 > 0.05/2
    h = holm([0.01, 0.04, 0.03, 0.005])
    assert isinstance(h, HolmResult)
    np.testing.assert_allclose(h.p_adjusted, [0.03, 0.06, 0.06, 0.02], rtol=RTOL)
    assert h.reject.tolist() == [True, False, False, True]
    # Holm rejects all four where Bonferroni (4 * 0.013 = 0.052) rejects one:
    # 0.004, 3*0.013 = 0.039, max(0.039, 2*0.014 = 0.028) = 0.039, 1*0.04 = 0.04
    h = holm([0.001, 0.013, 0.014, 0.04])
    np.testing.assert_allclose(h.p_adjusted, [0.004, 0.039, 0.039, 0.04], rtol=RTOL)
    assert h.reject.all() and not holm([0.001, 0.013, 0.014, 0.04], level=0.99).reject[1:].any()
    assert holm([0.2, 0.9]).p_adjusted.tolist() == [0.4, 0.9]


def test_holm_adjusts_the_verdicts_of_a_family_of_comparisons():
    n = 30
    z = _standardised(n)
    # t = 4, 2.2, -2.1 (p = 0.0004, 0.036, 0.044): each alone is a verdict, but over the family
    # of 3 the last two have adjusted p 2*0.036 = 0.072 > 0.05
    raw = [compare_runs(t / math.sqrt(n) + z, np.zeros(n)) for t in (4.0, 2.2, -2.1)]
    assert [r.verdict for r in raw] == ["higher", "higher", "lower"]
    adj = holm(raw)
    ps = np.array([r.p_value for r in raw])
    np.testing.assert_allclose([r.p_adjusted for r in adj], holm(ps).p_adjusted, rtol=RTOL)
    assert [r.verdict for r in adj] == ["higher", "not resolved by 30 runs", "not resolved by 30 runs"]
    assert all(r.tests == 3 for r in adj) and [r.p_value for r in adj] == ps.tolist()
    assert adj[0].ci == raw[0].ci  # intervals are not adjusted
    assert "Holm over 3 tests, adjusted p = 0.072" in adj[1].sentence()
    # a result with a margin adds its TOST to the family
    eq = compare_runs(0.01 + 0.1 * _standardised(100), np.zeros(100), margin=0.1)
    adj = holm([raw[0], eq])
    assert all(r.tests == 3 for r in adj) and adj[1].verdict == "equivalent within ±0.1"
    assert adj[1].p_equivalence_adjusted == pytest.approx(min(1.0, 2 * eq.p_equivalence), rel=RTOL)


# ------------------------------------------------------------------------------------------
# sweep
# ------------------------------------------------------------------------------------------
def test_sweep_returns_one_result_per_value_and_the_flips():
    z = _standardised(20)
    sw = compare_sweep([0.0, 0.1, 0.5, 1.0, 2.0], lambda s: (1.0 + 0.8 * (1.0 - s) + z, np.ones(20)))
    assert isinstance(sw, Sweep) and len(sw.results) == 5  # t = 0.8 (1 - s) sqrt(20) = 3.58 (1 - s); t_c = 2.09
    assert [r.kind for r in sw.results] == ["higher", "higher", "not resolved", "not resolved", "lower"]
    assert sw.values == (0.0, 0.1, 0.5, 1.0, 2.0) and sw.flips == ((0.1, 0.5), (1.0, 2.0))
    sw = compare_sweep([0.0, 1.0], lambda s: (1.0 + s * 0.6 + z, np.ones(20)), adjust="holm")
    assert [r.tests for r in sw.results] == [2, 2] and sw.results[1].verdict == "higher"


# ------------------------------------------------------------------------------------------
# sentences
# ------------------------------------------------------------------------------------------
def test_sentences_show_only_digits_above_the_standard_error():
    b = np.linspace(1.0, 2.0, 200)
    r = compare_runs(b * 0.93 * np.exp(0.1 * _standardised(200)), b, scale="log_ratio")  # se = 0.0066
    assert r.sentence("A", "B", "RMSE") == "A's RMSE is 0.930× B's (95 % CI 0.917–0.943, 200 paired runs): lower"
    r = compare_runs(-0.12 + 0.3 * _standardised(50), np.zeros(50))  # se = 0.042
    assert str(r) == "A's value minus B's is -0.12 (95 % CI -0.21 to -0.03, 50 paired runs): lower"
    assert r.sentence(unit="m").endswith("-0.21 to -0.03 m, 50 paired runs): lower")
    # a bound that would round onto 0 keeps the digits that show which side of 0 it lies
    n = 100
    tc = stats.t.ppf(0.975, n - 1)
    r = compare_runs(-(tc * 0.01 + 0.0002) + 0.1 * _standardised(n), np.zeros(n))
    assert r.verdict == "lower" and "to -0.0002," in str(r)
    r = compare_runs([1.3, 0.7, 1.15], [2.0, 2.1, 1.9], paired=False)
    assert "3 + 3 unpaired runs, Welch" in str(r)


def test_docstring_examples_hold():
    failed, attempted = doctest.testmod(cmp, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert attempted >= 8 and failed == 0


# ------------------------------------------------------------------------------------------
# bad input, named
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("args, kwargs, exc, match", [
    (([[1.0, 2.0], [3.0, 4.0]], [1.0, 2.0]), {}, ValueError, r"a must be 1-D .* got shape \(2, 2\)"),
    (([1.0, 2.0], [1.0]), {"paired": False}, ValueError, r"b must be 1-D .*at least 2 runs, got shape \(1,\)"),
    (([1.0, np.nan], [1.0, 2.0]), {}, ValueError, "a must be finite"),
    (([1.0, 2.0], [1.0, np.inf]), {}, ValueError, "b must be finite"),
    (([1.0, 2.0, 3.0], [1.0, 2.0]), {}, ValueError, r"same number of runs when paired, got shapes \(3,\) and \(2,\)"),
    (([1.0, 2.0], [1.0, 2.0]), {"level": 1.0}, ValueError, r"level must be in \(0, 1\)"),
    (([1.0, 2.0], [1.0, 2.0]), {"level": 95}, ValueError, r"level must be in \(0, 1\)"),
    (([1.0, 2.0], [1.0, 2.0]), {"level": "0.95"}, TypeError, "level must be a real number"),
    (([1.0, 2.0], [1.0, 2.0]), {"margin": 0.0}, ValueError, "margin must be > 0"),
    (([1.0, 2.0], [1.0, 2.0]), {"margin": float("nan")}, ValueError, "margin must be finite"),
    (([1.0, 2.0], [1.0, 2.0]), {"margin": 1.5, "scale": "log_ratio"}, ValueError, "margin must be > 0 and < 1"),
    (([1.0, 2.0], [1.0, 2.0]), {"margin": 0.1, "level": 0.4}, ValueError, "level must be > 0.5"),
    (([1.0, 0.0], [1.0, 2.0]), {"scale": "log_ratio"}, ValueError, "a must be > 0 for scale='log_ratio'"),
    (([1.0, 2.0], [1.0, 2.0]), {"scale": "ratio"}, ValueError, "scale must be one of"),
    (([1.0, 2.0], [1.0, 2.0]), {"paired": "yes"}, TypeError, "paired must be True or False"),
    (([1.0, 2.0], [1.0, 2.0]), {"rtol": -1e-9}, ValueError, r"rtol must be a relative round-off level in \[0, 1\)"),
    (([1.0, 2.0], [1.0, 2.0]), {"rtol": "1e-9"}, TypeError, "rtol must be a real number"),
    ((None, [1.0, 2.0]), {}, TypeError, "a must be an array of real numbers"),
])
def test_bad_input_names_the_argument(args, kwargs, exc, match):
    with pytest.raises(exc, match=match):
        compare_runs(*args, **kwargs)


def test_bad_input_to_holm_and_sweep_names_the_argument():
    r95 = compare_runs([1.0, 2.0, 3.0], [1.5, 2.0, 2.0])
    r90 = compare_runs([1.0, 2.0, 3.0], [1.5, 2.0, 2.0], level=0.9)
    with pytest.raises(TypeError, match="results must be a non-empty sequence"):
        holm([])
    with pytest.raises(ValueError, match="level must be the same for every result"):
        holm([r95, r90])
    with pytest.raises(ValueError, match="level must be the same for every result"):
        holm([r95], level=0.9)
    with pytest.raises(TypeError, match="not a mix"):
        holm([r95, 0.01])
    with pytest.raises(ValueError, match=r"p-values in \[0, 1\]"):
        holm([0.01, 1.2])
    with pytest.raises(TypeError, match="fn must be callable"):
        compare_sweep([1.0], None)
    with pytest.raises(ValueError, match="values must be a non-empty sequence"):
        compare_sweep([], lambda v: ([1.0, 2.0], [1.0, 2.0]))
    with pytest.raises(TypeError, match="fn must return a pair"):
        compare_sweep([1.0], lambda v: [1.0, 2.0])
    with pytest.raises(ValueError, match="adjust must be None or 'holm'"):
        compare_sweep([1.0], lambda v: ([1.0, 2.0], [1.0, 2.0]), adjust="bonferroni")
