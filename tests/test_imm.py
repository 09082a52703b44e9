"""Tests of kftrack.imm: the IMM (Blom & Bar-Shalom 1988), GPB1, the clairvoyant filter and the
Markov matrices from sojourn times."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import stats

from closed_forms import EPS, roundoff_tol
from kftrack import imm, kalman, metrics, models

DT = 1.0
R2 = 4.0 * np.eye(2)


def _cv(q=0.1, ndim=2):
    return models.ConstantVelocity(ndim=ndim, q=q)


class StubMode:
    """Identity dynamics (``F = I``, ``Q = 0``) and a fixed log-likelihood: isolates the IMM algebra."""

    def __init__(self, n, loglik=0.0):
        self.n, self.loglik = n, loglik

    def predict(self, x, P, dt):
        return x, P

    def update(self, x, P, z):
        ll = np.broadcast_to(np.asarray(self.loglik, dtype=float), x.shape[:-1])
        return SimpleNamespace(x=x, P=P, loglik=ll)


def _spd(rng, n):
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


def _close(actual, desired, scale, n, cond=1.0, c=10.0):
    """``|actual - desired| <= roundoff_tol(scale, n, cond, c)`` (normwise; see closed_forms)."""
    np.testing.assert_allclose(actual, desired, rtol=0, atol=roundoff_tol(scale, n, cond, c))


def _log_sum_tol(r, *logs):
    """Bound on |sum(mu) - 1| for mu = exp(l - logsumexp(l)), l = log mu + log L (or log mu +
    log Pi): each addition of logs errs by <= u |l| absolute, so every mu_j carries a relative
    error <= 2 u (1 + max|l|) (the exp and the logsumexp add a few u more); summed over r terms:
    roundoff_tol(1 + sum of the max |log| of each addend, r). Zero probabilities (log = -inf)
    stay exactly zero and are left out."""
    m = sum(float(np.max(np.abs(np.asarray(a)[np.isfinite(a)]), initial=0.0)) for a in logs)
    return roundoff_tol(1.0 + m, r)


def _mix_scales(w, xs, Ps):
    """Scales of the moment match sum_i w_i x_i and sum_i w_i (P_i + d_i d_i^T), d_i = x_i - x:
    sums of r nonnegative-weighted terms, round-off <= r eps times these (plus the weights' own
    few eps relative)."""
    x = sum(wi * xi for wi, xi in zip(w, xs))
    sx = sum(wi * np.abs(xi) for wi, xi in zip(w, xs))
    sP = sum(wi * (np.abs(Pi) + np.outer(np.abs(xi) + np.abs(x), np.abs(xi) + np.abs(x))) for wi, xi, Pi in zip(w, xs, Ps))
    return sx, sP


# --------------------------------------------------------------------------------------------
# reductions to the Kalman filter
# --------------------------------------------------------------------------------------------
def test_one_mode_equals_the_kalman_filter_exactly():
    rng = np.random.default_rng(0)
    cv = _cv()
    zs = rng.normal(scale=3.0, size=(40, 5, 2))
    zs[7, 2] = np.nan  # one run misses one measurement
    x0, P0 = np.array([0.0, 1.0, 0.0, -1.0]), 50.0 * np.eye(4)
    for cls in (imm.IMM, imm.GPB1):
        est = cls([imm.KalmanMode(cv, R2)], np.eye(1), [1.0])
        res = imm.imm_filter(est, zs, x0, P0, DT)
        kf = kalman.kalman_filter(zs, x0, P0, cv.F(DT), cv.Q(DT), cv.H, R2)
        np.testing.assert_array_equal(res.x, kf.x)
        np.testing.assert_array_equal(res.P, kf.P)
        np.testing.assert_array_equal(res.x_prior, kf.x_prior)
        np.testing.assert_array_equal(res.mu, 1.0)


def test_identical_modes_equal_the_kalman_filter_and_mu_follows_the_chain():
    rng = np.random.default_rng(1)
    cv = _cv()
    zs = rng.normal(scale=3.0, size=(30, 2))
    Pi = np.array([[0.9, 0.05, 0.05], [0.2, 0.7, 0.1], [0.3, 0.3, 0.4]])
    mu0 = np.array([0.2, 0.5, 0.3])
    est = imm.IMM([imm.KalmanMode(cv, R2)] * 3, Pi, mu0)
    x0, P0 = np.zeros(4), 50.0 * np.eye(4)
    res = imm.imm_filter(est, zs, x0, P0, DT)
    kf = kalman.kalman_filter(zs, x0, P0, cv.F(DT), cv.Q(DT), cv.H, R2)
    # identical modes: mixing r = 3 equal estimates with weights summing to 1 +- r eps changes them by
    # <= r eps |x| (|P|) per step, and the Kalman step then carries the perturbation (stable, so it
    # does not grow); after T = 30 steps at most T times that (T, r and the Kalman step's n + m = 6)
    T = zs.shape[0]
    _close(res.x, kf.x, np.abs(kf.x).max() + np.abs(zs).max(), T * 6)
    _close(res.P, kf.P, kf.P_prior, T * 6)
    # equal likelihoods: the posterior mu is the predicted one, mu0 Pi^k. Probabilities are sums of
    # nonnegative terms, so the round-off is entrywise relative: <= r eps per product, k products
    # one way, <= 2 log2(k) + 1 (matrix_power) the other, plus r eps for each normalisation
    expected = np.array([mu0 @ np.linalg.matrix_power(Pi, k) for k in range(30)])
    np.testing.assert_allclose(res.mu, expected, rtol=(2 * T + 2 * np.log2(T) + 1) * 3 * EPS, atol=0)
    # the stationary distribution is the fixed point of the chain: lstsq is backward stable, its
    # residual on this consistent system is <= c (r + 1) eps |A|_2 |pi| with A = [Pi^T - I; 1^T]
    # (|A|_2 <= 3 here), plus the product pi @ Pi (r eps |pi|)
    pi = imm.stationary_distribution(Pi)
    _close(pi @ Pi, pi, pi, 3 * (3 + 1) + 3)
    # mu0 Pi^500 - pi = (mu0 - pi) Pi^500: the transient is |lambda_2|^500 < 1e-80, so only
    # round-off remains: pi's forward error (residual times cond(A)) and matrix_power's ~ 2 log2(500)
    # products of r terms each
    A = np.vstack([Pi.T - np.eye(3), np.ones((1, 3))])
    _close(mu0 @ np.linalg.matrix_power(Pi, 500), pi, pi, 3 * (3 + 1) * np.linalg.cond(A) + 3 * 2 * np.log2(500))


def test_clairvoyant_filter_with_a_constant_mode_is_that_kalman_filter():
    rng = np.random.default_rng(2)
    slow, fast = _cv(0.01), _cv(10.0)
    zs = rng.normal(size=(25, 3, 2))
    x0, P0 = np.zeros(4), 10.0 * np.eye(4)
    modes = [imm.KalmanMode(slow, R2), imm.KalmanMode(fast, R2)]
    x, P = imm.clairvoyant_filter(modes, np.ones(25, int), zs, x0, P0, DT)
    kf = kalman.kalman_filter(zs, x0, P0, fast.F(DT), fast.Q(DT), fast.H, R2)
    np.testing.assert_array_equal(x, kf.x)
    np.testing.assert_array_equal(P, kf.P)
    # a per-run sequence: run 1 always slow, runs 0 and 2 fast
    seq = np.tile(np.array([1, 0, 1]), (25, 1))
    x, _ = imm.clairvoyant_filter(modes, seq, zs, x0, P0, DT)
    kf0 = kalman.kalman_filter(zs[:, 1], x0, P0, slow.F(DT), slow.Q(DT), slow.H, R2)
    np.testing.assert_array_equal(x[:, 1], kf0.x)


# --------------------------------------------------------------------------------------------
# the algebra of one cycle, against a hand-written two-mode example (EATN §11.6.6 structure)
# --------------------------------------------------------------------------------------------
def test_mixing_and_combination_match_the_textbook_formulas():
    rng = np.random.default_rng(3)
    Pi = np.array([[0.95, 0.05], [0.10, 0.90]])
    mu = np.array([0.7, 0.3])
    xs = [np.array([1.0, 2.0, -1.0]), np.array([1.5, 1.0, 0.5])]
    Ps = [_spd(rng, 3), _spd(rng, 3)]
    est = imm.IMM([StubMode(3, 0.0), StubMode(3, 0.0)], Pi, mu)
    state = est.initialize(np.zeros(3), np.eye(3))._replace(xs=tuple(xs), Ps=tuple(Ps), log_mu=np.log(mu), mu=mu)
    out = est.predict(state, DT)  # identity dynamics: the mode estimates are the mixed ones
    # by hand
    cbar = [Pi[0, j] * mu[0] + Pi[1, j] * mu[1] for j in range(2)]
    for j in range(2):
        w = [Pi[i, j] * mu[i] / cbar[j] for i in range(2)]
        x0 = w[0] * xs[0] + w[1] * xs[1]
        P0 = sum(w[i] * (Ps[i] + np.outer(xs[i] - x0, xs[i] - x0)) for i in range(2))
        sx, sP = _mix_scales(w, xs, Ps)  # r = 2 terms, weights from a product and a division
        _close(out.xs[j], x0, sx, 2 + 2)
        _close(out.Ps[j], P0, sP, 2 + 2)
    # cbar_j = sum_i Pi_ij mu_i: two nonnegative terms, entrywise relative error <= 2 eps each way
    # (the IMM may compute it in the log domain: exp/log add a few eps relative)
    np.testing.assert_allclose(out.mu, cbar, rtol=roundoff_tol(1.0, 2), atol=0)
    np.testing.assert_allclose(out.mu, mu @ Pi, rtol=roundoff_tol(1.0, 2), atol=0)
    # update with likelihoods L = (0.2, 0.6): mu_j proportional to L_j cbar_j
    est2 = imm.IMM([StubMode(3, np.log(0.2)), StubMode(3, np.log(0.6))], Pi, mu)
    up = est2.update(out, np.zeros(1))
    post = np.array([0.2 * cbar[0], 0.6 * cbar[1]])
    post /= post.sum()
    # Bayes' rule on r = 2 positive terms (products, a sum, a division; the IMM in the log domain,
    # |log L| < 2 here): entrywise relative error <= a few r eps
    np.testing.assert_allclose(up.mu, post, rtol=roundoff_tol(1.0, 2), atol=0)
    x = post[0] * out.xs[0] + post[1] * out.xs[1]
    P = sum(post[j] * (out.Ps[j] + np.outer(out.xs[j] - x, out.xs[j] - x)) for j in range(2))
    sx, sP = _mix_scales(post, out.xs, out.Ps)
    _close(up.x, x, sx, 2 + 2)
    _close(up.P, P, sP, 2 + 2)


def test_gpb1_starts_every_mode_from_the_combined_estimate():
    rng = np.random.default_rng(4)
    Pi = np.array([[0.95, 0.05], [0.10, 0.90]])
    mu = np.array([0.6, 0.4])
    xs = (rng.normal(size=2), rng.normal(size=2))
    Ps = (_spd(rng, 2), _spd(rng, 2))
    g = imm.GPB1([StubMode(2), StubMode(2)], Pi, mu)
    s = g.initialize(np.zeros(2), np.eye(2))._replace(xs=xs, Ps=Ps)
    s = g._state(np.log(mu), list(xs), list(Ps), s.loglik)
    out = g.predict(s, DT)
    for j in range(2):  # identity dynamics: the combined estimate itself, bit for bit
        np.testing.assert_array_equal(out.xs[j], s.x)
        np.testing.assert_array_equal(out.Ps[j], s.P)
    # two nonnegative terms: entrywise relative round-off <= 2 eps, a few eps more in the log domain
    np.testing.assert_allclose(out.mu, mu @ Pi, rtol=roundoff_tol(1.0, 2), atol=0)


def test_imm_matches_filterpy_step_by_step():
    from filterpy.kalman import IMMEstimator, KalmanFilter

    rng = np.random.default_rng(5)
    slow, fast = _cv(0.01), _cv(5.0)
    Pi = np.array([[0.97, 0.03], [0.05, 0.95]])
    mu0 = np.array([0.5, 0.5])
    x0, P0 = np.array([0.0, 1.0, 0.0, 1.0]), 20.0 * np.eye(4)

    def fp_filter(model):
        kf = KalmanFilter(dim_x=4, dim_z=2)
        kf.F, kf.Q, kf.H, kf.R = model.F(DT), model.Q(DT), model.H, R2.copy()
        kf.x, kf.P = x0.copy()[:, None], P0.copy()
        return kf

    fp = IMMEstimator([fp_filter(slow), fp_filter(fast)], mu0.copy(), Pi)
    est = imm.IMM([imm.KalmanMode(slow, R2), imm.KalmanMode(fast, R2)], Pi, mu0)
    s = est.initialize(x0, P0)
    truth = np.array([0.0, 1.0, 0.0, 1.0])
    for k in range(60):
        truth = (fast if 20 <= k < 35 else slow).F(DT) @ truth + np.array([0, 0, 0, 0.5 if 20 <= k < 35 else 0])
        z = truth[[0, 2]] + rng.normal(scale=2.0, size=2)
        fp.predict()
        fp.update(z)
        s = est.update(est.predict(s, DT), z)
        # per cycle: each mode's Kalman update (n + m = 6, solve with S), mixing and combination
        # (r = 2 terms, sensitivity |x_i - x| to mu); mu moves by <= 2 max |d loglik_j| with
        # d loglik_j <= (n + m) cond(S_j) eps (nis_j + m) (see test_kalman._update_tols). The IMM
        # forgets its past (stable mode filters mixed through Pi), so errors do not grow: after
        # k + 1 cycles at most k + 1 times one cycle's bound
        cS = max(np.linalg.cond(f.S) for f in fp.filters)
        nis = max(float(f.y.ravel() @ np.linalg.solve(f.S, f.y.ravel())) for f in fp.filters)
        spread = max(np.abs(f.x[:, 0] - s.x).max() for f in fp.filters)
        d_mu = (k + 1) * roundoff_tol(nis + 2, 6, cS)
        _close(s.x, fp.x[:, 0], np.abs(s.x).max() + np.abs(z).max() + spread * (1 + 2 * d_mu), (k + 1) * 6, cS)
        _close(s.P, fp.P, np.abs(fp.P).max() + spread**2 * (1 + 2 * d_mu), (k + 1) * 6, cS)
        np.testing.assert_allclose(s.mu, fp.mu, rtol=0, atol=2 * d_mu)


# --------------------------------------------------------------------------------------------
# mode probabilities
# --------------------------------------------------------------------------------------------
@st.composite
def _chains(draw):
    r = draw(st.integers(2, 5))
    raw = draw(arrays(float, (r, r), elements=st.floats(0.0, 1.0)))
    raw = raw + np.eye(r) * 1e-3  # at least one positive entry per row
    Pi = raw / raw.sum(axis=1, keepdims=True)
    m = draw(arrays(float, (r,), elements=st.floats(0.0, 1.0))) + 1e-6
    loglik = draw(arrays(float, (r,), elements=st.floats(-1e4, 50.0)))
    return Pi, m / m.sum(), loglik


@settings(max_examples=60, deadline=None)
@given(_chains())
def test_mode_probabilities_stay_a_probability_vector(case):
    Pi, mu0, loglik = case
    est = imm.IMM([StubMode(1, ll) for ll in loglik], Pi, mu0)
    s = est.initialize(np.zeros(1), np.eye(1))
    r = len(mu0)
    for _ in range(3):
        # the prediction sum_i Pi_ij mu_i keeps the sum of the incoming mu (no renormalisation): its
        # error carries over, plus the prediction's own log-domain round-off
        before, carried = s.log_mu, abs(s.mu.sum() - 1.0)
        s = est.predict(s, DT)
        with np.errstate(divide="ignore"):
            assert np.all(s.mu >= 0) and abs(s.mu.sum() - 1.0) <= carried + _log_sum_tol(r, before, np.log(Pi))
        before = s.log_mu
        s = est.update(s, np.zeros(1))
        assert np.all(np.isfinite(s.log_mu) | (s.mu == 0))
        assert np.all(s.mu >= 0) and abs(s.mu.sum() - 1.0) <= _log_sum_tol(r, before, loglik)


def test_mode_probabilities_stay_normalized_over_ten_thousand_steps():
    rng = np.random.default_rng(6)
    slow, fast = _cv(1e-4, ndim=1), _cv(1e3, ndim=1)
    est = imm.IMM([imm.KalmanMode(slow, np.eye(1)), imm.KalmanMode(fast, np.eye(1))],
                  [[0.999, 0.001], [0.001, 0.999]], [0.5, 0.5])
    zs = np.cumsum(rng.normal(size=(10_000, 1)), axis=0)
    res = imm.imm_filter(est, zs, np.zeros(2), np.eye(2), DT)
    assert np.all(np.isfinite(res.mu)) and np.all(res.mu >= 0)
    # normalised at every step in the log domain, so no accumulation (see _log_sum_tol)
    np.testing.assert_allclose(res.mu.sum(-1), 1.0, rtol=0, atol=_log_sum_tol(2, np.log(res.mu_prior), res.loglik))
    assert res.mu[:, 1].min() < 1e-3 and res.mu[:, 1].max() > 0.5  # it does switch


def test_a_step_without_measurement_propagates_mu_through_pi_only():
    rng = np.random.default_rng(7)
    cv_slow, cv_fast = _cv(0.01), _cv(5.0)
    Pi = np.array([[0.9, 0.1], [0.3, 0.7]])
    est = imm.IMM([imm.KalmanMode(cv_slow, R2), imm.KalmanMode(cv_fast, R2)], Pi, [0.8, 0.2])
    zs = rng.normal(scale=3.0, size=(12, 2))
    zs[5:8] = np.nan
    res = imm.imm_filter(est, zs, np.zeros(4), 30.0 * np.eye(4), DT)
    for k in (5, 6, 7):
        np.testing.assert_array_equal(res.mu[k], res.mu_prior[k])  # no fake update
        # two nonnegative terms: entrywise relative round-off <= 2 eps, a few eps more in the log domain
        np.testing.assert_allclose(res.mu_prior[k], res.mu[k - 1] @ Pi, rtol=roundoff_tol(1.0, 2), atol=0)
        assert np.all(np.isnan(res.loglik[k]))
    # the same by hand with predict alone
    s = est.initialize(np.zeros(4), 30.0 * np.eye(4))
    s2 = est.predict(est.predict(s, DT), DT)
    np.testing.assert_allclose(s2.mu, est.mu0 @ Pi @ Pi, rtol=roundoff_tol(1.0, 2 * 2), atol=0)  # two products


# --------------------------------------------------------------------------------------------
# sojourn times
# --------------------------------------------------------------------------------------------
def test_sojourn_transition_is_a_markov_semigroup():
    tau = np.array([200.0, 20.0, 50.0])
    for dt in (0.0, 0.5, 2.0, 4.0, 37.0):
        Pi = imm.sojourn_transition(tau, dt)
        imm.check_transition(Pi, 3)
        # rows divided by their sum: fl(p_i / s) = p_i / s (1 + d), |d| <= u, then a sum of r terms
        # adds (r - 1) u: |sum - 1| <= r u = r eps / 2 (c = 1 leaves a factor 2)
        np.testing.assert_allclose(Pi.sum(1), 1.0, rtol=0, atol=roundoff_tol(1.0, 3, c=1.0))
    np.testing.assert_array_equal(imm.sojourn_transition(tau, 0.0), np.eye(3))  # expm(0) = I exactly
    # expm (Pade, backward error <= u by design; |Lambda dt| <= 0.15 so its condition number is ~ 1)
    # three times, one 3-term product and the normalisations: <= 10 r eps (c = 10)
    _close(imm.sojourn_transition(tau, 3.0), imm.sojourn_transition(tau, 1.2) @ imm.sojourn_transition(tau, 1.8), 1.0, 3)
    Lam = imm.sojourn_generator(tau)
    # a row sum of r terms: |error| <= (r - 1) u sum|Lam_ij| = (r - 1) u 2 |Lam_ii| <= (r - 1) eps max|Lam|
    np.testing.assert_allclose(Lam.sum(1), 0.0, rtol=0, atol=roundoff_tol(Lam, 3 - 1, c=1.0))
    np.testing.assert_allclose(-1.0 / np.diag(Lam), tau, rtol=EPS, atol=0)  # two divisions: <= 2 u


def test_two_mode_sojourn_transition_closed_form():
    # two states: p12(t) = a/(a+b) (1 - exp(-(a+b) t)), a = 1/tau1, b = 1/tau2
    tau1, tau2, t = 200.0, 20.0, 4.0
    a, b = 1 / tau1, 1 / tau2
    p12 = a / (a + b) * (1 - np.exp(-(a + b) * t))
    p21 = b / (a + b) * (1 - np.exp(-(a + b) * t))
    Pi = imm.sojourn_transition([tau1, tau2], t)
    # expm of |Lambda t| = 0.22 (Pade backward error <= u, condition number <= e^0.44 < 1.6) and the
    # row normalisation (r u); the closed form: 1 - exp(-0.22) loses ~ 5 u to cancellation, relative
    # to p12, i.e. <= u absolute. Total <= (1.6 + 2 + 1) u < 4 eps: c = 2, n = r = 2
    _close(Pi, [[1 - p12, p12], [p21, 1 - p21]], 1.0, 2, c=2.0)
    # seed 001's first-order rule 1 - T/tau at T = 2 s: [[0.99, 0.01], [0.1, 0.9]]; a division and a
    # subtraction (<= 2 u relative) against the rounded literals (u): rtol = 3 u < 2 eps
    np.testing.assert_allclose(imm.first_order_transition([200.0, 20.0], 2.0), [[0.99, 0.01], [0.1, 0.9]], rtol=2 * EPS)
    # stationary distribution of the continuous chain: tau_i / sum(tau). lstsq's residual is
    # <= c (r + 1) eps |A| |pi|, its forward error that times cond(A), A = [Pi^T - I; 1^T]
    A = np.vstack([Pi.T - np.eye(2), np.ones((1, 2))])
    _close(imm.stationary_distribution(Pi), [tau1 / (tau1 + tau2), tau2 / (tau1 + tau2)], 1.0, 3, np.linalg.cond(A))


def test_sojourn_transition_inside_the_imm_depends_on_dt():
    est = imm.IMM([StubMode(1), StubMode(1)], imm.SojournTransition([10.0, 5.0]), [1.0, 0.0])
    s = est.initialize(np.zeros(1), np.eye(1))
    one = est.predict(s, 3.0)
    two = est.predict(est.predict(s, 1.0), 2.0)
    # the semigroup law to round-off: three expm of |Lambda dt| <= 0.6 (condition number < e^1.2),
    # a product and the normalisations: <= 10 r eps (c = 10, as in test_sojourn_transition_is_a_markov_semigroup)
    _close(one.mu, two.mu, 1.0, 2)
    _close(one.mu, imm.sojourn_transition([10.0, 5.0], 3.0)[0], 1.0, 2)


# --------------------------------------------------------------------------------------------
# modes of different dimension
# --------------------------------------------------------------------------------------------
def test_unbiased_mixing_across_dimensions():
    rng = np.random.default_rng(8)
    Pi = np.array([[0.9, 0.1], [0.2, 0.8]])
    mu = np.array([0.55, 0.45])
    xa, Pa = rng.normal(size=4), _spd(rng, 4)  # CV: [x, vx, y, vy]
    xb, Pb = np.append(rng.normal(size=4), 0.3), _spd(rng, 5)  # CT: [x, vx, y, vy, omega]
    est = imm.IMM([StubMode(4), StubMode(5)], Pi, mu)
    s = est.initialize(np.zeros(5), np.eye(5))._replace(xs=(xa, xb), Ps=(Pa, Pb), log_mu=np.log(mu))
    out = est.predict(s, DT)
    # the same mixing with CV completed by hand: omega and its variance from CT, no cross terms
    xa5 = np.append(xa, xb[4])
    Pa5 = np.zeros((5, 5))
    Pa5[:4, :4], Pa5[4, 4] = Pa, Pb[4, 4]
    same = imm.IMM([StubMode(5), StubMode(5)], Pi, mu)
    s5 = same.initialize(np.zeros(5), np.eye(5))._replace(xs=(xa5, xb), Ps=(Pa5, Pb), log_mu=np.log(mu))
    out5 = same.predict(s5, DT)
    sx, sP = _mix_scales([1.0, 1.0], [xa5, xb], [Pa5, Pb])  # weights <= 1: r = 2 terms, both ways
    _close(out.xs[1], out5.xs[1], sx, 2 + 2)
    _close(out.Ps[1], out5.Ps[1], sP, 2 + 2)
    _close(out.xs[0], out5.xs[0][:4], sx, 2 + 2)  # into CV: omega dropped
    _close(out.Ps[0], out5.Ps[0][:4, :4], sP, 2 + 2)
    # unbiased: the mixed omega is CT's own, not pulled towards zero as with zero padding; both
    # modes hold 0.3, weights summing to 1 within 2 eps: a relative error of a few eps
    assert out.xs[1][4] == pytest.approx(0.3, rel=roundoff_tol(1.0, 2), abs=0)
    assert out.Ps[1][4, 4] >= Pb[4, 4] * (1 - roundoff_tol(1.0, 2))  # sum_i w_i (P_i + d_i^2) >= Pb44 (1 +- 2 eps)
    # the combined output lives in the common 5-state
    assert out.x.shape == (5,) and out.P.shape == (5, 5)
    assert np.all(np.linalg.eigvalsh(out.P) > 0)


def test_combination_with_a_full_mode_holding_the_components_permuted():
    """A full mode may hold the common components in another order (here [omega, x, vx, y, vy]
    = common (4, 0, 1, 2, 3)): the combined output completes the CV mode with that mode's
    omega, read in the common order (it used to take the component at the same position)."""
    rng = np.random.default_rng(12)
    mu = np.array([0.4, 0.6])
    xa, Pa = rng.normal(size=4), _spd(rng, 4)
    xb, Pb = rng.normal(size=5), _spd(rng, 5)
    est = imm.IMM([StubMode(4), StubMode(5)], np.eye(2), mu, components=[(0, 1, 2, 3), (4, 0, 1, 2, 3)])
    s = est.from_modes([xa, xb], [Pa, Pb], mu)
    order = [1, 2, 3, 4, 0]  # mode b's positions of the common components 0..4
    xb_c, Pb_c = xb[order], Pb[np.ix_(order, order)]
    xa_c = np.append(xa, xb_c[4])
    Pa_c = np.zeros((5, 5))
    Pa_c[:4, :4], Pa_c[4, 4] = Pa, Pb_c[4, 4]
    x, P = imm.mix_gaussians(mu, np.stack([xa_c, xb_c]), np.stack([Pa_c, Pb_c]))
    sx, sP = _mix_scales(mu, [xa_c, xb_c], [Pa_c, Pb_c])
    _close(s.x, x, sx, 2 + 2)
    _close(s.P, P, sP, 2 + 2)


def test_imm_filter_takes_np_diff_of_the_timestamps_and_the_timestamps():
    """dt of length T - 1 (np.diff(t)) or times=t: the same intervals, the same bits."""
    rng = np.random.default_rng(13)
    est = imm.IMM([imm.KalmanMode(_cv(), R2), imm.KalmanMode(models.KnownTurn(0.05, q=0.1), R2)],
                  imm.SojournTransition([20.0, 20.0]), [0.5, 0.5])
    t = np.cumsum(rng.uniform(0.5, 1.5, 30))
    zs = rng.normal(scale=10.0, size=(30, 3, 2))
    x0, P0 = np.zeros(4), 100.0 * np.eye(4)
    ref = imm.imm_filter(est, zs, x0, P0, np.append(np.diff(t), 7.0))  # the last interval is never used
    for res in (imm.imm_filter(est, zs, x0, P0, np.diff(t)), imm.imm_filter(est, zs, x0, P0, times=t)):
        np.testing.assert_array_equal(res.x, ref.x)
        np.testing.assert_array_equal(res.P, ref.P)
        np.testing.assert_array_equal(res.mu, ref.mu)
    with pytest.raises(ValueError, match="dt and times"):
        imm.imm_filter(est, zs, x0, P0, 1.0, times=t)
    with pytest.raises(ValueError, match="times"):
        imm.imm_filter(est, zs, x0, P0, times=t[::-1])
    with pytest.raises(TypeError, match="dt"):
        imm.imm_filter(est, zs, x0, P0)


def test_cv_and_ekf_coordinated_turn_bank_runs_batched():
    rng = np.random.default_rng(9)
    cv = _cv(0.05)
    ct = models.CoordinatedTurn(ndim=2, sigma2=0.05, sigma2_omega=1e-4)
    est = imm.IMM([imm.KalmanMode(cv, R2), imm.EKFMode(ct, R2)], imm.SojournTransition([50.0, 20.0]), [0.9, 0.1])
    zs = rng.normal(size=(15, 8, 2))
    res = imm.imm_filter(est, zs, np.zeros(5), np.diag([100.0, 10, 100, 10, 0.01]), DT)
    assert res.x.shape == (15, 8, 5) and res.mu.shape == (15, 8, 2)
    single = imm.imm_filter(est, zs[:, 3], np.zeros(5), np.diag([100.0, 10, 100, 10, 0.01]), DT)
    # batched and single matmuls may take different BLAS paths: per cycle the mode updates' round-off
    # (n + m = 7, a solve with S, cond(S) largest at the first, least informed, step) and the mixing;
    # the IMM forgets its past, so after T cycles at most T times one cycle's bound
    cS = np.linalg.cond(cv.H @ single.P_prior[0][:4, :4] @ cv.H.T + R2)
    T = zs.shape[0]
    _close(res.x[:, 3], single.x, np.abs(single.x).max() + np.abs(zs[:, 3]).max(), T * 7, cS)


# --------------------------------------------------------------------------------------------
# consistency on a Markov-switching linear system
# --------------------------------------------------------------------------------------------
def _switching_runs(rng, models_, Pi, runs, steps, x0, P0, sigma):
    """Mode s[k] drives the transition from k-1 to k (the IMM's convention)."""
    s = np.empty((steps, runs), int)
    s[0] = rng.choice(len(models_), size=runs, p=imm.stationary_distribution(Pi))
    for k in range(1, steps):
        u = rng.random(runs)[:, None]
        s[k] = (u > np.cumsum(Pi[s[k - 1]], axis=1)).sum(1)
    x = np.empty((steps, runs, x0.size))
    x[0] = rng.multivariate_normal(x0, P0, size=runs)
    for k in range(1, steps):
        nxt = [x[k - 1] @ m.F(DT).T + rng.multivariate_normal(np.zeros(x0.size), m.Q(DT), size=runs) for m in models_]
        x[k] = np.choose(s[k][:, None], nxt)
    zs = x[..., ::2] + sigma * rng.normal(size=x[..., ::2].shape)
    return x, zs


def test_imm_nees_is_consistent_on_a_markov_switching_system():
    """Time-averaged NEES over 400 independent runs of a Markov-switching system (the mode sets
    the acceleration spectral density). Each run's time average is one value; the runs are
    independent, so their mean has a standard error estimated from the runs themselves (the
    correlation in time is inside each run's value): a consistent filter gives
    |mean - n| <= 3 SE with probability 0.997. The IMM collapses the mixture to one Gaussian,
    so this is the claim that the approximation is invisible at this sample size. Negative
    controls: the fast mode's density understated or overstated tenfold is rejected by > 20 SE."""
    rng = np.random.default_rng(10)
    slow, fast = _cv(0.01, ndim=1), _cv(10.0, ndim=1)
    Pi = np.array([[0.95, 0.05], [0.10, 0.90]])
    x0, P0 = np.array([0.0, 10.0]), np.diag([100.0, 4.0])
    x, zs = _switching_runs(rng, [slow, fast], Pi, 400, 100, x0, P0, 2.0)
    R = 4.0 * np.eye(1)

    def z_score(fast_model):
        est = imm.IMM([imm.KalmanMode(slow, R), imm.KalmanMode(fast_model, R)], Pi, imm.stationary_distribution(Pi))
        res = imm.imm_filter(est, zs, x0, P0, DT)
        per_run = metrics.nees(x, res.x, res.P).mean(axis=0)
        return (per_run.mean() - 2.0) / (per_run.std(ddof=1) / np.sqrt(per_run.size))

    # two-sided at level 0.003 with the standard error estimated from 400 runs: Student t, 399 dof
    assert abs(z_score(fast)) <= stats.t.isf(0.003 / 2, 400 - 1)
    assert z_score(_cv(1.0, ndim=1)) > 20.0
    assert z_score(_cv(100.0, ndim=1)) < -20.0


# --------------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------------
def _two():
    return [imm.KalmanMode(_cv(), R2), imm.KalmanMode(_cv(1.0), R2)]


@pytest.mark.parametrize("Pi, word", [
    ([[0.9, 0.2], [0.1, 0.9]], "rows must sum to 1"),
    ([[1.1, -0.1], [0.1, 0.9]], "non-negative"),
    ([[1.0]], "shape (2, 2)"),
    (np.eye(3), "shape (2, 2)"),
    ([[np.nan, 1.0], [0.0, 1.0]], "finite"),
])
def test_bad_transition_is_rejected_naming_it(Pi, word):
    with pytest.raises(ValueError, match="transition") as exc:
        imm.IMM(_two(), Pi, [0.5, 0.5])
    assert word in str(exc.value)


@pytest.mark.parametrize("mu0, word", [([0.6, 0.6], "sum to 1"), ([1.5, -0.5], ">= 0"), ([1.0], "(..., 2)")])
def test_bad_mu0_is_rejected_naming_it(mu0, word):
    with pytest.raises(ValueError, match="mu0") as exc:
        imm.IMM(_two(), np.eye(2), mu0)
    assert word in str(exc.value)


def test_bad_modes_and_components_are_rejected():
    with pytest.raises(ValueError, match="modes"):
        imm.IMM([], np.eye(1), [1.0])
    with pytest.raises(TypeError, match=r"modes\[1\]"):
        imm.IMM([imm.KalmanMode(_cv(), R2), object()], np.eye(2), [0.5, 0.5])
    with pytest.raises(ValueError, match="components"):
        imm.IMM([StubMode(4), StubMode(5)], np.eye(2), [0.5, 0.5], components=[(0, 1, 2, 3)])
    with pytest.raises(ValueError, match="every state component"):
        imm.IMM([StubMode(2), StubMode(2)], np.eye(2), [0.5, 0.5], components=[(0, 1), (2, 3)])
    with pytest.raises(ValueError, match="transition"):
        imm.IMM(_two(), imm.SojournTransition([1.0, 2.0, 3.0]), [0.5, 0.5])
    with pytest.raises(ValueError, match="tau"):
        imm.sojourn_transition([10.0, -1.0], 1.0)
    with pytest.raises(ValueError, match="dt"):
        imm.first_order_transition([10.0, 5.0], 6.0)
    with pytest.raises(ValueError, match="x0"):
        imm.IMM(_two(), np.eye(2), [0.5, 0.5]).initialize(np.zeros(5), np.eye(5))
    with pytest.raises(ValueError, match="same state dimension"):
        imm.clairvoyant_filter([StubMode(4), StubMode(5)], np.zeros(3, int), np.zeros((3, 2)), np.zeros(4),
                               np.eye(4), DT)
    with pytest.raises(ValueError, match="mode_sequence"):
        imm.clairvoyant_filter(_two(), np.full(3, 2), np.zeros((3, 2)), np.zeros(4), np.eye(4), DT)
    with pytest.raises(ValueError, match="weights"):
        imm.mix_gaussians([0.3, 0.3], np.zeros((2, 3)), np.stack([np.eye(3)] * 2))


def test_measurement_of_the_wrong_size_is_rejected_naming_it():
    """A 3-vector measurement for modes measuring 2 positions fails at the boundary with the
    argument's name, not as a broadcasting error inside the update."""
    est = imm.IMM(_two(), np.eye(2), [0.5, 0.5])
    with pytest.raises(ValueError, match=r"zs must have shape \(\.\.\., 2\)"):
        imm.imm_filter(est, np.zeros((4, 3)), np.zeros(4), np.eye(4), DT)
    with pytest.raises(ValueError, match=r"z must have shape \(\.\.\., 2\)"):
        est.update(est.initialize(np.zeros(4), np.eye(4)), np.zeros(3))
    with pytest.raises(ValueError, match=r"zs must have shape \(\.\.\., 2\)"):
        imm.clairvoyant_filter(_two(), np.zeros(4, int), np.zeros((4, 1)), np.zeros(4), np.eye(4), DT)


def test_imm_beats_both_single_model_filters_on_a_turning_track():
    """Straight 20 s, turn at 0.08 rad/s for 20 s, straight 20 s; 100 runs. The IMM's two modes,
    CV (q = 0.05) and the known turn, each run alone as a Kalman filter, and a CV with q = 5
    tuned to follow the turn. Stated margin: the IMM's mean per-run RMSE is at least 15 % below
    each single-model filter's (measured: 69 %, 72 % and 21 % below), and the run-by-run
    difference (paired over the same noise) is positive by more than 3 standard errors. The
    standard error of the ratio is below 1 %, so the 15 % margin is not a matter of luck."""
    rng = np.random.default_rng(11)
    x, truth = np.array([0.0, 15.0, 0.0, 0.0]), []
    for w in [0.0] * 20 + [0.08] * 20 + [0.0] * 20:
        truth.append(x)
        x = models.KnownTurn(omega=w, q=0.0).F(DT) @ x
    pos = np.array(truth)[:, [0, 2]]
    R = 64.0 * np.eye(2)
    zs = pos[:, None] + 8.0 * rng.normal(size=(60, 100, 2))
    x0, P0 = np.array([0.0, 15.0, 0.0, 0.0]), np.diag([64.0, 25.0, 64.0, 25.0])
    lo, turn, hi = _cv(0.05), models.KnownTurn(omega=0.08, q=0.05), _cv(5.0)
    bank = imm.IMM([imm.KalmanMode(lo, R), imm.KalmanMode(turn, R)], imm.SojournTransition([20.0, 20.0]), [0.5, 0.5])

    def per_run(xe):
        return metrics.rmse(pos[5:, None], xe[5:, :, [0, 2]], axis=0, vector=True)

    e_imm = per_run(imm.imm_filter(bank, zs, x0, P0, DT).x)
    N = e_imm.size
    t_crit = stats.t.isf(1e-3, N - 1)  # one-sided, level 1e-3, standard errors from the N = 100 runs
    for m in (lo, turn, hi):
        e = per_run(kalman.kalman_filter(zs, x0, P0, m.F(DT), m.Q(DT), m.H, R).x)
        d = e - e_imm
        # the ratio of means, its standard error by the delta method on the paired runs: the margin
        # holds at its upper confidence bound, not only at the point estimate
        ratio = e_imm.mean() / e.mean()
        se_ratio = (e_imm - ratio * e).std(ddof=1) / np.sqrt(N) / e.mean()
        assert ratio + t_crit * se_ratio < 0.85, (m, ratio, se_ratio)
        assert d.mean() > t_crit * d.std(ddof=1) / np.sqrt(N), (m, d.mean(), d.std(ddof=1))


# --------------------------------------------------------------------------------------------
# UKF modes, and banks that mix KF, EKF and UKF modes
# --------------------------------------------------------------------------------------------
def _ct(sigma2=0.05, sigma2_omega=1e-4):
    return models.CoordinatedTurn(ndim=2, sigma2=sigma2, sigma2_omega=sigma2_omega)


def test_one_ukf_mode_equals_the_unscented_kalman_filter_exactly():
    from kftrack import ukf

    rng = np.random.default_rng(12)
    ct = _ct()
    zs = 50.0 + rng.normal(scale=2.0, size=(30, 4, 2)).cumsum(axis=0)
    zs[9, 1] = np.nan
    x0, P0 = np.array([50.0, 1.0, 50.0, 1.0, 0.02]), np.diag([25.0, 4.0, 25.0, 4.0, 1e-3])
    pts = ukf.JulierSigmaPoints(kappa=0.0)
    res = imm.imm_filter(imm.IMM([imm.UKFMode(ct, R2, points=pts)], np.eye(1), [1.0]), zs, x0, P0, DT)
    ref = ukf.unscented_kalman_filter(zs, x0, P0, lambda x: ct.f(x, DT), ct.Q(DT),
                                      lambda x: (ct.H @ x[..., None])[..., 0], R2, pts)
    np.testing.assert_array_equal(res.x, ref.x)
    np.testing.assert_array_equal(res.P, ref.P)
    np.testing.assert_array_equal(res.x_prior, ref.x_prior)


def test_ukf_modes_on_linear_models_match_kalman_modes():
    """The unscented transform is exact for linear f and h, so a bank with UKF modes on linear
    models is the bank of Kalman modes up to round-off: x, P and mu to 1e-9 over 60 steps."""
    rng = np.random.default_rng(13)
    slow, fast = _cv(0.01), _cv(5.0)
    Pi = np.array([[0.97, 0.03], [0.05, 0.95]])
    zs = rng.normal(scale=2.0, size=(60, 3, 2)).cumsum(axis=0)
    x0, P0 = np.zeros(4), 20.0 * np.eye(4)
    kf_bank = imm.IMM([imm.KalmanMode(slow, R2), imm.KalmanMode(fast, R2)], Pi, [0.5, 0.5])
    ukf_bank = imm.IMM([imm.KalmanMode(slow, R2), imm.UKFMode(fast, R2)], Pi, [0.5, 0.5])
    a, b = imm.imm_filter(kf_bank, zs, x0, P0, DT), imm.imm_filter(ukf_bank, zs, x0, P0, DT)
    # per cycle: the sigma points (Cholesky, n eps |P|), the unscented sums of 2n + 1 terms with
    # weights of total size w = sum|W| (both for mean and covariance), the update's solve with S
    # (cond(S) largest at the first step, R = 4 I and the widest prior); mu through the
    # log-likelihoods as in test_imm_matches_filterpy_step_by_step; no growth (the IMM forgets
    # its past), so T cycles give at most T times one cycle's bound
    pts = ukf_bank.modes[1].points
    n, T = 4, zs.shape[0]
    w = max(np.abs(pts.weights(n)[0]).sum(), np.abs(pts.weights(n)[1]).sum())
    cS = np.linalg.cond(fast.H @ a.P_prior[0][0] @ fast.H.T + R2)
    count = T * (3 * n + 1 + 2) * w
    nis = np.max(metrics.nis(zs - a.x_prior[..., [0, 2]], fast.H @ a.P_prior @ fast.H.T + R2))  # scale of d loglik
    _close(b.x, a.x, np.abs(a.x).max() + np.abs(zs).max(), count, cS)
    _close(b.P, a.P, a.P_prior, count, cS)
    _close(b.mu, a.mu, 1.0 + nis, count, cS)
    assert a.mu[:, :, 1].min() < 0.2 < 0.8 < a.mu[:, :, 1].max()  # both modes take the lead in turn


def test_a_bank_of_kf_ekf_and_ukf_modes_of_different_dimension_runs_batched():
    """CV (4 states, KF) beside the coordinated turn (5 states) as an EKF and as a UKF mode:
    unbiased mixing across dimensions, batch rows equal to single runs, mu a probability vector,
    and the EKF and UKF turn modes (same model, small omega uncertainty) close to each other."""
    rng = np.random.default_rng(14)
    x, truth = np.array([0.0, 15.0, 0.0, 0.0, 0.0]), []
    ct_true = _ct(0.0, 0.0)
    for w in [0.0] * 15 + [0.08] * 15 + [0.0] * 15:
        x[4] = w
        truth.append(x.copy())
        x = ct_true.f(x, DT)
    truth = np.array(truth)
    zs = truth[:, None, [0, 2]] + 2.0 * rng.normal(size=(45, 6, 2))
    cv, ct = _cv(0.05), _ct()
    modes = [imm.KalmanMode(cv, R2), imm.EKFMode(ct, R2), imm.UKFMode(ct, R2)]
    bank = imm.IMM(modes, imm.SojournTransition([30.0, 15.0, 15.0]), [0.8, 0.1, 0.1])
    x0, P0 = np.array([0.0, 15.0, 0.0, 0.0, 0.0]), np.diag([4.0, 4.0, 4.0, 4.0, 0.01])
    res = imm.imm_filter(bank, zs, x0, P0, DT)
    assert res.x.shape == (45, 6, 5) and res.mu.shape == (45, 6, 3)
    np.testing.assert_allclose(res.mu.sum(-1), 1.0, rtol=0, atol=_log_sum_tol(3, np.log(res.mu_prior), res.loglik))
    single = imm.imm_filter(bank, zs[:, 2], x0, P0, DT)
    # batched and single matmuls may take different BLAS paths: per cycle <= the UKF mode's round-off
    # (sigma points and sums of 2n + 1 terms of total weight w, n = 5, m = 2, a solve with S, cond(S)
    # largest at the first step), and no growth across cycles (the IMM forgets its past): T times that
    w = max(np.abs(modes[2].points.weights(5)[0]).sum(), np.abs(modes[2].points.weights(5)[1]).sum())
    cS = np.linalg.cond(cv.H @ single.P_prior[0][:4, :4] @ cv.H.T + R2)
    T = zs.shape[0]
    scale_x = np.abs(single.x).max() + np.abs(zs).max()
    _close(res.x[:, 2], single.x, scale_x, T * (3 * 5 + 1 + 2) * w, cS)
    # step by step from an unbatched prior, the measurements' batch axes carry through; the EKF
    # and UKF turn modes see the same data and nearly agree; together they take the turn
    s = bank.initialize(x0, P0)
    for k in range(45):
        s = bank.update(s, zs[k])
        _close(s.x, res.x[k], scale_x, T * (3 * 5 + 1 + 2) * w, cS)  # as above: the same bound
        _close(s.P, res.P[k], res.P_prior, T * (3 * 5 + 1 + 2) * w, cS)
        np.testing.assert_allclose(s.xs[2][..., [0, 2]], s.xs[1][..., [0, 2]], atol=0.5)
        s = bank.predict(s, DT)
    with pytest.raises(ValueError, match="batch axes"):
        bank.update(s, np.zeros((4, 2)))  # 4 measurements for a state of 6 runs
    turning = res.mu[18:30, :, 1:].sum(-1).mean()
    straight = res.mu[38:, :, 1:].sum(-1).mean()
    assert turning > 0.8 and straight < turning - 0.3, (turning, straight)


def test_ukf_mode_bad_input_names_the_argument():
    with pytest.raises(TypeError, match="points"):
        imm.UKFMode(_ct(), R2, points="merwe")
    with pytest.raises(ValueError, match="state_angles"):
        imm.UKFMode(_ct(), R2, state_angles=[7])
    with pytest.raises(ValueError, match="H must have shape"):
        imm.UKFMode(_ct(), R2, H=np.eye(2))


def test_a_fully_missing_row_runs_no_mode_update():
    """With every run missing a measurement, imm_filter calls no mode's update at all: the step
    is the prediction alone (no update with an empty or zero measurement)."""

    class Counting(StubMode):
        calls = 0

        def update(self, x, P, z):
            Counting.calls += 1
            return super().update(x, P, z)

    est = imm.IMM([Counting(2, -1.0), Counting(2, -3.0)], [[0.9, 0.1], [0.2, 0.8]], [0.5, 0.5])
    zs = np.zeros((6, 3, 2))
    zs[2:4] = np.nan
    res = imm.imm_filter(est, zs, np.zeros(2), np.eye(2), DT)
    assert Counting.calls == 2 * 4  # two modes, four steps with a measurement
    Pi = est.transition(DT)
    np.testing.assert_allclose(res.mu[3], res.mu[1] @ Pi @ Pi, rtol=roundoff_tol(1.0, 2 * 2), atol=0)  # two products, r = 2


def test_progress_bar_does_not_change_the_result():
    rng = np.random.default_rng(15)
    zs = rng.normal(size=(20, 3, 2))
    a = imm.imm_filter(imm.IMM(_two(), np.array([[0.9, 0.1], [0.1, 0.9]]), [0.5, 0.5]), zs, np.zeros(4), np.eye(4), DT)
    b = imm.imm_filter(imm.IMM(_two(), np.array([[0.9, 0.1], [0.1, 0.9]]), [0.5, 0.5]), zs, np.zeros(4), np.eye(4), DT,
                       progress=True)
    for u, v in zip(a, b):
        np.testing.assert_array_equal(u, v)


def test_from_modes_builds_a_consistent_state_equal_to_mix_gaussians():
    rng = np.random.default_rng(5)
    cv = models.ConstantVelocity(ndim=2, q=1.0)
    est = imm.IMM([imm.KalmanMode(cv, np.eye(2)), imm.KalmanMode(models.ConstantVelocity(ndim=2, q=30.0), np.eye(2))],
                  np.array([[0.95, 0.05], [0.1, 0.9]]), [0.5, 0.5])
    xs = [rng.normal(size=(3, 4)), rng.normal(size=(3, 4))]
    A = rng.normal(size=(2, 3, 4, 4))
    Ps = [A[i] @ np.swapaxes(A[i], -1, -2) + np.eye(4) for i in range(2)]
    mu = np.array([0.3, 0.7])
    s = est.from_modes(xs, Ps, mu)
    x_ref, P_ref = imm.mix_gaussians(mu, np.stack(xs), np.stack(Ps))
    np.testing.assert_array_equal(s.x, x_ref)  # the same moment-matching kernel, bit for bit
    np.testing.assert_array_equal(s.P, P_ref)
    np.testing.assert_array_equal(s.mu, np.broadcast_to(mu, (3, 2)))
    np.testing.assert_array_equal(s.log_mu, np.log(np.broadcast_to(mu, (3, 2))))
    assert np.isnan(s.loglik).all() and s.loglik.shape == (3, 2)
    for a, b in zip(s.xs, xs):
        np.testing.assert_array_equal(a, b)
    # the state runs: one predict/update from it equals one from the same state built by hand
    z = rng.normal(size=(3, 2))
    s1 = est.update(est.predict(s, 1.0), z)
    assert s1.x.shape == (3, 4) and np.all(np.abs(s1.mu.sum(-1) - 1.0) <= _log_sum_tol(2, np.log(mu), s1.loglik))
    # mixed dimensions: a CV mode (4) with a coordinated turn (5), completed by unbiased mixing
    ct = models.CoordinatedTurn(sigma2=1.0, sigma2_omega=1e-4)
    est2 = imm.IMM([imm.KalmanMode(cv, np.eye(2)), imm.EKFMode(ct, np.eye(2))], np.eye(2), [0.5, 0.5])
    s2 = est2.from_modes([xs[0][0], np.append(xs[1][0], 0.1)], [Ps[0][0], np.diag([1.0, 2, 3, 4, 0.01])], [0.5, 0.5])
    full = np.append(xs[0][0], 0.1)
    # two terms with weight 0.5 (exact): one rounding each way, <= u (|a| + |b|) / 2 per entry
    other = np.append(xs[1][0], 0.1)
    np.testing.assert_allclose(s2.x, 0.5 * full + 0.5 * other, rtol=0, atol=roundoff_tol(0.5 * (np.abs(full) + np.abs(other)), 1, c=1.0))


def test_from_modes_bad_input_names_the_argument():
    cv = models.ConstantVelocity(ndim=2, q=1.0)
    est = imm.IMM([imm.KalmanMode(cv, np.eye(2))] * 2, np.eye(2), [0.5, 0.5])
    x, P = np.zeros(4), np.eye(4)
    with pytest.raises(ValueError, match="one estimate per mode"):
        est.from_modes([x], [P], [0.5, 0.5])
    with pytest.raises(ValueError, match=r"xs\[1\] must have shape"):
        est.from_modes([x, np.zeros(5)], [P, P], [0.5, 0.5])
    with pytest.raises(ValueError, match=r"Ps\[0\] must be positive semi-definite"):
        est.from_modes([x, x], [-P, P], [0.5, 0.5])
    with pytest.raises(ValueError, match="mu must sum to 1"):
        est.from_modes([x, x], [P, P], [0.5, 0.6])
    with pytest.raises(ValueError, match="batch axes do not broadcast"):
        est.from_modes([np.zeros((3, 4)), np.zeros((2, 4))], [P, P], [0.5, 0.5])


def test_ekf_and_ukf_modes_take_a_linear_measurement_matrix_as_h():
    ct = models.CoordinatedTurn(sigma2=1.0, sigma2_omega=1e-4)
    H = ct.H
    x, P, z = np.array([0.0, 10.0, 0.0, 5.0, 0.02]), np.diag([10.0, 4.0, 10.0, 4.0, 1e-3]), np.array([1.0, -2.0])
    for cls in (imm.EKFMode, imm.UKFMode):
        a, b = cls(ct, np.eye(2), h=H), cls(ct, np.eye(2), H=H)
        for name, p, q in zip(a.update(x, P, z)._fields, a.update(x, P, z), b.update(x, P, z)):
            assert np.array_equal(p, q), (cls.__name__, name)
    with pytest.raises(ValueError, match="H_jac must be None when h is an"):
        imm.EKFMode(ct, np.eye(2), h=H, H_jac=lambda s: H)
