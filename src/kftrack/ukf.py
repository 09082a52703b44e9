r"""The unscented transform and the unscented Kalman filter (UKF), with angle-aware means.

A Gaussian :math:`N(x, P)` is represented by :math:`2n+1` sigma points

.. math::

    \mathcal X_0 = x, \quad \mathcal X_{i} = x + \left[\sqrt{c P}\right]_i,
    \quad \mathcal X_{n+i} = x - \left[\sqrt{c P}\right]_i, \qquad i = 1..n,

(:math:`[\sqrt{cP}]_i` the ``i``-th column of the lower Cholesky factor; for a singular
:math:`P`, of the symmetric square root of its eigendecomposition) with mean weights
:math:`W^m` and covariance weights :math:`W^c`. The points go through the nonlinear function
and the weighted moments of the images approximate the transformed mean and covariance:

.. math::

    \bar y = \sum_i W^m_i\, \mathcal Y_i, \qquad
    P_y = \sum_i W^c_i (\mathcal Y_i \ominus \bar y)(\mathcal Y_i \ominus \bar y)^\top .

Two weightings: the scaled points of Wan & van der Merwe (2000)
(:class:`MerweScaledSigmaPoints`, :math:`\lambda = \alpha^2 (n + \kappa) - n`, :math:`c = n + \lambda`)
and the original points of Julier & Uhlmann (1997, 2004) (:class:`JulierSigmaPoints`, :math:`c = n + \kappa`).

Angle components (``angle_components`` for a measurement, ``state_angles`` for the state) get
the circular mean :math:`\operatorname{atan2}(\sum W^m \sin, \sum W^m \cos)` and wrapped residuals.

Shapes follow :mod:`kftrack.kalman` (batch axes first, time first for sequences). The model
functions must broadcast: ``f`` maps ``(..., n)`` to ``(..., n)`` and ``h`` to ``(..., m)``; the
UKF calls them on a stack of sigma points ``(..., 2n+1, n)``.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ._validate import (as_matrix, as_vector, broadcast_batch, call_checked, check_angles, check_covariance,
                        check_sequence, check_state, stand_in)
from .kernels import Update
from .results import FilterResult
from .engines import Given, Kernel, run_filter
from .kernels import SigmaPoints, moments, mv, sigma_points, ukf_predict as _k_predict
from .kernels import ukf_update as _k_update
from .kernels import unscented as _k_unscented

__all__ = ["SigmaPoints", "MerweScaledSigmaPoints", "JulierSigmaPoints", "Transformed",
           "weighted_moments", "unscented_transform", "ukf_predict", "ukf_update", "unscented_kalman_filter"]

Vector = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class MerweScaledSigmaPoints:
    r"""Scaled sigma points (Wan & van der Merwe 2000; Julier 2002).

    :math:`\lambda = \alpha^2 (n + \kappa) - n`, spread :math:`c = n + \lambda`,
    :math:`W^m_0 = \lambda / c`, :math:`W^c_0 = \lambda / c + 1 - \alpha^2 + \beta`,
    :math:`W^m_i = W^c_i = 1 / (2c)`.

    Parameters
    ----------
    alpha : spread, ``0 < alpha <= 1`` typically. Small values (the often quoted 1e-3) put
        the points close to the mean, where they see only the local curvature, and make
        :math:`W_0` of order :math:`-1/\alpha^2`, so every covariance is a difference of large
        numbers. The default 1 samples the whole prior; which is better depends on the
        problem (chapter 8 of the book shows one case each way).
    beta : prior knowledge of the distribution; 2 is optimal for a Gaussian.
    kappa : secondary scaling, usually 0 (or ``3 - n``).
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0

    def __post_init__(self):
        if not (np.isfinite(self.alpha) and self.alpha > 0):
            raise ValueError(f"alpha must be a positive number, got {self.alpha!r}")
        if not np.isfinite(self.beta):
            raise ValueError(f"beta must be finite, got {self.beta!r}")
        if not np.isfinite(self.kappa):
            raise ValueError(f"kappa must be finite, got {self.kappa!r}")

    def weights(self, n: int) -> tuple[np.ndarray, np.ndarray, float]:
        """``(Wm, Wc, c)`` for dimension ``n``."""
        lam = self.alpha**2 * (n + self.kappa) - n
        c = n + lam
        if c <= 0:
            raise ValueError(f"alpha**2 * (n + kappa) must be positive, got {c!r} for n={n}")
        Wm = np.full(2 * n + 1, 0.5 / c)
        Wc = Wm.copy()
        Wm[0] = lam / c
        Wc[0] = lam / c + 1.0 - self.alpha**2 + self.beta
        return Wm, Wc, c

    def __call__(self, x, P) -> SigmaPoints:
        """Sigma points of :math:`N(x, P)`: ``x`` ``(..., n)``, ``P`` ``(..., n, n)`` positive semi-definite."""
        x, P, n = _check_points_input(x, P)
        Wm, Wc, c = self.weights(n)
        return sigma_points(x, P, c, Wm, Wc)


