"""Tests of kftrack.imm.imm_smoother (Kim's fixed-interval smoother over the IMM's output) on a
synthetic switch: constant velocity, then a turn at a known rate, then constant velocity again,
sampled at irregular intervals."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from kftrack import imm, kalman, models, scenarios
from kftrack.montecarlo import paired_difference, per_run_error

EPS = np.finfo(float).eps
R2 = 25.0 * np.eye(2)  # 5 m position noise
OMEGA = 0.08  # rad/s, the known turn rate
CV, CT = models.ConstantVelocity(ndim=2, q=0.05), models.KnownTurn(omega=OMEGA, q=0.05)
X0, P0 = np.array([0.0, 20.0, 0.0, 0.0]), np.diag([100.0, 4.0, 100.0, 4.0])
T, RUNS = 90, 300
# one-sided level 0.001 for every Monte Carlo claim below (paired t over RUNS runs)
T_CRIT = scipy.stats.t.ppf(1 - 0.001, RUNS - 1)


def _scenario(seed=20240515, runs=RUNS):
    """Truth simulated from the switching model itself (so the clairvoyant smoother is the exact
    conditional mean given the mode sequence), irregular dt, two steps without a measurement."""
    rng = np.random.default_rng(seed)
    dts = rng.uniform(0.5, 1.5, T)  # dts[k]: interval after step k
    seq = np.zeros(T, dtype=int)  # seq[k]: mode in force from step k to k + 1
    seq[30:60] = 1
    truth = np.empty((T, runs, 4))
    truth[0] = rng.multivariate_normal(X0, P0, size=runs)
    mdl = (CV, CT)
    for k in range(T - 1):
        F, Q = mdl[seq[k]].F(dts[k]), mdl[seq[k]].Q(dts[k])
        truth[k + 1] = truth[k] @ F.T + rng.multivariate_normal(np.zeros(4), Q, size=runs)
    zs = truth[..., [0, 2]] + 5.0 * rng.standard_normal((T, runs, 2))
    zs[[15, 45]] = np.nan
    return dts, seq, truth, zs


def _bank(transition=None):
    modes = [imm.KalmanMode(CV, R2), imm.KalmanMode(CT, R2)]
    return imm.IMM(modes, imm.SojournTransition([20.0, 20.0]) if transition is None else transition, [0.5, 0.5])


def _clairvoyant_smoother(zs, seq, dts):
    """RTS smoother told the true mode sequence: per-step F_k = F_{seq[k]}(dt_k), Q_k likewise
    (kalman_filter/rts_smoother with time_varying=True). Returns filtered x, smoothed x, P."""
    mdl = (CV, CT)
    Fs = np.stack([mdl[seq[k]].F(dts[k]) for k in range(T)])
    Qs = np.stack([mdl[seq[k]].Q(dts[k]) for k in range(T)])
    kf = kalman.kalman_filter(zs, X0, P0, Fs, Qs, CV.H, R2, time_varying=True)
    rts = kalman.rts_smoother(kf, Fs, time_varying=True)
    return kf.x, rts.x, rts.P


@pytest.fixture(scope="module")
def study():
    dts, seq, truth, zs = _scenario()
    est = _bank()
    res = imm.imm_filter(est, zs, X0, P0, dts)
    sm = imm.imm_smoother(est, res, dts)
    clair_f, clair_s, _ = _clairvoyant_smoother(zs, seq, dts)
    return dict(dts=dts, seq=seq, truth=truth, zs=zs, est=est, res=res, sm=sm, clair_f=clair_f, clair_s=clair_s)


# --------------------------------------------------------------------------------------------
# (1) one mode: the RTS smoother
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("model", [CV, CT])
def test_one_mode_equals_the_rts_smoother(model):
    rng = np.random.default_rng(3)
    zs = rng.normal(scale=20.0, size=(60, 7, 2))
    zs[9, 3] = np.nan  # one run misses one measurement
    dt = 1.3
    est = imm.IMM([imm.KalmanMode(model, R2)], np.eye(1), [1.0])
    res = imm.imm_filter(est, zs, X0, P0, dt)
    sm = imm.imm_smoother(est, res, dt)
    kf = kalman.kalman_filter(zs, X0, P0, model.F(dt), model.Q(dt), model.H, R2)
    rts = kalman.rts_smoother(kf, model.F(dt))
    # same equations in the same order; round-off bound per backward step ~ 10 n cond(P^-) eps,
    # accumulated over T steps (in practice the results agree to the last bit)
    cond = np.linalg.cond(kf.P_prior).max()
    tol = 10 * 60 * 4 * cond * EPS
    assert np.max(np.abs(sm.x - rts.x)) <= tol * np.max(np.abs(rts.x))
    assert np.max(np.abs(sm.P - rts.P)) <= tol * np.max(np.abs(rts.P))
    np.testing.assert_array_equal(sm.mu, 1.0)


def test_two_identical_modes_equal_the_rts_smoother_with_irregular_dt():
    """Two copies of the CV mode: whatever the mode probabilities, every pair RTS step is the
    CV one, so the smoother is the RTS smoother with F(dt_k) (round-off: merges of equal terms
    with weights summing to one, ~ r n eps per step, times T steps and cond(P^-))."""
    dts, _, _, zs = _scenario(runs=20)
    two = imm.IMM([imm.KalmanMode(CV, R2), imm.KalmanMode(CV, R2)], imm.SojournTransition([20.0, 20.0]), [0.3, 0.7])
    sm = imm.imm_smoother(two, imm.imm_filter(two, zs, X0, P0, dts), dts)
    kf = kalman.kalman_filter(zs, X0, P0, CV.F, CV.Q, CV.H, R2, dt=dts)
    rts = kalman.rts_smoother(kf, CV.F, dt=dts)
    tol = 10 * T * 2 * 4 * np.linalg.cond(kf.P_prior).max() * EPS
    assert np.max(np.abs(sm.x - rts.x)) <= tol * np.max(np.abs(rts.x))
    assert np.max(np.abs(sm.P - rts.P)) <= tol * np.max(np.abs(rts.P))


def test_the_forward_pass_records_the_mode_posteriors(study):
    res, est = study["res"], study["est"]
    assert len(res.xs) == len(res.Ps) == est.r
    # the combined posterior is the moment match of the recorded per-mode ones
    x, P = imm.mix_gaussians(res.mu, np.stack(res.xs), np.stack(res.Ps))
    np.testing.assert_allclose(x, res.x, rtol=0, atol=1e-9 * np.abs(res.x).max())  # r n eps * |x| scale
    np.testing.assert_allclose(P, res.P, rtol=0, atol=1e-9 * np.abs(res.P).max())


def test_the_clairvoyant_reference_filters_like_clairvoyant_filter(study):
    """The test's own clairvoyant smoother starts from the package's clairvoyant filter."""
    modes = [imm.KalmanMode(CV, R2), imm.KalmanMode(CT, R2)]
    x, _ = imm.clairvoyant_filter(modes, study["seq"], study["zs"], X0, P0, study["dts"])
    np.testing.assert_allclose(study["clair_f"], x, rtol=0, atol=1e-9 * np.abs(x).max())


# --------------------------------------------------------------------------------------------
# (2) against the clairvoyant smoother and the IMM filter
# --------------------------------------------------------------------------------------------
def _mse(study, est):
    return per_run_error(study["truth"], est, components=[0, 2])


def test_smoother_is_no_better_than_clairvoyant_and_better_than_the_filter(study):
    e_sm, e_f, e_cl = _mse(study, study["sm"].x), _mse(study, study["res"].x), _mse(study, study["clair_s"])
    vs_clair = paired_difference(e_sm, e_cl)
    vs_filter = paired_difference(e_sm, e_f)
    # the clairvoyant smoother is the exact conditional mean given the true modes: the IMM
    # smoother cannot beat it beyond Monte Carlo error (one-sided paired t at level 0.001)
    assert vs_clair.z > -T_CRIT, vs_clair
    # and smoothing must beat filtering (one-sided paired t at level 0.001)
    assert vs_filter.z < -T_CRIT, vs_filter


def test_smoother_is_better_than_the_filter_inside_the_turn(study):
    """Where the modes switch, the smoother must still beat the filter (steps 25..70)."""
    sl = slice(25, 70)
    tr = study["truth"][sl]
    e_sm = per_run_error(tr, study["sm"].x[sl], components=[0, 2])
    e_f = per_run_error(tr, study["res"].x[sl], components=[0, 2])
    assert paired_difference(e_sm, e_f).z < -T_CRIT


# --------------------------------------------------------------------------------------------
# (3) smoothed mode probabilities
# --------------------------------------------------------------------------------------------
def test_smoothed_mode_probabilities_are_probabilities(study):
    mu = study["sm"].mu
    assert mu.shape == study["res"].mu.shape
    assert np.all((mu >= 0) & (mu <= 1))
    # normalized in log space: |sum - 1| within a few r eps
    assert np.max(np.abs(mu.sum(-1) - 1.0)) <= 8 * EPS


def test_smoothed_mode_probabilities_pick_the_true_mode_more_often(study):
    seq = study["seq"]
    true_mode = seq[:-1]  # mode M_k at step k >= 1 is the one in force from k - 1 to k
    hit_s = (study["sm"].mu[1:].argmax(-1) == true_mode[:, None]).mean(0)  # per run
    hit_f = (study["res"].mu[1:].argmax(-1) == true_mode[:, None]).mean(0)
    d = paired_difference(hit_s, hit_f)
    assert d.z > T_CRIT, d  # one-sided paired t at level 0.001


def test_mode_conditioned_outputs_combine_to_the_output(study):
    sm = study["sm"]
    x, P = imm.mix_gaussians(sm.mu, np.stack(sm.xs), np.stack(sm.Ps))
    np.testing.assert_allclose(x, sm.x, rtol=0, atol=1e-9 * np.abs(sm.x).max())
    np.testing.assert_allclose(P, sm.P, rtol=0, atol=1e-9 * np.abs(sm.P).max())
    assert np.all(np.linalg.eigvalsh(sm.P) > 0)


def test_last_step_is_the_filter(study):
    """At T - 1 the smoother is the filter, to the last bit (it reports the filter's numbers)."""
    sm, res = study["sm"], study["res"]
    for name in ("x", "P", "mu"):
        np.testing.assert_array_equal(getattr(sm, name)[-1], getattr(res, name)[-1])
    for i in range(2):
        np.testing.assert_array_equal(sm.xs[i][-1], res.xs[i][-1])
        np.testing.assert_array_equal(sm.Ps[i][-1], res.Ps[i][-1])


def test_dt_matters(study):
    """The smoother uses F(dt[k]) and Pi(dt[k]) per step: a wrong dt changes the result."""
    other = imm.imm_smoother(study["est"], study["res"], 1.0)
    assert np.max(np.abs(other.x - study["sm"].x)) > 1.0


# --------------------------------------------------------------------------------------------
# (4) errors name the argument
# --------------------------------------------------------------------------------------------
def test_errors_name_the_argument(study):
    est, res, dts = study["est"], study["res"], study["dts"]
    with pytest.raises(TypeError, match="estimator"):
        imm.imm_smoother("imm", res, dts)
    with pytest.raises(TypeError, match="result"):
        imm.imm_smoother(est, res.x, dts)
    with pytest.raises(TypeError, match="GPB1"):
        imm.imm_smoother(imm.GPB1(est.modes, est.transition, [0.5, 0.5]), res, dts)
    with pytest.raises(ValueError, match="result"):
        imm.imm_smoother(est, res._replace(xs=None, Ps=None), dts)
    with pytest.raises(ValueError, match="result"):
        imm.imm_smoother(est, res._replace(xs=res.xs[:1], Ps=res.Ps[:1]), dts)
    with pytest.raises(ValueError, match="dt"):
        imm.imm_smoother(est, res, dts[:-2])  # (T - 1,) is np.diff of the timestamps: legal
    with pytest.raises(ValueError, match="dt"):
        imm.imm_smoother(est, res, -1.0)
    with pytest.raises(ValueError, match="dt and times"):
        imm.imm_smoother(est, res, dts, times=np.arange(T, dtype=float))
    with pytest.raises(ValueError, match="times"):
        imm.imm_smoother(est, res, times=np.arange(T, dtype=float)[::-1])

    class Bare:  # follows the Mode protocol, but offers no transition matrix for the backward pass
        def __init__(self, mode):
            self.n, self.R, self.predict, self.update = mode.n, mode.R, mode.predict, mode.update

    bare = imm.IMM([est.modes[0], Bare(est.modes[1])], np.eye(2) * 0.9 + 0.05, [0.5, 0.5])
    with pytest.raises(TypeError, match=r"estimator\.modes\[1\].*predict_linearized"):
        imm.imm_smoother(bare, res, dts)
    ca = models.ConstantAcceleration(ndim=2, q=0.1)  # 6 states beside 4: the shapes of res do not fit
    mixed = imm.IMM([imm.KalmanMode(CV, R2), imm.KalmanMode(ca, R2)], np.eye(2) * 0.9 + 0.05, [0.5, 0.5],
                    components=[(0, 1, 3, 4), tuple(range(6))])
    with pytest.raises(ValueError, match=r"result\.xs\[1\]"):
        imm.imm_smoother(mixed, res, dts)


def test_dt_of_length_t_minus_1_and_timestamps(study):
    """dt as np.diff of the timestamps (T - 1 intervals; the last interval is never used) gives
    the same bits as the T intervals, and times=t the same bits as dt=np.diff(t)."""
    est, res, dts, ref = study["est"], study["res"], study["dts"], study["sm"]
    sm = imm.imm_smoother(est, res, dts[:-1])
    for name in ("x", "P", "mu"):
        np.testing.assert_array_equal(getattr(sm, name), getattr(ref, name))
    t = np.concatenate([[0.0], np.cumsum(dts[:-1])])
    a, b = imm.imm_smoother(est, res, times=t), imm.imm_smoother(est, res, np.diff(t))
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)


