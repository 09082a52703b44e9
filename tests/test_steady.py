"""Tests of kftrack.steady: Riccati solutions, alpha-beta(-gamma) gains, transfer functions,
complementarity, sampled filters and observability."""
import numpy as np
import pytest
import scipy.signal
import sympy as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from kftrack import steady

F_CV = np.array([[1.0, 1.0], [0.0, 1.0]])
GAM_CV = np.array([[0.5], [1.0]])
H_POS = np.array([[1.0, 0.0]])


def test_discrete_gain_equals_iterated_riccati():
    Q = 0.3**2 * GAM_CV @ GAM_CV.T
    R = np.array([[2.0]])
    ss = steady.discrete_gain(F_CV, H_POS, Q, R)
    Ks, Ps = steady.gain_sequence(F_CV, H_POS, Q, R, np.eye(2) * 50.0, 400)
    np.testing.assert_allclose(Ks[-1], ss.K, rtol=1e-10)
    np.testing.assert_allclose(Ps[-1], ss.P_prior, rtol=1e-10)
    # the posterior covariance is (I - KH) P_prior
    np.testing.assert_allclose(ss.P, (np.eye(2) - ss.K @ H_POS) @ ss.P_prior, rtol=1e-12)


def test_gain_sequence_first_gain_from_P0():
    P0 = np.diag([4.0, 1.0])
    Ks, _ = steady.gain_sequence(F_CV, H_POS, np.eye(2) * 0.01, [[1.0]], P0, 1)
    np.testing.assert_allclose(Ks[0, :, 0], [4.0 / 5.0, 0.0], atol=1e-15)


def test_continuous_gain_satisfies_care():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((3, 3))
    C = rng.standard_normal((2, 3))
    M = rng.standard_normal((3, 3))
    Q = M @ M.T + 0.1 * np.eye(3)
    R = np.diag([0.5, 2.0])
    L, P = steady.continuous_gain(A, C, Q, R)
    resid = A @ P + P @ A.T - P @ C.T @ np.linalg.solve(R, C @ P) + Q
    assert np.max(np.abs(resid)) < 1e-9 * np.max(np.abs(P))
    np.testing.assert_allclose(L, P @ C.T @ np.linalg.inv(R), rtol=1e-12)
    assert np.all(np.linalg.eigvals(A - L @ C).real < 0)  # stabilizing


def test_scalar_integrator_closed_form():
    L, P = steady.continuous_gain([[0.0]], [[1.0]], [[0.04]], [[0.25]])
    assert L[0, 0] == pytest.approx(0.4, rel=1e-12)
    assert P[0, 0] == pytest.approx(0.1, rel=1e-12)


@settings(max_examples=30, deadline=None)
@given(q=st.floats(1e-6, 1e3), r=st.floats(1e-6, 1e3))
def test_double_integrator_damping_is_one_over_sqrt2(q, r):
    A = np.array([[0.0, 1.0], [0.0, 0.0]])
    L, _ = steady.continuous_gain(A, [[1.0, 0.0]], [[q]], [[r]], G=[[0.0], [1.0]])
    l1, l2 = L[:, 0]
    assert l2 == pytest.approx(np.sqrt(q / r), rel=1e-6)
    assert l1 / (2 * np.sqrt(l2)) == pytest.approx(1 / np.sqrt(2), rel=1e-6)


@settings(max_examples=40, deadline=None)
@given(lam=st.floats(1e-4, 1e2))
def test_alpha_beta_closed_form_matches_dare(lam):
    a, b = steady.alpha_beta_gains(lam)
    K = steady.discrete_gain(F_CV, H_POS, lam**2 * GAM_CV @ GAM_CV.T, [[1.0]]).K[:, 0]
    assert a == pytest.approx(K[0], rel=1e-7, abs=1e-12)
    assert b == pytest.approx(K[1], rel=1e-6, abs=1e-12)
    assert lam**2 == pytest.approx(b**2 / (1 - a), rel=1e-6)


def test_alpha_beta_scales_with_T_and_sigma():
    T, sw, sv = 0.5, 3.0, 7.0
    lam = steady.tracking_index(sw, sv, T)
    F = np.array([[1.0, T], [0.0, 1.0]])
    G = np.array([[T**2 / 2], [T]])
    K = steady.discrete_gain(F, H_POS, sw**2 * G @ G.T, [[sv**2]]).K[:, 0]
    a, b = steady.alpha_beta_gains(lam)
    np.testing.assert_allclose([a, b / T], K, rtol=1e-9)


@pytest.mark.parametrize("lam", [0.01, 0.3, 1.0, 5.0, 50.0])
def test_alpha_beta_gamma_laws(lam):
    a, b, g = steady.alpha_beta_gamma_gains(lam)
    assert b == pytest.approx(2 * (2 - a) - 4 * np.sqrt(1 - a), rel=1e-8)
    assert g == pytest.approx(b**2 / a, rel=1e-8)
    assert lam**2 == pytest.approx(g**2 / (4 * (1 - a)), rel=1e-8)