@dataclass(frozen=True)
class JulierSigmaPoints:
    r"""The original sigma points of Julier & Uhlmann (1997, 2004).

    Spread :math:`c = n + \kappa`, :math:`W_0 = \kappa / c`, :math:`W_i = 1 / (2c)`, the same
    weights for mean and covariance. ``kappa = 3 - n`` matches the fourth moment of a Gaussian
    in one dimension; ``kappa = 0`` drops the centre point.
    """

    kappa: float = 0.0

    def __post_init__(self):
        if not np.isfinite(self.kappa):
            raise ValueError(f"kappa must be finite, got {self.kappa!r}")

    def weights(self, n: int) -> tuple[np.ndarray, np.ndarray, float]:
        """``(Wm, Wc, c)`` for dimension ``n``."""
        c = n + self.kappa
        if c <= 0:
            raise ValueError(f"n + kappa must be positive, got {c!r} for n={n}")
        W = np.full(2 * n + 1, 0.5 / c)
        W[0] = self.kappa / c
        return W, W.copy(), c

    def __call__(self, x, P) -> SigmaPoints:
        """Sigma points of :math:`N(x, P)`: ``x`` ``(..., n)``, ``P`` ``(..., n, n)`` positive semi-definite."""
        x, P, n = _check_points_input(x, P)
        Wm, Wc, c = self.weights(n)
        return sigma_points(x, P, c, Wm, Wc)


Points = MerweScaledSigmaPoints | JulierSigmaPoints


def check_points(points) -> Points:
    """A sigma-point scheme (``None``: the default ``MerweScaledSigmaPoints()``), else a ``TypeError``
    naming ``points``."""
    if points is None:
        return MerweScaledSigmaPoints()
    if not isinstance(points, (MerweScaledSigmaPoints, JulierSigmaPoints)):
        raise TypeError(f"points must be MerweScaledSigmaPoints or JulierSigmaPoints, got {type(points).__name__}")
    return points


def _check_points_input(x, P):
    """A state and its covariance, positive semi-definite (``P = 0``, a known state, is allowed: the
    sigma points then use a square root of the eigendecomposition where Cholesky fails)."""
    return check_state(x, P)


def weighted_moments(Y, Wm, Wc, angle_components: Sequence[int] = ()) -> tuple[np.ndarray, np.ndarray]:
    r"""Weighted mean and covariance of transformed sigma points ``Y`` ``(..., 2n+1, d)``.

    The angle components get the circular mean and wrapped deviations. Returns
    ``(mean (..., d), cov (..., d, d))``.
    """
    Y = as_vector(Y, "Y")
    if Y.ndim < 2:
        raise ValueError(f"Y must have shape (..., 2n+1, d), got shape {Y.shape}")
    Wm = as_vector(Wm, "Wm", Y.shape[-2])
    Wc = as_vector(Wc, "Wc", Y.shape[-2])
    if Wm.ndim != 1 or Wc.ndim != 1:
        raise ValueError(f"Wm and Wc must be 1-D, got shapes {Wm.shape} and {Wc.shape}")
    y, C, _ = moments(Y, Wm, Wc, check_angles(angle_components, Y.shape[-1]))
    return y, C


