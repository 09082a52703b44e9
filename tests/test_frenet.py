"""Tests of kftrack.frenet: frame, curvature and torsion; the exact and the Euler simulators."""
import numpy as np
import pytest
import scipy.linalg
import sympy as sp
from hypothesis import given, settings, strategies as st
from scipy.integrate import quad_vec, solve_ivp

from kftrack import frenet as fr


def _helix_derivatives(R, c, t):
    """Analytic velocity, acceleration, jerk of (R cos t, R sin t, c t) in the parameter t."""
    v = np.stack([-R * np.sin(t), R * np.cos(t), c + 0 * t], -1)
    a = np.stack([-R * np.cos(t), -R * np.sin(t), 0 * t], -1)
    j = np.stack([R * np.sin(t), -R * np.cos(t), 0 * t], -1)
    return v, a, j


def test_helix_symbolic_curvature_torsion():
    t = sp.Symbol("t", real=True)
    R, c = sp.symbols("R c", positive=True)
    d = fr.frenet_sym(fr.helix_sym(R, c, t), t)
    assert sp.simplify(d["kappa"] - R / (R**2 + c**2)) == 0
    assert sp.simplify(d["tau"] - c / (R**2 + c**2)) == 0
    E = sp.Matrix.vstack(d["t"].T, d["n"].T, d["b"].T)
    assert (E * E.T).applyfunc(sp.simplify) == sp.eye(3)
    # Frenet-Serret in the parameter t: t' = |r'| kappa n, b' = -|r'| tau n
    assert (d["t"].diff(t) - d["speed"] * d["kappa"] * d["n"]).applyfunc(sp.simplify) == sp.zeros(3, 1)
    assert (d["b"].diff(t) + d["speed"] * d["tau"] * d["n"]).applyfunc(sp.simplify) == sp.zeros(3, 1)


def test_symbolic_rejects_bad_shape():
    with pytest.raises(ValueError, match="r must be a 3x1"):
        fr.frenet_sym(sp.Matrix([1, 2]), sp.Symbol("t"))


@pytest.mark.parametrize("R,c", [(100.0, 20.0), (5.0, -3.0), (1.0, 0.0)])
def test_numeric_curvature_torsion_exact_on_helix(R, c):
    t = np.linspace(0, 7, 50)
    v, a, j = _helix_derivatives(R, c, t)
    k, tau = fr.curvature_torsion(v, a, j)
    np.testing.assert_allclose(k, R / (R * R + c * c), rtol=1e-13)
    np.testing.assert_allclose(tau, c / (R * R + c * c), rtol=1e-12, atol=1e-16)
    E = fr.frame_from_derivatives(v, a)
    assert fr.orthonormality_error(E).max() < 1e-14
    np.testing.assert_allclose(E[:, 1], np.stack([-np.cos(t), -np.sin(t), 0 * t], -1), atol=1e-14)
    np.testing.assert_allclose(fr.turn_rate(v, a), np.linalg.norm(v, axis=-1) * k, rtol=1e-13)


def test_straight_line_has_nan_torsion_and_no_jerk_means_none():
    v = np.array([[1.0, 0, 0]])
    a = np.array([[2.0, 0, 0]])
    k, tau = fr.curvature_torsion(v, a, np.zeros((1, 3)))
    assert k[0] == 0 and np.isnan(tau[0])
    assert fr.curvature_torsion(v, a)[1] is None


def test_from_samples_second_order():
    R, c = 100.0, 20.0
    kap, tau = R / (R * R + c * c), c / (R * R + c * c)
    errs = []
    for dt in (0.5, 0.25):
        tr = fr.simulate([fr.Segment(3000.0, kap, tau)], dt, v0=(30.0, 0, 0))
        k, t = fr.curvature_torsion_from_samples(tr.t, tr.r)
        errs.append(np.max(np.abs(t[3:-3] - tau)))
    assert 3.5 < errs[0] / errs[1] < 4.5