# --------------------------------------------------------------------------------------------
# against the exact Bayesian smoother (all 2^T mode sequences enumerated, short window)
# --------------------------------------------------------------------------------------------
def test_closer_to_the_exact_smoother_than_the_filter():
    """On a 10-step window around the switch, the exact posterior mean is the mixture of the
    2^10 clairvoyant RTS smoothers weighted by P(sequence | Z). The IMM smoother, an
    approximation of it, must be closer to it than the IMM filter is, in position and in the
    mode probabilities (one-sided paired t at level 0.001 over the runs)."""
    import itertools

    Tn, runs = 10, 60
    dts, _, truth, zs = _scenario()
    sl = slice(25, 25 + Tn)  # the turn starts at step 30; no missing rows in the window
    truth, zs, dts = truth[sl, :runs], zs[sl, :runs], dts[sl]
    x0 = truth[0]
    trans, mdl = imm.SojournTransition([20.0, 20.0]), (CV, CT)
    est = _bank(trans)
    res = imm.imm_filter(est, zs, x0, P0, dts)
    sm = imm.imm_smoother(est, res, dts)
    seqs = np.array(list(itertools.product([0, 1], repeat=Tn)))  # M_0 .. M_{T-1}; M_{k+1} governs k -> k+1
    S = len(seqs)
    eye = np.eye(4)
    Fs = np.array([[mdl[s[k + 1]].F(dts[k]) if k < Tn - 1 else eye for s in seqs] for k in range(Tn)])
    Qs = np.array([[mdl[s[k + 1]].Q(dts[k]) if k < Tn - 1 else eye for s in seqs] for k in range(Tn)])
    Fs, Qs = (np.broadcast_to(a[:, :, None], (Tn, S, runs, 4, 4)) for a in (Fs, Qs))
    kf = kalman.kalman_filter(np.broadcast_to(zs[:, None], (Tn, S, runs, 2)), x0, P0, Fs, Qs, CV.H, R2,
                              time_varying=True)
    rts = kalman.rts_smoother(kf, Fs, time_varying=True)
    log_prior = np.log(0.5) + sum(np.log(trans(dts[k])[seqs[:, k], seqs[:, k + 1]]) for k in range(Tn - 1))
    logw = log_prior[:, None] + kf.loglik.sum(0)  # (S, runs)
    w = np.exp(logw - logw.max(0))
    w /= w.sum(0)
    x_exact = np.einsum("sr,tsrn->trn", w, rts.x)
    mu_exact = np.einsum("sr,st->tr", w, (seqs == 1).astype(float))  # P(M_k = turn | Z), (T, runs)
    t_crit = scipy.stats.t.ppf(1 - 0.001, runs - 1)
    dist = lambda x: np.sum((x - x_exact)[..., [0, 2]] ** 2, -1).mean(0)  # per run, m^2
    d = paired_difference(dist(sm.x), dist(res.x))
    assert d.z < -t_crit, d
    dmu = lambda mu: np.abs(mu[..., 1] - mu_exact).mean(0)
    d = paired_difference(dmu(sm.mu), dmu(res.mu))
    assert d.z < -t_crit, d


