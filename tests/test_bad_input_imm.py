"""The IMM cases of the newcomer's bad-input list (shared/reviews/2026-12-newcomer/bad-input.md,
issue 25): each ends as a clear error naming the argument, or a correct result where the input
is legitimate. The setup follows the list's reproducers."""
from __future__ import annotations

import numpy as np
import pytest

from kftrack import imm, kalman, models

R = 4 * np.eye(2)
CV = models.ConstantVelocity(ndim=2, q=1.0)
CT = models.CoordinatedTurn(q=1.0, q_omega=1e-4)
X = np.zeros(4)
P = 10 * np.eye(4)
ZS = np.cumsum(np.ones((20, 2)), 0)
PI2 = np.array([[0.95, 0.05], [0.1, 0.9]])
X5 = np.array([0.0, 10.0, 0.0, 0.0, 0.05])
P5 = np.diag([10.0, 10.0, 10.0, 10.0, 0.01])
EPS = np.finfo(float).eps


def _est():
    return imm.IMM([imm.KalmanMode(CV, R), imm.KalmanMode(models.KnownTurn(0.05, q=1.0), R)], PI2, [0.5, 0.5])


def _dwna_est():
    """Modes with the direct-discrete (sigma2) noise: Q = sigma2 Gamma Gamma^T has rank 2 of 4."""
    return imm.IMM([imm.KalmanMode(models.ConstantVelocity(ndim=2, sigma2=1.0), R),
                    imm.KalmanMode(models.KnownTurn(0.05, sigma2=1.0), R)], PI2, [0.5, 0.5])


# --------------------------------------------------------------------------------------------
# a nonlinear model in a linear mode: refused when the mode is built
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("model", [CT, models.CoordinatedTurnPolar(),
                                   models.Turn3DAngles(sigma2=1.0, sigma2_omega=1e-4)],
                         ids=["CoordinatedTurn", "CoordinatedTurnPolar", "Turn3DAngles"])
def test_kalman_mode_refuses_a_nonlinear_model(model):
    """`imm.KalmanMode(ct, R)` was accepted and failed later inside imm_filter."""
    with pytest.raises(TypeError, match=r"model.*(EKFMode|UKFMode)") as err:
        imm.KalmanMode(model, np.eye(model.H.shape[0]))
    assert type(model).__name__ in str(err.value)


def test_imm_filter_with_kalman_mode_of_coordinated_turn_fails_at_the_mode():
    """The list's reproducer `imm_filter(IMM([KalmanMode(ct, R), Tm(0.05)], ...), zs, x5, P5, 1.0)`
    used to fail inside imm_filter with "CoordinatedTurn.F() missing 1 required positional
    argument"; it now stops at KalmanMode(ct, R), naming model, and the bank built as advised runs."""
    with pytest.raises(TypeError, match="model"):
        imm.IMM([imm.KalmanMode(CT, R), imm.KalmanMode(models.KnownTurn(0.05, q=1.0), R)], PI2, [0.5, 0.5],
                components=[range(5), range(4)])
    est = imm.IMM([imm.EKFMode(CT, R), imm.KalmanMode(models.KnownTurn(0.05, q=1.0), R)], PI2, [0.5, 0.5],
                  components=[range(5), range(4)])
    res = imm.imm_filter(est, ZS, X5, P5, 1.0)
    assert np.isfinite(res.x).all() and res.x.shape == (20, 5)


def test_kalman_mode_still_takes_a_linear_duck_typed_model():
    """What KalmanMode documents: anything with n, F(dt), Q(dt), H (e.g. chapter 11's wrapper)."""
    from types import SimpleNamespace

    m = SimpleNamespace(n=4, F=CV.F, Q=lambda dt: CV.Q(dt), H=CV.H)
    mode = imm.KalmanMode(m, R)
    x, _ = mode.predict(X, P, 1.0)
    np.testing.assert_array_equal(x, kalman.predict(X, P, CV.F(1.0), CV.Q(1.0))[0])


# --------------------------------------------------------------------------------------------
# imm_smoother after P0 = 0 with rank-deficient (DWNA) process noise: a correct result
# --------------------------------------------------------------------------------------------
def test_imm_smoother_after_a_known_start_with_dwna_modes():
    """P0 = 0 and Q of rank 2: the first predicted covariances are singular (it was a bare
    LinAlgError). The known start must stay known (x = x0, P = 0 at step 0), the last step is the
    filter's, and the result is the limit of P0 = eps I as eps -> 0."""
    est = _dwna_est()
    res = imm.imm_filter(est, ZS, X, np.zeros((4, 4)), 1.0)
    sm = imm.imm_smoother(est, res, 1.0)
    assert np.isfinite(sm.x).all() and np.isfinite(sm.P).all() and np.isfinite(sm.mu).all()
    # a known start: the filtered P at step 0 is exactly 0, so every RTS gain there is 0
    np.testing.assert_array_equal(sm.x[0], X)
    np.testing.assert_array_equal(sm.P[0], 0.0)
    for name in ("x", "P", "mu"):
        np.testing.assert_array_equal(getattr(sm, name)[-1], getattr(res, name)[-1])
    # continuity: the smoother is smooth in P0 near 0, so |sm(eps) - sm(0)| = O(eps); measured
    # slope about 2 (m per unit of P0) here; 1e-8 is far above round-off (cond ~ 1e8 x eps ~ 1e-8
    # relative would be the worst case, on values of about 20: 2e-7)
    diffs = []
    for eps in (1e-6, 1e-8):
        r_eps = imm.imm_filter(est, ZS, X, eps * np.eye(4), 1.0)
        diffs.append(np.abs(imm.imm_smoother(est, r_eps, 1.0).x - sm.x).max())
    assert diffs[1] <= 1e2 * 1e-8 + 2e-7, diffs
    assert diffs[0] > 10 * diffs[1], diffs  # shrinks with eps: a limit, not a fixed offset