def test_simulate_matches_ode_solver_with_speed_change():
    seg = fr.Segment(800.0, 0.01, -0.004, accel=0.3)
    v0 = np.array([10.0, 0, 0])
    tr = fr.simulate([seg], 0.5, v0=v0)
    E0 = fr.initial_frame(v0)
    G = fr.frenet_generator(seg.kappa, seg.tau)

    def rhs(_, y):
        E, v = y[3:12].reshape(3, 3), y[12]
        return np.concatenate([v * E[0], (v * G @ E).ravel(), [seg.accel]])

    sol = solve_ivp(rhs, (0, tr.t[-1]), np.concatenate([np.zeros(3), E0.ravel(), [10.0]]),
                    t_eval=tr.t, rtol=1e-12, atol=1e-10, method="DOP853")
    np.testing.assert_allclose(tr.r, sol.y[:3].T, atol=1e-6)
    np.testing.assert_allclose(tr.frame.reshape(-1, 9), sol.y[3:12].T, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(tr.v, axis=1), sol.y[12], rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(tr.v, axis=1) ** 2, 100.0 + 2 * 0.3 * tr.s, rtol=1e-12)


def test_frame_orthonormal_over_1e5_steps():
    long = [fr.Segment(1e5, 0.01, 0.005)]
    tr = fr.simulate(long, 1.0)
    assert len(tr.t) == 100001
    assert fr.orthonormality_error(tr.frame).max() < 1e-14
    steps = fr.simulate(long, 1.0, stepwise=True)
    assert fr.orthonormality_error(steps.frame).max() < 1e-10
    np.testing.assert_allclose(steps.r, tr.r, atol=1e-8)


def test_stepwise_and_direct_agree_across_segment_boundaries():
    segs = [fr.Segment(100), fr.Segment(50, 0.02, 0.01, accel=0.5), fr.Segment(80, -0.03, 0, accel=-0.2),
            fr.Segment(30)]
    a = fr.simulate(segs, 0.7, v0=(3, 1, 0))
    b = fr.simulate(segs, 0.7, v0=(3, 1, 0), stepwise=True)
    np.testing.assert_allclose(a.r, b.r, atol=1e-11)
    np.testing.assert_allclose(a.frame, b.frame, atol=1e-13)
    assert a.s[-1] <= 260.0 and 260.0 - a.s[-1] < np.linalg.norm(a.v[-1]) * 0.7


def test_full_circle_closes_and_euler_does_not():
    for ds in (1.0, 3.0):
        assert fr.circle_closure(100.0, ds, "exact") < 1e-11
    e1, e2 = fr.circle_closure(100.0, 1.0, "euler"), fr.circle_closure(100.0, 0.5, "euler")
    assert e1 > 1e-2 and abs(e1 / e2 - 4.0) < 0.1
    with pytest.raises(ValueError, match="method"):
        fr.circle_closure(100.0, 1.0, "rk4")
    # composing the 628 per-step rotations (not one rotation by 2 pi) also closes, to N eps
    n, R = 628, 100.0
    tr = fr.simulate([fr.Segment(2 * np.pi * R, 1 / R)], 2 * np.pi * R / n, n_max=n + 1, stepwise=True)
    assert len(tr.t) == n + 1 and np.linalg.norm(tr.r[-1] - tr.r[0]) < n * 1e-16 * R * 10
    np.testing.assert_allclose(tr.frame[-1], tr.frame[0], atol=n * 1e-16 * 10)


def test_euler_scheme_as_printed():
    # tau = 0: normalising u + kappa p ds turns the tangent by atan(kappa ds) per step
    kap, ds, n = 0.01, 1.0, 100
    tr = fr.simulate_euler([fr.Segment(n * ds, kap)], ds)
    heading = np.arctan2(tr.frame[:, 0, 1], tr.frame[:, 0, 0])
    np.testing.assert_allclose(heading, np.arange(n + 1) * np.arctan(kap * ds), atol=1e-13)
    # position uses the updated tangent
    np.testing.assert_allclose(tr.r[1], tr.frame[1, 0] * ds, atol=1e-15)
    assert len(tr.t) == n + 1 and tr.t[1] == ds
    # with torsion the frame is no longer orthonormal
    tr = fr.simulate_euler([fr.Segment(1e4, 0.01, 0.005)], 1.0)
    assert fr.orthonormality_error(tr.frame).max() > 1e-3


