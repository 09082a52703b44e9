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


EPS = np.finfo(float).eps


def care_residual(A, C, Q, R, G, P):
    """Largest entry of the CARE residual, in units of eps times the largest term."""
    terms = [A @ P, P @ A.T, -P @ C.T @ np.linalg.solve(R, C @ P), G @ Q @ G.T]
    return np.max(np.abs(sum(terms))) / (EPS * max(np.max(np.abs(t)) for t in terms))


def dare_residual(F, H, Q, R, P):
    """Largest entry of the DARE residual (P the prior), in units of eps times the largest term."""
    S = H @ P @ H.T + R
    terms = [F @ P @ F.T, -F @ P @ H.T @ np.linalg.solve(S, H @ P @ F.T), Q, -P]
    return np.max(np.abs(sum(terms))) / (EPS * max(np.max(np.abs(t)) for t in terms))


# the study's filters of chapter 14 (seed 004): dynamic pitch with bias, dynamic height with
# bias, kinematic height with bias; their R spans four decades
_PITCH_A = np.array([[-5.21, -16.9695, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
_PITCH_C = np.array([[2.8065, 7.0915, 0.0], [-7.530365, -47.62490175, 1.0]])
_HEIGHT_A = np.array([[-2.633, -2.206, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
_HEIGHT_C = np.array([[0.0, 2.169, 0.0], [-5.710977, -4.784814, 1.0]])
STUDY_FILTERS = [
    (_PITCH_A, _PITCH_C, np.diag([0.005, 0.005, 1e-4]), np.diag([0.19932, 8.3922e-4])),
    (_HEIGHT_A, _HEIGHT_C, np.diag([3.103e-4, 3.103e-4, 1e-4]), np.diag([2.4031e-5, 3.9e-3])),
    (np.array([[0.0, 1, 0], [0, 0, -1], [0, 0, 0]]), np.array([[1.0, 0, 0]]), np.diag([0, 3.9e-3, 1e-4]),
     np.array([[2.4031e-5]])),
]


def test_continuous_gain_satisfies_care():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((3, 3))
    C = rng.standard_normal((2, 3))
    M = rng.standard_normal((3, 3))
    Q = M @ M.T + 0.1 * np.eye(3)
    R = np.diag([0.5, 2.0])
    L, P = steady.continuous_gain(A, C, Q, R)
    # round-off: a few hundred ulps of the largest term (3x3 products, one solve)
    assert care_residual(A, C, Q, R, np.eye(3), P) < 1e3
    np.testing.assert_allclose(L, P @ C.T @ np.linalg.inv(R), rtol=1e-12)
    assert np.all(np.linalg.eigvals(A - L @ C).real < 0)  # stabilizing
    np.testing.assert_array_equal(P, P.T)


@pytest.mark.parametrize("A,C,Q,R", STUDY_FILTERS)
def test_study_filters_satisfy_care_and_sampled_dare(A, C, Q, R):
    L, P = steady.continuous_gain(A, C, Q, R)
    assert care_residual(A, C, Q, R, np.eye(3), P) < 1e3
    assert np.all(np.linalg.eigvals(A - L @ C).real < 0)
    assert np.all(np.linalg.eigvalsh(P) > 0)
    for dt in (1e-1, 1e-3):
        F, _, Qd = steady.sampled_model(A, None, Q, dt)
        sd = steady.sampled_gain(A, C, Q, R, dt)
        assert dare_residual(F, C, Qd, R / dt, sd.P_prior) < 1e3
        assert np.all(np.abs(np.linalg.eigvals(F - F @ sd.K @ C)) < 1)  # stable predictor


@pytest.mark.parametrize("lam", [1e-3, 1.0, 100.0])
def test_discrete_gain_satisfies_dare(lam):
    F3 = np.array([[1.0, 1.0, 0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    g3 = np.array([[0.5], [1.0], [1.0]])
    H3, Q3, R3 = np.array([[1.0, 0.0, 0.0]]), lam**2 * g3 @ g3.T, np.array([[1.0]])
    ss = steady.discrete_gain(F3, H3, Q3, R3)
    assert dare_residual(F3, H3, Q3, R3, ss.P_prior) < 1e3
    S = H3 @ ss.P_prior @ H3.T + R3
    np.testing.assert_allclose(ss.K, ss.P_prior @ H3.T / S, rtol=1e-12)


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


def test_complementary_angle_filters_symbolic():
    """Angle from a gyro (input) and an inclinometer, with and without a gyro-bias state."""
    s, l1, l2 = sp.symbols("s l1 l2")
    for A, B, C, L in [(sp.Matrix([[0]]), sp.Matrix([1]), sp.Matrix([[1]]), sp.Matrix([l1])),
                       (sp.Matrix([[0, -1], [0, 0]]), sp.Matrix([1, 0]), sp.Matrix([[1, 0]]), sp.Matrix([l1, l2]))]:
        M = (s * sp.eye(A.shape[0]) - A + L * C).inv()
        assert sp.simplify((C * M * L)[0] + s * (C * M * B)[0] - 1) == 0
        # the package's transfer functions of the same filter, at numeric gains, agree
        num = _package_residual(A, B, C, L.subs({l1: 1.3, l2: -0.4}))
        assert np.max(np.abs(num)) < 1e-12


def _package_residual(A, B, C, L):
    """T_slow + s T_fast - 1 of the estimator (A, B, C, L) by steady.estimator_tf and
    steady.complementary_residual: numerator coefficients, highest power first."""
    tf = steady.estimator_tf(*(np.array(M, dtype=float) for M in (A, B, C)), None, np.array(L, dtype=float))
    return steady.complementary_residual(tf[0][0], tf[0][1], 1)


def test_dynamic_model_filter_is_not_complementary_symbolic():
    """A model with its own dynamics (a leaky integrator, theta-dot = -a theta + omega_m): the
    two paths sum to one only for a = 0, the pure integrator; the defect is -a/(s + a + l1)."""
    s, a, l1 = sp.symbols("s a l1")
    A, B, C, L = sp.Matrix([[-a]]), sp.Matrix([1]), sp.Matrix([[1]]), sp.Matrix([l1])
    M = (s * sp.eye(1) - A + L * C).inv()
    assert sp.simplify((C * M * L)[0] + s * (C * M * B)[0] - 1 - (-a) / (s + a + l1)) == 0
    # the package finds the same defect: numerator -a over the common denominator s + a + l1
    vals = {a: 0.7, l1: 1.3}
    num = _package_residual(A.subs(vals), B, C, L.subs(vals))
    np.testing.assert_allclose(np.trim_zeros(num, "f"), [-0.7], rtol=1e-12)


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
    eK, eP = [], []
    for dt in [1e-2, 1e-3, 1e-4]:
        sd = steady.sampled_gain(A, C, Qc, R, dt, G=G)
        eK.append(np.linalg.norm(sd.K / dt - L) / np.linalg.norm(L))
        eP.append(np.linalg.norm(sd.P_prior - P) / np.linalg.norm(P))
    # an error c dt + O(dt^2) with c != 0 shrinks tenfold per decade of dt as dt -> 0
    for e in (eK, eP):
        assert e[0] > e[1] > e[2]
        assert 9.0 < e[1] / e[2] < 11.0
    # and the constant c is of the order of the filter's fastest rate |eig(A - LC)|
    rate = np.max(np.abs(np.linalg.eigvals(A - L @ C)))
    assert eK[2] < 1e-4 * rate and eP[2] < 1e-4 * rate


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


@pytest.mark.parametrize("lam", [0.02, 0.3, 2.0])
def test_alpha_beta_lag_matches_noise_free_run(lam):
    # noise-free constant-acceleration truth through the fixed-gain filter: the error settles to
    # the closed form. |A - KHA| < 1 so after 600 steps the transient is below eps; tolerance
    # 1e-9 relative covers the O(k eps |x_k|) round-off of the growing state x_k ~ a (kT)^2 / 2.
    a, b = steady.alpha_beta_gains(lam)
    T, acc = 0.5, 2.0
    F = np.array([[1.0, T], [0.0, 1.0]])
    K = np.array([[a], [b / T]])
    t = np.arange(600) * T
    xs = steady.run_steady_filter(F, None, H_POS, None, K, (0.5 * acc * t**2)[:, None], x0=np.zeros(2))
    ex, ev = steady.alpha_beta_lag(a, b, acc, T)
    scale = 0.5 * acc * t[-1] ** 2
    assert abs(xs[-1, 0] - 0.5 * acc * t[-1] ** 2 - ex) <= 1e-9 * scale
    assert abs(xs[-1, 1] - acc * t[-1] - ev) <= 1e-9 * scale
    assert ex < 0  # the estimate lags behind


def test_alpha_beta_lag_rejects_bad_gains():
    with pytest.raises(ValueError, match="beta"):
        steady.alpha_beta_lag(0.5, 0.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="alpha"):
        steady.alpha_beta_lag(1.5, 0.1, 1.0, 1.0)


def test_detectability_versus_observability():
    A2 = np.array([[0.0, 1.0], [0.0, 0.0]])
    assert steady.is_detectable(A2, [[1.0, 0.0]]) and not steady.is_detectable(A2, [[0.0, 1.0]])
    # a stable unobserved mode: not observable (rank 1) but detectable, and the CARE is solvable
    A = np.diag([0.0, -1.0])
    assert steady.observability_rank(A, [[1.0, 0.0]]) == 1 and steady.is_detectable(A, [[1.0, 0.0]])
    steady.continuous_gain(A, [[1.0, 0.0]], np.eye(2), [[1.0]])
    with pytest.raises(ValueError, match="detectable"):
        steady.continuous_gain(A2, [[0.0, 1.0]], np.eye(2), [[1.0]])
    # discrete: |lambda| = 0.5 unobserved is fine, |lambda| = 1 is not
    assert steady.is_detectable(np.diag([1.0, 0.5]), [[1.0, 0.0]], discrete=True)
    assert not steady.is_detectable(np.diag([1.0, 0.5]), [[0.0, 1.0]], discrete=True)
