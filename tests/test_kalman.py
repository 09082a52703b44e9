"""Tests of kftrack.kalman: algebra against filterpy (test-only oracle) and closed forms,
batch broadcasting, missing measurements, the RTS smoother, consistency by chi-square bounds,
and bad input."""
from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter
from filterpy.kalman import rts_smoother as fp_rts
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from closed_forms import roundoff_tol
from kftrack import kalman
from kftrack.metrics import chi2_bounds

EPS = np.finfo(float).eps


def _predict_tols(x, P, F, Q):
    """Round-off bounds (absolute, normwise) for two codes computing ``F x`` and ``F P F^T + Q``:
    length-n inner products, |error| <= n eps |F||x| and (n + 1) eps (|F||P||F|^T + |Q|) each."""
    n = len(x)
    aF = np.abs(F)
    return {"x": roundoff_tol(aF @ np.abs(x), n), "P": roundoff_tol(aF @ np.abs(P) @ aF.T + np.abs(Q), n + 1)}


def _update_tols(x, P, z, H, R, u):
    """Round-off bounds (absolute, normwise) for two codes computing one Kalman update ``u``.

    Products are of length <= n + m (roundoff_tol's ``n``). The gain K = P H^T S^{-1} is a solve
    with S: relative error <= cond(S) (n + m) eps, and so are x = x- + K y (scale |x| + |K||y|) and
    the NIS y^T S^{-1} y (scale |y|^2 / lambda_min(S) >= nis). The Joseph form
    (I - KH) P (I - KH)^T + K R K^T is stationary in K at the optimal gain, so the gain's error
    enters P only at second order: P carries the products' round-off, scale
    |I - KH||P||I - KH|^T + |K||R||K|^T. log det S from a Cholesky factor with backward error
    m eps |S| moves by tr(S^{-1} dS) <= m cond(S) m eps, added to the NIS's in the log-likelihood.
    """
    n, m = len(x), len(z)
    S, K = u.S, u.K
    cS = np.linalg.cond(S)
    aK, aH = np.abs(K), np.abs(H)
    A = np.abs(np.eye(n) - K @ H)
    nis_scale = np.sum(u.y**2) / np.linalg.eigvalsh(S)[0]
    return {
        "y": roundoff_tol(np.abs(z) + aH @ np.abs(x), n + 1),
        "S": roundoff_tol(aH @ np.abs(P) @ aH.T + np.abs(R), n + 1),
        "K": roundoff_tol(K, n + m, cS),
        "x": roundoff_tol(np.abs(x).max() + aK @ np.abs(u.y), n + m, cS),
        "P": roundoff_tol(A @ np.abs(P) @ A.T + aK @ np.abs(R) @ aK.T, n + m),
        "nis": roundoff_tol(nis_scale, m, cS),
        "loglik": roundoff_tol(nis_scale + m, m, cS),
    }


def random_spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


def random_system(rng, n=4, m=2):
    F = np.eye(n) + 0.3 * rng.normal(size=(n, n))
    H = rng.normal(size=(m, n))
    return F, random_spd(rng, n, 0.1), H, random_spd(rng, m)


def cv2d(dt=1.0, q=0.5, r=4.0):
    """2-D constant velocity, state [x, vx, y, vy] (test fixture, written out by hand)."""
    Fa = np.array([[1.0, dt], [0.0, 1.0]])
    Qa = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    F = np.kron(np.eye(2), Fa)
    Q = np.kron(np.eye(2), Qa)
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    return F, Q, H, r * np.eye(2)


def simulate(rng, F, Q, H, R, x0, P0, steps, runs):
    n, m = F.shape[0], H.shape[0]
    x = rng.multivariate_normal(x0, P0, size=runs)
    xs, zs = np.empty((steps, runs, n)), np.empty((steps, runs, m))
    for k in range(steps):
        xs[k] = x
        zs[k] = x @ H.T + rng.multivariate_normal(np.zeros(m), R, size=runs)
        x = x @ F.T + rng.multivariate_normal(np.zeros(n), Q, size=runs)
    return xs, zs


# --- algebra ---------------------------------------------------------------------------


