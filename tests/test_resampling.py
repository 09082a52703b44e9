"""Resampling schemes: unbiased offspring counts (chi-square), their variances, ESS, bad input."""
import numpy as np
import pytest
from scipy import stats

from kftrack import resampling as rs

LEVEL = 1e-3  # every statistical test below: two-sided (or stated one-sided) at this level
M = 20_000    # independent resamplings, one batch call


def _weights(N=12, seed=3):
    w = np.random.default_rng(seed).gamma(0.7, size=N)
    return w / w.sum()


def wald_statistic(counts: np.ndarray, expected: np.ndarray) -> tuple[float, int]:
    """Chi-square (Wald) statistic of the mean offspring counts against ``expected``.

    ``counts`` (M, N) from M independent resamplings. Under unbiasedness the mean count vector
    is asymptotically Gaussian with covariance Sigma / M, Sigma the (scheme-dependent, singular:
    the counts sum to N) covariance of one draw, estimated from the draws; the statistic
    M d^T Sigma^+ d is then chi-square with rank(Sigma) degrees of freedom.
    """
    d = counts.mean(axis=0) - expected
    S = np.cov(counts, rowvar=False)
    lam, V = np.linalg.eigh(S)
    keep = lam > 1e-9 * lam.max()
    proj = V[:, keep].T @ d
    stat = counts.shape[0] * np.sum(proj**2 / lam[keep])
    # directions of zero variance must show zero mean deviation (a deterministic count)
    assert np.all(np.abs(V[:, ~keep].T @ d) < 1e-9)
    return float(stat), int(keep.sum())


@pytest.mark.parametrize("method", rs.METHODS)
def test_offspring_counts_are_unbiased_by_chi_square(method):
    w = _weights()
    N = w.size
    c = rs.offspring_counts(np.broadcast_to(w, (M, N)), np.random.default_rng(11), method)
    assert c.shape == (M, N) and np.all(c.sum(axis=1) == N) and np.all(c >= 0)
    stat, dof = wald_statistic(c, N * w)
    assert stat < stats.chi2.ppf(1 - LEVEL, dof), (method, stat, dof)
    # the package's version of the same test agrees with this independent one
    s_pkg, dof_pkg, p = rs.offspring_chi_square(c, w)
    assert dof_pkg == dof and abs(s_pkg - stat) < 1e-8 * max(stat, 1.0) and p > LEVEL


def test_the_chi_square_test_rejects_a_biased_scheme():
    """The same test fails on a plausible but biased rule: largest-remainder rounding of N w
    (deterministic, so bias shows as soon as a count is not N w exactly), and on systematic
    resampling with the uniform fixed at 0.5 (the bias of 'deterministic systematic')."""
    w = _weights()
    N = w.size
    base = np.floor(N * w).astype(int)
    order = np.argsort(-(N * w - base))
    rounded = base.copy()
    rounded[order[: N - base.sum()]] += 1
    d = rounded - N * w
    assert np.max(np.abs(d)) > 0.1  # a real bias per draw, which M draws cannot average away
    # systematic with U = 0.5 for every draw: counts are deterministic, again biased
    C = np.cumsum(w)
    fixed = np.diff(np.clip(np.ceil(N * C - 0.5), 0, N), prepend=0)
    noisy = np.broadcast_to(fixed, (M, N)) + np.random.default_rng(0).normal(0, 0.05, (M, N))  # keep Sigma invertible
    stat, dof = wald_statistic(noisy, N * w)
    assert stat > stats.chi2.ppf(1 - LEVEL, dof)
    # the package's test: deterministic rounding has no variance in the directions it is off in
    assert rs.offspring_chi_square(np.broadcast_to(rounded, (M, N)), w)[2] < LEVEL
    assert rs.offspring_chi_square(noisy, w)[2] < LEVEL


