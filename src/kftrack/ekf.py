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
with ``functools.partial`` or a lambda, e.g. ``f=lambda x: model.f(x, dt)``.

On a linear model (``f(x) = F x``, ``h(x) = H x``) the EKF is the Kalman filter, bit for bit.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from ._validate import (as_float_array, as_matrix, as_vector, broadcast_batch, call_checked, check_angles,
                        check_covariance, check_rng, check_sequence, check_state, is_tracer, stand_in)
from .kernels import Update
from .results import FilterResult
from .kernels import ekf_predict as _k_predict
from .kernels import ekf_update as _k_update
from .engines import Given, Kernel, _jax, run_filter
from .kernels import matrix_transpose, mv, sym, wrap_angle
from .kernels import residual as _k_residual

__all__ = ["wrap_angle", "residual", "measurement_functions", "linearized_transform", "ekf_predict", "ekf_update", "extended_kalman_filter",
           "simulate_additive_gaussian"]

Vector = Callable[[np.ndarray], np.ndarray]


def residual(a, b, angle_components: Sequence[int] = ()) -> np.ndarray:
    r"""Difference ``a - b`` of vectors ``(..., m)`` with the angle components wrapped to :math:`(-\pi, \pi]`.

    Use it for innovations :math:`z - h(x)` when ``z`` holds a bearing: the residual of
    :math:`179^\circ` and :math:`-179^\circ` is :math:`-2^\circ`, not :math:`358^\circ`.
    """
    a = as_vector(a, "a")
    b = as_vector(b, "b", a.shape[-1])
    return _k_residual(a, b, check_angles(angle_components, a.shape[-1]))


def measurement_functions(h, H_jac, n: int, m: int | None = None) -> tuple[Vector, Vector]:
    """``(h, H_jac)`` as callables: a callable ``h`` needs its Jacobian ``H_jac``; an ``(m, n)``
    array ``h`` is the linear measurement :math:`h(x) = H x` with Jacobian ``H`` (then ``H_jac``
    must be None). ``n`` is the state size and ``m``, when known, the measurement size."""
    if callable(h):
        if H_jac is None:
            raise ValueError("H_jac must be a callable (the Jacobian of h) when h is a function; "
                             "pass h as an (m, n) array for a linear measurement H x")
        if not callable(H_jac):
            raise TypeError(f"H_jac must be a callable (..., n) -> (..., m, n), got {type(H_jac).__name__}")
        return h, H_jac
    H = as_matrix(h, "h", m, n, origin=f"a linear measurement matrix H of shape (m, n), n = {n} from the state")
    if H.ndim != 2:
        raise ValueError(f"h as a linear measurement matrix must have shape (m, {n}), got shape {H.shape}")
    if H_jac is not None:
        raise ValueError("H_jac must be None when h is a matrix (the linear measurement H x has Jacobian H), "
                         f"got {type(H_jac).__name__}")
    return (lambda x: mv(H, x)), (lambda x: H)


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------
def linearized_transform(fn: Vector, jac: Vector, x, P) -> tuple[np.ndarray, np.ndarray]:
    r"""First-order (EKF) approximation of the distribution of ``fn(x)``, :math:`x \sim N(\hat x, P)`:
    mean :math:`fn(\hat x)` and covariance :math:`J P J^\top` with :math:`J = \partial fn/\partial x\,(\hat x)`.

    ``fn`` maps ``(..., n)`` to ``(..., d)``, ``jac`` to ``(..., d, n)``. Returns ``(mean, cov)``.
    """
    x, P, n = check_state(x, P)
    y = call_checked(fn, x, "fn", ())
    J = call_checked(jac, x, "jac", (y.shape[-1], n))
    return y, sym(J @ P @ matrix_transpose(J))


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
    x, P, n = check_state(x, P)
    Q = check_covariance(Q, "Q", n)
    x_angles = check_angles(state_angles, n, "state_angles")
    call_checked(f, x, "f", (n,))
    F = call_checked(F_jac, x, "F_jac", (n, n))
    broadcast_batch({"x": x.shape[:-1], "P": P.shape[:-2], "F_jac(x)": F.shape[:-2], "Q": Q.shape[:-2]})
    return _k_predict(x, P, f, F_jac, Q, x_angles)