class Transformed(NamedTuple):
    """An approximation of the distribution of ``fn(x)``: ``mean`` ``(..., d)``, ``cov`` ``(..., d, d)``,
    the cross-covariance ``cross`` ``(..., n, d)`` of ``x`` and ``fn(x)``, and the sigma points used."""

    mean: np.ndarray
    cov: np.ndarray
    cross: np.ndarray
    sigma: SigmaPoints


def unscented_transform(fn: Vector, x, P, points: Points | None = None,
                        angle_components: Sequence[int] = (), state_angles: Sequence[int] = ()) -> Transformed:
    r"""The unscented transform of :math:`N(x, P)` through ``fn``.

    Parameters
    ----------
    fn : callable ``(..., n) -> (..., d)``, broadcasting (it receives ``(..., 2n+1, n)``).
    x : (..., n) mean; ``P`` (..., n, n) covariance, positive semi-definite.
    points : :class:`MerweScaledSigmaPoints` (default, ``alpha=1, beta=2, kappa=0``) or
        :class:`JulierSigmaPoints`.
    angle_components : components of ``fn(x)`` that are angles (circular mean, wrapped spread).
    state_angles : components of ``x`` that are angles (wrapped in the cross-covariance).

    Returns
    -------
    Transformed
        ``(mean, cov, cross, sigma)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.ukf import unscented_transform
    >>> A = np.array([[1.0, 2.0], [0.0, 1.0]])
    >>> t = unscented_transform(lambda x: x @ A.T, np.array([1.0, 1.0]), np.eye(2))   # exact for a linear map
    >>> print(np.round(t.mean, 9) + 0.0, np.round(t.cov, 9).tolist())
    [3. 1.] [[5.0, 2.0], [2.0, 1.0]]
    >>> polar = lambda p: np.stack([np.hypot(p[..., 0], p[..., 1]), np.arctan2(p[..., 1], p[..., 0])], -1)
    >>> print(np.round(unscented_transform(polar, np.array([10.0, 0.0]), np.eye(2)).mean, 6) + 0.0)   # range > 10
    [10.049752  0.      ]
    """
    points = check_points(points)
    x, P, n = _check_points_input(x, P)
    sp = points(x, P)
    Y = call_checked(fn, sp.X, "fn", ())
    if Y.ndim < 2 or Y.shape[:-1] != sp.X.shape[:-1]:
        raise ValueError(f"fn must map sigma points {sp.X.shape} to shape {sp.X.shape[:-1]} + (d,), got {Y.shape}")
    return Transformed(*_k_unscented(fn, x, P, points, check_angles(state_angles, n, "state_angles"),
                                     check_angles(angle_components, Y.shape[-1])))


# --------------------------------------------------------------------------------------------
# the filter
# --------------------------------------------------------------------------------------------
def ukf_predict(x, P, f: Vector, Q, points: Points | None = None,
                state_angles: Sequence[int] = ()) -> tuple[np.ndarray, np.ndarray]:
    r"""UKF time update: the unscented transform of :math:`N(x, P)` through ``f``, plus ``Q``.

    Parameters
    ----------
    x, P : (..., n), (..., n, n) state mean and covariance (positive semi-definite).
    f : broadcasting transition function ``(..., n) -> (..., n)``.
    Q : (n, n) or (..., n, n) process noise of the step.
    points : sigma-point scheme (default :class:`MerweScaledSigmaPoints`).
    state_angles : state components that are angles (circular mean, wrapped residuals).
    """
    points = check_points(points)
    x, P, n = _check_points_input(x, P)
    Q = check_covariance(Q, "Q", n)
    broadcast_batch({"x": x.shape[:-1], "P": P.shape[:-2], "Q": Q.shape[:-2]})
    call_checked(f, x, "f", (n,))
    return _k_predict(x, P, f, Q, points, check_angles(state_angles, n, "state_angles"))