def test_systematic_and_stratified_counts_vary_less_than_multinomial():
    """Sum over particles of Var(c_i): multinomial N(1 - sum w^2) exactly; the others estimated
    from M draws, with the upper end of a one-sided 1 - LEVEL confidence bound (delta method for
    a sample variance, Var(s^2) ~ (m4 - s^4)/M) required below the multinomial value."""
    w = _weights()
    N = w.size
    exact_multi = N * (1 - np.sum(w**2))
    c_multi = rs.offspring_counts(np.broadcast_to(w, (M, N)), np.random.default_rng(5), "multinomial")
    assert abs(c_multi.var(axis=0, ddof=1).sum() - exact_multi) < 0.05 * exact_multi
    z = stats.norm.ppf(1 - LEVEL)
    for method in ("systematic", "stratified", "residual"):
        c = rs.offspring_counts(np.broadcast_to(w, (M, N)), np.random.default_rng(6), method)
        dev = c - c.mean(axis=0)
        per_run = np.sum(dev**2, axis=1)  # sum_i (c_i - mean_i)^2: its mean is the total variance
        total, se = per_run.mean(), per_run.std(ddof=1) / np.sqrt(M)
        assert total + z * se < exact_multi, (method, total, se, exact_multi)
    # systematic: every count is floor or ceil of N w (the smallest variance of one count)
    c = rs.offspring_counts(np.broadcast_to(w, (M, N)), np.random.default_rng(7), "systematic")
    assert np.all((c == np.floor(N * w)) | (c == np.ceil(N * w)))


def test_counts_to_indices_and_batches_are_independent():
    rng = np.random.default_rng(1)
    w = rng.random((3, 5, 7))
    idx = rs.resample_indices(w, rng, "stratified")
    assert idx.shape == (3, 5, 7) and np.all(np.diff(idx, axis=-1) >= 0)
    c = np.apply_along_axis(np.bincount, -1, idx, minlength=7)
    np.testing.assert_array_equal(rs.counts_to_indices(c), idx)
    # a weight of zero never gets offspring; a weight of one gets all of them
    w0 = np.array([0.0, 1.0, 0.0])
    for method in rs.METHODS:
        np.testing.assert_array_equal(rs.offspring_counts(w0, rng, method), [0, 3, 0])


def test_ess_from_log_weights_never_underflows():
    lw = np.array([-1e6, -1e6 - 1.0, -2e6])  # linear weights: exp(-1e6) = 0.0 for all three
    assert np.all(np.exp(lw) == 0.0)
    e = 1.0 / (1.0 + np.exp(-1.0))
    ess = rs.effective_sample_size(lw)
    # closed form; the maximum is subtracted first (exact), then ~10 operations of relative error eps
    assert abs(ess / (1.0 / (e**2 + (1 - e) ** 2)) - 1) < 50 * np.finfo(float).eps
    assert rs.effective_sample_size(np.zeros((4, 10))).shape == (4,)
    np.testing.assert_allclose(rs.effective_sample_size(np.zeros(10)), 10.0, rtol=1e-14)


@pytest.mark.parametrize("bad, match", [
    ([0.5, np.nan, 0.5], "weights must be finite"),
    ([0.5, np.inf], "weights must be finite"),
    ([0.5, -0.1, 0.6], "weights must be non-negative"),
    ([0.0, 0.0], "weights must have a positive sum"),
    (np.ones((2, 0)), "weights must have shape"),
])
def test_bad_weights_are_named(bad, match):
    with pytest.raises(ValueError, match=f"^{match}"):
        rs.offspring_counts(bad, np.random.default_rng(0))


def test_bad_arguments_are_named():
    w = np.ones(4)
    with pytest.raises(ValueError, match="^method must be one of"):
        rs.offspring_counts(w, np.random.default_rng(0), "bogus")
    with pytest.raises(TypeError, match="^rng must be a numpy.random.Generator"):
        rs.offspring_counts(w, 42)
    with pytest.raises(ValueError, match="^size must be a positive integer"):
        rs.offspring_counts(w, np.random.default_rng(0), size=0)
    with pytest.raises(ValueError, match="^log_weights must be finite or -inf"):
        rs.effective_sample_size([0.0, np.nan])
    with pytest.raises(ValueError, match="^log_weights must give every cloud"):
        rs.normalize_log_weights([-np.inf, -np.inf])