def test_documented_limitation_fast_switching_drifts():
    """The docstring's limitation: with 5 s mean sojourn times on this scenario the collapsed
    backward pass drifts and the smoother is worse than the filter (paired t, level 0.001). If
    this test fails, the smoother improved: update the docstring."""
    dts, _, truth, zs = _scenario(runs=100)
    est = _bank(imm.SojournTransition([5.0, 5.0]))
    res = imm.imm_filter(est, zs, X0, P0, dts)
    sm = imm.imm_smoother(est, res, dts)
    d = paired_difference(per_run_error(truth, sm.x, components=[0, 2]),
                          per_run_error(truth, res.x, components=[0, 2]))
    assert d.z > scipy.stats.t.ppf(1 - 0.001, 99), d


# --------------------------------------------------------------------------------------------
# against Kim & Nelson's equations written out run by run (three modes, asymmetric Pi)
# --------------------------------------------------------------------------------------------
def _kim_reference(res, modes, Pi, dts, run):
    """Kim (1994) / Kim & Nelson (1999, §5.2) written out for one run with
    explicit loops and inverses, from the filter's recorded mode posteriors x^i_{k|k}, P^i_{k|k},
    mu^i_{k|k} and predicted mode probabilities Pr[M_{k+1} = j | Z^k] = mu_prior[k + 1]:
    Pr[M_k = i, M_{k+1} = j | Z^T] = mu^j_{k+1|T} mu^i_{k|k} Pi_ij / Pr[M_{k+1} = j | Z^k]."""
    Tn, r = res.mu.shape[0], len(modes)
    xs = [[None] * r for _ in range(Tn)]
    Ps = [[None] * r for _ in range(Tn)]
    mu = np.empty((Tn, r))
    mu[-1] = res.mu[-1, run]
    for j in range(r):
        xs[-1][j], Ps[-1][j] = res.xs[j][-1, run], res.Ps[j][-1, run]
    for k in range(Tn - 2, -1, -1):
        joint = np.array([[mu[k + 1, j] * res.mu[k, run, i] * Pi[i, j] / res.mu_prior[k + 1, run, j]
                           for j in range(r)] for i in range(r)])
        mu[k] = joint.sum(1)
        for i in range(r):
            x_i, P_i = res.xs[i][k, run], res.Ps[i][k, run]
            px, pP = [], []
            for j in range(r):
                F, Q = modes[j].F(dts[k]), modes[j].Q(dts[k])
                Pp = F @ P_i @ F.T + Q
                G = P_i @ F.T @ np.linalg.inv(Pp)
                px.append(x_i + G @ (xs[k + 1][j] - F @ x_i))
                pP.append(P_i + G @ (Ps[k + 1][j] - Pp) @ G.T)
            w = joint[i] / mu[k, i]
            xm = sum(w[j] * px[j] for j in range(r))
            xs[k][i] = xm
            Ps[k][i] = sum(w[j] * (pP[j] + np.outer(px[j] - xm, px[j] - xm)) for j in range(r))
    return mu, np.array(xs)