def test_torsion_sign_conventions():
    G = fr.frenet_generator(0.02, 0.01)
    np.testing.assert_array_equal(G, -G.T)
    assert not np.allclose(fr.frenet_generator(0.02, 0.01, "seed000-eq23"), -fr.frenet_generator(0.02, 0.01, "seed000-eq23").T)
    np.testing.assert_array_equal(fr.frenet_generator(0.02, 0.01, "seed000-eq26"), fr.frenet_generator(0.02, -0.01))
    seg = [fr.Segment(500.0, 0.02, 0.01)]
    std = fr.simulate_euler(seg, 0.1)
    rev = fr.simulate_euler(seg, 0.1, convention="seed000-eq26")
    mix = fr.simulate_euler(seg, 0.1, convention="seed000-eq23")
    tau_std = np.median(fr.curvature_torsion_from_samples(std.t, std.r)[1])
    tau_rev = np.median(fr.curvature_torsion_from_samples(rev.t, rev.r)[1])
    assert abs(tau_std - 0.01) < 1e-4 and abs(tau_rev + 0.01) < 1e-4
    assert np.max(np.abs(np.einsum("ki,ki->k", mix.frame[:, 1], mix.frame[:, 2]))) > 0.9
    with pytest.raises(ValueError, match="convention"):
        fr.frenet_generator(1, 1, "left")


@settings(max_examples=40, deadline=None)
@given(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(1e-6, 20.0))
def test_rotation_and_integral_closed_form(kappa, tau, h):
    M, p = fr._rotation_and_integral(np.array(kappa), np.array(tau), np.array(h))
    G = fr.frenet_generator(kappa, tau)
    np.testing.assert_allclose(M, scipy.linalg.expm(G * h), atol=1e-13)
    assert abs(np.linalg.det(M) - 1) < 1e-13
    ref, _ = quad_vec(lambda s: scipy.linalg.expm(G * s)[0], 0, h, epsabs=1e-13, epsrel=1e-13)
    np.testing.assert_allclose(p, ref, atol=1e-11 * max(1, h))


def test_jerk_and_turn_model_residual():
    seg = [fr.Segment(2000.0, 0.004, 0.003, accel=0.2)]
    tr = fr.simulate(seg, 0.05, v0=(30.0, 0, 0))
    j_fd = np.gradient(tr.a, tr.t, axis=0)
    np.testing.assert_allclose(tr.jerk[5:-5], j_fd[5:-5], rtol=1e-4, atol=1e-5)
    helix = fr.simulate([fr.Segment(2000.0, 0.004, 0.003)], 0.5, v0=(30.0, 0, 0))
    res = fr.turn_model_residual(helix.v, helix.a, helix.jerk)
    np.testing.assert_allclose(res, 30.0**3 * 0.004 * 0.003 * helix.frame[:, 2], atol=1e-12)
    planar = fr.simulate([fr.Segment(2000.0, 0.004)], 0.5, v0=(30.0, 0, 0), up=(0, 1, 1))
    assert np.abs(fr.turn_model_residual(planar.v, planar.a, planar.jerk)).max() < 1e-12


def test_segments_from_radii_and_labels():
    segs = fr.segments_from_radii([100, 0, -50], [10, 20, 30])
    assert [s.kappa for s in segs] == [0.01, 0.0, -0.02] and [s.turning for s in segs] == [True, False, True]
    tr = fr.simulate(segs, 1.0)
    np.testing.assert_array_equal(tr.turning, tr.kappa != 0)
    np.testing.assert_array_equal(tr.segment, np.r_[[0] * 10, [1] * 20, [2] * 31])


