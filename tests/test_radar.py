"""Tests of kftrack.sensors.radar: measurement functions against closed forms, every SymPy
Jacobian against 4th-order central differences, the polar/Cartesian round trip, the
debiased conversion against Gauss-Hermite quadrature and by Monte Carlo (chi-square bounds),
seed 001's 3-point velocity (weights, polyfit, noise gain sqrt(26)/(2T)), bad input."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from kftrack.sensors import radar as rd


def central_jacobian(fn, x, h):
    """4th-order central differences, column by column (error O(h^4))."""
    x = np.asarray(x, dtype=float)
    cols = []
    for i in range(x.shape[-1]):
        e = np.zeros_like(x)
        e[..., i] = h
        d = (-fn(x + 2 * e) + 8 * fn(x + e) - 8 * fn(x - e) + fn(x - 2 * e)) / (12 * h)
        cols.append(d)
    return np.stack(cols, axis=-1)


def states(rng, n, ndim, size):
    x = rng.normal(size=(size, n)) * 50.0
    x[:, [0, 2, 4][:ndim]] = rng.uniform(-3000, 3000, size=(size, ndim))
    return x


def test_h_matches_closed_form():
    rng = np.random.default_rng(0)
    x = states(rng, 4, 2, 20)
    r2 = rd.RangeBearing(sigmas=(1.0, 0.01), sensor=(10.0, -20.0))
    dx, dy = x[:, 0] - 10.0, x[:, 2] + 20.0
    assert np.allclose(r2.h(x), np.stack([np.hypot(dx, dy), np.arctan2(dy, dx)], -1), rtol=1e-14)
    x3 = states(rng, 7, 3, 20)
    r3 = rd.RangeAzimuthElevation(sigmas=(75.0, 0.0175, 0.0175))
    p = x3[:, [0, 2, 4]]
    want = np.stack([np.linalg.norm(p, axis=-1), np.arctan2(p[:, 1], p[:, 0]),
                     np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))], -1)
    assert np.allclose(r3.h(x3), want, rtol=1e-14)


@pytest.mark.parametrize("cls,n,ndim", [(rd.RangeBearing, 4, 2), (rd.RangeAzimuthElevation, 6, 3),
                                        (rd.RangeAzimuthElevation, 8, 3)])
def test_measurement_jacobian_against_finite_differences(cls, n, ndim):
    rng = np.random.default_rng(1)
    sensor = tuple(rng.normal(size=ndim) * 100)
    radar = cls(sigmas=(1.0,) + (0.01,) * (ndim - 1), sensor=sensor)
    x = states(rng, n, ndim, 10)
    H = radar.jacobian(x)
    assert H.shape == (10, ndim, n)
    # positions of order 1e3 m: a step of 0.1 m makes the O(h^4) truncation negligible; the
    # round-off of the difference quotient is ~ eps |h_row| / step, per measurement row
    step = 0.1
    num = central_jacobian(radar.h, x, step)
    roundoff = 100 * np.finfo(float).eps * np.max(np.abs(radar.h(x)), axis=0) / step
    assert np.all(np.abs(H - num) <= 1e-8 * np.abs(num) + roundoff[None, :, None])


@pytest.mark.parametrize("ndim", [2, 3])
def test_conversion_jacobian_against_finite_differences(ndim):
    rng = np.random.default_rng(2)
    g, J = rd._generated(ndim)["g"], rd._generated(ndim)["J"]
    z = np.column_stack([rng.uniform(100, 5000, 8)] + [rng.uniform(-1.4, 1.4, 8) for _ in range(ndim - 1)])
    num = central_jacobian(lambda v: g(*np.moveaxis(v, -1, 0))[..., 0], z, 1e-3)
    assert np.allclose(J(*np.moveaxis(z, -1, 0)), num, rtol=1e-8, atol=1e-9)


@pytest.mark.parametrize("ndim", [2, 3])
def test_round_trip_polar_cartesian(ndim):
    rng = np.random.default_rng(3)
    cls = rd.RangeBearing if ndim == 2 else rd.RangeAzimuthElevation
    radar = cls(sigmas=(1.0,) + (0.01,) * (ndim - 1), sensor=tuple(rng.normal(size=ndim)))
    x = states(rng, 2 * ndim, ndim, 30)
    conv = radar.to_cartesian(radar.h(x), method="linearized")
    assert np.allclose(conv.p, x[:, radar.position_indices], rtol=1e-12, atol=1e-9)
    # linearized covariance: J R J^T, range variance along the line of sight
    u = (conv.p - radar.sensor) / np.linalg.norm(conv.p - radar.sensor, axis=-1, keepdims=True)
    assert np.allclose(np.einsum("ki,kij,kj->k", u, conv.C, u), 1.0, rtol=1e-9)
    # the whole matrix in closed form: sigma_r along the line of sight, r cos(phi) sigma_theta
    # along the azimuth direction and r sigma_phi along the elevation direction
    z = radar.h(x)
    r, th = z[:, 0], z[:, 1]
    ph = z[:, 2] if ndim == 3 else np.zeros_like(r)
    e_th = np.stack([-np.sin(th), np.cos(th), np.zeros_like(th)], -1)[:, :ndim]
    dirs = [(u, radar.sigmas[0]), (e_th, r * np.cos(ph) * radar.sigmas[1])]
    if ndim == 3:
        e_ph = np.stack([-np.sin(ph) * np.cos(th), -np.sin(ph) * np.sin(th), np.cos(ph)], -1)
        dirs.append((e_ph, r * radar.sigmas[2]))
    C = sum(np.broadcast_to(s, r.shape)[:, None, None] ** 2 * e[:, :, None] * e[:, None, :] for e, s in dirs)
    assert np.allclose(conv.C, C, rtol=1e-10, atol=1e-10 * np.max(np.abs(C)))


def _gauss_hermite_conditioned(z, sig, ndim, order=40):
    """E[(p_u - p)(p_u - p)^T | z] and E[p | z] by tensor Gauss-Hermite quadrature over the
    true range and angles r = r_m - e_r, angle = angle_m - e (independent Gaussians)."""
    t, w = np.polynomial.hermite_e.hermegauss(order)
    w = w / w.sum()
    grids = np.meshgrid(*([t] * ndim), indexing="ij")
    W = np.prod(np.meshgrid(*([w] * ndim), indexing="ij"), axis=0).ravel()
    true = [z[i] - sig[i] * grids[i].ravel() for i in range(ndim)]
    g = rd._generated(ndim)["g"]
    p = g(*true)[..., 0]
    return np.einsum("k,ki->i", W, p), p, W


@pytest.mark.parametrize("ndim,z,sig", [
    (2, np.array([1000.0, 0.7]), np.array([20.0, 0.3])),
    (2, np.array([50.0, -2.9]), np.array([5.0, 0.5])),
    (3, np.array([42430.6, 0.9, 0.05]), np.array([75.0, 0.0175, 0.0175])),
    (3, np.array([2000.0, -1.0, 0.6]), np.array([10.0, 0.2, 0.3])),
])
def test_debiased_conversion_and_exact_moments_against_quadrature(ndim, z, sig):
    cls = rd.RangeBearing if ndim == 2 else rd.RangeAzimuthElevation
    conv = cls(sigmas=tuple(sig)).to_cartesian(z, method="debiased")
    Ep, p, W = _gauss_hermite_conditioned(z, sig, ndim)
    e = conv.p - p
    C = np.einsum("k,ki,kj->ij", W, e, e)
    assert np.allclose(conv.C, C, rtol=1e-10, atol=1e-9 * np.max(np.abs(C)))
    # the exact moments of g(z + noise): same quadrature, centred on E[p]
    ex = cls(sigmas=tuple(sig)).exact_moments(z)
    Cp = np.einsum("k,ki,kj->ij", W, p - Ep, p - Ep)
    assert np.allclose(ex.p, Ep, rtol=1e-12, atol=1e-12 * z[0])
    assert np.allclose(ex.C, Cp, rtol=1e-10, atol=1e-9 * np.max(np.abs(Cp)))
    # the debiased point divides each cos/sin by lambda = exp(-sigma^2/2)
    lam = np.exp(-0.5 * sig[1:] ** 2)
    lin = cls(sigmas=tuple(sig)).to_cartesian(z, method="linearized").p
    if ndim == 2:
        assert np.allclose(conv.p, lin / lam[0], rtol=1e-14)
    else:
        assert np.allclose(conv.p, lin / np.array([lam[0] * lam[1], lam[0] * lam[1], lam[1]]), rtol=1e-14)


@pytest.mark.parametrize("ndim", [2, 3])
def test_debiased_is_unbiased_linearized_is_not_monte_carlo(ndim):
    """Hotelling-type statistic N ebar^T C^-1 ebar ~ chi2(d) for an unbiased estimator."""
    rng = np.random.default_rng(4)
    cls = rd.RangeBearing if ndim == 2 else rd.RangeAzimuthElevation
    radar = cls(sigmas=(10.0,) + (0.4,) * (ndim - 1))  # large angle noise: the bias is visible
    x = np.zeros(2 * ndim)
    x[radar.position_indices[0]], x[radar.position_indices[1]] = 3000.0, 4000.0
    if ndim == 3:
        x[4] = 1000.0
    N = 20000
    z = radar.simulate(np.broadcast_to(x, (N, 2 * ndim)), rng)
    truth = x[list(radar.position_indices)]
    limit = stats.chi2.ppf(0.999, ndim)

    def stat(p):
        e = p - truth
        eb = e.mean(0)
        return N * eb @ np.linalg.solve(np.cov(e.T), eb)

    assert stat(radar.to_cartesian(z, "debiased").p) < limit
    assert stat(radar.to_cartesian(z, "linearized").p) > 100 * limit


def test_simulated_angles_are_wrapped():
    rng = np.random.default_rng(5)
    radar = rd.RangeBearing(sigmas=(1.0, 0.2))
    x = np.tile([-1000.0, 0.0, 0.0, 0.0], (1000, 1))  # bearing exactly pi
    z = radar.simulate(x, rng)
    assert np.all(z[:, 1] > -np.pi) and np.all(z[:, 1] <= np.pi)
    assert np.mean(z[:, 1] < 0) > 0.3  # noise crosses the cut both ways


def test_compass_conversion():
    d = np.deg2rad
    assert np.isclose(rd.compass_to_math(0.0), np.pi / 2)  # North = +y
    assert np.isclose(rd.compass_to_math(d(90.0)), 0.0)  # East = +x
    assert np.isclose(rd.math_to_compass(d(38.31)), d(51.69))  # seed 001: heading 38.31 deg from +x
    a = np.linspace(0, 2 * np.pi, 13)[:-1]
    assert np.allclose(rd.math_to_compass(rd.compass_to_math(a)), a, atol=1e-14)


# --- seed 001: 3-point velocity ---------------------------------------------------------


def test_three_point_weights_uniform_and_gain():
    T = 4.0
    w = rd.three_point_weights([0.0, T, 2 * T])
    assert np.allclose(w, np.array([1.0, -4.0, 3.0]) / (2 * T), rtol=1e-15)
    assert np.isclose(rd.three_point_velocity_gain(T), np.sqrt(np.sum(w**2)), rtol=1e-15)
    assert round(rd.three_point_velocity_gain(4.0), 3) == 0.637  # seed note C7: 0.637 sigma_p at T = 4 s


def test_three_point_velocity_equals_least_squares_quadratic_derivative():
    rng = np.random.default_rng(6)
    for _ in range(10):
        t = np.sort(rng.uniform(0, 20, 3)) + np.array([0.0, 0.5, 1.0])
        p = rng.normal(size=(3, 3)) * 100
        v = rd.three_point_velocity(p, times=t)
        for axis in range(3):
            c = np.polyfit(t - t[-1], p[:, axis], 2)  # least squares, centred time (conditioning)
            assert np.isclose(v[axis], c[1], rtol=1e-9, atol=1e-9)


def test_three_point_velocity_exact_on_quadratic_and_covariance():
    T = 2.0
    t = np.array([0.0, T, 2 * T])
    a, b, c = np.array([1.0, -2.0]), np.array([3.0, 0.5]), np.array([0.25, 0.1])
    p = a + b * t[:, None] + c * t[:, None] ** 2
    assert np.allclose(rd.three_point_velocity(p, dt=T), b + 2 * c * t[-1], rtol=1e-14)
    C = np.stack([np.eye(2) * s for s in (1.0, 2.0, 3.0)])
    v, Cv = rd.three_point_velocity(p, dt=T, covariances=C)
    w = np.array([1.0, -4.0, 3.0]) / (2 * T)
    assert np.allclose(Cv, np.eye(2) * np.sum(w**2 * np.array([1.0, 2.0, 3.0])), rtol=1e-14)
    # batch axes: (3, N, d)
    pb = np.repeat(p[:, None, :], 4, axis=1)
    assert rd.three_point_velocity(pb, dt=T).shape == (4, 2)


def test_three_point_state_covariance_by_monte_carlo_and_algebra():
    rng = np.random.default_rng(7)
    T = 4.0
    C = np.stack([np.array([[4.0, 1.0], [1.0, 9.0]]) * s for s in (1.0, 1.5, 2.0)])
    clean = np.array([[0.0, 0.0], [400.0, 100.0], [800.0, 200.0]])  # constant velocity (100, 25)
    x, P = rd.three_point_state(clean, C, dt=T)
    assert np.allclose(x, [800.0, 100.0, 200.0, 25.0], rtol=1e-14)
    # the linear map [p2; v] = A [p0; p1; p2] gives P = A blockdiag(C) A^T (interleaved order)
    w = np.array([1.0, -4.0, 3.0]) / (2 * T)
    A = np.zeros((4, 6))
    for axis in range(2):
        A[2 * axis, 4 + axis] = 1.0
        A[2 * axis + 1, [axis, 2 + axis, 4 + axis]] = w
    Cb = np.zeros((6, 6))
    for i in range(3):
        Cb[2 * i:2 * i + 2, 2 * i:2 * i + 2] = C[i]
    assert np.allclose(P, A @ Cb @ A.T, rtol=1e-13)
    # Monte Carlo: the NEES of the initial state is chi2(4)
    N = 4000
    noisy = clean[:, None, :] + np.stack([rng.multivariate_normal(np.zeros(2), C[i], size=N) for i in range(3)])
    xs, Ps = rd.three_point_state(noisy, np.broadcast_to(C[:, None], (3, N, 2, 2)), dt=T)
    e = xs - x
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(Ps), e)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], 4 * N) / N
    assert lo < nees.mean() < hi


def test_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="sigmas"):
        rd.RangeBearing(sigmas=(1.0,))
    with pytest.raises(ValueError, match="sigmas"):
        rd.RangeAzimuthElevation(sigmas=(1.0, -0.1, 0.1))
    with pytest.raises(ValueError, match="position_indices"):
        rd.RangeBearing(sigmas=(1.0, 0.1), position_indices=(0, 0))
    with pytest.raises(ValueError, match="sensor"):
        rd.RangeBearing(sigmas=(1.0, 0.1), sensor=(0.0, 0.0, 0.0))
    radar = rd.RangeBearing(sigmas=(1.0, 0.1))
    with pytest.raises(ValueError, match=r"^x must"):
        radar.h(np.zeros(2))
    with pytest.raises(ValueError, match="method"):
        radar.to_cartesian([1.0, 0.0], method="exact")
    with pytest.raises(ValueError, match=r"^z must"):
        radar.to_cartesian([1.0, 0.0, 0.0])
    with pytest.raises(TypeError, match="rng"):
        radar.simulate(np.zeros(4), rng=1)
    with pytest.raises(ValueError, match="positions"):
        rd.three_point_velocity(np.zeros((2, 3)), dt=1.0)
    with pytest.raises(ValueError, match="times"):
        rd.three_point_velocity(np.zeros((3, 2)), times=[0.0, 2.0, 1.0])
    with pytest.raises(ValueError, match="dt"):
        rd.three_point_velocity(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="dt"):
        rd.three_point_velocity_gain(0.0)
    with pytest.raises(ValueError, match="ndim"):
        rd.polar_measurement(4)


def test_angle_sigmas_in_degrees_are_refused_with_a_hint():
    with pytest.raises(ValueError, match=r"sigmas\[1\] is an angle standard deviation in radians.*at most pi.*15.0.*np.deg2rad"):
        rd.RangeBearing(sigmas=(20, 15))
    with pytest.raises(ValueError, match=r"sigmas\[2\].*np.deg2rad"):
        rd.RangeAzimuthElevation(sigmas=(75.0, 0.01, 3.5))
    assert rd.RangeBearing(sigmas=(20.0, np.pi)).sigmas == (20.0, np.pi)  # pi itself is allowed
    assert rd.RangeBearing(sigmas=(20.0, np.deg2rad(15))).sigmas[1] == pytest.approx(0.2618, abs=1e-4)