def test_matches_kim_equations_written_out_with_asymmetric_transition():
    mdl = (CV, models.KnownTurn(omega=OMEGA, q=0.05), models.KnownTurn(omega=-2 * OMEGA, q=0.05))
    Pi = np.array([[0.90, 0.07, 0.03], [0.20, 0.75, 0.05], [0.10, 0.25, 0.65]])  # Pi != Pi.T
    est = imm.IMM([imm.KalmanMode(m, R2) for m in mdl], Pi, [0.6, 0.3, 0.1])
    dts, _, _, zs = _scenario(runs=3)
    Tn = 40
    dts, zs = dts[:Tn], zs[20:20 + Tn].copy()  # through the switch at step 30; one missing row (45)
    res = imm.imm_filter(est, zs, X0, P0, dts)
    sm = imm.imm_smoother(est, res, dts)
    # round-off: each backward step ~ 10 n cond(P^-) eps relative (P^- = F P F' + Q, cond(P^-)
    # <= cond(F)^2 cond(P) with cond(F) < 10 here), r merges, over Tn steps
    cond = max(np.linalg.cond(p).max() for p in res.Ps) * 1e2
    tol = 10 * Tn * 4 * 3 * cond * EPS
    for run in range(zs.shape[1]):
        mu, xs = _kim_reference(res, mdl, Pi, dts, run)
        assert np.max(np.abs(sm.mu[:, run] - mu)) <= tol
        xs_sm = np.stack([a[:, run] for a in sm.xs], 1)
        assert np.max(np.abs(xs_sm - xs)) <= tol * np.abs(xs).max()
        # power: the same reference with the transposed Pi is far off
        mu_t, _ = _kim_reference(res, mdl, Pi.T, dts, run)
        assert np.max(np.abs(mu_t - mu)) > 1e3 * tol


