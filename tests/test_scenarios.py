"""Tests of kftrack.scenarios: printed-number parsing, seed 003's printed record, the
reconstructed truths, the simulated scenarios (shapes, seeding, noise by chi-square bounds)
and bad input."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from kftrack import kalman, scenarios
from kftrack.models import ConstantAcceleration
from kftrack.scenarios import COSTA2023_CAR, COSTA2023_ROBOT, printed


# --- printed numbers -------------------------------------------------------------------
@pytest.mark.parametrize("text, value, tol", [
    ("0.9412", 0.9412, 5e-5), ("12.9", 12.9, 0.05), ("10000.15", 10000.15, 0.005),
    ("0", 0.0, 0.5), ("-0.91", -0.91, 0.005), ("0.410", 0.41, 5e-4), ("1.5e-3", 1.5e-3, 5e-5),
])
def test_printed_value_and_half_unit_tolerance(text, value, tol):
    p = printed(text)
    assert p.value == pytest.approx(value, abs=1e-15)
    assert p.tol == pytest.approx(tol, rel=1e-12)


def test_printed_nested_blank_and_agrees():
    p = printed([["1.25", ""], ["3", "0.5"]])
    assert p.value.shape == (2, 2) and np.isnan(p.value[0, 1]) and np.isnan(p.tol[0, 1])
    ok = p.agrees([[1.2549, 123.0], [3.6, 0.56]])
    np.testing.assert_array_equal(ok, [[True, True], [False, False]])
    assert not printed("0.9412").agrees(0.94126)


def test_printed_bad_input():
    with pytest.raises(TypeError, match="printed numbers must be given as text"):
        printed(0.5)
    with pytest.raises(ValueError, match="dot decimal"):
        printed("0,5")
    with pytest.raises(ValueError, match="computed must have the printed shape"):
        printed(["1", "2"]).agrees([1.0, 2.0, 3.0])


# --- the printed record of seed 003 ------------------------------------------------------
def test_car_record_is_read_only_and_consistent():
    s = COSTA2023_CAR
    assert (s.x0, s.p0, s.q, s.r) == (10.0, 10_000.0, 0.15, 0.01)
    assert s.speed == pytest.approx((161.131 - 49.732) / 11)
    with pytest.raises(TypeError):
        s.printed["K"][2] = "1"
    with pytest.raises(Exception):
        s.q = 0.2


def test_robot_record_has_full_printed_matrices():
    p = COSTA2023_ROBOT.printed
    for key in ("P_1_0", "P_1_1", "P_2_1", "P_2_2", "P_3_2", "P_35_35", "P_36_35"):
        assert printed(p[key]).value.shape == (6, 6), key
    for key in ("K_1", "K_2", "K_35"):
        assert printed(p[key]).value.shape == (6, 2), key
    assert np.isnan(printed(p["P_36_35"]).value[:3, 5]).all()  # the blank column of the print


def test_robot_record_reproduces_the_data_independent_printed_numbers():
    """P_{1,0}, K_35, and the x blocks of P_{35,35}, P_{36,35} depend on no measurement."""
    s = COSTA2023_ROBOT
    model = ConstantAcceleration(ndim=2, sigma2=s.sigma_a**2)
    F, Q, H, R = model.F(s.dt), model.Q(s.dt), model.H, s.sigma_m**2 * np.eye(2)
    x, P = kalman.predict(np.zeros(6), s.p0 * np.eye(6), F, Q)
    assert printed(s.printed["P_1_0"]).agrees(P).all()
    res = kalman.kalman_filter(np.zeros((35, 2)), x, P, F, Q, H, R)
    K35 = kalman.update(res.x_prior[34], res.P_prior[34], np.zeros(2), H, R).K
    assert printed(s.printed["K_35"]).agrees(K35).all()
    assert printed(s.printed["P_35_35"]).agrees(res.P[34])[:3, :3].all()
    # with the later-stated sigma_a = 0.2 the printed gain is not reproduced
    model2 = ConstantAcceleration(ndim=2, sigma2=s.sigma_a_stated_later**2)
    x2, P2 = kalman.predict(np.zeros(6), s.p0 * np.eye(6), model2.F(1.0), model2.Q(1.0))
    res2 = kalman.kalman_filter(np.zeros((35, 2)), x2, P2, model2.F(1.0), model2.Q(1.0), H, R)
    K35b = kalman.update(res2.x_prior[34], res2.P_prior[34], np.zeros(2), H, R).K
    assert not printed(s.printed["K_35"]).agrees(K35b).all()


# --- reconstructed truths -----------------------------------------------------------------
def test_robot_truth_matches_printed_measurements_and_is_self_consistent():
    n = np.array(sorted(COSTA2023_ROBOT.z))
    truth = scenarios.robot_truth(n)
    z = np.array([COSTA2023_ROBOT.z[k] for k in n])
    assert np.abs(z - truth[:, [0, 3]]).max() < 1.0
    t0 = scenarios.robot_truth(0.0)
    np.testing.assert_allclose(t0[[0, 3]], [15.0, np.sqrt(2.0)])
    # velocities and accelerations are the time derivatives (central differences)
    t, h = np.linspace(0.0, 40.0, 9), 1e-4
    d = (scenarios.robot_truth(t + h) - scenarios.robot_truth(t - h)) / (2 * h)
    x = scenarios.robot_truth(t)
    np.testing.assert_allclose(d[:, [0, 1, 3, 4]], x[:, [1, 2, 4, 5]], rtol=1e-7, atol=1e-9)
    assert scenarios.robot_truth(np.zeros((3, 4))).shape == (3, 4, 6)


def test_car_radar_truth_defaults_to_the_study():
    sc = scenarios.car_radar(np.random.default_rng(0), n_steps=12)
    np.testing.assert_allclose(sc.truth[0, 0], COSTA2023_CAR.z[1])
    np.testing.assert_allclose(sc.truth[-1, 0], COSTA2023_CAR.z[12])
    np.testing.assert_allclose(sc.truth[:, 1], COSTA2023_CAR.speed)
    np.testing.assert_allclose(sc.t, np.arange(1.0, 13.0))


# --- simulated scenarios --------------------------------------------------------------------
@pytest.mark.parametrize("make, n, m", [(scenarios.robot, 6, 2), (scenarios.car_radar, 2, 1)])
def test_shapes_time_first_and_seeding(make, n, m):
    a = make(np.random.default_rng(5), 20)
    assert a.t.shape == (20,) and a.truth.shape == (20, n) and a.z.shape == (20, m)
    b = make(np.random.default_rng(5), 20, runs=7)
    assert b.truth.shape == (20, 7, n) and b.z.shape == (20, 7, m)
    c = make(np.random.default_rng(5), 20, runs=7)
    np.testing.assert_array_equal(b.z, c.z)
    assert not np.array_equal(b.z[:, 0], b.z[:, 1])


@pytest.mark.parametrize("make, sigma", [(scenarios.robot, 3.0), (scenarios.robot, 0.5), (scenarios.car_radar, 0.1)])
def test_noise_variance_by_chi_square(make, sigma):
    sc = make(np.random.default_rng(11), 30, sigma=sigma, runs=200)
    pos = sc.truth[..., [0, 3]] if sc.z.shape[-1] == 2 else sc.truth[..., :1]
    e = (sc.z - pos) / sigma
    dof = e.size
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], dof)
    assert lo < np.sum(e**2) < hi
    assert abs(e.mean()) < 3.5 / np.sqrt(dof)


@pytest.mark.parametrize("kwargs, exc, match", [
    ({"rng": 1}, TypeError, "rng must be a numpy.random.Generator"),
    ({"n_steps": 0}, ValueError, "n_steps must be a positive integer"),
    ({"n_steps": 2.5}, ValueError, "n_steps must be a positive integer"),
    ({"sigma": -1.0}, ValueError, "sigma must be > 0"),
    ({"sigma": np.nan}, ValueError, "sigma must be finite"),
    ({"dt": 0.0}, ValueError, "dt must be > 0"),
    ({"runs": 0}, ValueError, "runs must be a positive integer or None"),
])
@pytest.mark.parametrize("make", [scenarios.robot, scenarios.car_radar])
def test_bad_input_names_the_argument(make, kwargs, exc, match):
    args = {"rng": np.random.default_rng(0), "n_steps": 5} | kwargs
    with pytest.raises(exc, match=match):
        make(args.pop("rng"), args.pop("n_steps"), **args)


def test_robot_truth_rejects_nan():
    with pytest.raises(ValueError, match="t must be finite"):
        scenarios.robot_truth([1.0, np.nan])
