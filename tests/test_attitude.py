"""Tests of kftrack.attitude: inclinometer, the study's models and filters, the integrated
LTV filter and the sensor simulation."""
import numpy as np
import pytest
import scipy.linalg
import scipy.signal
import scipy.stats
from hypothesis import given, settings
from hypothesis import strategies as st

from kftrack import attitude as at
from kftrack import steady

angles = st.floats(-1.4, 1.4)


@settings(max_examples=50, deadline=None)
@given(pitch=angles, roll=angles)
def test_tilt_roundtrip(pitch, roll):
    a = at.accel_from_tilt(pitch, roll)
    th, ph = at.tilt_from_accel(a)
    assert th == pytest.approx(pitch, abs=1e-12)
    assert ph == pytest.approx(roll, abs=1e-12)
    th2, ph2 = at.tilt_from_accel(a, wide=True)
    assert ph2 == pytest.approx(roll, abs=1e-12)
    # at rest the vertical acceleration is zero and the gravity vector has norm g
    assert at.vertical_acceleration(a, th, ph) == pytest.approx(0.0, abs=1e-12)
    assert np.linalg.norm(a) == pytest.approx(at.GRAVITY)


def test_wide_roll_beyond_90_degrees():
    a = at.accel_from_tilt(0.1, 2.5)
    assert at.tilt_from_accel(a, wide=True)[1] == pytest.approx(2.5)
    assert at.tilt_from_accel(a)[1] != pytest.approx(2.5)   # the study's arctan folds it


def test_study_tilt_experiment_A():
    a = np.array([13.5774, 4.6363, -977.2680])   # cm/s^2: ratios, units do not matter
    th, ph = at.tilt_from_accel(a)
    assert np.degrees(th) == pytest.approx(0.796, abs=5e-4)
    assert np.degrees(ph) == pytest.approx(-0.272, abs=5e-4)


def test_altimeter_tilt_correction():
    assert at.altimeter_tilt_correction(2.0, np.pi / 3, 0.0) == pytest.approx(1.0)


def test_dynamic_models_match_the_study():
    m = at.dynamic_model(*at.PITCH_PLANT, 1)
    np.testing.assert_allclose(m.A, [[-5.21, -16.9695], [1, 0]])
    np.testing.assert_allclose(m.C, [[2.8065, 7.0915], [-7.530365, -47.62490175]], rtol=1e-9)
    np.testing.assert_allclose(m.D, [[0], [2.8065]])
    h = at.dynamic_model(*at.HEIGHT_PLANT, 2, bias=True)
    np.testing.assert_allclose(h.C, [[0, 2.169, 0], [-5.710977, -4.784814, 1]], rtol=1e-9)
    np.testing.assert_allclose(h.D, [[0], [2.169]])


def test_dynamic_model_second_output_is_the_derivative():
    """The gyro row of C' reproduces the derivative of a simulated plant output."""
    m = at.dynamic_model(*at.PITCH_PLANT, 1)
    t = np.linspace(0, 5, 5001)
    u = np.sin(2 * t)
    _, y, x = scipy.signal.lsim((m.A, m.B, m.C, m.D), u, t)
    np.testing.assert_allclose(np.gradient(y[:, 0], t)[10:-10], y[10:-10, 1], atol=2e-4)


def test_height_model_second_output_is_the_acceleration():
    """The accelerometer row C A^2 x + C A B u of the height model is the second derivative of h."""
    m = at.dynamic_model(*at.HEIGHT_PLANT, 2)
    t = np.linspace(0, 5, 5001)
    u = np.sin(2 * t)
    _, y, _ = scipy.signal.lsim((m.A, m.B, m.C, m.D), u, t)
    d2 = np.gradient(np.gradient(y[:, 0], t), t)
    np.testing.assert_allclose(d2[10:-10], y[10:-10, 1], atol=1e-3)


def test_plant_response_matches_lsim_and_delay():
    t = np.arange(0, 10, 0.01)
    ref = np.where(t >= 1.0, 1.0, 0.0)
    out = at.plant_response(*at.HEIGHT_PLANT, t, ref, 2)
    _, y, _ = scipy.signal.lsim(at.HEIGHT_PLANT, ref, t, interp=False)
    np.testing.assert_allclose(out[:, 0], y, atol=1e-10)
    delayed = at.plant_response(*at.HEIGHT_PLANT, t, ref, 2, delay=0.5)
    np.testing.assert_allclose(delayed[50:, 0], out[:-50, 0], atol=1e-10)
    assert out[-1, 0] == pytest.approx(2.169 / 2.206, rel=1e-3)