def test_one_dwna_mode_after_a_known_start_is_the_rts_smoother():
    """With one mode the IMM smoother is the RTS smoother, singular priors included (both take the
    pseudo-inverse of rts_step); round-off as in tests/test_imm_smoother.py, 10 n T cond(P^-) eps
    with the condition number of the regular steps (k >= 2; P^-_0 = 0 and P^-_1 = Q are singular)
    and 1e3 for the pseudo-inverse's cut-off at 1e3 n eps max|lambda|."""
    m = models.ConstantVelocity(ndim=2, sigma2=1.0)
    est = imm.IMM([imm.KalmanMode(m, R)], np.eye(1), [1.0])
    sm = imm.imm_smoother(est, imm.imm_filter(est, ZS, X, np.zeros((4, 4)), 1.0), 1.0)
    kf = kalman.kalman_filter(ZS, X, np.zeros((4, 4)), m.F(1.0), m.Q(1.0), m.H, R)
    rts = kalman.rts_smoother(kf, m.F(1.0))
    tol = 10 * 4 * 20 * np.linalg.cond(kf.P_prior[2:]).max() * 1e3 * EPS
    assert np.max(np.abs(sm.x - rts.x)) <= tol * np.abs(rts.x).max()
    assert np.max(np.abs(sm.P - rts.P)) <= tol * np.abs(rts.P).max()


# --------------------------------------------------------------------------------------------
# a result with NaN mode probabilities
# --------------------------------------------------------------------------------------------
def test_imm_smoother_refuses_nan_mode_probabilities():
    est = _est()
    fr = imm.imm_filter(est, ZS, X, P, 1.0)
    with pytest.raises(ValueError, match=r"result\.mu"):
        imm.imm_smoother(est, fr._replace(mu=fr.mu * np.nan), 1.0)
    bad = fr.mu.copy()
    bad[7] = [0.7, 0.7]
    with pytest.raises(ValueError, match=r"result\.mu.*sum"):
        imm.imm_smoother(est, fr._replace(mu=bad), 1.0)
    bad[7] = [1.5, -0.5]
    with pytest.raises(ValueError, match=r"result\.mu"):
        imm.imm_smoother(est, fr._replace(mu=bad), 1.0)


def test_imm_smoother_takes_a_float32_result():
    """The sum check allows float32 round-off (a float32 run is legitimate input)."""
    est = _est()
    fr = imm.imm_filter(est, ZS, X, P, 1.0, dtype="float32")
    assert np.isfinite(imm.imm_smoother(est, fr, 1.0).x).all()


# --------------------------------------------------------------------------------------------
# huge but finite measurements
# --------------------------------------------------------------------------------------------
@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # NumPy's overflow warnings come first
@pytest.mark.parametrize("scale", [1e40, 1e160, 1e300])
def test_imm_filter_names_zs_when_its_scale_breaks_float64(scale):
    """zs * 1e160 returned NaN (and 1e40 raised a bare LinAlgError): no float64 result can be right
    there (the innovations' squares overflow beyond 1.3e154; at 1e40 the numbers are resolved
    only to 1e25, far coarser than the 2 m noise), so a ValueError names zs and its scale."""
    with pytest.raises(ValueError, match=r"^zs has entries up to") as err:
        imm.imm_filter(_est(), ZS * scale, X, P, 1.0)
    assert f"{ZS.max() * scale:.3g}" in str(err.value)


def test_imm_filter_large_but_resolvable_measurements_still_work():
    """Scale invariance where float64 still resolves the noise: positions of 1e6 m with the same
    shape give the same estimates, shifted (relative round-off ~ 1e6 eps per step over 20 steps)."""
    est = _est()
    a = imm.imm_filter(est, ZS, X, P, 1.0)
    off = np.array([1e6, 0.0, -1e6, 0.0])
    b = imm.imm_filter(est, ZS + off[[0, 2]], X + off, P, 1.0)
    assert np.max(np.abs(b.x - off - a.x)) <= 20 * 1e6 * 100 * EPS
