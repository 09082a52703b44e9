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
