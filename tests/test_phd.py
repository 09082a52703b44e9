"""Tests of kftrack.phd: the Gaussian-mixture PHD filter (Vo & Ma 2006)."""
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment
from scipy.stats import multivariate_normal

from kftrack import phd
from kftrack.kalman import predict as kalman_predict, update as kalman_update
from kftrack.models import ConstantVelocity
from kftrack.sensors.radar import RangeBearing

EPS = np.finfo(float).eps
RADAR = RangeBearing(sigmas=(20.0, np.deg2rad(0.2)))
CV = ConstantVelocity(ndim=2, q=0.5)


class LinearPosition:
    """A linear position sensor z = H x + v (test double with the duck-typed sensor interface)."""

    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    R = np.array([[25.0, 5.0], [5.0, 16.0]])
    angle_components = ()

    def h(self, x):
        return (self.H @ np.asarray(x)[..., None])[..., 0]

    def jacobian(self, x):
        return np.broadcast_to(self.H, np.shape(x)[:-1] + self.H.shape)


def _scan(time, times, z):
    return SimpleNamespace(time=float(time), times=np.asarray(times, float), z=np.asarray(z, float).reshape(-1, 2))


def _truth(x0, t):
    """Constant-velocity truth (N, 4) at times t (N,)."""
    x = x0.copy()
    x[:, 0] += t * x0[:, 1]
    x[:, 2] += t * x0[:, 3]
    return x


@pytest.mark.parametrize("P_G", [None, 1 - 1e-6])
def test_cardinality_is_exact_with_certain_detection_and_no_clutter(P_G):
    # 5 well-separated aircraft (>= 20 km apart), P_D = 1, no clutter, P_S = 1, no birth, the
    # intensity started at the truth; the antenna sweeps every 4 s and each detection has its own
    # time. With kappa = 0 the update weights of each measurement sum to 1 exactly, and the missed
    # terms vanish (1 - P_D = 0): the mass is N but for the components pruned (each < T = 1e-5),
    # at most J_prev (M + 1) of them; the extraction rounds it to N. The same with the gate (the
    # weights of a measurement are normalised over the components in its gates).
    rng = np.random.default_rng(3)
    N, period = 5, 4.0
    x0 = np.zeros((N, 4))
    x0[:, 0] = [30e3, -25e3, 0.0, 40e3, -40e3]
    x0[:, 2] = [10e3, 30e3, -35e3, -30e3, -10e3]
    x0[:, [1, 3]] = rng.normal(0, 150, (N, 2))
    P0 = np.broadcast_to(np.diag([200.0**2, 30.0**2, 200.0**2, 30.0**2]), (N, 4, 4))
    f = phd.GMPHD(RADAR, CV, P_D=1.0, clutter_density=0.0, P_S=1.0, birth=None, initial=(np.ones(N), x0, P0), t0=0.0,
                  P_G=P_G)
    J_prev = N
    for k in range(1, 31):
        t = k * period
        az = np.mod(0.5 * np.pi - np.arctan2(x0[:, 2], x0[:, 0]), 2 * np.pi)  # clockwise sweep from north
        times = t + az / (2 * np.pi) * period
        z = RADAR.simulate(_truth(x0, times - 0.0), rng)
        step = f.step(_scan(t, times, z))
        assert abs(step.cardinality - N) <= J_prev * (N + 1) * 1e-5 + 100 * N * EPS, (k, step.cardinality)
        assert step.states.shape == (N, 4)
        truth = _truth(x0, np.full(N, step.time))
        D = np.linalg.norm(step.states[:, None, [0, 2]] - truth[None, :, [0, 2]], axis=-1)
        r, c = linear_sum_assignment(D)
        assert D[r, c].max() < 500.0  # each estimate on its own aircraft (separation >= 20 km)
        J_prev = len(step.weights)


def _one_component(P_D, lam, dt):
    sensor = LinearPosition()
    m0 = np.array([100.0, 3.0, -50.0, 1.0])
    P0 = np.diag([400.0, 4.0, 300.0, 9.0])
    w0 = 0.7
    z = np.array([112.0, -41.0])
    f = phd.GMPHD(sensor, CV, P_D=P_D, clutter_density=lam, P_S=0.9, birth=None, prune_threshold=0.0,
                  merge_threshold=0.0, initial=([w0], [m0], [P0]), t0=10.0)
    step = f.step(_scan(10.0 + dt, [10.0 + dt], z))
    # the Kalman filter: predict over dt, update with z
    xp, Pp = kalman_predict(m0, P0, CV.F(dt), CV.Q(dt))
    kp = SimpleNamespace(x=xp, P=Pp)
    ku = kalman_update(xp, Pp, z, sensor.H, sensor.R)
    q = multivariate_normal(sensor.H @ xp, sensor.H @ Pp @ sensor.H.T + sensor.R).pdf(z)
    wp = 0.9 * w0  # survival
    return step, kp, ku, wp, q