def test_predict_and_update_match_filterpy():
    rng = np.random.default_rng(1)
    F, Q, H, R = random_system(rng)
    x, P = rng.normal(size=4), random_spd(rng, 4)
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.x, kf.P, kf.F, kf.Q, kf.H, kf.R = x.copy(), P.copy(), F, Q, H, R
    kf.predict()
    xp, Pp = kalman.predict(x, P, F, Q)
    tol = _predict_tols(x, P, F, Q)  # derivations in _predict_tols / _update_tols
    np.testing.assert_allclose(xp, kf.x, rtol=0, atol=tol["x"])
    np.testing.assert_allclose(Pp, kf.P, rtol=0, atol=tol["P"])
    z = rng.normal(size=2)
    kf.update(z)
    u = kalman.update(xp, Pp, z, H, R)
    tol = _update_tols(xp, Pp, z, H, R, u)
    fp = {"x": kf.x, "P": kf.P, "y": kf.y, "S": kf.S, "K": kf.K, "loglik": kf.log_likelihood, "nis": kf.mahalanobis**2}
    for name, want in fp.items():
        np.testing.assert_allclose(getattr(u, name), want, rtol=0, atol=tol[name], err_msg=name)


def test_update_equals_information_form_and_loglik_equals_scipy():
    rng = np.random.default_rng(2)
    F, Q, H, R = random_system(rng, 5, 3)
    x, P, z = rng.normal(size=5), random_spd(rng, 5), rng.normal(size=3)
    u = kalman.update(x, P, z, H, R)
    # information form: P+^{-1} = P^{-1} + H^T R^{-1} H; x+ = P+ (P^{-1} x + H^T R^{-1} z)
    Y = np.linalg.inv(P) + H.T @ np.linalg.solve(R, H)
    P_info = np.linalg.inv(Y)
    x_info = P_info @ (np.linalg.solve(P, x) + H.T @ np.linalg.solve(R, z))
    # the information form inverts P and R (relative errors cond(P), cond(R) times n eps) and then
    # Y = P+^{-1}, which amplifies Y's relative error by cond(Y); the Kalman form solves with S
    c_info = np.linalg.cond(Y) * (np.linalg.cond(P) + np.linalg.cond(R)) + np.linalg.cond(u.S)
    np.testing.assert_allclose(u.P, P_info, rtol=0, atol=roundoff_tol(P_info, 5 + 3, c_info))
    x_scale = np.abs(P_info) @ (np.abs(np.linalg.solve(P, x)) + np.abs(H.T) @ np.abs(np.linalg.solve(R, z)))
    np.testing.assert_allclose(u.x, x_info, rtol=0, atol=roundoff_tol(x_scale, 5 + 3, c_info))
    S = H @ P @ H.T + R
    tol = _update_tols(x, P, z, H, R, u)  # scipy: eigh of S, the same first-order bound in cond(S)
    assert u.loglik == pytest.approx(stats.multivariate_normal(H @ x, S).logpdf(z), rel=0, abs=tol["loglik"])
    assert u.nis == pytest.approx((z - H @ x) @ np.linalg.solve(S, z - H @ x), rel=0, abs=tol["nis"])


def test_batch_equals_loop_with_shared_and_per_batch_matrices():
    rng = np.random.default_rng(3)
    F, Q, H, R = random_system(rng)
    B = 7
    x = rng.normal(size=(B, 4))
    P = np.stack([random_spd(rng, 4) for _ in range(B)])
    Rb = np.stack([random_spd(rng, 2) for _ in range(B)])
    z = rng.normal(size=(B, 2))
    xp, Pp = kalman.predict(x, P, F, Q)
    u = kalman.update(xp, Pp, z, H, Rb)
    for b in range(B):
        # batched and single matmuls may take different BLAS paths: each step is compared on the
        # same inputs, within the round-off bounds of _predict_tols / _update_tols
        xb, Pb = kalman.predict(x[b], P[b], F, Q)
        tp = _predict_tols(x[b], P[b], F, Q)
        np.testing.assert_allclose(xp[b], xb, rtol=0, atol=tp["x"])
        np.testing.assert_allclose(Pp[b], Pb, rtol=0, atol=tp["P"])
        ub = kalman.update(xp[b], Pp[b], z[b], H, Rb[b])
        tol = _update_tols(xp[b], Pp[b], z[b], H, Rb[b], ub)
        for field in kalman.Update._fields:
            np.testing.assert_allclose(getattr(u, field)[b], getattr(ub, field), rtol=0, atol=tol[field], err_msg=field)
    # two batch axes broadcast against each other
    x2 = np.broadcast_to(x[:, None, :], (B, 3, 4))
    u2 = kalman.update(x2, Pp[:, None], z[None, :3, :].repeat(B, 0), H, R)
    assert u2.x.shape == (B, 3, 4) and u2.nis.shape == (B, 3)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 6), m=st.integers(1, 4),
       scale=st.floats(1e-6, 1e6))
