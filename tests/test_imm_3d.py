"""Tests for chapter 12 (seed 001's 3-D radar IMM): the state-dependent process noise of
:class:`kftrack.imm.EKFMode` and the running-RMS metric of :mod:`kftrack.metrics` (eqs. 44–46)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from kftrack import ekf, imm, metrics, models
from kftrack.sensors.radar import RangeAzimuthElevation

T = 4.0
RADAR = RangeAzimuthElevation(sigmas=(75.0, np.deg2rad(1.0), np.deg2rad(1.0)))
CT = models.Turn3DAngles(form="nonsingular", sigma2=10.0**2, sigma2_omega=0.005**2)
X = np.array([-30000.0, 196.16, -30000.0, 154.98, 600.0, 5.0, 0.04, 0.01])


def _polar_mode(model, **kw):
    return imm.EKFMode(model, RADAR.R, h=RADAR.h, H_jac=RADAR.jacobian,
                       angle_components=RADAR.angle_components, **kw)


# --------------------------------------------------------------------------------------------
# EKFMode with a state-dependent Q
# --------------------------------------------------------------------------------------------
def test_state_dependent_q_is_read_from_the_model_attribute():
    assert models.Turn3DAngles.state_dependent_noise is True
    assert _polar_mode(CT).state_dependent_Q
    assert not _polar_mode(models.ConstantVelocity(ndim=3, sigma2=1.0)).state_dependent_Q
    assert not imm.EKFMode(models.CoordinatedTurn(q=1.0, q_omega=1e-4), np.eye(2)).state_dependent_Q
    for cls in (models.ConstantVelocity, models.ConstantAcceleration, models.Singer, models.KnownTurn,
                models.CoordinatedTurn, models.CoordinatedTurnPolar, models.Turn3D):
        assert cls.state_dependent_noise is False, cls
    with pytest.raises(TypeError, match="state_dependent_Q"):
        _polar_mode(CT, state_dependent_Q="yes")


def test_ekf_mode_predict_uses_q_at_the_estimate_exactly():
    P = np.diag([1e4, 100.0, 1e4, 100.0, 1e4, 100.0, 1e-3, 1e-3])
    xb = X + np.array([[0.0] * 8, [0, 30.0, 0, -20.0, 0, 10.0, 0.02, -0.01]])  # two runs, two Qs
    x1, P1 = _polar_mode(CT).predict(xb, P, T)
    J = CT.jacobian(xb, T)
    np.testing.assert_array_equal(x1, CT.f(xb, T))
    expected = J @ P @ np.swapaxes(J, -1, -2) + CT.Q(xb, T)
    np.testing.assert_allclose(P1, expected, rtol=1e-13, atol=1e-9)
    assert not np.allclose(CT.Q(xb[0], T), CT.Q(xb[1], T))  # the test can tell the two Qs apart


def test_explicit_flag_overrides_the_model_attribute():
    class Stub:
        n = 2
        H = np.eye(2)

        def f(self, x, dt):
            return x

        def jacobian(self, x, dt):
            return np.eye(2)

        def Q(self, *args):  # signature hides whether the state is passed
            return np.eye(2) * (args[0][..., :1, None] ** 2 if len(args) == 2 else 1.0)

    class StateStub(Stub):
        state_dependent_noise = True

    x, P = np.array([3.0, 0.0]), np.eye(2)
    assert not imm.EKFMode(Stub(), np.eye(2)).state_dependent_Q  # no attribute: Q(dt)
    assert imm.EKFMode(StateStub(), np.eye(2)).state_dependent_Q
    np.testing.assert_array_equal(imm.EKFMode(StateStub(), np.eye(2)).predict(x, P, 1.0)[1], 10.0 * np.eye(2))
    assert not imm.EKFMode(StateStub(), np.eye(2), state_dependent_Q=False).state_dependent_Q
    _, P_dt = imm.EKFMode(Stub(), np.eye(2)).predict(x, P, 1.0)
    _, P_x = imm.EKFMode(Stub(), np.eye(2), state_dependent_Q=True).predict(x, P, 1.0)
    np.testing.assert_array_equal(P_dt, 2.0 * np.eye(2))
    np.testing.assert_array_equal(P_x, 10.0 * np.eye(2))


def test_one_mode_imm_with_turn3d_equals_a_hand_written_ekf():
    rng = np.random.default_rng(12)
    truth = np.stack([models.Turn3DAngles.f_exact(X, k * T) for k in range(12)])
    zs = RADAR.simulate(np.broadcast_to(truth[:, None], (12, 3, 8)), rng)
    P0 = np.diag([300.0**2, 50.0**2] * 3 + [0.05**2] * 2)
    res = imm.imm_filter(imm.IMM([_polar_mode(CT)], np.eye(1), [1.0]), zs, X, P0, T)
    x, P = np.broadcast_to(X, (3, 8)), np.broadcast_to(P0, (3, 8, 8))
    for k in range(12):
        np.testing.assert_allclose(res.x_prior[k], x, rtol=1e-12, atol=1e-9)
        u = ekf.ekf_update(x, P, zs[k], RADAR.h, RADAR.jacobian, RADAR.R, RADAR.angle_components)
        np.testing.assert_allclose(res.x[k], u.x, rtol=1e-12, atol=1e-9)
        x, P = ekf.ekf_predict(u.x, u.P, lambda s: CT.f(s, T), lambda s: CT.jacobian(s, T), CT.Q(u.x, T))


def test_mixed_dimension_imm_runs_with_cv6_and_turn8():
    rng = np.random.default_rng(3)
    truth = np.stack([models.Turn3DAngles.f_exact(X, k * T) for k in range(15)])
    zs = RADAR.simulate(np.broadcast_to(truth[:, None], (15, 4, 8)), rng)
    cv = _polar_mode(models.ConstantVelocity(ndim=3, sigma2=3.5**2))
    est = imm.IMM([cv, _polar_mode(CT)], imm.first_order_transition([200.0, 20.0], T), [0.5, 0.5])
    res = imm.imm_filter(est, zs, X, np.diag([300.0**2, 50.0**2] * 3 + [0.05**2] * 2), T)
    np.testing.assert_allclose(res.mu.sum(-1), 1.0, atol=1e-12)
    assert np.isfinite(res.x).all() and res.x.shape == (15, 4, 8)


# --------------------------------------------------------------------------------------------
# running RMS, eqs. 44–46
# --------------------------------------------------------------------------------------------
def test_running_rms_by_hand():
    e = np.array([[3.0, 0.0], [4.0, 0.0], [0.0, 6.0]])
    r = metrics.running_rms(e)
    np.testing.assert_allclose(r[:, 0], [3.0, np.sqrt(12.5), np.sqrt(25.0 / 3)], rtol=1e-15)
    np.testing.assert_allclose(r[:, 1], [0.0, 0.0, np.sqrt(12.0)], rtol=1e-15)
    rms_bar, norm = metrics.mean_running_rms(e)
    np.testing.assert_allclose(rms_bar, r.mean(axis=0), rtol=1e-15)
    np.testing.assert_allclose(norm, np.hypot(*rms_bar), rtol=1e-15)


def test_a_single_early_error_counts_more_than_a_late_one():
    n = 25
    early, late = np.zeros((n, 1)), np.zeros((n, 1))
    early[0], late[-1] = 10.0, 10.0
    # 1/n * sum_k 10/sqrt(k) against 10/(n sqrt(n))
    np.testing.assert_allclose(metrics.mean_running_rms(early)[1], 10.0 * np.sum(1 / np.sqrt(np.arange(1, n + 1))) / n)
    np.testing.assert_allclose(metrics.mean_running_rms(late)[1], 10.0 / (n * np.sqrt(n)))


@settings(max_examples=50, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 30), st.integers(1, 3), st.integers(1, 3)),
              elements=st.floats(-1e4, 1e4)))
def test_running_rms_laws(e):
    r = metrics.running_rms(e)
    # the last running RMS is the RMSE of the whole span; constant errors give |e|; bounded by max |e|
    np.testing.assert_allclose(r[-1], metrics.rmse(np.zeros_like(e), e, axis=0), rtol=1e-12, atol=1e-12)
    assert np.all(r <= np.abs(e).max(axis=0) * (1 + 1e-12) + 1e-12)
    c = np.broadcast_to(e[:1], e.shape)
    np.testing.assert_allclose(metrics.running_rms(c), np.abs(c), rtol=1e-12, atol=1e-12)


def test_running_rms_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="errors"):
        metrics.running_rms(np.array([[1.0], [np.nan]]))
    with pytest.raises(ValueError, match="errors"):
        metrics.mean_running_rms(np.ones(5))
    with pytest.raises(ValueError, match="errors"):
        metrics.running_rms(np.zeros((0, 3)))


def test_first_order_rule_reproduces_eq_43():
    np.testing.assert_allclose(imm.first_order_transition([200.0, 20.0], 2.0), [[0.99, 0.01], [0.1, 0.9]],
                               atol=1e-15)