def _measurement(h, n: int, m: int) -> Vector:
    """``h`` as a callable: an ``(m, n)`` array is the linear measurement ``H x``."""
    if callable(h):
        return h
    H = as_matrix(h, "h", m, n, origin=f"a linear measurement matrix H of shape (m, n), m = {m} from z, n = {n} from x")
    if H.ndim != 2:
        raise ValueError(f"h as a linear measurement matrix must have shape ({m}, {n}), got shape {H.shape}")
    return lambda X: mv(H, X)


def ukf_update(x, P, z, h: Vector | np.ndarray, R, points: Points | None = None,
               angle_components: Sequence[int] = (), state_angles: Sequence[int] = ()) -> Update:
    r"""UKF measurement update.

    :math:`\hat z, S` are the unscented moments of ``h`` plus ``R``, :math:`P_{xz}` the
    cross-covariance, :math:`K = P_{xz} S^{-1}`, :math:`x^+ = x + K (z \ominus \hat z)`,
    :math:`P^+ = P - K S K^\top`.

    Parameters
    ----------
    x, P : prior mean ``(..., n)`` and covariance ``(..., n, n)``.
    z : (..., m) measurement; ``h`` broadcasting ``(..., n) -> (..., m)``, or an ``(m, n)`` array
        ``H`` for the linear measurement :math:`Hx`.
    R : (m, m) or (..., m, m) measurement noise, positive definite.
    points : sigma-point scheme (default :class:`MerweScaledSigmaPoints`).
    angle_components : measurement components that are angles.
    state_angles : state components that are angles.

    Returns
    -------
    kftrack.kalman.Update
        ``(x, P, y, S, K, nis, loglik)``.
    """
    points = check_points(points)
    x, P, n = _check_points_input(x, P)
    z = as_vector(z, "z")
    m = z.shape[-1]
    R = check_covariance(R, "R", m, positive_definite=True)
    broadcast_batch({"x": x.shape[:-1], "P": P.shape[:-2], "z": z.shape[:-1], "R": R.shape[:-2]})
    h = _measurement(h, n, m)
    call_checked(h, x, "h", (m,))
    return _k_update(x, P, z, h, R, points, check_angles(state_angles, n, "state_angles"),
                       check_angles(angle_components, m))


