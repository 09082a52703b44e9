"""Tests of the 3-D turn models in kftrack.models: Turn3D (a_dot = -omega^2 v) and seed 001's
Turn3DAngles (heading and flight-path-angle rates)."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.integrate import solve_ivp

from kftrack import models as M
from kftrack import frenet as fr


# ------------------------------------------------------------------ Turn3D
def _F_ref(w, T):
    s, c = np.sin(w * T), np.cos(w * T)
    return np.array([[1, s / w, (1 - c) / w**2], [0, c, s / w], [0, -w * s, c]])


def _Q_ref(w, T, q):
    wT = w * T
    Q11 = (6 * wT - 8 * np.sin(wT) + np.sin(2 * wT)) / (4 * w**5)
    Q12 = (1 - np.cos(wT)) ** 2 / (2 * w**4)
    Q13 = (4 * np.sin(wT) - 2 * wT - np.sin(2 * wT)) / (4 * w**3)
    Q22 = (2 * wT - np.sin(2 * wT)) / (4 * w**3)
    Q23 = np.sin(wT) ** 2 / (2 * w**2)
    Q33 = (2 * wT + np.sin(2 * wT)) / (4 * w)
    return q * np.array([[Q11, Q12, Q13], [Q12, Q22, Q23], [Q13, Q23, Q33]])


@pytest.mark.parametrize("w,T", [(0.05, 4.0), (0.3, 2.0), (-0.2, 7.0), (1.0, 10.0)])
def test_turn3d_closed_form(w, T):
    m = M.Turn3D(omega=w, q=2.5)
    F, Q = m.F(T), m.Q(T)
    assert F.shape == Q.shape == (9, 9)
    for i in range(3):
        blk = slice(3 * i, 3 * i + 3)
        np.testing.assert_allclose(F[blk, blk], _F_ref(w, T), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(Q[blk, blk], _Q_ref(w, T, 2.5), rtol=1e-9, atol=1e-12)
    A = np.array([[0, 1, 0], [0, 0, 1], [0, -w * w, 0]])
    Fv, Qv = M.van_loan(A, np.array([[0.0], [0.0], [1.0]]), np.array([[2.5]]), T)
    np.testing.assert_allclose(Q[:3, :3], Qv, rtol=1e-8)
    np.testing.assert_allclose(F[:3, :3], Fv, atol=1e-12)


def test_turn3d_zero_rate_is_constant_acceleration_and_continuous():
    ca = M.ConstantAcceleration(ndim=3, q=1.0)
    np.testing.assert_allclose(M.Turn3D(omega=0.0, q=1.0).F(3.0), ca.F(3.0), atol=1e-15)
    np.testing.assert_allclose(M.Turn3D(omega=0.0, q=1.0).Q(3.0), ca.Q(3.0), rtol=1e-14, atol=1e-15)
    # across the series switch (|omega T| = 0.5)
    below, above = M.Turn3D(omega=0.5 / 4 * (1 - 1e-9), q=1.0), M.Turn3D(omega=0.5 / 4 * (1 + 1e-9), q=1.0)
    np.testing.assert_allclose(below.F(4.0), above.F(4.0), rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(below.Q(4.0), above.Q(4.0), rtol=1e-7)


@settings(max_examples=30, deadline=None)
@given(st.floats(-1.0, 1.0), st.floats(0.0, 10.0))
def test_turn3d_q_psd_and_f_inverse(w, T):
    m = M.Turn3D(omega=w, q=1.0, ndim=2)
    Q = m.Q(T)
    np.testing.assert_allclose(Q, Q.T, atol=1e-12)
    assert np.linalg.eigvalsh(Q).min() > -1e-9 * max(1.0, np.abs(Q).max())
    np.testing.assert_allclose(m.F(T) @ m.F(-T), np.eye(6), atol=1e-9)


def test_turn3d_exact_on_planar_turn_not_on_helix():
    up = np.array([0.0, -0.5, np.sqrt(3) / 2])  # a plane tilted 30 degrees
    for seg, exact in [(fr.Segment(3000.0, 1 / 800), True), (fr.Segment(3000.0, 1 / 800, 1 / 1500), False)]:
        tr = fr.simulate([seg], 2.0, v0=(100.0, 0, 0), up=up)
        x = np.stack([tr.r, tr.v, tr.a], -1).reshape(-1, 9)
        w = fr.turn_rate(tr.v[0], tr.a[0])
        pred = M.Turn3D(omega=w).f(x[:-1], 2.0)
        err = np.abs(pred - x[1:]).max()
        assert (err < 1e-8) if exact else (err > 1e-4)


def test_turn3d_bad_input():
    with pytest.raises(ValueError, match="omega"):
        M.Turn3D(omega=[0.1, 0.2])
    with pytest.raises(ValueError, match=r"^q must"):
        M.Turn3D(omega=0.1, q=-1.0)
    with pytest.raises(ValueError, match="dt"):
        M.Turn3D(omega=0.1, q=1.0).Q(-1.0)


# ------------------------------------------------------------------ seed 001
def _state(wc, wg, chi=np.deg2rad(38.31), gam=np.deg2rad(5.0), v=250.0):
    return np.array([10.0, v * np.cos(chi) * np.cos(gam), -20.0, v * np.sin(chi) * np.cos(gam),
                     300.0, v * np.sin(gam), wc, wg])


def _printed_F(x, T):
    """Seed 001 eq. (30) as printed, chi from the velocity."""
    chi = np.arctan2(x[3], x[1])
    s, c = np.sin(chi), np.cos(chi)
    wc, wg = x[6], x[7]
    F = np.eye(8)
    F[0, 1] = F[2, 3] = F[4, 5] = T
    F[0, 3], F[0, 5] = -wc * T**2 / 2, -c * wg * T**2 / 2
    F[1, 1], F[1, 3] = 1 - wc**2 * T**2 / 2, -wc * T - c * wg**2 / s * T**2 / 2
    F[1, 5] = -c * wg * T + s * wc * wg * T**2 / 2
    F[2, 1], F[2, 5] = wc * T**2 / 2, -s * wg * T**2 / 2
    F[3, 1], F[3, 3] = wc * T, 1 - (wc**2 + wg**2) * T**2 / 2
    F[3, 5] = -s * wg * T - c * wc * wg * T**2 / 2
    F[4, 3] = wg / s * T**2 / 2
    F[5, 1], F[5, 3], F[5, 5] = wg * wc / s * T**2 / 2, wg / s * T, 1 - wg**2 * T**2 / 2
    return F


def _printed_Gamma(x, T):
    """Seed 001's noise gain (30) with its spurious 6th printed row deleted."""
    chi = np.arctan2(x[3], x[1])
    s, c = np.sin(chi), np.cos(chi)
    wc, wg = x[6], x[7]
    b23, b43 = -c * wg * T**2 / 2, -s * wg * T**2 / 2
    return np.array([[T**2 / 2, 0, 0, 0, 0], [T, -wc * T**2 / 2, b23, 0, 0], [0, T**2 / 2, 0, 0, 0],
                     [wc * T**2 / 2, T, b43, 0, 0], [0, 0, T**2 / 2, 0, 0], [0, wg / s * T**2 / 2, T, 0, 0],
                     [0, 0, 0, T, 0], [0, 0, 0, 0, T]])