def test_joseph_update_is_symmetric_psd_and_not_larger_than_prior(seed, n, m, scale):
    rng = np.random.default_rng(seed)
    P = random_spd(rng, n, scale)
    H = rng.normal(size=(m, n))
    R = random_spd(rng, m, scale)
    x, z = rng.normal(size=n), rng.normal(size=m)
    u = kalman.update(x, P, z, H, R)
    np.testing.assert_array_equal(u.P, u.P.T)
    # The Joseph form with the computed gain K is PSD in exact arithmetic for any K; evaluating it
    # errs by <= _update_tols' "P" entrywise (normwise max), so by Weyl its eigenvalues move by
    # <= |E|_2 <= n max|E|; eigvalsh's backward error adds n eps |P|. P - P+ = K S K^T >= 0
    # exactly, the subtraction adds eps |P|.
    tol = n * _update_tols(x, P, z, H, R, u)["P"] + roundoff_tol(P, n, c=2.0)
    assert np.linalg.eigvalsh(u.P).min() >= -tol
    assert np.linalg.eigvalsh(P - u.P).min() >= -tol  # a measurement never adds uncertainty


# --- sequences ---------------------------------------------------------------------------


def test_kalman_filter_equals_step_by_step_and_nan_row_predicts_only():
    rng = np.random.default_rng(4)
    F, Q, H, R = cv2d()
    x0, P0 = np.zeros(4), 100.0 * np.eye(4)
    _, zs = simulate(rng, F, Q, H, R, x0, P0, 12, 1)
    zs = zs[:, 0]
    zs[5] = np.nan
    res = kalman.kalman_filter(zs, x0, P0, F, Q, H, R)
    x, P = x0, P0
    for k in range(12):  # one run: the same kernel calls on the same shapes, so the same bits
        np.testing.assert_array_equal(res.x_prior[k], x)
        if k == 5:
            assert np.isnan(res.nis[k]) and np.isnan(res.loglik[k])
        else:
            u = kalman.update(x, P, zs[k], H, R)
            x, P = u.x, u.P
            assert res.nis[k] == u.nis
        np.testing.assert_array_equal(res.x[k], x)
        np.testing.assert_array_equal(res.P[k], P)
        x, P = kalman.predict(x, P, F, Q)


def test_kalman_filter_batch_with_missing_in_some_runs_only():
    rng = np.random.default_rng(5)
    F, Q, H, R = cv2d()
    _, zs = simulate(rng, F, Q, H, R, np.zeros(4), np.eye(4), 10, 3)
    zs[4, 1] = np.nan
    res = kalman.kalman_filter(zs, np.zeros(4), np.eye(4), F, Q, H, R)
    for r in range(3):
        single = kalman.kalman_filter(zs[:, r], np.zeros(4), np.eye(4), F, Q, H, R)
        # batched and single matmuls may take different BLAS paths: each step adds at most the
        # round-off of one predict + update (n + m = 6 terms, cond(S) <= max over steps), and the
        # filter contracts earlier errors (|I - KH| F stable), so after T steps at most T times that
        T, cS = zs.shape[0], max(np.linalg.cond(H @ p @ H.T + R) for p in single.P_prior)
        np.testing.assert_allclose(res.x[:, r], single.x, rtol=0,
                                   atol=T * roundoff_tol(np.abs(single.x).max() + np.nanmax(np.abs(zs[:, r])), 6, cS))
        np.testing.assert_allclose(res.P[:, r], single.P, rtol=0, atol=T * roundoff_tol(single.P_prior, 6))
    assert np.isnan(res.nis[4, 1]) and not np.isnan(res.nis[4, 0])


def test_kalman_filter_without_priors_same_bits_less_memory():
    import tracemalloc

    rng = np.random.default_rng(7)
    F, Q, H, R = cv2d()
    x0, P0 = np.zeros(4), 10.0 * np.eye(4)
    _, zs = simulate(rng, F, Q, H, R, x0, P0, 40, 3)
    zs[6] = np.nan
    zs[9, 1] = np.nan  # one run only: per-run covariances
    for z in (zs[:, 0], zs):
        full = kalman.kalman_filter(z, x0, P0, F, Q, H, R)
        post = kalman.kalman_filter(z, x0, P0, F, Q, H, R, priors=False)
        assert post.x_prior is None and post.P_prior is None
        for name in ("x", "P", "nis", "loglik"):  # the same operations in the same order: the same bits
            assert np.array_equal(getattr(full, name), getattr(post, name), equal_nan=True), name
    with pytest.raises(ValueError, match=r"^result has no priors .*priors=True"):
        kalman.rts_smoother(post, F)
    with pytest.raises(TypeError, match=r"^priors must be True or False, got 'no'"):
        kalman.kalman_filter(zs, x0, P0, F, Q, H, R, priors="no")
    with pytest.raises(TypeError, match=r"^priors must be True or False, got 0"):
        kalman.kalman_filter(zs, x0, P0, F, Q, H, R, priors=0)
    # neither sequence of predictions is allocated: the peak drops by at least 90 % of their size
    # (the step's temporaries, a few (runs, n, n) arrays, are the same in both calls)
    big = np.broadcast_to(zs[:, :1], (40, 2000, 2)).copy()
    R_runs = np.broadcast_to(R, (2000, 2, 2))  # per-run covariances: P_prior is (T, runs, n, n)
    peak = {}
    for priors in (True, False):
        tracemalloc.start()
        kalman.kalman_filter(big, x0, P0, F, Q, H, R_runs, priors=priors)
        peak[priors] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    prior_bytes = 40 * 2000 * (4 + 16) * 8
    assert peak[True] - peak[False] >= 0.9 * prior_bytes, (peak, prior_bytes)