def test_bad_inputs_name_the_argument():
    with pytest.raises(ValueError, match="length"):
        fr.Segment(-1.0)
    with pytest.raises(ValueError, match="kappa"):
        fr.Segment(1.0, np.inf)
    with pytest.raises(ValueError, match="dt"):
        fr.simulate([fr.Segment(1.0)], 0.0)
    with pytest.raises(ValueError, match="decelerates"):
        fr.simulate([fr.Segment(100.0, accel=-1.0)], 1.0, v0=(1, 0, 0))
    with pytest.raises(ValueError, match="up"):
        fr.initial_frame((0, 0, 5.0))
    with pytest.raises(ValueError, match="v0"):
        fr.initial_frame((0, 0, 0))
    with pytest.raises(TypeError, match="segments"):
        fr.simulate([(1.0, 0.0)], 1.0)
    with pytest.raises(ValueError, match="v must have shape"):
        fr.curvature_torsion(np.ones(2), np.ones(3))
    with pytest.raises(ValueError, match="accel"):
        fr.simulate_euler([fr.Segment(1.0, accel=1.0)], 0.1)
    with pytest.raises(ValueError, match="radii"):
        fr.segments_from_radii([1, 2], [1])
    with pytest.raises(ValueError, match="v must be non-zero"):
        fr.curvature_torsion(np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match="t must be strictly increasing"):
        fr.curvature_torsion_from_samples(np.array([0, 1, 1, 2, 3.0]), np.ones((5, 3)))
    with pytest.raises(ValueError, match="frame0's tangent"):
        fr.simulate([fr.Segment(10.0)], 1.0, v0=(0, 1, 0), frame0=np.eye(3))
    with pytest.raises(ValueError, match="frame0 must be a right-handed"):
        fr.simulate([fr.Segment(10.0)], 1.0, frame0=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="n_max"):
        fr.simulate([fr.Segment(10.0)], 1.0, n_max=0)
    with pytest.raises(ValueError, match="r0"):
        fr.simulate([fr.Segment(10.0)], 1.0, r0=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="ds"):
        fr.simulate_euler([fr.Segment(1.0)], [0.1, 0.2])
    with pytest.raises(ValueError, match="ds"):
        fr.circle_closure(1.0, 0.0)
    E = fr.initial_frame((0.0, 0.0, 5.0), up=(1.0, 0.0, 0.0))  # vertical start: frame0 needs no `up`
    assert fr.simulate([fr.Segment(10.0, 0.1)], 1.0, v0=(0.0, 0.0, 5.0), frame0=E).r.shape == (3, 3)


def test_euler_endpoint_error_is_first_order_on_an_arc():
    # one arc of 1 rad (study 000's demo 1): error = (ds/2)|t(L) - t(0)| + O(ds^2), with the
    # O(ds^2) part at most ds^2 (kappa^3 L^2 / 6 + kappa |n(L) - n(0)| / 24) (heading deficit
    # (kappa ds)^3 / 3 per step, accumulated; midpoint-rule remainder)
    segs = fr.segments_from_radii([100.0], [100.0])
    kappa, L = 0.01, 100.0
    for ds in (2.0, 1.0, 0.5, 0.25):
        err, lead = fr.euler_endpoint_error(segs, ds)
        assert lead == pytest.approx(ds * np.sin(kappa * L / 2), rel=1e-12)
        assert abs(err - lead) <= ds**2 * (kappa**3 * L**2 / 6 + kappa * 2 * np.sin(kappa * L / 2) / 24)


def test_euler_endpoint_error_checks_ds():
    with pytest.raises(ValueError, match="ds"):
        fr.euler_endpoint_error(fr.segments_from_radii([100.0], [100.0]), -1.0)


def test_simulate_refuses_dt_longer_than_a_segment():
    from kftrack import frenet as fr_

    segs = [fr_.Segment(100.0, 0.0, 0.0), fr_.Segment(20.0, 0.01, 0.0), fr_.Segment(100.0, 0.0, 0.0)]
    # at 10 m/s the middle segment lasts 2 s: dt = 2 samples it, dt = 2.5 could skip it
    assert len(fr_.simulate(segs, 2.0, v0=(10.0, 0.0, 0.0)).t) == 12
    with pytest.raises(ValueError, match=r"dt must be at most the duration of every segment.*dt = 2.5 s.*segment 1 lasts 2 s"):
        fr_.simulate(segs, 2.5, v0=(10.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="dt must be at most"):  # dt longer than the whole track: one sample
        fr_.simulate([fr_.Segment(10.0, 0.0, 0.0)], 30.0)