def test_kinematic_filters_closed_forms():
    (L, P), (slow, fast) = at.filter_tfs(at.kinematic_model(1), [[8.3922e-4]], [[0.2431]])
    assert L[0, 0] == pytest.approx(np.sqrt(8.3922e-4 / 0.2431), rel=1e-12)
    assert L[0, 0] == pytest.approx(0.05876, abs=5e-6)
    (L, _), _ = at.filter_tfs(at.kinematic_model(2), np.diag([0, 3.9e-3]), [[2.4031e-5]])
    assert np.all(np.abs(L[:, 0] - [5.048, 12.74]) <= [5e-4, 5e-3])
    (L, _), (slow, fast) = at.filter_tfs(at.kinematic_model(1, True), np.diag([8.3922e-4, 1e-4]), [[0.2431]])
    assert np.all(np.abs(L[:, 0] - [0.2098, -0.02028]) <= [5e-5, 5e-6])
    assert np.max(np.abs(steady.complementary_residual(slow, fast, 1))) < 1e-12


def test_dynamic_pitch_filter_reproduces_study_tf():
    (L, P), tfs = at.filter_tfs(at.dynamic_model(*at.PITCH_PLANT, 1), 0.005 * np.eye(2),
                                np.diag([0.19932, 8.3922e-4]))
    (n1, den), (n2, _), (n3, _) = tfs
    assert np.all(np.abs(den - [1, 120.3, 317.9]) <= [0, 0.05, 0.05])
    assert np.all(np.abs(n1 - [0.02472, 1.59]) <= [5e-6, 5e-3])
    np.testing.assert_allclose(n2, [-17.64, 23.21], atol=5e-3)
    # unbiased at DC when the model is exact
    assert n1[-1] / den[-1] * 7.0915 / 16.9695 + n3[-1] / den[-1] == pytest.approx(7.0915 / 16.9695, rel=1e-9)
    assert np.max(np.abs(steady.complementary_residual((n1, den), (n2, den), 1))) > 1


def test_observability_ranks():
    mb = at.dynamic_model(*at.PITCH_PLANT, 1, bias=True)
    assert steady.observability_rank(mb.A, mb.C) == 3
    assert steady.observability_rank(mb.A, mb.C[:1]) == 2
    k = at.kinematic_model(2, bias=True)
    np.testing.assert_array_equal(steady.observability_matrix(k.A, k.C), [[1, 0, 0], [0, 1, 0], [0, 0, -1]])


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(0)
    v, w = rng.standard_normal((2, 5, 3))
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", at.skew(v), w), np.cross(v, w), atol=1e-14)


def test_integrated_model_propagates_gravity_vector():
    """With the true (bias-free) rate and zero bias states, e^{A t} carries y0 to R(t)^T y0."""
    w = np.array([0.3, -0.2, 0.5])
    y0 = np.array([0.0, 0.0, -9.81])
    A = at.integrated_A(y0, w)          # A depends on y only through the bias columns
    x = scipy.linalg.expm(A * 2.0) @ np.concatenate([y0, np.zeros(3)])
    expected = scipy.linalg.expm(-at.skew(w) * 2.0) @ y0
    np.testing.assert_allclose(x[:3], expected, atol=1e-12)


@pytest.mark.parametrize("omega,rank", [([0, 0, 0], 5), ([0, 0, 0.5], 5), ([0.5, 0, 0], 6), ([0, 0.2, 0.3], 6)])
def test_integrated_gramian_rank(omega, rank):
    sv = np.linalg.svd(at.integrated_gramian(omega, [0, 0, -9.81], 5.0), compute_uv=False)
    assert int(np.sum(sv > 1e-9 * sv[0])) == rank


def test_integrated_filter_recovers_bias_when_rocking():
    rng = np.random.default_rng(3)
    dt = 0.01
    t = np.arange(0, 60, dt)
    w = 2 * np.pi * 0.2
    roll, droll = 0.4 * np.sin(w * t), 0.4 * w * np.cos(w * t)
    pitch, dpitch = 0.3 * np.cos(w * t), -0.3 * w * np.sin(w * t)
    rates = at.body_rates(roll, pitch, droll, dpitch, np.zeros_like(t))
    b = np.array([0.02, -0.01, 0.015])
    imu = at.simulate_imu(rng, rates, pitch, roll, gyro_bias=b, gyro_var=1e-6, accel_var=1e-4)
    Xi = np.diag([1e-4] * 3 + [1e-10] * 3)
    res = at.integrated_filter(dt, imu.accel, imu.gyro, Xi=Xi, Theta=np.eye(3) * 1e-6)
    err = res.x[-1, 3:] - b
    sd = np.sqrt(np.diag(res.P[-1])[3:])
    assert np.all(np.abs(err) < 4 * sd + 1e-4)
    assert np.degrees(np.max(np.abs(res.roll[-500:] - roll[-500:]))) < 0.5