def test_alpha_beta_zero_index_and_bad_input():
    assert steady.alpha_beta_gamma_gains(0.0) == (0.0, 0.0, 0.0)
    a, b = steady.alpha_beta_gains(0.0)
    assert a == 0 and b == 0
    with pytest.raises(ValueError, match="lam"):
        steady.alpha_beta_gains(-1.0)
    with pytest.raises(ValueError, match="sigma_v"):
        steady.tracking_index(1.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="dt"):
        steady.tracking_index(1.0, 1.0, -1.0)


def test_estimator_tf_matches_frequency_response_of_state_space():
    A = np.array([[-1.0, 2.0], [0.0, -3.0]])
    B = np.array([[1.0], [0.5]])
    C = np.array([[1.0, 0.0], [1.0, 1.0]])
    D = np.array([[0.0], [0.2]])
    L, _ = steady.continuous_gain(A, C, np.eye(2), np.eye(2))
    tfs = steady.estimator_tf(A, B, C, D, L, outputs=[[1.0, 0.0]])
    w = np.array([0.1, 1.0, 10.0])
    for j, (num, den) in enumerate(tfs[0]):
        _, h = scipy.signal.freqs(num, den, worN=w)
        Bj = np.hstack([L, B - L @ D])[:, j]
        direct = [np.array([1.0, 0.0]) @ np.linalg.solve(1j * wk * np.eye(2) - (A - L @ C), Bj) for wk in w]
        np.testing.assert_allclose(h, direct, rtol=1e-10)


def test_estimator_tf_against_simulation():
    """Step response of the transfer function equals a direct simulation of the estimator."""
    A, B, C = np.zeros((1, 1)), np.ones((1, 1)), np.ones((1, 1))
    L = np.array([[0.5]])
    (slow, fast), = steady.estimator_tf(A, B, C, None, L)
    t = np.linspace(0, 10, 201)
    _, y = scipy.signal.step((slow[0], slow[1]), T=t)
    np.testing.assert_allclose(y, 1 - np.exp(-0.5 * t), atol=1e-10)


def test_complementary_residual_symbolic():
    s, l1, l2 = sp.symbols("s l1 l2", positive=True)
    A = sp.Matrix([[0, 1], [0, 0]])
    L = sp.Matrix([l1, l2])
    C = sp.Matrix([[1, 0]])
    B = sp.Matrix([0, 1])
    M = (s * sp.eye(2) - A + L * C).inv()
    total = (C * M * L)[0] + s**2 * (C * M * B)[0]
    assert sp.simplify(total - 1) == 0
    # and numerically through the package, for arbitrary gains
    num = steady.complementary_residual(([3.0, 7.0], [1.0, 3.0, 7.0]), ([1.0], [1.0, 3.0, 7.0]), 2)
    np.testing.assert_allclose(num, 0, atol=1e-15)


def test_complementary_residual_detects_non_complementary_and_bad_input():
    num = steady.complementary_residual(([1.0], [1.0, 2.0]), ([1.0], [1.0, 2.0]), 1)
    assert np.max(np.abs(num)) > 0.5
    with pytest.raises(ValueError, match="denominator"):
        steady.complementary_residual(([1.0], [1.0, 2.0]), ([1.0], [1.0, 3.0]), 1)
    with pytest.raises(ValueError, match=r"^k must"):
        steady.complementary_residual(([1.0], [1.0, 2.0]), ([1.0], [1.0, 2.0]), -1)


@pytest.mark.parametrize("A,C,G", [
    (np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[1.0, 0.0]]), np.array([[0.0], [1.0]])),
    (np.array([[-5.21, -16.9695], [1.0, 0.0]]), np.array([[2.8065, 7.0915], [-7.530365, -47.6249]]), np.eye(2)),
])
def test_sampled_gain_converges_to_continuous(A, C, G):
    Qc = np.eye(G.shape[1]) * 0.01
    R = np.eye(C.shape[0]) * 0.02
    L, P = steady.continuous_gain(A, C, Qc, R, G=G)
    errs = []
    for dt in [1e-2, 1e-3, 1e-4]:
        sd = steady.sampled_gain(A, C, Qc, R, dt, G=G)
        errs.append(np.linalg.norm(sd.K / dt - L) / np.linalg.norm(L))
        np.testing.assert_allclose(sd.P_prior, P, rtol=20 * dt ** 0.5, atol=20 * dt ** 0.5 * np.abs(P).max())
    assert errs[-1] < 1e-2
    assert errs[1] / errs[2] > 5  # first-order convergence