@pytest.mark.parametrize("wc,wg,T", [(0.05, 0.02, 4.0), (-0.1, 0.03, 2.0), (0.0, 0.0, 1.0)])
def test_paper_F_and_Gamma_as_printed(wc, wg, T):
    x = _state(wc, wg)
    m = M.Turn3DAngles(form="paper", sigma2=3.5**2, sigma2_omega=0.044**2)
    np.testing.assert_allclose(m.F(x, T), _printed_F(x, T), atol=1e-12)
    np.testing.assert_allclose(m.f(x, T), _printed_F(x, T) @ x, rtol=1e-13)
    G = _printed_Gamma(x, T)
    np.testing.assert_allclose(m.Q(x, T), G @ np.diag([3.5**2] * 3 + [0.044**2] * 2) @ G.T, rtol=1e-12, atol=1e-12)


def test_forms_agree_without_path_angle_rate():
    x = _state(0.07, 0.0)
    np.testing.assert_allclose(M.Turn3DAngles(form="paper", sigma2=0.0, sigma2_omega=0.0).f(x, 4.0),
                               M.Turn3DAngles(sigma2=0.0, sigma2_omega=0.0).f(x, 4.0), rtol=1e-13)


def test_exact_transition_against_ode_and_group_law():
    x = _state(0.05, 0.02)
    A = lambda s: np.array([[0, -s[6], -np.cos(np.arctan2(s[3], s[1])) * s[7]],
                            [s[6], 0, -np.sin(np.arctan2(s[3], s[1])) * s[7]],
                            [np.cos(np.arctan2(s[3], s[1])) * s[7], np.sin(np.arctan2(s[3], s[1])) * s[7], 0]])

    def rhs(_, s):
        v = s[[1, 3, 5]]
        a = A(s) @ v
        return np.array([v[0], a[0], v[1], a[1], v[2], a[2], 0, 0])

    sol = solve_ivp(rhs, (0, 4.0), x, rtol=1e-12, atol=1e-9, method="DOP853")
    np.testing.assert_allclose(M.Turn3DAngles.f_exact(x, 4.0), sol.y[:, -1], rtol=1e-9, atol=1e-6)
    two = M.Turn3DAngles.f_exact(M.Turn3DAngles.f_exact(x, 1.5), 2.5)
    np.testing.assert_allclose(two, M.Turn3DAngles.f_exact(x, 4.0), rtol=1e-12, atol=1e-8)
    still = _state(0.0, 0.0)
    expect = still.copy()
    expect[[0, 2, 4]] += 3.0 * still[[1, 3, 5]]
    np.testing.assert_allclose(M.Turn3DAngles.f_exact(still, 3.0), expect, rtol=1e-14)