def test_body_rates_pure_cases():
    np.testing.assert_allclose(at.body_rates(0, 0, 0.1, 0.2, 0.3), [0.1, 0.2, 0.3])
    # level yaw only: rate about body z
    np.testing.assert_allclose(at.body_rates(0.0, 0.0, 0.0, 0.0, 1.0), [0, 0, 1], atol=1e-15)


def test_simulation_statistics_and_dead_zone():
    rng = np.random.default_rng(7)
    n = 20000
    h = np.linspace(0, 2, n)
    hm, am = at.simulate_height_sensors(rng, h, np.zeros(n), accel_bias=0.05, accel_var=4e-3, alt_var=2.5e-5)
    assert np.all(hm[h < 0.25] == 0)
    lo, hi = (scipy.stats.chi2.ppf([0.0005, 0.9995], n - 1) / (n - 1))
    assert lo < np.var(am, ddof=1) / 4e-3 < hi
    assert abs(am.mean() - 0.05) < 4 * np.sqrt(4e-3 / n)


def test_sampled_filter_converges_to_continuous():
    m = at.kinematic_model(1, bias=True)
    Q, R = np.diag([8.3922e-4, 1e-4]), [[0.2431]]
    L = at.filter_tfs(m, Q, R)[0].L
    e = [np.linalg.norm(at.sampled_filter(m, Q, R, dt).K / dt - L) for dt in (1e-1, 1e-2, 1e-3)]
    assert e[0] > 5 * e[1] > 25 * e[2]


def test_bad_input():
    with pytest.raises(ValueError, match=r"^a must"):
        at.tilt_from_accel([1.0, 2.0])
    with pytest.raises(ValueError, match="order"):
        at.kinematic_model(3)
    with pytest.raises(ValueError, match="derivative"):
        at.dynamic_model(*at.PITCH_PLANT, 0)
    with pytest.raises(ValueError, match="proper"):
        at.dynamic_model([1.0, 0.0, 0.0], [1.0, 1.0, 1.0], 1)
    with pytest.raises(TypeError, match="rng"):
        at.simulate_imu(1, np.zeros((2, 3)), np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match="y_a"):
        at.integrated_filter(0.01, np.zeros((5, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="Theta"):
        at.integrated_filter(0.01, np.zeros((5, 3)), np.zeros((5, 3)), Theta=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="delay"):
        at.plant_response(*at.PITCH_PLANT, np.arange(3.0), np.zeros(3), delay=-1)
    # the pitch plant has relative degree 1: its second derivative needs d(ref)/dt
    with pytest.raises(ValueError, match=r"^derivative=2 exceeds the relative degree 1"):
        at.dynamic_model(*at.PITCH_PLANT, 2)
    with pytest.raises(ValueError, match=r"^derivatives=2 exceeds the relative degree 1"):
        at.plant_response(*at.PITCH_PLANT, np.arange(3.0), np.zeros(3), 2)
    with pytest.raises(ValueError, match=r"^t must be uniformly spaced"):
        at.plant_response(*at.HEIGHT_PLANT, np.array([0.0, 1.0, 3.0]), np.zeros(3))
    with pytest.raises(ValueError, match=r"^gyro_var must"):
        at.simulate_imu(np.random.default_rng(0), np.zeros((2, 3)), np.zeros(2), np.zeros(2), gyro_var=-1.0)
    with pytest.raises(ValueError, match=r"^alt_var must"):
        at.simulate_height_sensors(np.random.default_rng(0), np.ones(3), np.zeros(3), alt_var=-1e-4)


def test_density_from_variance_and_scale_invariance():
    # a per-sample variance sigma2 at dt is the density sigma2 * dt
    assert at.density_from_variance(4e-3, 0.01) == pytest.approx(4e-5, rel=1e-15)
    np.testing.assert_allclose(at.density_from_variance(np.array([1.0, 2.0]), 0.5), [0.5, 1.0], rtol=0, atol=0)
    with pytest.raises(ValueError, match="dt"):
        at.density_from_variance(1.0, 0.0)
    with pytest.raises(ValueError, match="dt"):
        at.sampled_filter(at.kinematic_model(1), [[1.0]], [[1.0]], -0.01)
    # scaling both densities by the same factor leaves the sampled gain unchanged: reading the
    # study's variances as densities or as per-sample variances changes P, not the estimates of
    # a filter whose q and r are both sensor noises (round-off bound: a few eps x cond ~ 1e-12)
    m = at.kinematic_model(1, bias=True)
    q, r = np.diag([8.3922e-4, 1e-4]), np.array([[0.2431]])
    dt = 0.01
    K1 = at.sampled_filter(m, q, r, dt).K
    K2 = at.sampled_filter(m, at.density_from_variance(q, dt), at.density_from_variance(r, dt), dt).K
    np.testing.assert_allclose(K2, K1, rtol=1e-9, atol=0)