# --------------------------------------------------------------------------------------------
# nonlinear modes and modes of different dimension (the bank the imm module docstring shows)
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("Mode", [imm.EKFMode, imm.UKFMode])
def test_one_nonlinear_mode_on_a_linear_model_is_the_rts_smoother(Mode):
    """On a linear model the EKF's Jacobian and the UKF's statistical linearization are both
    F(dt): the IMM smoother of one such mode is the RTS smoother. Round-off: the EKF mode runs
    the same products (~ 10 n cond(P^-) eps per backward step, over T steps, as above); the UKF
    mode's unscented moments and C^T P^+ add a few n eps cond(P) per step, the same order."""
    rng = np.random.default_rng(5)
    zs = rng.normal(scale=20.0, size=(60, 4, 2))
    dt = 1.3
    est = imm.IMM([Mode(CT, R2)], np.eye(1), [1.0])
    res = imm.imm_filter(est, zs, X0, P0, dt)
    sm = imm.imm_smoother(est, res, dt)
    kf = kalman.kalman_filter(zs, X0, P0, CT.F(dt), CT.Q(dt), CT.H, R2)
    rts = kalman.rts_smoother(kf, CT.F(dt))
    cond = max(np.linalg.cond(kf.P_prior).max(), np.linalg.cond(kf.P).max())
    tol = 10 * 60 * 4 * cond * EPS
    assert np.max(np.abs(sm.x - rts.x)) <= tol * np.max(np.abs(rts.x))
    assert np.max(np.abs(sm.P - rts.P)) <= tol * np.max(np.abs(rts.P))