def test_rts_smoother_matches_filterpy_and_reduces_covariance():
    rng = np.random.default_rng(6)
    F, Q, H, R = cv2d()
    x0, P0 = np.zeros(4), 10.0 * np.eye(4)
    _, zs = simulate(rng, F, Q, H, R, x0, P0, 30, 1)
    res = kalman.kalman_filter(zs[:, 0], x0, P0, F, Q, H, R)
    sm = kalman.rts_smoother(res, F)
    xs_fp, Ps_fp, _, _ = fp_rts(res.x, res.P, [F] * 30, [Q] * 30)
    # Each backward step solves with P-_{k+1} (relative error <= n cond eps, n = 4) and carries the
    # later steps' errors through the gain G_k = P_k F^T (P-_{k+1})^{-1}: dx_k = local_k + G_k dx_{k+1},
    # so |dx_k| <= sum_{j >= k} |G_k ... G_{j-1}|_2 local_j (dP_k: the squares of those norms)
    cP = max(np.linalg.cond(p) for p in res.P_prior[1:])
    G = [np.linalg.solve(res.P_prior[k + 1], F @ res.P[k]).T for k in range(29)]
    amp_x = amp_P = 0.0
    for k in range(30):
        M, gx, gP = np.eye(4), 0.0, 0.0
        for j in range(k, 30):
            g = np.linalg.norm(M, 2)
            gx, gP = gx + g, gP + g * g
            M = M @ G[j] if j < 29 else M
        amp_x, amp_P = max(amp_x, gx), max(amp_P, gP)
    x_scale = np.abs(sm.x).max() + np.abs(res.x).max()
    np.testing.assert_allclose(sm.x, xs_fp, rtol=0, atol=amp_x * roundoff_tol(x_scale, 4, cP))
    np.testing.assert_allclose(sm.P, Ps_fp, rtol=0, atol=amp_P * roundoff_tol(res.P_prior, 4, cP))
    np.testing.assert_array_equal(sm.x[-1], res.x[-1])  # the last smoothed state is the filtered one
    for k in range(29):  # P - P^s = G (P- - P^s_{k+1}) G^T >= 0 exactly; Weyl: eigenvalues move by <= n max|dP|
        assert np.linalg.eigvalsh(res.P[k] - sm.P[k]).min() >= -4 * amp_P * roundoff_tol(res.P_prior, 4, cP)


# --- statistics --------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_nees_and_nis_inside_chi_square_bounds_on_random_systems(seed):
    """A correctly modelled KF is consistent: the Monte Carlo average NEES (NIS) at a fixed
    step lies in its two-sided 99.9 % chi-square interval. With 3 seeds x 2 statistics x 2
    steps the chance of a false failure is below 1.2 %."""
    rng = np.random.default_rng(seed)
    n, m, runs = 4, 2, 500
    F, Q, H, R = random_system(rng, n, m)
    F = F / max(1.0, np.abs(np.linalg.eigvals(F)).max())  # keep it stable
    x0, P0 = rng.normal(size=n), random_spd(rng, n)
    xs, zs = simulate(rng, F, Q, H, R, x0, P0, 20, runs)
    res = kalman.kalman_filter(zs, x0, P0, F, Q, H, R)
    err = xs - res.x
    nees = np.einsum("tri,tri->tr", err, np.linalg.solve(res.P, err[..., None])[..., 0])
    lo_x, hi_x = chi2_bounds(n, runs, 0.999)
    lo_y, hi_y = chi2_bounds(m, runs, 0.999)
    for k in (5, 19):
        assert lo_x <= nees[k].mean() <= hi_x
        assert lo_y <= res.nis[k].mean() <= hi_y


