"""Tests of kftrack.symbolic: every derivation against the closed form written out again here
(Bar-Shalom et al. 2001; Singer 1970; Li & Jilkov 2003; seed 000 eqs. 59-62), the singular
limits with sympy.limit, the fast series against sympy.series, and the generated functions
against high-precision evaluation at the series switch."""
from __future__ import annotations

import numpy as np
import pytest
import sympy as sp

from kftrack import symbolic as S

import closed_forms

T, w, a = S.T, S.omega, S.alpha
EPS = np.finfo(float).eps


def zero(M) -> bool:
    return all(sp.simplify(e) == 0 for e in sp.Matrix(M))


def test_kinematic_transition_and_noise_closed_forms():
    F1 = S.transition_matrix(S.kinematic_A(1))
    assert F1 == sp.Matrix([[1, T], [0, 1]])
    Q1 = S.continuous_white_noise(S.kinematic_A(1), S.white_noise_gain(2, [1]), sp.Matrix([[1]]))
    assert zero(Q1 - sp.Matrix([[T**3 / 3, T**2 / 2], [T**2 / 2, T]]))
    F2 = S.transition_matrix(S.kinematic_A(2))
    assert F2 == sp.Matrix([[1, T, T**2 / 2], [0, 1, T], [0, 0, 1]])
    Q2 = S.continuous_white_noise(S.kinematic_A(2), S.white_noise_gain(3, [2]), sp.Matrix([[1]]))
    cwpa = sp.Matrix([[T**5 / 20, T**4 / 8, T**3 / 6], [T**4 / 8, T**3 / 3, T**2 / 2], [T**3 / 6, T**2 / 2, T]])
    assert zero(Q2 - cwpa)


def test_discrete_gains():
    # the direct-discrete gain of CV is the integral of e^{A tau} G; CA's (DWPA) is [T^2/2, T, 1]
    G = S.piecewise_constant_gain(S.kinematic_A(1), S.white_noise_gain(2, [1]))
    assert zero(G - S.kinematic_discrete_gain(1))
    assert S.kinematic_discrete_gain(2) == sp.Matrix([T**2 / 2, T, 1])
    Q = S.discrete_white_noise(S.kinematic_discrete_gain(1), 1)
    assert zero(Q - sp.Matrix([[T**4 / 4, T**3 / 2], [T**3 / 2, T**2]]))
    assert Q.rank() == 1
    with pytest.raises(ValueError, match="order"):
        S.kinematic_discrete_gain(3)
    with pytest.raises(ValueError, match="order"):
        S.kinematic_A(0)


def test_singer_closed_forms_and_limit():
    A = S.singer_A()
    F = S.transition_matrix(A)
    F_list, Q_ref = closed_forms.singer(T, a, sp.exp)
    assert zero(F - sp.Matrix(F_list))
    Q = S.continuous_white_noise(A, S.white_noise_gain(3, [2]), sp.Matrix([[1]]))
    for (i, j), ref in Q_ref.items():
        assert sp.simplify(Q[i, j] - ref) == 0 and sp.simplify(Q[j, i] - ref) == 0
    # alpha -> 0: constant acceleration
    assert zero(F.applyfunc(lambda v: sp.limit(v, a, 0)) - S.transition_matrix(S.kinematic_A(2)))
    assert sp.limit(Q[0, 0], a, 0) == T**5 / 20


def test_turn_closed_forms():
    F = S.transition_matrix(S.turn_A())
    F_ref, Q_ref = closed_forms.known_turn(T, w, sp.sin, sp.cos)
    assert zero(F - sp.Matrix(F_ref))
    Q = S.continuous_white_noise(S.turn_A(), S.white_noise_gain(4, [1, 3]), sp.eye(2))
    assert zero(Q - sp.Matrix(Q_ref))
    cwna = sp.Matrix([[T**3 / 3, T**2 / 2], [T**2 / 2, T]])
    assert zero(Q.applyfunc(lambda v: sp.limit(v, w, 0)) - sp.diag(cwna, cwna))


def test_coordinated_turn_jacobian_matches_seed000_and_limit():
    s, f = S.coordinated_turn_transition(2)
    J = S.jacobian(f, s)
    vx, vy = s[1], s[3]
    sn, c = sp.sin(w * T), sp.cos(w * T)
    d1 = c * T / w * vx - sn / w**2 * vx - sn * T / w * vy - (c - 1) / w**2 * vy  # seed 000, eq. 59
    d2 = -sn * T * vx - c * T * vy  # eq. 60
    d3 = sn * T / w * vx - (1 - c) / w**2 * vx + c * T / w * vy - sn / w**2 * vy  # eq. 61
    d4 = c * T * vx - sn * T * vy  # eq. 62
    assert zero(J[:4, 4] - sp.Matrix([d1, d2, d3, d4]))
    assert J[4, :] == sp.Matrix([[0, 0, 0, 0, 1]])
    limit = J[:4, 4].applyfunc(lambda v: sp.limit(v, w, 0))
    assert zero(limit - sp.Matrix([-T**2 * vy / 2, -T * vy, T**2 * vx / 2, T * vx]))
    s3, f3 = S.coordinated_turn_transition(3)
    assert zero(f3[[0, 1, 2, 3, 6], 0] - f.subs(dict(zip(s, s3[[0, 1, 2, 3, 6], 0]))))
    assert f3[4] == s3[4] + T * s3[5]
    with pytest.raises(ValueError, match="ndim"):
        S.coordinated_turn_state(1)