def _cv_with_heading_state():
    """A 5-state linear model, state [w, x, vx, y, vy]: CV plus a random walk w that nothing
    measures and that does not enter the motion (decoupled)."""
    from types import SimpleNamespace

    block = lambda a, b: np.block([[a, np.zeros((1, 4))], [np.zeros((4, 1)), b]])  # noqa: E731
    return SimpleNamespace(n=5, F=lambda dt: block(np.eye(1), CT.F(dt)),
                           Q=lambda dt: block(np.array([[0.01 * dt]]), CT.Q(dt)),
                           H=np.hstack([np.zeros((2, 1)), CT.H]))


def test_modes_of_different_dimension_with_a_decoupled_component_and_permuted_order():
    """CV (common components 0-3) beside a turn mode holding [w, x, vx, y, vy] = common
    (4, 0, 1, 2, 3), where w is decoupled and never measured: on components 0-3 the mixed bank
    must smooth exactly as the two-mode bank without w (the completion, the pair space and the
    index maps then add zeros, up to round-off). Round-off: different matrix sizes change the
    BLAS summation order, ~ 10 n cond(P) eps per step over T steps."""
    dts, _, _, zs = _scenario(runs=20)
    trans = imm.SojournTransition([20.0, 20.0])
    small = imm.IMM([imm.KalmanMode(CV, R2), imm.KalmanMode(CT, R2)], trans, [0.5, 0.5])
    big = imm.IMM([imm.KalmanMode(CV, R2), imm.KalmanMode(_cv_with_heading_state(), R2)], trans, [0.5, 0.5],
                  components=[(0, 1, 2, 3), (4, 0, 1, 2, 3)])
    P0_5 = np.zeros((5, 5))
    P0_5[:4, :4], P0_5[4, 4] = P0, 0.3
    x0_5 = np.append(X0, 0.7)
    rs, rb = imm.imm_filter(small, zs, X0, P0, dts), imm.imm_filter(big, zs, x0_5, P0_5, dts)
    ss, sb = imm.imm_smoother(small, rs, dts), imm.imm_smoother(big, rb, dts)
    cond = max(np.linalg.cond(p).max() for p in rs.Ps)
    tol = 10 * T * 5 * cond * EPS
    assert np.max(np.abs(sb.x[..., :4] - ss.x)) <= tol * np.abs(ss.x).max()
    assert np.max(np.abs(sb.P[..., :4, :4] - ss.P)) <= tol * np.abs(ss.P).max()
    assert np.max(np.abs(sb.mu - ss.mu)) <= tol
    assert np.max(np.abs(sb.xs[1][..., 1:] - ss.xs[1])) <= tol * np.abs(ss.x).max()
    # w: nothing measures it, so it stays at its prior mean (its cross-covariances are round-off:
    # mixing weights that sum to 1 within a few eps). Before the fix of IMM._combine for a full
    # mode holding the components permuted, the combined w was filled from the wrong component.
    assert np.max(np.abs(sb.x[..., 4] - 0.7)) <= tol
    assert np.max(np.abs(rb.x[..., 4] - 0.7)) <= tol


CTN = models.CoordinatedTurn(ndim=2, q=0.05, q_omega=1e-3)


