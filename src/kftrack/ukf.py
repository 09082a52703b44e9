r"""The unscented transform and the unscented Kalman filter (UKF), with angle-aware means.

A Gaussian :math:`N(x, P)` is represented by :math:`2n+1` sigma points

.. math::

    \mathcal X_0 = x, \quad \mathcal X_{i} = x + \left[\sqrt{c P}\right]_i,
    \quad \mathcal X_{n+i} = x - \left[\sqrt{c P}\right]_i, \qquad i = 1..n,

(:math:`[\sqrt{cP}]_i` the ``i``-th column of the lower Cholesky factor) with mean weights
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

from ._validate import as_vector, check_covariance
from .ekf import _angles, _call, _residual, _wrap_state
from .kalman import (FilterResult, Update, _batch, _check_sequence, _check_state, _innovation_score, _run_sequence,
                     _sym, _T)

__all__ = ["SigmaPoints", "MerweScaledSigmaPoints", "JulierSigmaPoints", "Transformed",
           "weighted_moments", "unscented_transform", "ukf_predict", "ukf_update", "unscented_kalman_filter"]

Vector = Callable[[np.ndarray], np.ndarray]


class SigmaPoints(NamedTuple):
    """Sigma points ``X`` ``(..., 2n+1, n)`` with mean weights ``Wm`` and covariance weights ``Wc`` ``(2n+1,)``."""

    X: np.ndarray
    Wm: np.ndarray
    Wc: np.ndarray


def _points(x: np.ndarray, P: np.ndarray, c: float, Wm: np.ndarray, Wc: np.ndarray) -> SigmaPoints:
    L = np.linalg.cholesky(c * P)  # lower: columns are the offsets
    offsets = _T(L)  # (..., n, n), row i = column i of L
    zero = np.zeros(offsets.shape[:-2] + (1, x.shape[-1]))
    X = x[..., None, :] + np.concatenate([zero, offsets, -offsets], axis=-2)
    return SigmaPoints(X, Wm, Wc)


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
        """Sigma points of :math:`N(x, P)`: ``x`` ``(..., n)``, ``P`` ``(..., n, n)`` positive definite."""
        x, P, n = _check_points_input(x, P)
        Wm, Wc, c = self.weights(n)
        return _points(x, P, c, Wm, Wc)


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
        """Sigma points of :math:`N(x, P)`: ``x`` ``(..., n)``, ``P`` ``(..., n, n)`` positive definite."""
        x, P, n = _check_points_input(x, P)
        Wm, Wc, c = self.weights(n)
        return _points(x, P, c, Wm, Wc)


Points = MerweScaledSigmaPoints | JulierSigmaPoints


def _check_points_input(x, P):
    x, P, n = _check_state(x, P)
    if np.min(np.linalg.eigvalsh(P)[..., 0]) <= 0:
        raise ValueError("P must be positive definite for the Cholesky factor of the sigma points, "
                         f"but its smallest eigenvalue is {np.min(np.linalg.eigvalsh(P)[..., 0]):.3g}")
    return x, P, n


def _check_points(points) -> Points:
    if points is None:
        return MerweScaledSigmaPoints()
    if not isinstance(points, (MerweScaledSigmaPoints, JulierSigmaPoints)):
        raise TypeError(f"points must be MerweScaledSigmaPoints or JulierSigmaPoints, got {type(points).__name__}")
    return points


def _mean(Y: np.ndarray, Wm: np.ndarray, angles: tuple[int, ...]) -> np.ndarray:
    y = np.einsum("i,...id->...d", Wm, Y)
    if angles:
        a = Y[..., angles]
        y[..., angles] = np.arctan2(np.einsum("i,...id->...d", Wm, np.sin(a)),
                                    np.einsum("i,...id->...d", Wm, np.cos(a)))
    return y


def _moments(Y, Wm, Wc, angles):
    y = _mean(Y, Wm, angles)
    dY = _residual(Y, y[..., None, :], angles)
    return y, _sym(np.einsum("i,...id,...ie->...de", Wc, dY, dY)), dY


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
    y, C, _ = _moments(Y, Wm, Wc, _angles(angle_components, Y.shape[-1]))
    return y, C


class Transformed(NamedTuple):
    """An approximation of the distribution of ``fn(x)``: ``mean`` ``(..., d)``, ``cov`` ``(..., d, d)``,
    the cross-covariance ``cross`` ``(..., n, d)`` of ``x`` and ``fn(x)``, and the sigma points used."""

    mean: np.ndarray
    cov: np.ndarray
    cross: np.ndarray
    sigma: SigmaPoints


def _ut(fn, x, P, points, x_angles, y_angles):
    n = x.shape[-1]
    Wm, Wc, c = points.weights(n)
    sp = _points(x, P, c, Wm, Wc)
    Y = fn(sp.X)
    y, C, dY = _moments(Y, Wm, Wc, y_angles)
    dX = _residual(sp.X, x[..., None, :], x_angles)
    cross = np.einsum("i,...id,...ie->...de", Wc, dX, dY)
    return Transformed(y, C, cross, sp)


def unscented_transform(fn: Vector, x, P, points: Points | None = None,
                        angle_components: Sequence[int] = (), state_angles: Sequence[int] = ()) -> Transformed:
    r"""The unscented transform of :math:`N(x, P)` through ``fn``.

    Parameters
    ----------
    fn : callable ``(..., n) -> (..., d)``, broadcasting (it receives ``(..., 2n+1, n)``).
    x : (..., n) mean; ``P`` (..., n, n) covariance, positive definite.
    points : :class:`MerweScaledSigmaPoints` (default, ``alpha=1, beta=2, kappa=0``) or
        :class:`JulierSigmaPoints`.
    angle_components : components of ``fn(x)`` that are angles (circular mean, wrapped spread).
    state_angles : components of ``x`` that are angles (wrapped in the cross-covariance).

    Returns
    -------
    Transformed
        ``(mean, cov, cross, sigma)``.
    """
    points = _check_points(points)
    x, P, n = _check_points_input(x, P)
    sp = points(x, P)
    Y = _call(fn, sp.X, "fn", ())
    if Y.ndim < 2 or Y.shape[:-1] != sp.X.shape[:-1]:
        raise ValueError(f"fn must map sigma points {sp.X.shape} to shape {sp.X.shape[:-1]} + (d,), got {Y.shape}")
    return _ut(fn, x, P, points, _angles(state_angles, n, "state_angles"),
               _angles(angle_components, Y.shape[-1]))


# --------------------------------------------------------------------------------------------
# the filter
# --------------------------------------------------------------------------------------------
def _ukf_predict(x, P, f, Q, points, x_angles):
    t = _ut(f, x, P, points, x_angles, x_angles)
    return t.mean, _sym(t.cov + Q)


def _ukf_update(x, P, z, h, R, points, x_angles, z_angles) -> Update:
    t = _ut(h, x, P, points, x_angles, z_angles)
    S = _sym(t.cov + R)
    y = _residual(z, t.mean, z_angles)
    K = _T(np.linalg.solve(S, _T(t.cross)))  # K = Pxz S^{-1}, S symmetric
    x_post = _wrap_state(x + (K @ y[..., None])[..., 0], x_angles)
    P_post = _sym(P - K @ S @ _T(K))
    return Update(x_post, P_post, y, S, K, *_innovation_score(y, S))


def ukf_predict(x, P, f: Vector, Q, points: Points | None = None,
                state_angles: Sequence[int] = ()) -> tuple[np.ndarray, np.ndarray]:
    r"""UKF time update: the unscented transform of :math:`N(x, P)` through ``f``, plus ``Q``.

    Parameters
    ----------
    x, P : (..., n), (..., n, n) state mean and covariance (positive definite).
    f : broadcasting transition function ``(..., n) -> (..., n)``.
    Q : (n, n) or (..., n, n) process noise of the step.
    points : sigma-point scheme (default :class:`MerweScaledSigmaPoints`).
    state_angles : state components that are angles (circular mean, wrapped residuals).
    """
    points = _check_points(points)
    x, P, n = _check_points_input(x, P)
    Q = check_covariance(Q, "Q", n)
    _batch({"x": x.shape[:-1], "P": P.shape[:-2], "Q": Q.shape[:-2]})
    _call(f, x, "f", (n,))
    return _ukf_predict(x, P, f, Q, points, _angles(state_angles, n, "state_angles"))


def ukf_update(x, P, z, h: Vector, R, points: Points | None = None,
               angle_components: Sequence[int] = (), state_angles: Sequence[int] = ()) -> Update:
    r"""UKF measurement update.

    :math:`\hat z, S` are the unscented moments of ``h`` plus ``R``, :math:`P_{xz}` the
    cross-covariance, :math:`K = P_{xz} S^{-1}`, :math:`x^+ = x + K (z \ominus \hat z)`,
    :math:`P^+ = P - K S K^\top`.

    Parameters
    ----------
    x, P : prior mean ``(..., n)`` and covariance ``(..., n, n)``.
    z : (..., m) measurement; ``h`` broadcasting ``(..., n) -> (..., m)``.
    R : (m, m) or (..., m, m) measurement noise, positive definite.
    points : sigma-point scheme (default :class:`MerweScaledSigmaPoints`).
    angle_components : measurement components that are angles.
    state_angles : state components that are angles.

    Returns
    -------
    kftrack.kalman.Update
        ``(x, P, y, S, K, nis, loglik)``.
    """
    points = _check_points(points)
    x, P, n = _check_points_input(x, P)
    z = as_vector(z, "z")
    m = z.shape[-1]
    R = check_covariance(R, "R", m, positive_definite=True)
    _batch({"x": x.shape[:-1], "P": P.shape[:-2], "z": z.shape[:-1], "R": R.shape[:-2]})
    _call(h, x, "h", (m,))
    return _ukf_update(x, P, z, h, R, points, _angles(state_angles, n, "state_angles"),
                       _angles(angle_components, m))


def unscented_kalman_filter(zs, x0, P0, f: Vector, Q, h: Vector, R, points: Points | None = None,
                            angle_components: Sequence[int] = (), state_angles: Sequence[int] = (),
                            *, progress: bool = False) -> FilterResult:
    """Filter a whole measurement sequence with the UKF: update with ``zs[k]``, then predict.

    Same conventions as :func:`kftrack.kalman.kalman_filter` and
    :func:`kftrack.ekf.extended_kalman_filter`: time first, ``x0`` the prior of step 0, rows
    of NaN missing, one broadcast call per step for all batch members (Monte Carlo runs).
    ``progress=True`` shows a tqdm bar.
    """
    points = _check_points(points)
    zs, x0, P0, Q, R, n, m, batch, row_missing = _check_sequence(zs, x0, P0, Q, R)
    _check_points_input(x0, P0)
    x_angles = _angles(state_angles, n, "state_angles")
    z_angles = _angles(angle_components, m)
    xb = np.broadcast_to(x0, batch + (n,))
    _call(f, xb, "f", (n,))
    _call(h, xb, "h", (m,))
    return _run_sequence(zs, x0, P0, batch, row_missing,
                lambda x, P: _ukf_predict(x, P, f, Q, points, x_angles),
                lambda x, P, z: _ukf_update(x, P, z, h, R, points, x_angles, z_angles), progress)