def unscented_kalman_filter(zs, x0, P0, f: Vector, Q, h: Vector | np.ndarray, R, points: Points | None = None,
                            angle_components: Sequence[int] = (), state_angles: Sequence[int] = (),
                            *, progress: bool = False, dtype=None, missing=None) -> FilterResult:
    r"""Filter a whole measurement sequence with the UKF: update with ``zs[k]``, then predict.

    Same conventions as :func:`kftrack.kalman.kalman_filter` and
    :func:`kftrack.ekf.extended_kalman_filter`: time first, ``x0`` the prior of step 0, rows
    of NaN missing, one broadcast call per step for all batch members (Monte Carlo runs).
    ``h`` is a broadcasting callable or an ``(m, n)`` array ``H`` (linear measurement :math:`Hx`).
    ``progress=True`` shows a tqdm bar (NumPy engine only). ``dtype``: None or ``"float64"``
    (default), or ``"float32"`` (explicit, about nine decimal digits lost); see
    :func:`kftrack.kalman.kalman_filter`. With JAX arrays among ``zs``, ``x0``, ``P0``, ``Q``,
    ``R`` the JAX engine runs (JAX arrays out); ``f`` and ``h`` must then be written with
    ``jax.numpy`` or the array API (the same function objects reuse the compiled loop). The
    filter composes: inside ``jax.jit``, ``jax.grad`` and ``jax.vmap`` the shapes of abstract
    inputs are checked, not their values. ``missing``: None (rows of NaN of ``zs`` are missing),
    False (none is) or a boolean mask ``(T,)`` or ``(T, ...)`` of the rows not to use, as in
    :func:`kftrack.kalman.kalman_filter`.

    ``P0`` may be positive semi-definite (a known start, ``P0 = 0``): where the Cholesky factor
    of :math:`cP` does not exist, the sigma points use the symmetric square root
    :math:`V \operatorname{diag}(\sqrt{\lambda}) V^\top` of its eigendecomposition (NumPy
    engine; the JAX engine's Cholesky factor of a singular matrix is NaN).

    **NaN from your functions.** On the NumPy engine the output of ``f`` and ``h`` is checked
    right after each call (on the sigma points): NaN or inf raises a ``ValueError`` naming the
    function and the step. The JAX engine cannot check values inside its compiled loop: there a
    NaN propagates to every later estimate.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.models import ConstantVelocity
    >>> from kftrack.sensors.radar import RangeBearing
    >>> from kftrack.ukf import unscented_kalman_filter
    >>> cv, radar = ConstantVelocity(ndim=2, q=0.01), RangeBearing(sigmas=(1.0, 0.01))   # m, rad
    >>> truth = np.array([[100.0 + 5.0 * k, 5.0, 50.0, 0.0] for k in range(20)])   # [x, vx, y, vy]
    >>> zs = radar.h(truth) + np.random.default_rng(0).normal(size=(20, 2)) * radar.sigmas
    >>> x0, P0 = np.array([100.0, 0.0, 50.0, 0.0]), np.diag([25.0, 100.0, 25.0, 100.0])
    >>> res = unscented_kalman_filter(zs, x0, P0, lambda x: cv.f(x, 1.0), cv.Q(1.0), radar.h, radar.R,
    ...                               angle_components=[1])
    >>> print(np.round(res.x[-1], 1).tolist())        # the truth is [195, 5, 50, 0]
    [194.8, 5.1, 50.9, 0.1]
    """
    sources = (zs, x0, P0, Q, R)  # the caller's arrays choose the engine
    points = check_points(points)
    zs_h, x0_h, P0_h, Q_h, R_h, n, m, batch, gone = check_sequence(zs, x0, P0, Q, R, missing)
    _check_points_input(x0_h, P0_h)
    x_angles = check_angles(state_angles, n, "state_angles")
    z_angles = check_angles(angle_components, m)
    xb = np.broadcast_to(x0_h, batch + (n,))
    h_h = h if callable(h) else stand_in(h, "matrix")
    call_checked(f, xb, "f", (n,))
    call_checked(_measurement(h_h, n, m), xb, "h", (m,))
    opts = (("points", points), ("x_angles", x_angles))
    user = (("f", "f"), ("h", "h"))
    predict = Kernel(_predict, (("f", f),) + opts, user)
    if callable(h):
        update, upd_args = Kernel(_update, (("h", h), ("z_angles", z_angles)) + opts, user), (Given(R, R_h),)
    else:  # a linear measurement: H travels as an array (no closure over it)
        H = as_matrix(h_h, "h", m, n)
        update, upd_args = Kernel(_update_linear, (("z_angles", z_angles),) + opts), (Given(h, H), Given(R, R_h))
    return run_filter(Given(zs, zs_h), gone, Given(x0, x0_h), Given(P0, P0_h), batch, predict, update,
                      pred_args=(Given(Q, Q_h),), upd_args=upd_args, sources=sources, dtype=dtype, progress=progress)


# adapters from the engines' argument order (x, P, arrays..., static options) to the kernels
def _predict(x, P, Q, *, f, points, x_angles):
    return _k_predict(x, P, f, Q, points, x_angles)


def _update(x, P, z, R, *, h, points, x_angles, z_angles):
    return _k_update(x, P, z, h, R, points, x_angles, z_angles)


def _update_linear(x, P, z, H, R, *, points, x_angles, z_angles):
    return _k_update(x, P, z, lambda X: mv(H, X), R, points, x_angles, z_angles)