def test_jacobian_of_a_measurement_function():
    # range and bearing of a target at (x, y) seen from the origin: the textbook Jacobian
    x, y = sp.symbols("x y", real=True)
    r = sp.sqrt(x**2 + y**2)
    H = S.jacobian(sp.Matrix([r, sp.atan2(y, x)]), sp.Matrix([x, y]))
    assert zero(H - sp.Matrix([[x / r, y / r], [-y / r**2, x / r**2]]))


def test_polar_form_is_the_same_motion():
    s, f = S.coordinated_turn_transition(2)
    p, g = S.polar_turn_transition()
    x, vx, y, vy, _ = s
    v, h = p[2], p[3]
    sub = {x: p[0], y: p[1], vx: v * sp.cos(h), vy: v * sp.sin(h)}
    fc = f.subs(sub)
    assert sp.simplify(sp.expand_trig(fc[0] - g[0])) == 0
    assert sp.simplify(sp.expand_trig(fc[2] - g[1])) == 0
    assert sp.simplify(sp.expand_trig(fc[1] - g[2] * sp.cos(g[3]))) == 0
    assert sp.simplify(sp.expand_trig(fc[3] - g[2] * sp.sin(g[3]))) == 0


def test_taylor_transition():
    A = S.kinematic_A(1)
    assert S.taylor_transition(A) == S.transition_matrix(A)  # A^2 = 0: exact
    At = S.turn_A()
    err = S.transition_matrix(At) - S.taylor_transition(At, 2)
    lead = err.applyfunc(lambda v: sp.series(v, T, 0, 4).removeO())
    assert lead[0, 1] == -(w**2) * T**3 / 6  # third-order error


def test_series_branch_equals_sympy_series():
    Q = S.continuous_white_noise(S.singer_A(), S.white_noise_gain(3, [2]), sp.Matrix([[1]]))
    fast = S.series_branch(Q, a, 8)
    slow = Q.applyfunc(lambda v: sp.series(v, a, 0, 8).removeO())
    assert zero(fast - slow)
    _, f = S.polar_turn_transition()
    fast = S.series_branch(f, w, 6)
    slow = f.applyfunc(lambda v: sp.series(v, w, 0, 6).removeO())
    assert zero(fast - slow)
    with pytest.raises(ValueError, match="singular"):
        S.series_branch(sp.Matrix([1 / w + sp.sin(w)]), w, 4)
    with pytest.raises(ValueError, match="proportional"):
        S.series_branch(sp.Matrix([sp.sin(w**2 + 1) / w]), w, 4)


def test_generated_function_broadcasts_and_switches():
    Q = S.continuous_white_noise(S.turn_A(), S.white_noise_gain(4, [1, 3]), sp.eye(2))
    thr = 0.5
    g = S.GeneratedFunction([T, w], Q, (w, w * T, thr, 20))
    dts = np.array([[0.5], [2.0]])
    ws = np.array([0.0, 0.1, 0.3, 2.0])
    out = g(dts, ws)
    assert out.shape == (2, 4, 4, 4)
    for i, dt in enumerate(dts[:, 0]):
        for j, wj in enumerate(ws):
            assert np.array_equal(out[i, j], g(dt, wj))
    # at omega = 0 the series is exact: the constant-velocity noise
    cwna = np.array([[8 / 3, 2.0], [2.0, 2.0]])
    assert np.allclose(g(2.0, 0.0)[:2, :2], cwna, rtol=2 * EPS, atol=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        assert np.isnan(g.exact(2.0, 0.0)).any()  # the closed form alone is 0/0
    # both branches at the switch against a 40-digit evaluation. The closed form loses
    # about eps/(omega T)^2 relative in (omega T - sin omega T)/omega^3, i.e. 4 eps at 0.5.
    dt = 2.0
    wv = sp.Rational(1, 4)
    ref = np.array(Q.subs({T: 2, w: wv}).evalf(40), dtype=float)
    for branch in (g.exact, g.series):
        err = np.abs(branch(dt, float(wv)) - ref)
        assert np.all(err <= 16 * EPS * np.abs(ref) + 1e-300)