def _local_errors(method, x, T):
    m = M.Turn3DAngles(form="paper" if method == "paper" else "nonsingular", sigma2=0.0, sigma2_omega=0.0)
    step = m.f_taylor_exact if method == "taylor_exact" else m.f
    d = step(x, T) - M.Turn3DAngles.f_exact(x, T)
    return np.linalg.norm(d[[0, 2, 4]]), np.linalg.norm(d[[1, 3, 5]])


# Local (one-step) error orders against the exact transition. The position rows of every
# variant are an exact second-order Taylor step (x'' = v' = A v holds), so their error is
# O(T^3). The velocity rows of F = I + TA + T^2 A^2/2 drop the dA/dt v part of the second
# derivative: O(T^2) as soon as both rates are non-zero, O(T^3) when omega_gamma = 0 (then A
# does not depend on chi); the true Taylor-2 step x + Tg + T^2/2 J_g g is O(T^3) throughout.
@pytest.mark.parametrize("method,wg,p_vel", [("paper", 0.02, 2), ("nonsingular", 0.02, 2), ("taylor_exact", 0.02, 3),
                                             ("paper", 0.0, 3), ("nonsingular", 0.0, 3), ("taylor_exact", 0.0, 3)])
def test_taylor_steps_local_order(method, wg, p_vel):
    x = _state(0.05, wg)
    (p1, v1), (p2, v2) = (_local_errors(method, x, T) for T in (0.02, 0.01))
    # e(T)/e(T/2) = 2^p (1 + O(T)); at T = 0.02 s the O(T) term is below 1 %
    assert p1 / p2 == pytest.approx(8.0, rel=0.01)
    assert v1 / v2 == pytest.approx(2.0**p_vel, rel=0.01)


def test_nonsingular_velocity_error_leading_term():
    # -T^2/2 (dA/dt) v with the non-singular A: dA/dt v = omega_chi omega_gamma v_h [sin chi, -cos chi, 0]
    x = _state(0.05, 0.02)
    _, ev = _local_errors("nonsingular", x, 0.01)
    assert ev / 0.01**2 == pytest.approx(0.05 * 0.02 * x[5] / 2, rel=0.01)  # next term O(T): 0.7 % here


def test_turn3d_one_step_error_on_a_helix_is_the_missing_jerk():
    # true jerk = -omega^2 v + v^3 kappa tau b; Turn3D drops the last term m, so one step errs by
    # m T^3/6 in position and m T^2/2 in velocity. The next term is m' T^4/24 (T^3/6) with
    # |m'| = v |tau| |m| (b turns at the rate v tau): relative v|tau|T/4 (/3); we allow twice that.
    kap, tau, v, T = 1 / 800, 1 / 1500, 100.0, 1.0
    errs = []
    for dt in (T, T / 2):
        tr = fr.simulate([fr.Segment(3000.0, kap, tau)], dt, v0=(v, 0, 0), n_max=2)
        x = np.stack([tr.r, tr.v, tr.a], -1).reshape(-1, 9)
        e = x[1] - M.Turn3D(omega=float(fr.turn_rate(tr.v[0], tr.a[0]))).f(x[0], dt)  # truth - prediction
        lead = v**3 * kap * tau * tr.frame[0, 2]
        bound = v * abs(tau) * dt / 2
        np.testing.assert_allclose(e[[0, 3, 6]], lead * dt**3 / 6, rtol=0, atol=bound * np.linalg.norm(lead) * dt**3 / 6)
        np.testing.assert_allclose(e[[1, 4, 7]], lead * dt**2 / 2, rtol=0, atol=bound * np.linalg.norm(lead) * dt**2 / 2)
        errs.append(np.linalg.norm(e[[0, 3, 6]]))
    assert errs[0] / errs[1] == pytest.approx(8.0, rel=0.01)


