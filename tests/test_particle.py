"""Particle filters against the Kalman filter, log weights, the jump-Markov filter, bad input.

Every statistical test states its level; the Monte Carlo standard errors come from
independent replications (one batch axis of independent filters on independent data)."""
import numpy as np
import pytest
from scipy import stats

from kftrack import ekf, kalman, particle as pf
from kftrack.models import ConstantVelocity, KnownTurn

LEVEL = 1e-3  # two-sided level of every statistical test here (Bonferroni-split where several)
DT = 1.0
CV = ConstantVelocity(ndim=1, q=1.0)
F, Q, H = CV.F(DT), CV.Q(DT), CV.H
R = np.array([[4.0]])
X0, P0 = np.array([0.0, 1.0]), np.diag([25.0, 4.0])
f = lambda x: CV.f(x, DT)  # noqa: E731
h = lambda x: x[..., :1]  # noqa: E731


def _data(runs=200, steps=8, seed=0):
    truth, zs = ekf.simulate_additive_gaussian(f, h, X0, P0, Q, R, steps, np.random.default_rng(seed), runs=runs)
    return truth, zs, kalman.kalman_filter(zs, X0, P0, F, Q, H, R)


def _normalized_errors(res, kf, k=-1):
    """Per-run errors of the PF against the exact posterior, in units of the KF's standard
    deviations: mean (R, n) and the covariance diagonal relative to the KF's (R, n)."""
    s2 = np.diagonal(kf.P[k], axis1=-2, axis2=-1)
    dm = (res.x[k] - kf.x[k]) / np.sqrt(s2)
    dP = np.diagonal(res.P[k], axis1=-2, axis2=-1) / s2 - 1.0
    return dm, dP


@pytest.fixture(scope="module")
def linear_runs():
    truth, zs, kf = _data()
    out = {}
    for N in (250, 2000):
        out[N] = pf.bootstrap_filter(zs, X0, P0, f, Q, h, R, N, np.random.default_rng(N))
    out["opt"] = pf.optimal_proposal_filter(zs, X0, P0, f, Q, H, R, 2000, np.random.default_rng(7))
    return zs, kf, out


def test_particle_mean_and_covariance_match_the_kalman_filter_within_monte_carlo_error(linear_runs):
    """At N = 2000 the mean error over 200 replications, per component of the mean and of the
    covariance diagonal, is within t-bounds (two-sided, LEVEL split over the 4 tests) of zero:
    no bias the Monte Carlo error cannot explain (the O(1/N) covariance bias is ~1e-3 here)."""
    _, kf, out = linear_runs
    for key in (2000, "opt"):
        dm, dP = _normalized_errors(out[key], kf)
        R_ = dm.shape[0]
        t = stats.t.ppf(1 - LEVEL / 8, R_ - 1)
        for d in (dm, dP):
            se = d.std(axis=0, ddof=1) / np.sqrt(R_)
            assert np.all(np.abs(d.mean(axis=0)) < t * se), (key, d.mean(axis=0), se)


def test_particle_error_falls_as_one_over_n():
    """Mean square error against the KF on ONE data set (the Monte Carlo error is a property of
    the data: for fixed data it is c/N with c depending on the data), 400 independent filters at
    N = 250 and at N = 2000: the ratio must be 8 (the 1/N law) within the delta-method bound of
    the log of a ratio of two independent sample means, two-sided at LEVEL (split over the mean
    and the covariance). The bound is asserted tight enough to reject a ratio of sqrt(8) (an
    error falling as N^-1/4) and of 64 (1/N^2). Pooling different data sets instead mixes their
    constants c, whose heavy tail (a few data sets leave a handful of effective particles) makes
    such a test weak."""
    _, zs, kf = _data(runs=1, steps=8)
    rep = 400
    zs_rep = np.broadcast_to(zs, (zs.shape[0], rep, 1))
    res = {N: pf.bootstrap_filter(zs_rep, X0, P0, f, Q, h, R, N, np.random.default_rng(N)) for N in (250, 2000)}
    z = stats.norm.ppf(1 - LEVEL / 4)  # two claims (mean, covariance), two-sided
    for part in (0, 1):
        e = {N: np.mean(_normalized_errors(res[N], kf)[part] ** 2, axis=1) for N in (250, 2000)}
        log_ratio = np.log(e[250].mean() / e[2000].mean())
        se = np.sqrt(sum(v.var(ddof=1) / (v.size * v.mean() ** 2) for v in e.values()))
        assert abs(log_ratio - np.log(8.0)) < z * se, (part, np.exp(log_ratio), se)
        assert 2 * z * se < np.log(8.0) / 2  # power: sqrt(8) and 64 lie two bounds away from 8