def ekf_update(x, P, z, h: Vector | np.ndarray, H_jac: Vector | None, R, angle_components: Sequence[int] = (),
               state_angles: Sequence[int] = ()) -> Update:
    r"""EKF measurement update (Joseph form) with innovation :math:`y = z \ominus h(x)`.

    Parameters
    ----------
    x : (..., n) prior mean; ``P`` (..., n, n) prior covariance.
    z : (..., m) measurement.
    h : callable ``(..., n) -> (..., m)``; ``H_jac`` its Jacobian ``(..., n) -> (..., m, n)``.
        Or ``h`` an ``(m, n)`` array ``H``: the linear measurement :math:`h(x) = Hx` with
        Jacobian ``H`` (then ``H_jac`` must be None); the update is then
        :func:`kftrack.kalman.update`'s, bit for bit.
    R : (m, m) or (..., m, m) measurement-noise covariance, positive definite.
    angle_components : indices of ``z`` that are angles (rad); their innovation is wrapped
        to :math:`(-\pi, \pi]`.
    state_angles : indices of the state that are angles; the posterior mean is wrapped there.

    Returns
    -------
    Update
        ``(x, P, y, S, K, nis, loglik)`` as in :func:`kftrack.kalman.update`.
    """
    x, P, n = check_state(x, P)
    z = as_vector(z, "z")
    m = z.shape[-1]
    R = check_covariance(R, "R", m, positive_definite=True)
    angles = check_angles(angle_components, m)
    x_angles = check_angles(state_angles, n, "state_angles")
    h, H_jac = measurement_functions(h, H_jac, n, m)
    call_checked(h, x, "h", (m,))
    H = call_checked(H_jac, x, "H_jac", (m, n))
    broadcast_batch({"x": x.shape[:-1], "P": P.shape[:-2], "z": z.shape[:-1], "H_jac(x)": H.shape[:-2], "R": R.shape[:-2]})
    return _k_update(x, P, z, h, H_jac, R, angles, x_angles)