@pytest.mark.parametrize("P_D, lam, dt", [(1.0, 0.0, 0.0), (0.8, 1e-4, 0.0), (0.6, 3e-3, 2.5)])
def test_single_linear_component_is_a_kalman_update(P_D, lam, dt):
    # one component, one measurement, a linear sensor: the posterior is the missed term
    # (1 - P_D) w with the prediction, and P_D w q / (kappa + P_D w q) with the Kalman update
    # (Vo & Ma 2006, eq. 20-21). Tolerances: a few hundred operations on O(1)-conditioned
    # 4 x 4 matrices, relative round-off below 1e-12.
    step, kp, ku, wp, q = _one_component(P_D, lam, dt)
    w_det = P_D * wp * q / (lam + P_D * wp * q)
    order = np.argsort(-step.weights)
    expect = sorted([(w_det, ku.x, ku.P), ((1 - P_D) * wp, kp.x, kp.P)], key=lambda e: -e[0])
    expect = [e for e in expect if e[0] > 0]
    assert len(step.weights) == len(expect)
    for j, (w, x, P) in zip(order, expect):
        assert step.weights[j] == pytest.approx(w, rel=1e-12)
        np.testing.assert_allclose(step.means[j], x, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(step.covs[j], P, rtol=1e-12, atol=1e-9)
    assert step.cardinality == pytest.approx(w_det + (1 - P_D) * wp, rel=1e-12)
    assert step.time == 10.0 + dt


def test_bearing_residual_is_wrapped_across_pi():
    # a target due west, just below the -x axis (bearing near -pi) measured just above it (near
    # +pi): unwrapped, the residual would be ~2 pi rad and the update would throw the estimate away
    x = np.array([-30e3, 0.0, -10.0, 0.0])
    z = np.array([30e3, np.pi - 2e-4])  # 6 m on the other side
    f = phd.GMPHD(RADAR, CV, P_D=1.0, clutter_density=0.0, P_S=1.0, birth=None,
                  initial=([1.0], [x], [np.diag([100.0**2, 10.0, 100.0**2, 10.0])]), t0=0.0)
    step = f.step(_scan(0.0, [0.0], z))
    assert step.cardinality == pytest.approx(1.0, abs=1e-12)
    assert abs(step.means[0, 2] - 6.0) < 20.0 and abs(step.means[0, 0] + 30e3) < 30.0


def test_merging_preserves_mass_mean_and_second_moment():
    # five nearby components merged into one (U large): mass sum w, mean sum w m / w and second
    # moment sum w (P + m m^T) are kept; relative round-off ~ 5 terms x eps x cond, below 1e-12
    rng = np.random.default_rng(11)
    w = rng.uniform(0.1, 1.0, 5)
    m = rng.normal(0, 1.0, (5, 4))
    A = rng.normal(size=(5, 4, 4))
    P = A @ np.swapaxes(A, -1, -2) + np.eye(4)
    wr, mr, Pr = phd.reduce_mixture(w, m, P, prune_threshold=0.0, merge_threshold=1e6)
    assert wr.shape == (1,)
    assert wr[0] == pytest.approx(w.sum(), rel=1e-14)
    np.testing.assert_allclose(mr[0], w @ m / w.sum(), rtol=1e-12, atol=1e-14)
    second = np.einsum("k,kij->ij", w, P + m[:, :, None] * m[:, None, :])
    np.testing.assert_allclose(wr[0] * (Pr[0] + np.outer(mr[0], mr[0])), second, rtol=1e-12)


def test_pruning_capping_and_extraction():
    m = np.arange(12.0).reshape(4, 3) * 100.0  # far apart: no merging at U = 4
    P = np.broadcast_to(np.eye(3), (4, 3, 3))
    w = np.array([1e-6, 0.6, 2.4, 1.6])
    wr, mr, _ = phd.reduce_mixture(w, m, P, prune_threshold=1e-5, merge_threshold=4.0)
    np.testing.assert_array_equal(wr, [2.4, 1.6, 0.6])  # pruned, heaviest first, not renormalised
    wc, _, _ = phd.reduce_mixture(w, m, P, max_components=2)
    np.testing.assert_array_equal(wc, [2.4, 1.6])
    # extraction: round(w) copies of each mean with w > 0.5: 2 + 2 + 1
    s = phd.extract_states(wr, mr)
    np.testing.assert_array_equal(s, mr[[0, 0, 1, 1, 2]])
    assert phd.extract_states([0.5, 0.2], [[0.0], [1.0]]).shape == (0, 1)


def test_measurement_driven_birth_finds_a_new_target():
    # one aircraft, P_D = 1, no clutter: scan 0 spawns a birth component on its measurement; at
    # scan 1 that component is the only one, so the measurement's update weight is exactly 1
    # (kappa = 0) and the missed term vanishes: cardinality 1, one state near the aircraft
    rng = np.random.default_rng(5)
    x0 = np.array([[20e3, -120.0, 15e3, 80.0]])
    f = phd.GMPHD(RADAR, CV, P_D=1.0, clutter_density=0.0, P_S=0.99, birth_rate=0.2, birth_speed_sigma=200.0)
    s0 = f.step(_scan(0.0, [0.0], RADAR.simulate(x0[0], rng)))
    assert s0.cardinality == 0.0 and s0.states.shape == (0, 4)
    for k in (1, 2, 3):
        s = f.step(_scan(4.0 * k, [4.0 * k], RADAR.simulate(_truth(x0, np.array([4.0 * k]))[0], rng)))
        assert s.cardinality == pytest.approx(1.0, abs=1e-12)
        assert s.states.shape == (1, 4)
        assert np.hypot(*(s.states[0, [0, 2]] - _truth(x0, np.array([4.0 * k]))[0, [0, 2]])) < 300.0
    np.testing.assert_allclose(f.states_at(s.time + 2.0), (CV.F(2.0) @ s.states[0])[None])


def test_phd_filter_returns_one_step_per_scan():
    scans = [_scan(4.0 * k, [4.0 * k + 1.0], RADAR.h(np.array([20e3, 0, 15e3, 0]))) for k in range(3)]
    out = phd.phd_filter(scans, RADAR, CV, P_D=0.9, clutter_density=1e-9)
    assert len(out) == 3 and all(isinstance(s, phd.PHDStep) for s in out)
    assert [s.time for s in out] == [1.0, 5.0, 9.0]
    empty = phd.phd_filter([_scan(0.0, [], np.zeros((0, 2)))], RADAR, CV, P_D=0.9, clutter_density=1e-9)
    assert empty[0].cardinality == 0.0 and empty[0].states.shape == (0, 4)


def test_bad_input():
    ok = dict(P_D=0.9, clutter_density=1e-9)
    for kw, match in [(dict(P_D=0.0), "P_D"), (dict(P_D=1.5), "P_D"), (dict(P_S=0.0), "P_S"),
                      (dict(clutter_density=-1.0), "clutter_density"), (dict(birth="fixed"), "birth"),
                      (dict(birth=([1.0], [[0.0, 0.0]], [np.eye(2)])), r"\(J, 4\)"),
                      (dict(birth_rate=-0.1), "birth_rate"), (dict(birth_speed_sigma=0.0), "birth_speed_sigma"),
                      (dict(prune_threshold=0.7), "prune_threshold"), (dict(merge_threshold=-1.0), "merge_threshold"),
                      (dict(max_components=0), "max_components"), (dict(initial=[1.0]), "initial"),
                      (dict(P_G=1.0), "P_G")]:
        with pytest.raises(ValueError, match=match):
            phd.GMPHD(RADAR, CV, **{**ok, **kw})
    with pytest.raises(TypeError, match="sensor must have h, jacobian and R"):
        phd.GMPHD(object(), CV, **ok)
    with pytest.raises(TypeError, match="motion must have F"):
        phd.GMPHD(RADAR, object(), **ok)
    with pytest.raises(TypeError, match="to_cartesian"):
        phd.GMPHD(LinearPosition(), CV, **ok)  # measurement-driven birth needs the conversion
    f = phd.GMPHD(RADAR, CV, **ok)
    with pytest.raises(TypeError, match="scan must have time, times and z"):
        f.step((0.0, np.zeros((1, 2))))
    with pytest.raises(ValueError, match=r"\(m, 2\) and \(m,\).*\(3, 2\) and \(2,\)"):
        f.step(_scan(0.0, [0.0, 0.1], np.ones((3, 2))))
    f.step(_scan(10.0, [10.5], [[1e4, 0.1]]))
    with pytest.raises(ValueError, match="time order"):
        f.step(_scan(5.0, [5.5], [[1e4, 0.1]]))
    with pytest.raises(ValueError, match="weights of the mixture must be finite and >= 0"):
        phd.reduce_mixture([-1.0], [[0.0]], [[[1.0]]])