def test_optimal_proposal_keeps_more_effective_particles(linear_runs):
    """With the same N the optimal proposal's time-averaged ESS exceeds the bootstrap's in a
    paired t-test (one-sided, LEVEL), and its error against the KF is smaller."""
    _, kf, out = linear_runs
    d = out["opt"].ess.mean(axis=0) - out[2000].ess.mean(axis=0)
    assert d.mean() > stats.t.ppf(1 - LEVEL, d.size - 1) * d.std(ddof=1) / np.sqrt(d.size)
    e_opt = np.mean(_normalized_errors(out["opt"], kf)[0] ** 2, axis=1)
    e_boot = np.mean(_normalized_errors(out[2000], kf)[0] ** 2, axis=1)
    diff = e_boot - e_opt
    assert diff.mean() > stats.t.ppf(1 - LEVEL, diff.size - 1) * diff.std(ddof=1) / np.sqrt(diff.size)


def test_log_weights_survive_a_very_informative_measurement():
    """sigma = 1e-6 m against a prior of 10 m: even the best likelihood is below exp(-1e3), zero in
    floating point. Linear weights give 0/0 = NaN; log weights give the exact posterior of
    the cloud (the particle nearest the measurement carries almost all the weight)."""
    rng = np.random.default_rng(2)
    Rt = np.array([[1e-12]])
    zs = np.array([[3.0]])
    res = pf.bootstrap_filter(zs, X0, np.diag([100.0, 1.0]), f, Q, h, Rt, 500, rng)
    X, lw = res.particles, res.log_weights
    ll = pf.gaussian_log_likelihood(zs[0], h(X), Rt)
    assert ll.max() < -745.2 * 2  # below log of the smallest subnormal, twice over
    # the same update with linear weights fails: every weight underflows to 0, 0/0 = NaN
    with np.errstate(invalid="ignore"):
        w_lin = np.exp(ll) / np.exp(ll).sum()
    assert np.all(np.exp(ll) == 0.0) and np.all(np.isnan(w_lin))
    # the log-weight filter: finite, normalized, the best particle dominates
    assert np.all(np.isfinite(res.x)) and abs(np.exp(lw).sum() - 1) < 1e-12
    best = np.argmax(ll)
    np.testing.assert_array_equal(np.argmax(lw), best)
    # exact weights from the log-likelihood differences, which are representable
    w_exact = np.exp(ll - ll.max()) / np.exp(ll - ll.max()).sum()
    np.testing.assert_allclose(np.exp(lw), w_exact, rtol=1e-9, atol=1e-300)
    assert res.ess[0] < 2.0


def test_batch_axes_run_independent_filters():
    truth, zs, _ = _data(runs=6, steps=4)
    zs = zs.reshape(4, 2, 3, 1)
    res = pf.bootstrap_filter(zs, X0, P0, f, Q, h, R, 64, np.random.default_rng(1), method="stratified")
    assert res.x.shape == (4, 2, 3, 2) and res.P.shape == (4, 2, 3, 2, 2) and res.ess.shape == (4, 2, 3)
    assert res.particles.shape == (2, 3, 64, 2) and res.log_weights.shape == (2, 3, 64)
    assert len({tuple(np.round(c[:, 0], 12)) for c in res.particles.reshape(6, 64, 2)}) == 6
    # a missing measurement (row of NaN) skips the update: the weights do not change
    zs_m = zs.copy()
    zs_m[-1, 0, 0] = np.nan
    res_m = pf.bootstrap_filter(zs_m, X0, P0, f, Q, h, R, 64, np.random.default_rng(1), threshold=1.0)
    assert res_m.log_evidence[-1, 0, 0] == 0.0 and np.all(res_m.log_evidence[-1, 1] != 0.0)


