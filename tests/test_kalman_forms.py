"""Tests of the ``form`` keyword of kftrack.kalman.update ("joseph" | "standard")."""
from __future__ import annotations

import numpy as np
import pytest
import sympy as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from kftrack import kalman


def _spd(rng, n):
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 5), m=st.integers(1, 3))
def test_forms_agree_for_well_conditioned_problems(seed, n, m):
    rng = np.random.default_rng(seed)
    x, P, z = rng.normal(size=n), _spd(rng, n), rng.normal(size=m)
    H, R = rng.normal(size=(m, n)), _spd(rng, m)
    uj = kalman.update(x, P, z, H, R)
    us = kalman.update(x, P, z, H, R, form="standard")
    # error bound: both forms carry the gain's round-off, relative size ~ n cond(S) eps; the short
    # form's error is first order in it, times |K H P| <= cond(P) |P|; 10x safety for the constants
    eps = np.finfo(float).eps
    S = H @ P @ H.T + R
    tol = 10 * (n + m) * np.linalg.cond(S) * np.linalg.cond(P) * eps
    assert np.max(np.abs(uj.P - us.P)) <= tol * np.abs(P).max()
    for a, b in zip(uj[:2] + uj[2:], us[:2] + us[2:]):
        if a is not uj.P:  # x, y, S, K, nis, loglik do not depend on the form (same formulas)
            np.testing.assert_allclose(a, b, rtol=tol, atol=tol * max(1.0, float(np.max(np.abs(a)))))


def test_default_is_joseph_and_standard_is_the_short_form_as_computed():
    rng = np.random.default_rng(3)
    n, m = 4, 2
    x, P, z, H, R = rng.normal(size=n), _spd(rng, n), rng.normal(size=m), rng.normal(size=(m, n)), _spd(rng, m)
    default = kalman.update(x, P, z, H, R)
    joseph = kalman.update(x, P, z, H, R, form="joseph")
    np.testing.assert_array_equal(default.P, joseph.P)
    std = kalman.update(x, P, z, H, R, form="standard")
    np.testing.assert_array_equal(std.P, (np.eye(n) - std.K @ H) @ P)


def test_batch_broadcasting_with_standard_form():
    rng = np.random.default_rng(4)
    x = rng.normal(size=(5, 3))
    P = np.stack([_spd(rng, 3) for _ in range(5)])
    z = rng.normal(size=(5, 1))
    H, R = np.array([[1.0, 0.0, 0.0]]), np.array([[0.5]])
    out = kalman.update(x, P, z, H, R, form="standard")
    for i in range(5):
        one = kalman.update(x[i], P[i], z[i], H, R, form="standard")
        # batched and single matmuls may take different BLAS paths: a 3x3 product and subtraction
        # differ by at most ~ 3 * 3 eps relative to |P| (cond(P) enters through (I - KH) P)
        tol = 9 * np.linalg.cond(P[i]) * np.finfo(float).eps
        assert np.max(np.abs(out.P[i] - one.P)) <= tol * np.abs(one.P).max()


def test_round_off_short_form_loses_definiteness_joseph_does_not():
    """Two nearly parallel precise sensors (chapter 2): exact rational reference from SymPy."""
    p0, delta, r = 10**6, sp.Rational(1, 10**5), sp.Rational(1, 10**11)
    Hs = sp.Matrix([[1, 0], [1, delta]])
    Ps, Rs = p0 * sp.eye(2), r * sp.eye(2)
    Ks = Ps * Hs.T * (Hs * Ps * Hs.T + Rs).inv()
    exact = np.array(((sp.eye(2) - Ks * Hs) * Ps).evalf(30).tolist(), dtype=float)
    H, R = np.array(Hs.evalf().tolist(), dtype=float), float(r) * np.eye(2)
    P = float(p0) * np.eye(2)
    joseph = kalman.update(np.zeros(2), P, np.zeros(2), H, R).P
    short = kalman.update(np.zeros(2), P, np.zeros(2), H, R, form="standard").P
    # Joseph: the gain's relative round-off ~ cond(S) eps enters at second order; entrywise bound
    # 4 cond(S) eps (2x2 solve), about 4e-5 here. The short form is 100 % wrong.
    tol = 4 * np.linalg.cond(H @ P @ H.T + R) * np.finfo(float).eps
    assert np.all(np.abs(joseph - exact) <= tol * np.abs(exact))
    assert np.linalg.eigvalsh(joseph)[0] > 0
    assert np.linalg.eigvalsh(0.5 * (short + short.T))[0] < 0


def test_short_form_is_not_symmetrized():
    p0, delta, r = 1e6, 1e-5, 1e-8
    H = np.array([[1.0, 0.0], [1.0, delta]])
    short = kalman.update(np.zeros(2), p0 * np.eye(2), np.zeros(2), H, r * np.eye(2), form="standard").P
    joseph = kalman.update(np.zeros(2), p0 * np.eye(2), np.zeros(2), H, r * np.eye(2)).P
    assert np.abs(short - short.T).max() > 1e-3 * np.abs(short[0, 1])
    np.testing.assert_array_equal(joseph, joseph.T)


@pytest.mark.parametrize("form", ["Joseph", "short", "", None, 1])
def test_bad_form_names_the_argument(form):
    with pytest.raises(ValueError, match=r"form must be one of \('joseph', 'standard'\)"):
        kalman.update(np.zeros(2), np.eye(2), np.zeros(1), np.array([[1.0, 0.0]]), np.eye(1), form=form)


def test_form_is_keyword_only():
    with pytest.raises(TypeError):
        kalman.update(np.zeros(1), np.eye(1), np.zeros(1), np.eye(1), np.eye(1), "standard")