# --- bad input ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(x=np.zeros(3)), "P must have shape"),
        (dict(P=np.array([[1.0, 0.5], [0.0, 1.0]])), "P must be symmetric"),
        (dict(P=np.diag([1.0, -1.0])), "P must be positive semi-definite"),
        (dict(x=np.array([np.nan, 0.0])), "x must be finite"),
        (dict(z=np.array([1.0, 2.0])), "H must have shape"),
        (dict(R=np.zeros((1, 1))), "R must be positive definite"),
        (dict(z=np.array([np.inf])), "z must be finite"),
        (dict(H=np.ones((1, 3))), "H must have shape"),
        (dict(x="abc"), "x must be an array of real numbers"),
    ],
)
def test_update_bad_input_names_the_argument(kwargs, match):
    args = dict(x=np.zeros(2), P=np.eye(2), z=np.array([1.0]), H=np.array([[1.0, 0.0]]), R=np.eye(1))
    args.update(kwargs)
    with pytest.raises((ValueError, TypeError), match=match):
        kalman.update(**args)


def test_predict_bad_input_and_batch_mismatch():
    with pytest.raises(ValueError, match="F must have shape"):
        kalman.predict(np.zeros(2), np.eye(2), np.eye(3), np.eye(2))
    with pytest.raises(ValueError, match="Q must be symmetric"):
        kalman.predict(np.zeros(2), np.eye(2), np.eye(2), np.array([[1.0, 1.0], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="batch axes do not broadcast"):
        kalman.predict(np.zeros((3, 2)), np.eye(2), np.broadcast_to(np.eye(2), (4, 2, 2)), np.eye(2))


def test_kalman_filter_bad_input():
    F, Q, H, R = cv2d()
    zs = np.zeros((5, 2))
    zs[2, 0] = np.nan
    with pytest.raises(ValueError, match="only partly NaN"):
        kalman.kalman_filter(zs, np.zeros(4), np.eye(4), F, Q, H, R)
    with pytest.raises(ValueError, match="zs must have shape \\(T, ..., m\\)"):
        kalman.kalman_filter(np.zeros(2), np.zeros(4), np.eye(4), F, Q, H, R)
    with pytest.raises(ValueError, match="zs must be finite or NaN"):
        kalman.kalman_filter(np.full((3, 2), np.inf), np.zeros(4), np.eye(4), F, Q, H, R)
    with pytest.raises(TypeError, match="result must be a FilterResult"):
        kalman.rts_smoother((1, 2), F)
    res = kalman.kalman_filter(np.zeros((5, 2)), np.zeros(4), np.eye(4), F, Q, H, R)
    with pytest.raises(ValueError, match=r"F must have shape \(4, 4\) or the filter's batch axes"):
        kalman.rts_smoother(res, np.broadcast_to(F, (3, 4, 4)))  # more batch axes than the filter had
    with pytest.raises(ValueError, match="F must have shape"):
        kalman.rts_smoother(res, np.eye(3))


def test_bad_input_says_where_the_expected_sizes_come_from():
    x, P, H, R = np.zeros(2), np.eye(2), np.array([[1.0, 0.0]]), np.eye(1)
    # a measurement of the wrong size: H is blamed, and the message says m comes from z
    with pytest.raises(ValueError, match=r"H must have shape \(\.\.\., 2, 2\), got shape \(1, 2\) \(m = 2 from z, n = 2 from x\)"):
        kalman.update(x, P, np.zeros(2), H, R)
    with pytest.raises(ValueError, match=r"R must have shape \(\.\.\., 1, 1\), got shape \(2, 2\) \(m = 1 from z\)"):
        kalman.update(x, P, np.zeros(1), H, np.eye(2))
    with pytest.raises(ValueError, match=r"F must have shape \(\.\.\., 2, 2\), got shape \(3, 3\) \(n = 2 from x\)"):
        kalman.predict(x, P, np.eye(3), np.eye(2))
    with pytest.raises(ValueError, match=r"batch axes do not broadcast: x \(3,\), P \(4,\).*must be equal or 1"):
        kalman.update(np.zeros((3, 2)), np.broadcast_to(P, (4, 2, 2)), np.zeros(1), H, R)


def test_kalman_filter_names_x0_and_P0():
    F, Q, H, R = cv2d()
    zs = np.zeros((3, 2))
    with pytest.raises(ValueError, match="^x0 must be finite"):
        kalman.kalman_filter(zs, np.array([np.nan, 0, 0, 0]), np.eye(4), F, Q, H, R)
    with pytest.raises(ValueError, match=r"^P0 must have shape \(\.\.\., 4, 4\), got shape \(2, 2\) \(n = 4 from x0\)"):
        kalman.kalman_filter(zs, np.zeros(4), np.eye(2), F, Q, H, R)
    with pytest.raises(ValueError, match="^P0 must be positive semi-definite"):
        kalman.kalman_filter(zs, np.zeros(4), -np.eye(4), F, Q, H, R)
    with pytest.raises(ValueError, match=r"^R must have shape \(\.\.\., 1, 1\), got shape \(2, 2\) \(m = 1 from zs\)"):
        kalman.kalman_filter(np.zeros((3, 1)), np.zeros(4), np.eye(4), F, Q, H, R)


@pytest.mark.parametrize("bad", [None, 1j * np.eye(2), [[1.0, 0.0], [0.0, 1.0 + 1e-9j]]])
def test_none_and_complex_input_is_refused_not_coerced(bad):
    """NumPy would turn None into NaN and drop an imaginary part with only a warning."""
    with pytest.raises(TypeError, match="^F must be an array of real numbers, got (None|complex)"):
        kalman.predict(np.zeros(2), np.eye(2), bad, np.eye(2))


# --- the stepper: validated once, the covariance recursion reused once it repeats ----------------


def stepper_data(T=500, missing=250, runs=None):
    """The benchmark's workload (2-D constant velocity, q = 0.1, sigma_z = 5 m, P0 = 100 I) with
    one missing measurement."""
    F, Q, H, R = cv2d(dt=1.0, q=0.1, r=25.0)
    x0, P0 = np.zeros(4), 100.0 * np.eye(4)
    _, zs = simulate(np.random.default_rng(19), F, Q, H, R, x0, P0, T, runs or 1)
    zs = zs if runs else zs[:, 0]
    zs[missing] = np.nan
    return zs, x0, P0, F, Q, H, R


def run_stepper(s, zs):
    """Step ``s`` through ``zs`` (update then predict); everything it shows after each update."""
    out = {k: [] for k in ("x", "P", "nis", "loglik", "x_prior", "P_prior", "reused_from")}
    for z in zs:
        out["x_prior"].append(s.x)
        out["P_prior"].append(s.P)
        s.update(z)
        for k in ("x", "P", "nis", "loglik", "reused_from"):
            out[k].append(getattr(s, k))
        s.predict()
    return out


def test_stepper_is_the_kernels_bit_for_bit_and_reuses_the_covariances():
    from kftrack.kernels import kf_predict, kf_update

    zs, x0, P0, F, Q, H, R = stepper_data()
    T = zs.shape[0]
    got = run_stepper(kalman.KalmanStepper(x0, P0, F, Q, H, R), zs)
    x, P = x0, P0  # the unchecked kernels at every step
    last_in, expected, run = None, [], None  # the oracle of reused_from, from the kernels' own bits
    for k in range(T):
        assert np.array_equal(got["x_prior"][k], x) and np.array_equal(got["P_prior"][k], P), k
        if k == 250:  # missing: no update
            assert np.isnan(got["nis"][k]) and np.isnan(got["loglik"][k])
            run = None
        else:
            # the design: update k reuses iff its prior covariance has the bits of the prior of the
            # last update with a measurement (the inputs of the recursion; F, Q, H, R are constant)
            repeats = last_in is not None and last_in.tobytes() == P.tobytes()
            run = (k if run is None else run) if repeats else None
            last_in = P
            u = kf_update(x, P, zs[k], H, R)
            x, P = u.x, u.P
            assert got["nis"][k] == u.nis and got["loglik"][k] == u.loglik, k
        expected.append(run)
        assert np.array_equal(got["x"][k], x) and np.array_equal(got["P"][k], P), k
        x, P = kf_predict(x, P, F, Q)
    rf = got["reused_from"]
    # exactly where the kernels repeat: a stepper that reuses one update too early or too late, or
    # never, fails here (on this workload the kernels repeat from about update 100 on, before and
    # after the missing step; where the rounded recursion never repeats, reuse must not happen)
    assert rf == expected
    if all(e is None for e in expected[:250]) or all(e is None for e in expected[251:]):
        pytest.skip("the rounded covariance recursion has no fixed point on this arithmetic")
    first = next(k for k in range(T) if rf[k] is not None)
    assert got["P"][first] is got["P"][first - 1]  # really reused: the same array, not recomputed
    assert rf[250] is None and rf[251] is None  # a missing measurement breaks the fixed point
    again = next(k for k in range(251, T) if rf[k] is not None)
    assert got["P"][-1] is got["P"][again]


def test_stepper_equals_kalman_filter_bit_for_bit():
    from kftrack.models import ConstantVelocity

    zs, x0, P0, F, Q, H, R = stepper_data(T=300, missing=120)
    ref = kalman.kalman_filter(zs, x0, P0, F, Q, H, R)
    got = run_stepper(kalman.KalmanStepper(x0, P0, F, Q, H, R), zs)
    for name in kalman.FilterResult._fields:  # the same kernel calls: the same bits, not a tolerance
        assert np.array_equal(np.stack(got[name]), getattr(ref, name), equal_nan=True), name
    # F, Q as callables of the interval, as kalman_filter takes a model (cv2d is this model written out)
    cv = ConstantVelocity(ndim=2, q=0.1)
    np.testing.assert_array_equal(cv.F(1.0), F)
    got_dt = run_stepper(kalman.KalmanStepper(x0, P0, cv.F, cv.Q, H, R, dt=1.0), zs)
    ref_dt = kalman.kalman_filter(zs, x0, P0, cv.F, cv.Q, H, R, dt=1.0)
    assert np.array_equal(np.stack(got_dt["x"]), ref_dt.x)
    # many tracks in one stepper, the covariances shared, a step missing in all of them
    zb, *_ = stepper_data(T=80, missing=30, runs=3)
    refb = kalman.kalman_filter(zb, x0, P0, F, Q, H, R)
    gotb = run_stepper(kalman.KalmanStepper(np.zeros((3, 4)), P0, F, Q, H, R), zb)
    assert np.array_equal(np.stack(gotb["x"]), refb.x)
    assert np.array_equal(np.stack(gotb["nis"]), refb.nis, equal_nan=True)
    assert np.array_equal(np.stack(gotb["P"]), refb.P[:, 0])


def test_stepper_missing_measurement_forms_and_read_only_state():
    F, Q, H, R = cv2d()
    s = kalman.KalmanStepper(np.zeros(4), np.eye(4), F, Q, H, R)
    assert np.isnan(s.nis) and s.y is None and s.K is None and s.steps == 0
    s.update(None)
    s.update(np.full(2, np.nan))
    np.testing.assert_array_equal(s.x, np.zeros(4))
    np.testing.assert_array_equal(s.P, np.eye(4))
    assert s.steps == 2 and np.isnan(s.loglik) and s.reused_from is None
    s.update([1.0, 2.0])  # a list is converted (slow path), the same as an array
    u = kalman.update(np.zeros(4), np.eye(4), np.array([1.0, 2.0]), H, R)
    assert np.array_equal(s.x, u.x) and s.nis == u.nis and s.loglik == u.loglik
    assert np.array_equal(s.K, u.K) and np.array_equal(s.S, u.S) and np.array_equal(s.y, u.y)
    for name in ("P", "S", "K", "y"):  # P, S, K are shared with the cache; nis, loglik come from y
        with pytest.raises(ValueError, match="read-only"):
            getattr(s, name)[0, ...] = 5.0


def test_stepper_standard_form_and_copied_inputs():
    from kftrack.kernels import kf_predict, kf_update

    zs, x0, P0, F, Q, H, R = stepper_data(T=200, missing=60)
    F_in, P0_in = F.copy(), P0.copy()
    s = kalman.KalmanStepper(x0, P0_in, F_in, Q, H, R, form="standard")
    F_in[0, 1] = 7.0  # the caller's arrays change after construction: the stepper has its own copies
    P0_in[:] = 0.0
    got = run_stepper(s, zs)
    x, P = x0, P0
    for k in range(zs.shape[0]):  # the short form (I - KH)P, as the kernels compute it, to the last bit
        if k != 60:
            u = kf_update(x, P, zs[k], H, R, "standard")
            x, P = u.x, u.P
            assert got["nis"][k] == u.nis, k
        assert np.array_equal(got["x"][k], x) and np.array_equal(got["P"][k], P), k
        x, P = kf_predict(x, P, F, Q)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(x0=np.zeros(3)), r"^P0 must have shape"),
        (dict(P0=-np.eye(4)), "^P0 must be positive semi-definite"),
        (dict(F=np.eye(3)), r"^F must have shape \(\.\.\., 4, 4\)"),
        (dict(Q=np.ones((4, 4)) - 2 * np.eye(4)), "^Q must be positive semi-definite"),
        (dict(H=np.ones((2, 3))), r"^H must have shape \(\.\.\., 2, 4\)"),
        (dict(R=np.zeros((2, 2))), "^R must be positive definite"),
        (dict(R=np.eye(3)), r"^R must have shape \(\.\.\., 2, 2\), got shape \(3, 3\) \(m = 2 from H\)"),
        (dict(F=lambda dt: np.eye(4)), "F is a callable"),
        (dict(F=lambda dt: np.eye(4), Q=lambda dt: np.eye(4), dt=-1.0), "dt must be"),
        (dict(form="short"), "form must be one of"),
        (dict(x0=np.zeros((3, 4)), R=np.broadcast_to(np.eye(2), (2, 2, 2))), "batch axes do not broadcast"),
    ],
)
def test_stepper_bad_input_names_the_argument(kwargs, match):
    F, Q, H, R = cv2d()
    args = dict(x0=np.zeros(4), P0=np.eye(4), F=F, Q=Q, H=H, R=R)
    args.update(kwargs)
    with pytest.raises((ValueError, TypeError), match=match):
        kalman.KalmanStepper(**args)


