r"""The extended Kalman filter (EKF) for additive-Gaussian models, with angle-aware residuals.

Model (Bar-Shalom, Li & Kirubarajan 2001, §10.3):

.. math::

    x_{k+1} = f(x_k) + w_k,\quad w_k \sim N(0, Q), \qquad
    z_k = h(x_k) + v_k,\quad v_k \sim N(0, R).

The EKF propagates the mean through ``f`` and ``h`` and the covariance through their
Jacobians :math:`F = \partial f/\partial x`, :math:`H = \partial h/\partial x` evaluated at the
current estimate:

.. math::

    x^- = f(x), \quad P^- = F P F^\top + Q, \qquad
    y = z \ominus h(x^-), \quad S = H P^- H^\top + R, \quad K = P^- H^\top S^{-1},

and the Joseph-form update of :mod:`kftrack.kalman`. :math:`\ominus` is subtraction with the
components listed in ``angle_components`` wrapped to :math:`(-\pi, \pi]`; state components
listed in ``state_angles`` (a heading) are wrapped after each prediction and update.

Shapes follow :mod:`kftrack.kalman`: ``x`` ``(..., n)``, ``P`` ``(..., n, n)``, time first for
sequences. The callables must broadcast: ``f(x)`` maps ``(..., n)`` to ``(..., n)``,
``F_jac(x)`` to ``(..., n, n)``, ``h(x)`` to ``(..., m)`` and ``H_jac(x)`` to ``(..., m, n)``;
so one call filters one track or every Monte Carlo run at once. Pass the sampling interval
with :func:`functools.partial` or a lambda, e.g. ``f=lambda x: model.f(x, dt)``.

On a linear model (``f(x) = F x``, ``h(x) = H x``) the EKF is the Kalman filter, bit for bit.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from ._validate import as_float_array, as_matrix, as_vector, check_covariance, check_rng
from .kalman import FilterResult, Update, _batch, _check_sequence, _check_state, _predict, _run_sequence, _sym, _T, _update

__all__ = ["wrap_angle", "residual", "linearized_transform", "ekf_predict", "ekf_update", "extended_kalman_filter",
           "simulate_additive_gaussian"]

Vector = Callable[[np.ndarray], np.ndarray]


def wrap_angle(a) -> np.ndarray:
    r"""Wrap angles (rad) to :math:`(-\pi, \pi]`: :math:`\pi - ((\pi - a) \bmod 2\pi)`.

    ``wrap_angle(pi) == pi`` and ``wrap_angle(-pi) == pi``; any shape.
    """
    a = np.asarray(a, dtype=float)
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


def _angles(angle_components, m: int, name: str = "angle_components") -> tuple[int, ...]:
    """Validate a tuple of component indices into a vector of length ``m``."""
    try:
        idx = tuple(int(i) for i in angle_components)
    except TypeError:
        raise TypeError(f"{name} must be a sequence of integer indices, got {angle_components!r}") from None
    bad = [i for i in idx if not -m <= i < m]
    if bad:
        raise ValueError(f"{name} must index a vector of length {m}, got {bad}")
    return tuple(sorted({i % m for i in idx}))


def _residual(a: np.ndarray, b: np.ndarray, angles: tuple[int, ...]) -> np.ndarray:
    d = a - b
    if angles:
        d = d.copy()
        d[..., angles] = wrap_angle(d[..., angles])
    return d


def residual(a, b, angle_components: Sequence[int] = ()) -> np.ndarray:
    r"""Difference ``a - b`` of vectors ``(..., m)`` with the angle components wrapped to :math:`(-\pi, \pi]`.

    Use it for innovations :math:`z - h(x)` when ``z`` holds a bearing: the residual of
    :math:`179^\circ` and :math:`-179^\circ` is :math:`-2^\circ`, not :math:`358^\circ`.
    """
    a = as_vector(a, "a")
    b = as_vector(b, "b", a.shape[-1])
    return _residual(a, b, _angles(angle_components, a.shape[-1]))


# --------------------------------------------------------------------------------------------
# unchecked kernels (shared with the UKF and the Monte Carlo loops)
# --------------------------------------------------------------------------------------------
def _wrap_state(x, x_angles):
    """Wrap the state components ``x_angles`` to (-pi, pi] (a copy; ``x`` itself when there are none)."""
    if not x_angles:
        return x
    x = np.array(x, dtype=float)
    x[..., x_angles] = wrap_angle(x[..., x_angles])
    return x


def _ekf_predict(x, P, f, F_jac, Q, x_angles=()):
    F = F_jac(x)
    _, P_pred = _predict(x, P, F, Q)
    return _wrap_state(f(x), x_angles), P_pred


def _gain_update(x, P, y, H, R) -> Update:
    """Update with a given innovation ``y``. Runs :func:`kalman._update` linearized at zero
    (where its innovation is ``y`` exactly) and shifts the mean back by ``x``; every number is
    then the one the Kalman filter computes, to the last bit."""
    u = _update(np.zeros_like(x), P, y, H, R)
    return u._replace(x=x + u.x)


def _ekf_update(x, P, z, h, H_jac, R, angles, x_angles=()) -> Update:
    y = _residual(z, h(x), angles)
    u = _gain_update(x, P, y, H_jac(x), R)
    return u._replace(x=_wrap_state(u.x, x_angles)) if x_angles else u


def _call(fn, x, name: str, shape: tuple) -> np.ndarray:
    """Call a user function once at the boundary and check the shape of what it returns."""
    try:
        out = np.asarray(fn(x), dtype=float)
    except Exception as exc:  # report which argument failed, keep the cause
        raise ValueError(f"{name} failed on x of shape {x.shape}: {exc}") from exc
    if shape and (out.ndim < len(shape) or out.shape[-len(shape):] != shape):
        raise ValueError(f"{name}(x) must return shape (..., {', '.join(map(str, shape))}), got {out.shape}")
    return out


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------
def linearized_transform(fn: Vector, jac: Vector, x, P) -> tuple[np.ndarray, np.ndarray]:
    r"""First-order (EKF) approximation of the distribution of ``fn(x)``, :math:`x \sim N(\hat x, P)`:
    mean :math:`fn(\hat x)` and covariance :math:`J P J^\top` with :math:`J = \partial fn/\partial x\,(\hat x)`.

    ``fn`` maps ``(..., n)`` to ``(..., d)``, ``jac`` to ``(..., d, n)``. Returns ``(mean, cov)``.
    """
    x, P, n = _check_state(x, P)
    y = _call(fn, x, "fn", ())
    J = _call(jac, x, "jac", (y.shape[-1], n))
    return y, _sym(J @ P @ _T(J))


def ekf_predict(x, P, f: Vector, F_jac: Vector, Q, state_angles: Sequence[int] = ()) -> tuple[np.ndarray, np.ndarray]:
    r"""EKF time update :math:`x^- = f(x)`, :math:`P^- = F P F^\top + Q` with :math:`F = \partial f/\partial x\,(x)`.

    Parameters
    ----------
    x : (..., n) state mean.
    P : (..., n, n) state covariance.
    f : callable ``(..., n) -> (..., n)``, the transition function.
    F_jac : callable ``(..., n) -> (..., n, n)``, its Jacobian.
    Q : (n, n) or (..., n, n) process-noise covariance of the step.
    state_angles : indices of the state that are angles (rad), e.g. a heading; ``f(x)`` is
        wrapped to :math:`(-\pi, \pi]` there.
    """
    x, P, n = _check_state(x, P)
    Q = check_covariance(Q, "Q", n)
    x_angles = _angles(state_angles, n, "state_angles")
    _call(f, x, "f", (n,))
    F = _call(F_jac, x, "F_jac", (n, n))
    _batch({"x": x.shape[:-1], "P": P.shape[:-2], "F_jac(x)": F.shape[:-2], "Q": Q.shape[:-2]})
    return _ekf_predict(x, P, f, F_jac, Q, x_angles)


def ekf_update(x, P, z, h: Vector, H_jac: Vector, R, angle_components: Sequence[int] = (),
               state_angles: Sequence[int] = ()) -> Update:
    r"""EKF measurement update (Joseph form) with innovation :math:`y = z \ominus h(x)`.

    Parameters
    ----------
    x : (..., n) prior mean; ``P`` (..., n, n) prior covariance.
    z : (..., m) measurement.
    h : callable ``(..., n) -> (..., m)``; ``H_jac`` its Jacobian ``(..., n) -> (..., m, n)``.
    R : (m, m) or (..., m, m) measurement-noise covariance, positive definite.
    angle_components : indices of ``z`` that are angles (rad); their innovation is wrapped
        to :math:`(-\pi, \pi]`.
    state_angles : indices of the state that are angles; the posterior mean is wrapped there.

    Returns
    -------
    Update
        ``(x, P, y, S, K, nis, loglik)`` as in :func:`kftrack.kalman.update`.
    """
    x, P, n = _check_state(x, P)
    z = as_vector(z, "z")
    m = z.shape[-1]
    R = check_covariance(R, "R", m, positive_definite=True)
    angles = _angles(angle_components, m)
    x_angles = _angles(state_angles, n, "state_angles")
    _call(h, x, "h", (m,))
    H = _call(H_jac, x, "H_jac", (m, n))
    _batch({"x": x.shape[:-1], "P": P.shape[:-2], "z": z.shape[:-1], "H_jac(x)": H.shape[:-2], "R": R.shape[:-2]})
    return _ekf_update(x, P, z, h, H_jac, R, angles, x_angles)


def extended_kalman_filter(zs, x0, P0, f: Vector, F_jac: Vector, Q, h: Vector, H_jac: Vector, R,
                           angle_components: Sequence[int] = (), *, state_angles: Sequence[int] = (),
                           R_per_step: bool = False, progress: bool = False) -> FilterResult:
    r"""Filter a whole measurement sequence with the EKF: update with ``zs[k]``, then predict.

    Same conventions as :func:`kftrack.kalman.kalman_filter` (``x0`` is the prior of step 0,
    rows of NaN are missing measurements); inputs are validated once, then the loop runs the
    unchecked kernels, one broadcast call per step for every batch member (Monte Carlo run).

    Parameters
    ----------
    zs : (T, ..., m) measurements, time first.
    x0, P0 : (..., n), (..., n, n) prior of step 0.
    f, F_jac, Q : transition, its Jacobian, process noise (see :func:`ekf_predict`). ``Q`` may
        also be a callable ``(..., n) -> (..., n, n)``: state-dependent process noise evaluated
        at the filtered estimate before each prediction (seed 001's
        :math:`Q = \Gamma(\hat x)\,\Sigma\,\Gamma(\hat x)^\top`, :meth:`kftrack.models.Turn3DAngles.Q`).
    h, H_jac, R : measurement function, its Jacobian, measurement noise (see :func:`ekf_update`).
    angle_components : indices of the measurement that are angles (innovations wrapped).
    state_angles : indices of the state that are angles (predicted and filtered means wrapped
        to :math:`(-\pi, \pi]`).
    R_per_step : if True, ``R`` is time first, ``(T, ..., m, m)``: one covariance per step (and
        per run), as converted measurements need (:meth:`kftrack.sensors.radar.Radar.to_cartesian`).
    progress : show a tqdm progress bar over the time steps (its timings are not reproducible
        output, so the book's executed notebooks leave it off).

    Returns
    -------
    kftrack.kalman.FilterResult
    """
    Q_fn = Q if callable(Q) else None
    x0c, _, n0 = _check_state(x0, P0, ("x0", "P0"))
    if Q_fn is not None:
        Q = _call(Q_fn, x0c, "Q", (n0, n0))
    R_seq = None
    if R_per_step:
        R_seq, R = _per_step(R, zs)
    zs, x0, P0, Q, R, n, m, batch, row_missing = _check_sequence(zs, x0, P0, Q, R)
    angles = _angles(angle_components, m)
    x_angles = _angles(state_angles, n, "state_angles")
    xb = np.broadcast_to(x0, batch + (n,))
    _call(f, xb, "f", (n,))
    _call(F_jac, xb, "F_jac", (n, n))
    _call(h, xb, "h", (m,))
    _call(H_jac, xb, "H_jac", (m, n))
    if Q_fn is not None:
        check_covariance(_call(Q_fn, xb, "Q", (n, n)), "Q(x0)", n)  # every run's start
        predict = lambda x, P: _ekf_predict(x, P, f, F_jac, Q_fn(x), x_angles)  # noqa: E731
    else:
        predict = lambda x, P: _ekf_predict(x, P, f, F_jac, Q, x_angles)  # noqa: E731
    if R_seq is None:
        return _run_sequence(zs, x0, P0, batch, row_missing, predict,
                             lambda x, P, z: _ekf_update(x, P, z, h, H_jac, R, angles, x_angles), progress)
    # one covariance per step: carry it through the loop next to the measurement
    T = zs.shape[0]
    try:
        R_seq = np.broadcast_to(R_seq, (T,) + batch + (m, m))
    except ValueError:
        raise ValueError(f"R must have shape (T, ..., {m}, {m}) matching the batch {batch}, got {R_seq.shape}") from None
    zb = np.broadcast_to(zs, (T,) + batch + (m,))
    R_seq = np.where(np.isnan(zb).all(-1)[..., None, None], np.eye(m), R_seq)
    packed = np.concatenate([zb, R_seq.reshape((T,) + batch + (m * m,))], axis=-1)

    def update(x, P, z):
        Rk = z[..., m:].reshape(z.shape[:-1] + (m, m))
        # runs without a measurement arrive zeroed (their result is discarded): keep S invertible
        Rk = np.where(np.all(Rk == 0.0, axis=(-2, -1))[..., None, None], np.eye(m), Rk)
        return _ekf_update(x, P, z[..., :m], h, H_jac, Rk, angles, x_angles)

    return _run_sequence(packed, x0, P0, batch, row_missing, predict, update, progress)


def _per_step(R, zs) -> tuple[np.ndarray, np.ndarray]:
    """Check a time-first ``R`` ``(T, ..., m, m)`` against ``zs`` ``(T, ..., m)``; return it and
    its first step (for the shared boundary checks)."""
    zs_arr = np.asarray(zs, dtype=float)
    R = as_float_array(R, "R")
    gone = np.isnan(zs_arr).all(-1) if zs_arr.ndim else np.zeros(())
    if R.shape[:-2] == gone.shape and gone.any():  # steps without a measurement may carry NaN covariances
        R = np.where(gone[..., None, None], np.eye(R.shape[-1]), R)
    R = check_covariance(R, "R", zs_arr.shape[-1] if zs_arr.ndim else None, positive_definite=True)
    if R.ndim < 3 or R.shape[0] != zs_arr.shape[0]:
        raise ValueError(f"R must have shape (T, ..., m, m) with T = {zs_arr.shape[0] if zs_arr.ndim else '?'} "
                         f"steps when R_per_step=True, got shape {R.shape}")
    return R, R[0]


def simulate_additive_gaussian(f: Vector, h: Vector, x0, P0, Q, R, steps: int, rng: np.random.Generator,
                               runs: int | None = None,
                               angle_components: Sequence[int] = ()) -> tuple[np.ndarray, np.ndarray]:
    r"""Simulate :math:`x_{k+1} = f(x_k) + w_k`, :math:`z_k = h(x_k) + v_k` for many runs at once.

    The initial state of each run is drawn from :math:`N(x_0, P_0)`; ``Q`` and ``P0`` may be
    singular (sampled through their eigen-decomposition).

    Parameters
    ----------
    f, h : broadcasting callables as in :func:`extended_kalman_filter`.
    x0 : (n,) mean of the initial state; ``P0`` (n, n) its covariance.
    Q : (n, n) process noise; ``R`` (m, m) measurement noise.
    steps : number of time steps ``T``.
    rng : the random generator.
    runs : number of Monte Carlo runs ``N`` (``None``: a single run, no run axis).
    angle_components : measurement components that are angles, wrapped to :math:`(-\pi, \pi]`.

    Returns
    -------
    truth : (T, N, n) or (T, n) true states.
    zs : (T, N, m) or (T, m) measurements.
    """
    check_rng(rng)
    if int(steps) != steps or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    if runs is not None and (int(runs) != runs or runs < 1):
        raise ValueError(f"runs must be a positive integer or None, got {runs!r}")
    x0 = as_vector(x0, "x0")
    if x0.ndim != 1:
        raise ValueError(f"x0 must have shape (n,), got shape {x0.shape}")
    n = x0.shape[0]
    P0 = check_covariance(as_matrix(P0, "P0", n, n), "P0", n)
    Q = check_covariance(Q, "Q", n)
    R = check_covariance(R, "R")
    m = R.shape[-1]
    angles = _angles(angle_components, m)
    size = () if runs is None else (int(runs),)

    def draw(mean, cov):
        return rng.multivariate_normal(mean, cov, size=size or None, method="eigh", check_valid="ignore")

    x = draw(x0, P0)
    truth = np.empty((int(steps),) + size + (n,))
    zs = np.empty((int(steps),) + size + (m,))
    for k in range(int(steps)):
        if k:
            x = f(x) + draw(np.zeros(n), Q)
        truth[k] = x
        zs[k] = h(x) + draw(np.zeros(m), R)
        if angles:
            zs[k][..., angles] = wrap_angle(zs[k][..., angles])
    return truth, zs