def test_regularize_adds_the_kernel_covariance():
    """The jitter has covariance h^2 P: 20000 draws, each variance within a chi-square bound."""
    rng = np.random.default_rng(4)
    P = np.array([[4.0, 1.0], [1.0, 2.0]])
    Nn = 20000
    Y = pf.regularize(np.zeros((Nn, 2)), P, rng)
    hb = pf.kernel_bandwidth(Nn, 2)
    assert abs(hb - (4 / (Nn * 4)) ** (1 / 6)) < 1e-15
    for i in range(2):
        s2 = Y[:, i].var() / (hb**2 * P[i, i])
        lo, hi = stats.chi2.ppf([LEVEL / 4, 1 - LEVEL / 4], Nn) / Nn
        assert lo < s2 < hi


def test_regularized_and_moving_sensor_run():
    truth, zs, kf = _data(runs=50, steps=5)
    hs = [lambda x, s=s: x[..., :1] - s for s in range(5)]  # a sensor moving 1 m per step
    zs_shift = zs - np.arange(5)[:, None, None]
    res = pf.bootstrap_filter(zs_shift, X0, P0, f, Q, hs, R, 400, np.random.default_rng(3), regularized=True,
                              threshold=1.0)
    assert res.resampled[:-1].all()
    # the moving sensor is modelled right and the Liu-West kernel keeps the mean: no bias against
    # the Kalman filter beyond the Monte Carlo error (t-bound, two-sided LEVEL over the 2 components)
    dm, _ = _normalized_errors(res, kf)
    t = stats.t.ppf(1 - LEVEL / 4, dm.shape[0] - 1)
    assert np.all(np.abs(dm.mean(0)) < t * dm.std(0, ddof=1) / np.sqrt(dm.shape[0]))
    # a sensor model off by the motion (the static h) is biased by 1-4 m, far outside that bound
    wrong = pf.bootstrap_filter(zs_shift, X0, P0, f, Q, h, R, 400, np.random.default_rng(3), regularized=True)
    dw, _ = _normalized_errors(wrong, kf)
    assert np.abs(dw.mean(0)[0]) > t * dw.std(0, ddof=1)[0] / np.sqrt(dw.shape[0])
    with pytest.raises(ValueError, match="^h must be a callable or a sequence of at least 5"):
        pf.bootstrap_filter(zs, X0, P0, f, Q, hs[:3], R, 10, np.random.default_rng(0))


def test_jump_markov_modes_follow_the_markov_chain():
    """Two identical models: the data say nothing about the mode, so the mode probabilities
    must equal mu0 Pi^k (rows 'from', columns 'to'); each run's estimate is a weighted share of
    N particles, averaged over 100 runs, within t-bounds (two-sided, LEVEL over the steps).
    A transposed Pi gives mu1 = [0.9, 0.3] and fails."""
    truth, zs, _ = _data(runs=100, steps=5)
    Pi = np.array([[0.9, 0.1], [0.3, 0.7]])
    res = pf.jump_markov_filter(zs, X0, P0, [CV, CV], Pi, [1.0, 0.0], h, R, 500, np.random.default_rng(8), DT)
    expected = np.array([[1.0, 0.0]])
    for k in range(1, 5):
        expected = np.vstack([expected, expected[-1] @ Pi])
        m1 = res.mu[k, :, 1]
        t = stats.t.ppf(1 - LEVEL / 8, m1.size - 1)
        assert abs(m1.mean() - expected[k, 1]) < t * m1.std(ddof=1) / np.sqrt(m1.size), (k, m1.mean(), expected[k])
    np.testing.assert_allclose(res.mu.sum(-1), 1.0, rtol=1e-12)
    assert res.modes.shape == (100, 500)


