r"""Symbolic derivations of motion models (SymPy) and the code generated from them.

The functions here return SymPy objects, so a chapter can ``display`` the derivation, and
:class:`GeneratedFunction` turns an expression into a fast NumPy function once (with
``sympy.lambdify(..., cse=True)``), with a Taylor-series branch at a removable singularity
(turn rate :math:`\omega \to 0`, Singer's :math:`\alpha T \to 0`).

Continuous-time linear model, per Bar-Shalom, Li & Kirubarajan (2001, ch. 6) and Van Loan (1978):

.. math::

    \dot x = A x + G w(t), \qquad E[w(t) w(s)^\top] = Q_c\,\delta(t - s),

    F(T) = e^{A T}, \qquad Q(T) = \int_0^T e^{A\tau} G Q_c G^\top e^{A^\top \tau}\, d\tau .

The direct-discrete alternative holds a white sequence :math:`v_k \sim N(0, \sigma^2)` constant
over each interval: :math:`x_{k+1} = F x_k + \Gamma v_k`, :math:`Q = \Gamma \sigma^2 \Gamma^\top`.

State order is interleaved by axis, ``[x, vx, y, vy, z, vz]``, the turn rate last.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import sympy as sp

__all__ = [
    "T", "tau", "omega", "alpha",
    "kinematic_A", "singer_A", "turn_A", "white_noise_gain",
    "transition_matrix", "continuous_white_noise", "kinematic_discrete_gain", "discrete_white_noise",
    "piecewise_constant_gain",
    "taylor_transition", "coordinated_turn_state", "coordinated_turn_transition",
    "polar_turn_state", "polar_turn_transition", "jacobian", "series_branch", "GeneratedFunction",
]

#: The sampling interval (s). Signed: ``F(-T)`` is the inverse of ``F(T)``.
T = sp.Symbol("T", real=True)
#: Integration variable of the noise integral (s).
tau = sp.Symbol("tau", real=True)
#: Turn rate (rad/s), counter-clockwise positive. Declared non-zero so that SymPy returns the
#: generic formula; the value at zero is the series branch of :class:`GeneratedFunction`.
omega = sp.Symbol("omega", real=True, nonzero=True)
#: Singer's manoeuvre-correlation rate :math:`\alpha = 1/\tau_m` (1/s).
alpha = sp.Symbol("alpha", positive=True)


# --------------------------------------------------------------------------------------------
# continuous-time models (per axis, or the planar turn)
# --------------------------------------------------------------------------------------------
def kinematic_A(order: int) -> sp.Matrix:
    r"""Chain of integrators for one axis: ``order=1`` constant velocity ``[p, v]``,
    ``order=2`` constant acceleration ``[p, v, a]``. The white noise drives the last state.

    Examples
    --------
    >>> from kftrack.symbolic import kinematic_A
    >>> kinematic_A(1)                                # [p, v]: p' = v, v' = w
    Matrix([
    [0, 1],
    [0, 0]])
    """
    if order not in (1, 2):
        raise ValueError(f"order must be 1 (constant velocity) or 2 (constant acceleration), got {order!r}")
    n = order + 1
    return sp.Matrix(n, n, lambda i, j: 1 if j == i + 1 else 0)


def singer_A(a: sp.Expr = alpha) -> sp.Matrix:
    r"""Singer (1970) model for one axis, state ``[p, v, a]``: :math:`\dot a = -\alpha a + w`."""
    return sp.Matrix([[0, 1, 0], [0, 0, 1], [0, 0, -a]])


def turn_A(w: sp.Expr = omega) -> sp.Matrix:
    r"""Planar coordinated turn with known rate :math:`\omega`, state ``[x, vx, y, vy]``:
    :math:`\ddot x = -\omega \dot y`, :math:`\ddot y = \omega \dot x` (counter-clockwise positive)."""
    return sp.Matrix([[0, 1, 0, 0], [0, 0, 0, -w], [0, 0, 0, 1], [0, w, 0, 0]])


def white_noise_gain(n: int, rows: Sequence[int]) -> sp.Matrix:
    """Gain ``G`` (n × len(rows)) with a one in each listed row: the states the white noise drives."""
    G = sp.zeros(n, len(rows))
    for col, row in enumerate(rows):
        G[row, col] = 1
    return G


# --------------------------------------------------------------------------------------------
# discretization
# --------------------------------------------------------------------------------------------
def _simplify(M: sp.Matrix) -> sp.Matrix:
    """Simplify entrywise; exponentials are then expanded back into sums of decaying terms, so
    that no ``exp(+alpha T)`` factor overflows in the generated code."""

    def one(e):
        e = sp.simplify(sp.expand(e))
        return sp.expand(e) if e.has(sp.exp) else e

    return M.applyfunc(one)


def transition_matrix(A: sp.Matrix, t: sp.Expr = T) -> sp.Matrix:
    r"""The exact transition matrix :math:`F(t) = e^{A t}` (SymPy's matrix exponential).

    Examples
    --------
    >>> from kftrack.symbolic import kinematic_A, transition_matrix
    >>> transition_matrix(kinematic_A(1))             # exp(A T)
    Matrix([
    [1, T],
    [0, 1]])
    """
    return _simplify((A * t).exp())


def continuous_white_noise(A: sp.Matrix, G: sp.Matrix, Qc: sp.Matrix, t: sp.Expr = T) -> sp.Matrix:
    r"""Process noise of continuous white noise,
    :math:`Q(t) = \int_0^t e^{A\tau} G Q_c G^\top e^{A^\top\tau} d\tau` (Bar-Shalom et al. 2001, ch. 4 and 6).

    ``Qc`` holds the power spectral densities (e.g. m²/s³ for white acceleration).

    Examples
    --------
    >>> import sympy as sp
    >>> from kftrack.symbolic import continuous_white_noise, kinematic_A
    >>> q = sp.Symbol("q", positive=True)
    >>> continuous_white_noise(kinematic_A(1), sp.Matrix([0, 1]), sp.Matrix([[q]]))
    Matrix([
    [T**3*q/3, T**2*q/2],
    [T**2*q/2,      T*q]])
    """
    Ft = transition_matrix(A, tau)
    integrand = Ft * G * Qc * G.T * Ft.T
    Q = integrand.applyfunc(lambda e: sp.integrate(sp.expand(sp.trigsimp(e)), (tau, 0, t)))
    return _simplify(Q)


def piecewise_constant_gain(A: sp.Matrix, G: sp.Matrix, t: sp.Expr = T) -> sp.Matrix:
    r"""Gain :math:`\Gamma = \int_0^t e^{A\tau} d\tau\, G` of a noise held constant over the interval
    (the direct-discrete model); for constant velocity :math:`\Gamma = [T^2/2, T]^\top`."""
    Ft = transition_matrix(A, tau)
    return _simplify((Ft * G).applyfunc(lambda e: sp.integrate(e, (tau, 0, t))))


def kinematic_discrete_gain(order: int) -> sp.Matrix:
    r"""Gain of the direct-discrete kinematic models (Bar-Shalom et al. 2001, ch. 6):
    ``order=1`` DWNA, :math:`\Gamma = [T^2/2, T]^\top` (the noise is the acceleration held over
    the interval); ``order=2`` DWPA, :math:`\Gamma = [T^2/2, T, 1]^\top` (the noise is the
    acceleration increment over the interval)."""
    if order not in (1, 2):
        raise ValueError(f"order must be 1 (constant velocity) or 2 (constant acceleration), got {order!r}")
    return sp.Matrix([T ** (2 - i) / sp.factorial(2 - i) for i in range(order + 1)])


def discrete_white_noise(Gamma: sp.Matrix, sigma2: sp.Matrix | sp.Expr) -> sp.Matrix:
    r"""Direct-discrete process noise :math:`Q = \Gamma \sigma^2 \Gamma^\top`; ``sigma2`` holds the
    variances of the piecewise-constant noise (e.g. m²/s⁴ for acceleration). Rank ≤ columns of Γ."""
    S = sigma2 if isinstance(sigma2, sp.MatrixBase) else sigma2 * sp.eye(Gamma.shape[1])
    return _simplify(Gamma * S * Gamma.T)


def taylor_transition(A: sp.Matrix, order: int = 2, t: sp.Expr = T) -> sp.Matrix:
    r"""Truncated Taylor discretization :math:`\sum_{k\le \text{order}} (A t)^k / k!`
    (seed 001 uses order 2); exact only when :math:`A^{\text{order}+1} = 0`."""
    M = sp.eye(A.shape[0])
    term = sp.eye(A.shape[0])
    for k in range(1, order + 1):
        term = term * A * t / k
        M = M + term
    return sp.expand(M)


# --------------------------------------------------------------------------------------------
# nonlinear turn models
# --------------------------------------------------------------------------------------------
def coordinated_turn_state(ndim: int = 2) -> sp.Matrix:
    """State symbols of the coordinated turn with the rate in the state:
    ``[x, vx, y, vy, omega]`` (2-D) or ``[x, vx, y, vy, z, vz, omega]`` (3-D)."""
    names = {2: "x vx y vy", 3: "x vx y vy z vz"}
    if ndim not in names:
        raise ValueError(f"ndim must be 2 or 3 for a coordinated turn, got {ndim!r}")
    return sp.Matrix([*sp.symbols(names[ndim], real=True), omega])


def coordinated_turn_transition(ndim: int = 2) -> tuple[sp.Matrix, sp.Matrix]:
    r"""The coordinated-turn map :math:`x_{k+1} = f(x_k)` with the turn rate in the state
    (Li & Jilkov 2003; Bar-Shalom et al. 2001, §11.7): the horizontal part is
    :math:`F_{CT}(\omega) [x, v_x, y, v_y]^\top`, the vertical axis (3-D) moves at constant
    velocity, :math:`\omega` is constant. Returns ``(state, f)``."""
    s = coordinated_turn_state(ndim)
    F = transition_matrix(turn_A(omega))
    horiz = F * s[:4, 0]
    rest = [s[4] + T * s[5], s[5]] if ndim == 3 else []
    return s, sp.Matrix([*horiz, *rest, omega])


def polar_turn_state() -> sp.Matrix:
    """State ``[x, y, v, chi, omega]``: position, speed, heading chi (rad from +x, counter-clockwise), turn rate."""
    return sp.Matrix([*sp.symbols("x y v chi", real=True), omega])


def polar_turn_transition() -> tuple[sp.Matrix, sp.Matrix]:
    r"""Coordinated turn in polar-velocity form, exact for a constant turn rate:
    :math:`x^+ = x + \frac{2v}{\omega}\sin\frac{\omega T}{2}\cos(\chi + \frac{\omega T}{2})`, same with sin
    for :math:`y`, :math:`v^+ = v`, :math:`\chi^+ = \chi + \omega T` (heading :math:`\chi`, as in
    chapters 6 and 12). Returns ``(state, f)``."""
    s = polar_turn_state()
    x, y, v, chi, w = s
    chord = 2 * v / w * sp.sin(w * T / 2)
    f = sp.Matrix([x + chord * sp.cos(chi + w * T / 2), y + chord * sp.sin(chi + w * T / 2), v, chi + w * T, w])
    return s, f


def jacobian(f: sp.Matrix, x: sp.Matrix) -> sp.Matrix:
    r"""Jacobian :math:`\partial f / \partial x` of a vector function, simplified.

    Examples
    --------
    >>> import sympy as sp
    >>> from kftrack.symbolic import jacobian
    >>> x, v = sp.symbols("x v")
    >>> jacobian(sp.Matrix([x**2, sp.sin(v)]), sp.Matrix([x, v]))
    Matrix([
    [2*x,      0],
    [  0, cos(v)]])
    """
    return _simplify(f.jacobian(x))


# --------------------------------------------------------------------------------------------
# code generation with a series branch
# --------------------------------------------------------------------------------------------
def _power_of(term: sp.Expr, var: sp.Symbol) -> int:
    """Exponent of ``var`` in a product term (negative for a division)."""
    return int(term.as_coeff_exponent(var)[1])


def series_branch(expr: sp.Matrix, var: sp.Symbol, order: int) -> sp.Matrix:
    """Taylor polynomial of every entry of ``expr`` in ``var`` about 0, up to (excluding) ``var**order``.

    Works for entries that are rational in ``var`` and in ``exp``, ``sin``, ``cos`` of multiples of
    it (every model here): each transcendental factor is replaced by a Taylor polynomial long enough
    to cover the largest negative power of ``var``, the result is expanded, and the negative
    powers, which cancel exactly at a removable singularity, are checked to be gone. This is the
    same polynomial as ``sympy.series`` but much faster.
    """

    def one(e: sp.Expr) -> sp.Expr:
        e = sp.expand_trig(e)  # sin(h + w T) -> sin h cos wT + cos h sin wT
        for f in e.atoms(sp.exp, sp.sin, sp.cos):
            if f.has(var) and sp.simplify(f.args[0] / var).has(var):
                raise ValueError(f"series_branch needs arguments proportional to {var}, got {f}")
        neg = max([0] + [-_power_of(t, var) for t in sp.Add.make_args(sp.expand(e))])
        n = order + neg + 2

        def taylor(f):
            u = f.args[0]
            if f.func is sp.exp:
                return sp.Add(*[u**k / sp.factorial(k) for k in range(n)])
            start = 1 if f.func is sp.sin else 0
            return sp.Add(*[(-1) ** k * u ** (2 * k + start) / sp.factorial(2 * k + start) for k in range(n // 2 + 1)])

        poly = sp.expand(e.replace(lambda f: f.func in (sp.exp, sp.sin, sp.cos) and f.has(var), taylor))
        kept, low = [], []
        for t in sp.Add.make_args(poly):
            k = _power_of(t, var)
            (low if k < 0 else kept if k < order else []).append(t)
        if sp.simplify(sp.Add(*low)) != 0:
            raise ValueError(f"expr is singular in {var} at 0 (not a removable singularity): {e}")
        return sp.Add(*kept)

    return expr.applyfunc(one)


class GeneratedFunction:
    r"""A NumPy function generated once from a SymPy matrix, broadcasting over its arguments.

    Parameters
    ----------
    args : sequence of SymPy symbols, the positional arguments of the numeric function.
    expr : SymPy Matrix, shape ``(r, c)``; the result has shape ``(..., r, c)`` where ``...`` is
        the broadcast shape of the arguments.
    singular : optional ``(var, scale, threshold, order)``. Where ``|scale| < threshold``
        (``scale`` a SymPy expression of the arguments, e.g. :math:`\omega T`), the Taylor
        polynomial of ``expr`` in ``var`` to ``var**order`` (excluded) is used instead of the
        closed form, which cancels catastrophically (or divides 0 by 0) near ``var = 0``.
    """

    def __init__(self, args: Sequence[sp.Symbol], expr: sp.Matrix,
                 singular: tuple[sp.Symbol, sp.Expr, float, int] | None = None):
        self.args = tuple(args)
        self.expr = sp.Matrix(expr)
        self.shape = self.expr.shape
        self._exact = sp.lambdify(self.args, list(self.expr), modules="numpy", cse=True)
        self._series = self._scale = None
        self.threshold = None
        if singular is not None:
            var, scale, threshold, order = singular
            self.series_expr = series_branch(self.expr, var, order)
            self._series = sp.lambdify(self.args, list(self.series_expr), modules="numpy", cse=True)
            self._scale = sp.lambdify(self.args, scale, modules="numpy")
            self.threshold = float(threshold)

    def _eval(self, fn, vals, shape):
        entries = fn(*vals)
        flat = np.stack([np.broadcast_to(np.asarray(e, dtype=float), shape) for e in entries], axis=-1)
        return flat.reshape(shape + self.shape)

    def exact(self, *vals) -> np.ndarray:
        """The closed form only (no series branch); NaN or inaccurate at the singular point."""
        vals = [np.asarray(v, dtype=float) for v in vals]
        return self._eval(self._exact, vals, np.broadcast_shapes(*(v.shape for v in vals)))

    def series(self, *vals) -> np.ndarray:
        """The Taylor branch only (accurate for ``|scale|`` below the threshold)."""
        vals = [np.asarray(v, dtype=float) for v in vals]
        return self._eval(self._series, vals, np.broadcast_shapes(*(v.shape for v in vals)))

    def __call__(self, *vals) -> np.ndarray:
        vals = [np.asarray(v, dtype=float) for v in vals]
        shape = np.broadcast_shapes(*(v.shape for v in vals))
        if self._series is None:
            return self._eval(self._exact, vals, shape)
        small = np.broadcast_to(np.abs(np.asarray(self._scale(*vals), dtype=float)) < self.threshold, shape)
        if not small.any():
            return self._eval(self._exact, vals, shape)
        near = self._eval(self._series, vals, shape)
        if small.all():
            return near
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            far = self._eval(self._exact, vals, shape)
        return np.where(small[(...,) + (None,) * len(self.shape)], near, far)