def extended_kalman_filter(zs, x0, P0, f: Vector, F_jac: Vector, Q, h: Vector | np.ndarray, H_jac: Vector | None, R,
                           angle_components: Sequence[int] = (), *, state_angles: Sequence[int] = (),
                           R_per_step: bool = False, progress: bool = False, dtype=None,
                           missing=None) -> FilterResult:
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
    h, H_jac, R : measurement function, its Jacobian, measurement noise (see :func:`ekf_update`);
        ``h`` may be an ``(m, n)`` matrix ``H`` (linear measurement) with ``H_jac=None``.
    angle_components : indices of the measurement that are angles (innovations wrapped).
    state_angles : indices of the state that are angles (predicted and filtered means wrapped
        to :math:`(-\pi, \pi]`).
    R_per_step : if True, ``R`` is time first, ``(T, ..., m, m)``: one covariance per step (and
        per run), as converted measurements need (:meth:`kftrack.sensors.radar.Radar.to_cartesian`).
        At the missing rows it is not used and may be NaN; under ``jax.grad`` keep it finite
        there if it depends on a differentiated parameter (``0 * NaN`` is NaN in the gradient).
    progress : show a tqdm progress bar over the time steps (its timings are not reproducible
        output, so the book's executed notebooks leave it off; NumPy engine only).
    dtype : None or ``"float64"`` (default), or ``"float32"`` (explicit, about nine decimal
        digits lost); see :func:`kftrack.kalman.kalman_filter`.
    missing : None (rows of NaN of ``zs`` are missing), False (none is) or a boolean mask
        ``(T,)`` or ``(T, ...)`` of the rows not to use, as in :func:`kftrack.kalman.kalman_filter`.

    With JAX arrays among ``zs``, ``x0``, ``P0``, ``Q``, ``R`` the JAX engine runs (JAX arrays
    out); then ``f``, ``F_jac``, ``h``, ``H_jac`` (and a callable ``Q``) must be written with
    ``jax.numpy`` (or the array API), and the same function objects reuse the compiled loop.
    The filter composes: inside ``jax.jit``, ``jax.grad`` (of ``jnp.nansum(result.loglik)``, say,
    with respect to the noise) and ``jax.vmap`` (over data or parameters) the shapes of the
    abstract inputs are checked, their values cannot be (and with ``missing=None`` the missing
    rows are found inside the trace). The functions are called once at the boundary on a
    NumPy state (``x0`` or a stand-in of its shape) to check the shapes they return.

    **NaN from your functions.** On the NumPy engine the output of ``f``, ``F_jac``, ``h``,
    ``H_jac`` (and a callable ``Q``) is checked right after each call: NaN or inf raises a
    ``ValueError`` naming the function and the step. The JAX engine cannot check values inside
    its compiled loop: there a NaN from your function propagates to every later estimate (check
    ``np.isfinite(result.x)``).

    Returns
    -------
    kftrack.kalman.FilterResult

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.ekf import extended_kalman_filter
    >>> from kftrack.models import ConstantVelocity
    >>> from kftrack.sensors.radar import RangeBearing
    >>> cv, radar = ConstantVelocity(ndim=2, q=0.01), RangeBearing(sigmas=(1.0, 0.01))   # m, rad
    >>> truth = np.array([[100.0 + 5.0 * k, 5.0, 50.0, 0.0] for k in range(20)])   # [x, vx, y, vy]
    >>> zs = radar.h(truth) + np.random.default_rng(0).normal(size=(20, 2)) * radar.sigmas   # range, bearing
    >>> x0, P0 = np.array([100.0, 0.0, 50.0, 0.0]), np.diag([25.0, 100.0, 25.0, 100.0])
    >>> res = extended_kalman_filter(zs, x0, P0, lambda x: cv.f(x, 1.0), lambda x: cv.jacobian(x, 1.0), cv.Q(1.0),
    ...                              radar.h, radar.jacobian, radar.R, angle_components=[1])
    >>> res.x.shape, res.P.shape
    ((20, 4), (20, 4, 4))
    >>> print(np.round(res.x[-1], 1).tolist())        # the truth is [195, 5, 50, 0]
    [194.8, 5.1, 50.9, 0.1]
    """
    sources = (zs, x0, P0, Q, R)  # the caller's arrays choose the engine
    Q_fn = Q if callable(Q) else None
    x0c, _, n0 = check_state(stand_in(x0, "vector"), stand_in(P0, "cov"), ("x0", "P0"))
    Q_h = Q if Q_fn is None else call_checked(Q_fn, x0c, "Q", (n0, n0))
    R_seq, R_h = None, R
    if R_per_step:
        R_seq, R_h = _per_step(stand_in(R, "cov"), zs, missing)
    zs_h, x0_h, P0_h, Q_h, R_h, n, m, batch, gone = check_sequence(zs, x0, P0, Q_h, R_h, missing)
    angles = check_angles(angle_components, m)
    x_angles = check_angles(state_angles, n, "state_angles")
    xb = np.broadcast_to(x0_h, batch + (n,))
    h_h = h if callable(h) else stand_in(h, "matrix")
    H_lin = None if callable(h) else measurement_functions(h_h, H_jac, n, m)[1](None)  # the (m, n) matrix
    h_, H_jac_ = measurement_functions(h_h, H_jac, n, m)
    call_checked(f, xb, "f", (n,))
    call_checked(F_jac, xb, "F_jac", (n, n))
    call_checked(h_, xb, "h", (m,))
    call_checked(H_jac_, xb, "H_jac", (m, n))
    user = (("f", "f"), ("F_jac", "F_jac"), ("Q_fn", "Q"), ("h", "h"), ("H_jac", "H_jac"))
    if Q_fn is not None:
        check_covariance(call_checked(Q_fn, xb, "Q", (n, n)), "Q(x0)", n)  # every run's start
        predict, pred_args = Kernel(_predict_state_q, (("f", f), ("F_jac", F_jac), ("Q_fn", Q_fn),
                                                       ("x_angles", x_angles)), user), ()
    else:
        predict, pred_args = Kernel(_predict, (("f", f), ("F_jac", F_jac), ("x_angles", x_angles)), user), \
            (Given(Q, Q_h),)
    meas = (("angles", angles), ("x_angles", x_angles))
    if H_lin is None:
        update, upd_args = Kernel(_update, (("h", h_), ("H_jac", H_jac_)) + meas, user), ()
    else:  # a linear measurement: H travels as an array (no closure over it)
        update, upd_args = Kernel(_update_linear, meas), (Given(h, H_lin),)
    upd_steps = ()
    T = zs_h.shape[0]
    if R_seq is not None:  # one covariance per step, next to the measurement
        try:  # batch axes of R align from the right, after the time axis
            R_seq = _time_batch(np, R_seq, T, batch, (m, m))
        except ValueError:
            raise ValueError(f"R must have shape (T, ..., {m}, {m}) matching the batch {batch}, "
                             f"got {R_seq.shape}") from None
        if gone is not None:  # unused at the missing rows; the identity keeps S invertible
            R_seq = np.where(_time_batch(np, gone, T, batch, ())[..., None, None], np.eye(m), R_seq)
        R_raw = R_seq
        if is_tracer(R):  # the caller's abstract R, prepared the same way inside the trace
            jnp = _jax().numpy
            R_raw = _time_batch(jnp, R, T, batch, (m, m))
            g = jnp.isnan(zs).all(-1) if gone is None else gone
            R_raw = jnp.where(_time_batch(jnp, g, T, batch, ())[..., None, None], jnp.eye(m, dtype=R_raw.dtype),
                              R_raw)
        upd_steps = (Given(R_raw, R_seq),)
    else:
        upd_args = upd_args + (Given(R, R_h),)
    return run_filter(Given(zs, zs_h), gone, Given(x0, x0_h), Given(P0, P0_h), batch, predict, update,
                      pred_args=pred_args, upd_args=upd_args, upd_steps=upd_steps, sources=sources, dtype=dtype,
                      progress=progress)


def _time_batch(xp, a, T: int, batch: tuple, tail: tuple):
    """``a`` ``(T, ..., *tail)``, its batch axes aligned from the right after the time axis,
    broadcast to ``(T, *batch, *tail)`` (a ``ValueError`` if they do not broadcast)."""
    nb = a.ndim - 1 - len(tail)
    a = xp.reshape(a, (T,) + (1,) * max(len(batch) - nb, 0) + tuple(a.shape[1:]))
    return xp.broadcast_to(a, (T,) + batch + tail)


# adapters from the engines' argument order (x, P, arrays..., static options) to the kernels
def _predict(x, P, Q, *, f, F_jac, x_angles):
    return _k_predict(x, P, f, F_jac, Q, x_angles)


def _predict_state_q(x, P, *, f, F_jac, Q_fn, x_angles):
    return _k_predict(x, P, f, F_jac, Q_fn(x), x_angles)


def _update(x, P, z, R, *, h, H_jac, angles, x_angles):
    return _k_update(x, P, z, h, H_jac, R, angles, x_angles)


def _update_linear(x, P, z, H, R, *, angles, x_angles):
    return _k_update(x, P, z, lambda s: mv(H, s), lambda s: H, R, angles, x_angles)


def _per_step(R, zs, missing) -> tuple[np.ndarray, np.ndarray]:
    """Check a time-first ``R`` ``(T, ..., m, m)`` against ``zs`` ``(T, ..., m)``; return it and
    its first step (for the shared boundary checks). The covariances of rows not used (rows of NaN
    of ``zs``, or marked by a ``missing`` mask) may be NaN: they are replaced by the identity."""
    zs_arr = np.asarray(stand_in(zs, "vector"), dtype=float)
    R = as_float_array(R, "R")
    if missing is None:
        gone = np.isnan(zs_arr).all(-1) if zs_arr.ndim else np.zeros(())
    elif isinstance(missing, np.ndarray) and missing.dtype == bool and missing.ndim:
        gone = missing
    else:
        gone = np.zeros(())
    if R.shape[:-2] == gone.shape and gone.any():  # steps without a measurement may carry NaN covariances
        R = np.where(gone[..., None, None], np.eye(R.shape[-1]), R)
    elif gone.ndim and gone.any() and R.ndim >= 3 and R.shape[0] == gone.shape[0]:
        try:
            g = _time_batch(np, gone, R.shape[0], R.shape[1:-2], ())
        except ValueError:
            pass
        else:
            R = np.where(g[..., None, None], np.eye(R.shape[-1]), R)
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
    angles = check_angles(angle_components, m)
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