def test_jump_markov_filter_finds_the_turn():
    """A target turning at the model's rate: the turn mode's probability is above one half at
    the end in all but a binomially small share of the runs (>= 90%, one-sided LEVEL)."""
    turn = KnownTurn(omega=0.1, q=0.01)
    cv2 = ConstantVelocity(ndim=2, q=0.01)
    x0 = np.array([0.0, 10.0, 0.0, 0.0])
    P0_ = np.diag([4.0, 1.0, 4.0, 1.0])
    hh = lambda x: x[..., [0, 2]]  # noqa: E731
    truth, zs = ekf.simulate_additive_gaussian(lambda x: turn.f(x, 1.0), hh, x0, P0_, turn.Q(1.0), np.eye(2), 20,
                                               np.random.default_rng(5), runs=60)
    res = pf.jump_markov_filter(zs, x0, P0_, [cv2, turn], np.array([[0.95, 0.05], [0.05, 0.95]]), [0.5, 0.5], hh,
                                np.eye(2), 400, np.random.default_rng(6), 1.0)
    share = np.mean(res.mu[-1, :, 1] > 0.5)
    assert share >= stats.binom.ppf(LEVEL, 60, 0.9) / 60


@pytest.mark.parametrize("kwargs, exc, match", [
    ({"N": 0}, ValueError, "^N must be a positive integer"),
    ({"N": 2.5}, ValueError, "^N must be a positive integer"),
    ({"threshold": 0.0}, ValueError, r"^threshold must be a number in \(0, 1\]"),
    ({"threshold": 1.5}, ValueError, r"^threshold must be a number in \(0, 1\]"),
    ({"threshold": np.nan}, ValueError, r"^threshold must be a number in \(0, 1\]"),
    ({"method": "best"}, ValueError, "^method must be one of"),
    ({"rng": 1}, TypeError, "^rng must be a numpy.random.Generator"),
    ({"x0": [0.0, np.inf]}, ValueError, "^x0 must be finite"),
    ({"R": np.array([[-1.0]])}, ValueError, "^R must be positive"),
])
def test_bad_input_names_the_argument(kwargs, exc, match):
    _, zs, _ = _data(runs=2, steps=3)
    args = dict(zs=zs, x0=X0, P0=P0, f=f, Q=Q, h=h, R=R, N=10, rng=np.random.default_rng(0))
    args.update(kwargs)
    with pytest.raises(exc, match=match):
        pf.bootstrap_filter(**args)
    if set(kwargs) <= {"N", "threshold", "method", "rng"}:
        with pytest.raises(exc, match=match):
            pf.optimal_proposal_filter(zs, X0, P0, f, Q, H, R, **{**dict(N=10, rng=np.random.default_rng(0)), **kwargs})


def test_non_finite_weights_are_refused():
    X = np.zeros((5, 2))
    with pytest.raises(ValueError, match="^log_weights must be finite or -inf"):
        pf.cloud_moments(X, [0.0, np.nan, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="^loglik must be finite or -inf"):
        pf.reweight(np.zeros(5), [0.0, np.inf, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="^loglik gives every particle"):
        pf.reweight(np.zeros(5), np.full(5, -np.inf))
    with pytest.raises(ValueError, match="^log_weights must have shape"):
        pf.cloud_moments(X, np.zeros(4))
    with pytest.raises(ValueError, match="^N must be a positive integer"):
        pf.gaussian_particles(X0, P0, 0, np.random.default_rng(0))
    with pytest.raises(ValueError, match="^transition rows must sum to 1"):
        pf.jump_markov_filter(np.zeros((2, 1)), X0, P0, [CV, CV], [[0.5, 0.6], [0.5, 0.5]], [1.0, 0.0], h, R, 10,
                              np.random.default_rng(0), DT)
    with pytest.raises(ValueError, match="^mu0 must be 2 non-negative probabilities"):
        pf.jump_markov_filter(np.zeros((2, 1)), X0, P0, [CV, CV], np.eye(2), [0.5, 0.6], h, R, 10,
                              np.random.default_rng(0), DT)