@pytest.mark.parametrize(
    "z, match",
    [
        (np.zeros(3), r"^z must have shape \(\.\.\., 2\)"),
        (np.zeros((2, 2)), r"^z must have shape \(2,\)"),
        (np.array([1.0, np.inf]), "^z must be finite, or None or NaN"),
        (np.array([1.0, np.nan]), "^z is only partly NaN"),
        (np.array([1e200, 1e200]), None),  # huge but finite: a valid measurement
        ("ab", "^z must be an array of real numbers"),
        (np.array([1j, 0.0]), "^z must be an array of real numbers, got complex"),
    ],
)
def test_stepper_bad_measurement_names_z(z, match):
    F, Q, H, R = cv2d()
    s = kalman.KalmanStepper(np.zeros(4), np.eye(4), F, Q, H, R)
    if match is None:
        s.update(z)
        assert np.isfinite(s.x).all() and s.steps == 1
        return
    with pytest.raises((ValueError, TypeError), match=match):
        s.update(z)
    assert s.steps == 0  # a refused measurement does not count as a step


def test_unbatched_numpy_solve_path_keeps_the_bits_and_the_errors():
    """The unbatched NumPy branch of kernels._spd_factor/_spd_solve/_spd_logdet calls the gufuncs of
    numpy.linalg.solve/slogdet directly once LAPACK dpotrf has factored S: the same bits as
    numpy.linalg; a matrix that is not symmetric positive definite takes numpy.linalg itself."""
    from kftrack import kernels

    rng = np.random.default_rng(7)
    for m in (1, 2, 3, 6):
        S = random_spd(rng, m)
        S = 0.5 * (S + S.T)
        B = rng.normal(size=(m, 4))
        assert kernels._spd_factor(np, S) is kernels._NP_SPD
        assert np.array_equal(kernels.solve_spd(S, B), np.linalg.solve(S, B))
        assert np.array_equal(kernels.solve_spd(S, B[None].repeat(3, 0)), np.linalg.solve(S, B[None].repeat(3, 0)))
        assert kernels.logdet_spd(S) == np.linalg.slogdet(S)[1]
        y = rng.normal(size=m)
        nis, _ = kernels.innovation_score(y, S)
        assert nis == np.sum(y * np.linalg.solve(S, y[:, None])[:, 0])
    indefinite = np.array([[1.0, 2.0], [2.0, 1.0]])  # not positive definite, but not singular
    B = rng.normal(size=(2, 3))
    assert kernels._spd_factor(np, indefinite) is None
    assert np.array_equal(kernels.solve_spd(indefinite, B), np.linalg.solve(indefinite, B))
    nonsym = np.array([[1.0, 2.0], [0.5, 1.0]])  # singular, with a positive definite lower triangle
    assert kernels._spd_factor(np, nonsym) is None
    for singular in (nonsym, np.zeros((2, 2)), np.array([[1.0, 1.0], [1.0, 1.0]])):
        with pytest.raises(np.linalg.LinAlgError, match="Singular matrix"):
            kernels.solve_spd(singular, B)
    for bad in (np.full((2, 2), np.nan), np.array([[np.inf, 1.0], [1.0, 1.0]])):  # dpotrf says info = 0 here
        assert kernels._spd_factor(np, bad) is None
    # the other cases keep numpy.linalg itself: a batch of matrices, float32, a 1-D right-hand side
    S = random_spd(rng, 3)
    S = 0.5 * (S + S.T)
    Sb = np.stack([S, 2.0 * S])
    assert kernels._spd_factor(np, Sb) is None and kernels._spd_factor(np, S.astype(np.float32)) is None
    b = rng.normal(size=3)
    assert np.array_equal(kernels.solve_spd(S, b), np.linalg.solve(S, b))
    B32 = rng.normal(size=(3, 2)).astype(np.float32)
    assert np.array_equal(kernels.solve_spd(S, B32), np.linalg.solve(S, B32))
    assert np.array_equal(kernels.logdet_spd(Sb), np.linalg.slogdet(Sb)[1])