def test_seed001_one_step_claims_c14_c15():
    paper, nons = M.Turn3DAngles(form="paper", sigma2=0.0, sigma2_omega=0.0), M.Turn3DAngles(sigma2=0.0, sigma2_omega=0.0)
    x = _state(0.05, 0.0)
    ex = M.Turn3DAngles.f_exact(x, 4.0)
    assert round(np.linalg.norm((paper.f(x, 4.0) - ex)[[0, 2, 4]]), 1) == 6.6
    cv = np.linalg.norm(x[[0, 2, 4]] + 4.0 * x[[1, 3, 5]] - ex[[0, 2, 4]])
    assert round(cv, 1) == 99.5
    x = _state(0.05, 0.02)
    ex = M.Turn3DAngles.f_exact(x, 4.0)
    vel = [1, 3, 5]
    assert round(np.linalg.norm((paper.f(x, 4.0) - ex)[vel]), 2) == 2.63
    assert round(np.linalg.norm((nons.f(x, 4.0) - ex)[vel]), 2) == 0.67
    assert round(np.linalg.norm((nons.f_taylor_exact(x, 4.0) - ex)[vel]), 2) == 0.49


def test_full_jacobian_and_partial():
    m = M.Turn3DAngles(form="paper", sigma2=0.0, sigma2_omega=0.0)
    x = _state(0.05, 0.02)
    J = m.jacobian(x, 4.0)
    h = 1e-6 * np.maximum(1.0, np.abs(x))
    fd = np.stack([(m.f(x + h[i] * np.eye(8)[i], 4.0) - m.f(x - h[i] * np.eye(8)[i], 4.0)) / (2 * h[i])
                   for i in range(8)], axis=1)
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-5)
    Fp = m.F(x, 4.0)
    np.testing.assert_array_equal(Fp[:6, 6:], 0.0)
    assert np.abs(J[:6, 6:]).max() > 100
    # notes section 3.3: d x+ / d omega_chi = -v_y T^2 / 2
    assert J[0, 6] == pytest.approx(-x[3] * 16 / 2)


def test_paper_form_singular_along_x():
    paper = M.Turn3DAngles(form="paper", sigma2=1.0, sigma2_omega=1e-4)
    nons = M.Turn3DAngles(sigma2=1.0, sigma2_omega=1e-4)
    x = _state(0.05, 0.02, chi=1e-9)
    with np.errstate(all="ignore"):
        assert np.abs(paper.F(x, 4.0)).max() > 1e6
    assert np.abs(nons.F(x, 4.0)).max() < 10
    assert nons.H.shape == (3, 8)
    # exactly at chi = 0 (and 180 deg) the paper form would return NaN/inf: it raises, naming x and chi
    for chi, deg in ((0.0, "0"), (np.pi, "180")):
        x0 = _state(0.05, 0.02, chi=chi)
        x0[3] = 0.0
        for fn in (paper.F, paper.f, paper.jacobian, paper.Q):
            with pytest.raises(ValueError, match=rf"x has v_y = 0, heading chi = {deg} deg.*nonsingular"):
                fn(x0, 4.0)
        assert np.all(np.isfinite(nons.F(x0, 4.0))) and np.all(np.isfinite(nons.Q(x0, 4.0)))
    xb = np.stack([_state(0.05, 0.02), x0])
    with pytest.raises(ValueError, match=r"x\[1\] has v_y = 0"):
        paper.f(xb, 4.0)


def test_turn3d_angles_bad_input():
    with pytest.raises(ValueError, match="form"):
        M.Turn3DAngles(form="exact")
    with pytest.raises(ValueError, match="x must have shape"):
        M.Turn3DAngles(sigma2=0.0, sigma2_omega=0.0).f(np.zeros(6), 1.0)
    with pytest.raises(ValueError, match="sigma2"):
        M.Turn3DAngles(sigma2=-1.0, sigma2_omega=0.0)
    # the noise is required (no silent Q = 0), keyword only
    for kw in ({}, {"sigma2": 1.0}, {"sigma2_omega": 1e-4}):
        with pytest.raises(TypeError, match="requires sigma2"):
            M.Turn3DAngles(**kw)
    with pytest.raises(TypeError):
        M.Turn3DAngles("nonsingular", 1.0, 1e-4)
    with pytest.raises(ValueError, match="form"):
        M.turn3d_angles_A("singular")


def test_turn3d_angles_broadcasts_over_batch():
    xs = np.stack([_state(0.05, 0.02), _state(-0.03, 0.01, chi=2.0), _state(0.0, 0.0, chi=-1.0)])
    for form in ("paper", "nonsingular"):
        m = M.Turn3DAngles(form=form, sigma2=1.0, sigma2_omega=0.01)
        for fn in (m.f, m.jacobian, m.F, m.Q, M.Turn3DAngles.f_exact):
            batch = fn(xs, 4.0)
            for i in range(3):
                np.testing.assert_allclose(batch[i], fn(xs[i], 4.0), rtol=1e-14, atol=1e-12)
    dts = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(M.Turn3DAngles.f_exact(xs, dts)[1], M.Turn3DAngles.f_exact(xs[1], 2.0), rtol=1e-14)
