"""Closed forms written out again from the literature, for the tests to compare against.

Each takes the exponential (or sine/cosine) it needs, so the same formula serves SymPy
(exact algebra) and mpmath (high-precision numbers).
"""


def singer(T, a, exp):
    """Singer (1970) F (3x3 nested list) and Q/q (dict of the upper triangle); Stone Soup's
    docstring and stonesoup_models.md 1.2 give the same."""
    e, e2 = exp(-a * T), exp(-2 * a * T)
    F = [[1, T, (a * T - 1 + e) / a**2], [0, 1, (1 - e) / a], [0, 0, e]]
    Q = {
        (0, 0): ((1 - e2) + 2 * a * T + 2 * a**3 * T**3 / 3 - 2 * a**2 * T**2 - 4 * a * T * e) / (2 * a**5),
        (0, 1): (a * T - (1 - e)) ** 2 / (2 * a**4),
        (0, 2): ((1 - e2) - 2 * a * T * e) / (2 * a**3),
        (1, 1): (2 * a * T - 4 * (1 - e) + (1 - e2)) / (2 * a**3),
        (1, 2): (1 - e) ** 2 / (2 * a**2),
        (2, 2): (1 - e2) / (2 * a),
    }
    return F, Q


def known_turn(T, w, sin, cos):
    """Known-rate turn, state [x, vx, y, vy]: F (4x4 nested list) and the exact continuous
    white-noise Q/q (4x4 nested list), Li & Jilkov (2003)."""
    s, c = sin(w * T), cos(w * T)
    F = [[1, s / w, 0, -(1 - c) / w], [0, c, 0, -s], [0, (1 - c) / w, 1, s / w], [0, s, 0, c]]
    q11, q12, q14 = 2 * (w * T - s) / w**3, (1 - c) / w**2, (w * T - s) / w**2
    Q = [[q11, q12, 0, q14], [q12, T, -q14, 0], [0, -q14, q11, q12], [q14, 0, q12, T]]
    return F, Q


# --- tolerances derived from error bounds ---------------------------------------------------------

EPS = 2.0**-52  # float64 machine epsilon (unit round-off u = EPS / 2)


def roundoff_tol(A, n, cond=1.0, c=10.0):
    """Normwise round-off bound ``c * n * cond * eps * max|A|`` for two computations of one quantity.

    Derivation (Higham 2002, ch. 3 and 7): a length-n inner product, or a sum of n terms, computed
    in floating point has absolute error <= gamma_n sum|terms| ~ n u max|A| (u = eps / 2) for
    products of matrices of norm ~ |A|; a solve with a matrix of condition number ``cond`` (in the
    2-norm) amplifies the relative backward error to a forward error <= cond * n * eps to first
    order. Two codes each within the bound differ by at most twice it; ``c`` (10 unless the caller
    derives another) covers that factor 2 and the few such operations chained in one filter step.
    The bound is normwise (scaled by the largest entry), not entrywise: a small entry that arises
    by cancellation carries the absolute error of the large ones.
    """
    import numpy as np

    return c * n * cond * EPS * float(np.max(np.abs(A)))


def scaled_cond(S):
    """Condition number of ``D^{-1/2} S D^{-1/2}``, ``D = diag(S)``, for a symmetric positive definite S.

    A Cholesky factorization and solve is invariant to diagonal scaling (van der Sluis 1969;
    Demmel 1989; Higham 2002, Thm 10.7): its forward error is bounded by this condition number,
    not by cond(S), which mixed units (metres and radians) inflate without any loss of accuracy.
    """
    import numpy as np

    d = np.sqrt(np.diagonal(S, axis1=-2, axis2=-1))
    return np.linalg.cond(S / (d[..., :, None] * d[..., None, :]))