def test_sampled_model_zoh_input():
    F, Bd, Qd = steady.sampled_model([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[2.0]], 0.5,
                                     G=[[0.0], [1.0]])
    np.testing.assert_allclose(F, [[1, 0.5], [0, 1]], atol=1e-15)
    np.testing.assert_allclose(Bd[:, 0], [0.125, 0.5], atol=1e-15)
    np.testing.assert_allclose(Qd, 2.0 * np.array([[0.5**3 / 3, 0.5**2 / 2], [0.5**2 / 2, 0.5]]), atol=1e-14)
    with pytest.raises(ValueError, match="dt"):
        steady.sampled_model([[0.0]], None, [[1.0]], 0.0)


def test_run_steady_filter_equals_kalman_in_steady_state():
    from kftrack.kalman import kalman_filter
    rng = np.random.default_rng(1)
    Q = 0.2 * GAM_CV @ GAM_CV.T
    R = np.array([[1.0]])
    ss = steady.discrete_gain(F_CV, H_POS, Q, R)
    zs = np.cumsum(rng.standard_normal((300, 1)), axis=0)
    xs = steady.run_steady_filter(F_CV, None, H_POS, None, ss.K, zs, x0=np.zeros(2))
    res = kalman_filter(zs, np.zeros(2), ss.P_prior, F_CV, Q, H_POS, R)
    np.testing.assert_allclose(xs, res.x, rtol=1e-9, atol=1e-9)
    zs[5] = np.nan  # a missing row only predicts
    xs2 = steady.run_steady_filter(F_CV, None, H_POS, None, ss.K, zs, x0=np.zeros(2))
    np.testing.assert_allclose(xs2[5], F_CV @ xs2[4])
    with pytest.raises(ValueError, match="us"):
        steady.run_steady_filter(F_CV, [[0.0], [1.0]], H_POS, None, ss.K, zs)
    with pytest.raises(ValueError, match=r"x0 must have shape \(2,\)"):
        steady.run_steady_filter(F_CV, None, H_POS, None, ss.K, zs, x0=np.zeros(3))


def test_observability_known_cases():
    A = np.array([[0.0, 1.0], [0.0, 0.0]])
    np.testing.assert_array_equal(steady.observability_matrix(A, [[1.0, 0.0]]), [[1, 0], [0, 1]])
    assert steady.observability_rank(A, [[1.0, 0.0]]) == 2
    assert steady.observability_rank(A, [[0.0, 1.0]]) == 1
    # diagonal system with a zero in C: that mode is unobservable
    assert steady.observability_rank(np.diag([1.0, 2.0, 3.0]), [[1.0, 0.0, 1.0]]) == 2


def test_gramian_of_lti_system_matches_lyapunov_integral():
    A = np.array([[0.0, 1.0], [0.0, 0.0]])
    C = np.array([[1.0, 0.0]])
    W = steady.observability_gramian(lambda t: A, C, 0.0, 2.0)
    # Phi = [[1, t], [0, 1]] -> integrand [[1, t], [t, t^2]]
    np.testing.assert_allclose(W, [[2.0, 2.0], [2.0, 8.0 / 3.0]], rtol=1e-8)
    Wv = steady.observability_gramian(lambda t: A, [[0.0, 1.0]], 0.0, 2.0)
    assert np.linalg.matrix_rank(Wv) == 1


def test_bad_input_messages():
    with pytest.raises(ValueError, match=r"^R must"):
        steady.continuous_gain([[0.0]], [[1.0]], [[1.0]], [[0.0]])
    with pytest.raises(ValueError, match=r"^Q must"):
        steady.discrete_gain(F_CV, H_POS, [[1.0, 0.0], [0.0, -1.0]], [[1.0]])
    with pytest.raises(ValueError, match=r"^A must"):
        steady.continuous_gain(np.ones((2, 3)), [[1.0, 0.0]], np.eye(2), [[1.0]])
    with pytest.raises(ValueError, match=r"^C must"):
        steady.observability_matrix(np.eye(2), [[1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="steps"):
        steady.gain_sequence(F_CV, H_POS, np.eye(2), [[1.0]], np.eye(2), 0)
    with pytest.raises(TypeError, match=r"^A must"):
        steady.observability_gramian(np.eye(2), [[1.0, 0.0]], 0.0, 1.0)
    with pytest.raises(ValueError, match="t1"):
        steady.observability_gramian(lambda t: np.eye(2), [[1.0, 0.0]], 1.0, 1.0)
    with pytest.raises(ValueError, match=r"^L must"):
        steady.estimator_tf(np.eye(2), None, [[1.0, 0.0]], None, np.ones((3, 1)))
    # an unstable mode that is not measured (H = 0): no stabilizing Riccati solution
    with pytest.raises(ValueError, match=r"no stabilizing solution: \(F, H\) must be detectable"):
        steady.discrete_gain([[2.0]], [[0.0]], [[1.0]], [[1.0]])
    with pytest.raises(ValueError, match=r"no stabilizing solution: \(A, C\) must be detectable"):
        steady.continuous_gain([[1.0]], [[0.0]], [[1.0]], [[1.0]])