def _kim_reference_mixed(res, dts, Pi, run):
    """Kim's recursion for the bank CV (4 states) + CT-EKF (5 states), one run, written out
    pair by pair with explicit completions and inverses (independent of kftrack.imm's index
    maps): pair CV -> CT completes x^CV with CT's own omega estimate (zero cross-covariance),
    pair CT -> CV runs CV's F on the first 4 components and smooths omega through its covariance."""
    Tn = res.mu.shape[0]
    mu = np.empty((Tn, 2))
    mu[-1] = res.mu[-1, run]
    xs = [[None, None] for _ in range(Tn)]
    xs[-1] = [res.xs[0][-1, run], res.xs[1][-1, run]]
    Ps = [[None, None] for _ in range(Tn)]
    Ps[-1] = [res.Ps[0][-1, run], res.Ps[1][-1, run]]
    for k in range(Tn - 2, -1, -1):
        d = dts[k]
        joint = np.array([[mu[k + 1, j] * res.mu[k, run, i] * Pi[i, j] / res.mu_prior[k + 1, run, j]
                           for j in range(2)] for i in range(2)])
        mu[k] = joint.sum(1)
        xa, Pa = res.xs[0][k, run], res.Ps[0][k, run]  # CV at k
        xb, Pb = res.xs[1][k, run], res.Ps[1][k, run]  # CT at k
        pairs = [[None, None], [None, None]]
        Fcv, Qcv = CV.F(d), CV.Q(d)
        # CV -> CV
        Pp = Fcv @ Pa @ Fcv.T + Qcv
        G = Pa @ Fcv.T @ np.linalg.inv(Pp)
        pairs[0][0] = (xa + G @ (xs[k + 1][0] - Fcv @ xa), Pa + G @ (Ps[k + 1][0] - Pp) @ G.T)
        # CV -> CT: complete with CT's omega
        xu = np.append(xa, xb[4])
        Pu = np.zeros((5, 5))
        Pu[:4, :4], Pu[4, 4] = Pa, Pb[4, 4]
        J = CTN.jacobian(xu, d)
        Pp = J @ Pu @ J.T + CTN.Q(d)
        G = Pu @ J.T @ np.linalg.inv(Pp)
        pairs[0][1] = ((xu + G @ (xs[k + 1][1] - CTN.f(xu, d)))[:4], (Pu + G @ (Ps[k + 1][1] - Pp) @ G.T)[:4, :4])
        # CT -> CV: CV's F on the kinematic components, omega carried by its covariance
        Fr = np.hstack([Fcv, np.zeros((4, 1))])
        Pp = Fr @ Pb @ Fr.T + Qcv
        G = Pb @ Fr.T @ np.linalg.inv(Pp)
        pairs[1][0] = (xb + G @ (xs[k + 1][0] - Fr @ xb), Pb + G @ (Ps[k + 1][0] - Pp) @ G.T)
        # CT -> CT
        J = CTN.jacobian(xb, d)
        Pp = J @ Pb @ J.T + CTN.Q(d)
        G = Pb @ J.T @ np.linalg.inv(Pp)
        pairs[1][1] = (xb + G @ (xs[k + 1][1] - CTN.f(xb, d)), Pb + G @ (Ps[k + 1][1] - Pp) @ G.T)
        for i in range(2):
            w = joint[i] / mu[k, i]
            xm = w[0] * pairs[i][0][0] + w[1] * pairs[i][1][0]
            xs[k][i] = xm
            Ps[k][i] = sum(w[j] * (pairs[i][j][1] + np.outer(pairs[i][j][0] - xm, pairs[i][j][0] - xm))
                           for j in range(2))
    return mu, xs


def test_cv_and_ct_ekf_bank_matches_kim_equations_written_out():
    Pi = np.array([[0.93, 0.07], [0.15, 0.85]])
    est = imm.IMM([imm.KalmanMode(CV, R2), imm.EKFMode(CTN, R2)], Pi, [0.6, 0.4])
    dts, _, _, zs = _scenario(runs=3)
    Tn = 40
    dts, zs = dts[:Tn], zs[20:20 + Tn]  # through the switch at step 30; one missing row (45)
    x0 = np.append(X0, 0.0)
    P0_5 = np.diag(np.append(np.diag(P0), 0.05 ** 2))
    res = imm.imm_filter(est, zs, x0, P0_5, dts)
    sm = imm.imm_smoother(est, res, dts)
    # round-off as in the linear written-out test: 10 Tn n r cond eps (cond(F) < 10 squared)
    cond = max(np.linalg.cond(p).max() for p in res.Ps) * 1e2
    tol = 10 * Tn * 5 * 2 * cond * EPS
    for run in range(zs.shape[1]):
        mu, xs = _kim_reference_mixed(res, dts, Pi, run)
        assert np.max(np.abs(sm.mu[:, run] - mu)) <= tol
        for i in range(2):
            ref = np.array([xs[k][i] for k in range(Tn)])
            assert np.max(np.abs(sm.xs[i][:, run] - ref)) <= tol * np.abs(ref).max()


@pytest.fixture(scope="module")
def turning_target():
    """Study 000's scenario II (kftrack.scenarios.drone_scenario, chapter 11): 50 m straight, a
    90 deg left turn of radius 30 m, 50 m straight, a right turn, 50 m straight, at 2.24 m/s,
    sampled every 0.447 s (245 steps) with 2 m noise; horizontal plane. Noise redrawn per run."""
    rng = np.random.default_rng(20261203)
    sc = scenarios.drone_scenario(rng, "II")
    truth = sc.truth[:, :4]
    runs = 60
    zs = truth[:, None, [0, 2]] + 2.0 * rng.standard_normal((len(sc.t), runs, 2))
    return truth, zs, float(np.diff(sc.t)[0]), runs


@pytest.mark.parametrize("Mode", [imm.EKFMode, imm.UKFMode])
def test_cv_and_ct_bank_smooths_a_turning_target(turning_target, Mode):
    """The imm module docstring's bank, CV (4 states) + coordinated turn (5 states, EKF or UKF):
    the smoother's last step is the filter's, exactly; and its position RMSE per run is lower
    than the filter's (one-sided paired t over the runs at level 0.001)."""
    truth, zs, dt, runs = turning_target
    R = 4.0 * np.eye(2)
    est = imm.IMM([imm.KalmanMode(CV, R), Mode(CTN, R)], imm.SojournTransition([20.0, 20.0]), [0.5, 0.5])
    x0 = np.append(truth[0], 0.0)
    P0_5 = np.diag([4.0, 1.0, 4.0, 1.0, 0.05 ** 2])
    res = imm.imm_filter(est, zs, x0, P0_5, dt)
    sm = imm.imm_smoother(est, res, dt)
    for name in ("x", "P", "mu"):
        np.testing.assert_array_equal(getattr(sm, name)[-1], getattr(res, name)[-1])
    assert sm.xs[0].shape == res.xs[0].shape and sm.xs[1].shape == res.xs[1].shape
    rmse = lambda x: np.sqrt(per_run_error(truth[:, None], x[..., :4], components=[0, 2]))  # noqa: E731
    d = paired_difference(rmse(sm.x), rmse(res.x))
    assert d.z < -scipy.stats.t.ppf(1 - 0.001, runs - 1), d


def test_ukf_mode_with_a_heading_state_smooths_across_plus_minus_pi():
    """A UKF mode on the polar turn [x, y, v, chi, omega] with chi an angle (state_angles=[3]): the
    heading passes +-pi, where the filter wraps it. The backward residual is wrapped too, so the
    smoothed heading stays in (-pi, pi] and close to the truth (an unwrapped residual would be off
    by 2 pi there), and the position RMSE per run beats the filter's (paired t, level 0.001)."""
    from types import SimpleNamespace

    rng = np.random.default_rng(3)
    Tn, runs, dt, w, v, chi0 = 80, 40, 1.0, 0.1, 10.0, 2.5
    chi = chi0 + w * dt * np.arange(Tn)  # crosses pi at step 6 and 3 pi at step 69
    pos = np.stack([v / w * (np.sin(chi) - np.sin(chi0)), -v / w * (np.cos(chi) - np.cos(chi0))], -1)
    zs = pos[:, None] + 3.0 * rng.standard_normal((Tn, runs, 2))
    polar = models.CoordinatedTurnPolar()
    model = SimpleNamespace(n=5, f=polar.f, H=polar.H, Q=lambda d: np.diag([0.1, 0.1, 0.1, 1e-4, 1e-5]) * d)
    est = imm.IMM([imm.UKFMode(model, 9.0 * np.eye(2), state_angles=[3])], np.eye(1), [1.0])
    res = imm.imm_filter(est, zs, np.array([0.0, 0.0, v, chi0, w]), np.diag([9.0, 9.0, 1.0, 0.01, 1e-4]), dt)
    sm = imm.imm_smoother(est, res, dt)
    assert np.all(np.abs(sm.x[..., 3]) <= np.pi)
    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi  # noqa: E731
    assert np.abs(wrap(sm.x[..., 3] - chi[:, None])).max() < 0.5  # measured below 0.1 rad
    rmse = lambda x: np.sqrt(np.sum((x[..., :2] - pos[:, None]) ** 2, -1).mean(0))  # noqa: E731
    d = paired_difference(rmse(sm.x), rmse(res.x))
    assert d.z < -scipy.stats.t.ppf(1 - 0.001, runs - 1), d
