r"""The linear Kalman filter: predict, update, a whole-sequence filter and the RTS smoother.

Shapes broadcast over leading batch axes, so one call filters one track or many Monte
Carlo runs at once:

* state ``x``: ``(..., n)``; covariance ``P``: ``(..., n, n)``;
* measurement ``z``: ``(..., m)``;
* ``F``, ``Q`` ``(n, n)`` and ``H`` ``(m, n)``, ``R`` ``(m, m)``, either shared or with the
  same leading batch axes as ``x``.

Time series put time first: ``(T, ..., n)``.

The unchecked kernels behind these functions live in :mod:`kftrack.kernels`; the time loop of
:func:`kalman_filter` runs on one of the two engines of :mod:`kftrack.engines` (NumPy arrays in:
the Python loop; JAX arrays in: ``jax.lax.scan`` under ``jax.jit``, JAX arrays out). The
transition may be constant, a function of irregular sampling intervals ``dt``, or a time-first
stack (``time_varying=True``). The result types :class:`FilterResult` and :class:`SmootherResult`
live in :mod:`kftrack.results` (so the drivers can build them without importing this module) and
are re-exported here.

Equations (Bar-Shalom, Li & Kirubarajan 2001, §5.2):

.. math::

    x^- = F x, \quad P^- = F P F^\top + Q

    y = z - H x^-, \quad S = H P^- H^\top + R, \quad K = P^- H^\top S^{-1}

    x^+ = x^- + K y, \quad P^+ = (I - K H) P^- (I - K H)^\top + K R K^\top \;\text{(Joseph form)}
"""
from __future__ import annotations

import math

import numpy as np

from ._validate import (as_matrix, as_vector, broadcast_batch, check_covariance, check_finite, check_form,
                        check_missing, check_state)
from .engines import Given, Kernel, PerDt, check_dts, run_filter, run_smoother_scan, stand_in, to_engine, use_jax
from .kernels import Update, kf_correct, kf_gain, kf_predict, kf_score, kf_update, rts_step
from .results import FilterResult, SmootherResult  # re-exported: the result types live at the bottom

__all__ = ["Update", "FilterResult", "SmootherResult", "predict", "update", "kalman_filter", "rts_smoother",
           "KalmanStepper"]


def predict(x, P, F, Q) -> tuple[np.ndarray, np.ndarray]:
    r"""Time update :math:`x^- = F x`, :math:`P^- = F P F^\top + Q`.

    Parameters
    ----------
    x : (..., n) state mean.
    P : (..., n, n) state covariance, symmetric positive semi-definite.
    F : (n, n) or (..., n, n) transition matrix.
    Q : (n, n) or (..., n, n) process-noise covariance of the step (a discrete covariance).

    Returns
    -------
    x, P : the predicted mean ``(..., n)`` and covariance ``(..., n, n)``.

    Raises
    ------
    ValueError, TypeError
        On bad input, naming the argument; also when the prediction overflows float64 (e.g.
        ``P = 1e308 I``), naming the input of largest magnitude.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.kalman import predict
    >>> F = np.array([[1.0, 1.0], [0.0, 1.0]])        # constant velocity, T = 1 s; state [x, vx]
    >>> x, P = predict(np.array([0.0, 1.0]), np.eye(2), F, 0.1 * np.eye(2))
    >>> print(x)
    [1. 1.]
    >>> print(np.round(P, 6))                         # F P F^T + Q
    [[2.1 1. ]
     [1.  1.1]]
    """
    x, P, n = check_state(x, P)
    F = as_matrix(F, "F", n, n, origin=f"n = {n} from x")
    Q = check_covariance(Q, "Q", n, origin=f"n = {n} from x")
    broadcast_batch({"x": x.shape[:-1], "P": P.shape[:-2], "F": F.shape[:-2], "Q": Q.shape[:-2]})
    out = kf_predict(x, P, F, Q)
    if not (np.isfinite(out[0]).all() and np.isfinite(out[1]).all()):
        raise ValueError(_overflow("the prediction F x, F P F^T + Q", x=x, P=P, F=F, Q=Q))
    return out


def _overflow(what: str, **args) -> str:
    """The message for a result that overflows float64 from finite inputs: it names the input of
    largest magnitude first, and gives every input's largest entry."""
    mags = {k: float(np.abs(v).max()) for k, v in args.items()}
    big = max(mags, key=mags.get)
    desc = ", ".join(f"max |{k}| = {v:.3g}" for k, v in mags.items())
    return (f"{big} is too large: {what} overflows float64 (is not finite) with {desc}; rescale the units "
            "of the state and the measurement")


def update(x, P, z, H, R, *, form: str = "joseph") -> Update:
    r"""Measurement update, by default with the Joseph-form covariance.

    Parameters
    ----------
    x : (..., n) prior mean.
    P : (..., n, n) prior covariance.
    z : (..., m) measurement.
    H : (m, n) or (..., m, n) measurement matrix.
    R : (m, m) or (..., m, m) measurement-noise covariance, positive definite.
    form : ``"joseph"`` (default), :math:`P^+ = (I-KH)P^-(I-KH)^\top + KRK^\top`, symmetrized;
        or ``"standard"``, the short form :math:`P^+ = (I-KH)P^-` returned exactly as computed
        (not symmetrized), to study its round-off (Grewal & Andrews 2001).

    Returns
    -------
    Update
        ``(x, P, y, S, K, nis, loglik)``; see :class:`Update`. A measurement so far from the
        prediction that :math:`y^\top S^{-1} y` exceeds the float64 range (about 1.8e308) gets
        ``nis = inf`` and ``loglik = -inf``, the correctly rounded values (``x``, ``P`` are
        unaffected); a posterior ``x`` or ``P`` that overflows raises a ``ValueError`` naming
        the input of largest magnitude.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.kalman import update
    >>> u = update(np.array([1.0, 1.0]), np.diag([2.0, 1.0]), z=np.array([1.5]), H=np.array([[1.0, 0.0]]), R=np.eye(1))
    >>> print(np.round(u.x, 6), np.round(u.K[:, 0], 6), np.round(u.nis, 6))   # gain 2 / (2 + 1)
    [1.333333 1.      ] [0.666667 0.      ] 0.083333
    >>> print(np.round(u.P, 6) + 0.0)
    [[0.666667 0.      ]
     [0.       1.      ]]
    """
    form = check_form(form)
    x, P, n = check_state(x, P)
    z = as_vector(z, "z")
    m = z.shape[-1]
    H = as_matrix(H, "H", m, n, origin=f"m = {m} from z, n = {n} from x")
    R = check_covariance(R, "R", m, positive_definite=True, origin=f"m = {m} from z")
    broadcast_batch({"x": x.shape[:-1], "P": P.shape[:-2], "z": z.shape[:-1], "H": H.shape[:-2], "R": R.shape[:-2]})
    u = kf_update(x, P, z, H, R, form)
    if not (np.isfinite(u.x).all() and np.isfinite(u.P).all()):
        raise ValueError(_overflow("the updated mean x + K (z - H x) or covariance", x=x, P=P, z=z, H=H, R=R))
    return u


def _transitions(F, Q, n: int, T: int, dt, time_varying: bool, what: str = "x0", times=None):
    """``F``, ``Q`` in one of the three forms of :func:`kalman_filter`, checked. Returns
    ``(F, Q, per_step)``: constant ``(..., n, n)`` matrices, or (``per_step`` True) stacks
    ``(T, ..., n, n)`` with ``F[k]`` mapping step ``k`` to ``k + 1``. The intervals come from
    ``dt`` or ``times`` (:func:`kftrack.engines.check_dts`)."""
    if not isinstance(time_varying, (bool, np.bool_)):
        raise TypeError(f"time_varying must be True or False, got {time_varying!r}")
    origin = f"n = {n} from {what}"
    if dt is not None or times is not None:
        given = "dt" if times is None else "times"
        if time_varying:
            raise ValueError(f"{given} and time_varying=True exclude each other: give F, Q as callables of dt "
                             f"({given}=...) or as (T, ..., n, n) stacks (time_varying=True)")
        for name, fn in (("F", F), ("Q", Q)):
            if not callable(fn):
                raise TypeError(f"{name} must be a callable of the interval dt (e.g. model.{name}) when {given} is "
                                f"given, got {type(fn).__name__}")
        dts = check_dts(dt, T, times)
        per_dt = PerDt(lambda d: (F(d), Q(d)))  # each distinct interval evaluated once
        distinct, where = np.unique(dts, return_inverse=True)
        mats = []
        for d in distinct:
            Fd, Qd = per_dt(d)
            mats.append((as_matrix(Fd, "F(dt)", n, n, origin=f"{origin}, dt = {d:g}"),
                         check_covariance(Qd, "Q(dt)", n, origin=f"{origin}, dt = {d:g}")))
        if distinct.size == 1:  # one interval: the constant form, to the last bit
            return mats[0][0], mats[0][1], False
        shp = broadcast_batch({"F(dt)": np.broadcast_shapes(*(a.shape[:-2] for a, _ in mats)),
                               "Q(dt)": np.broadcast_shapes(*(b.shape[:-2] for _, b in mats))})
        Fs = np.stack([np.broadcast_to(a, shp + (n, n)) for a, _ in mats])[where]
        Qs = np.stack([np.broadcast_to(b, shp + (n, n)) for _, b in mats])[where]
        return Fs, Qs, True
    for name, fn in (("F", F), ("Q", Q)):
        if callable(fn) and not hasattr(fn, "shape"):
            raise TypeError(f"{name} is a callable ({type(fn).__name__}); pass the sampling intervals dt=... "
                            f"(or the timestamps times=...) to evaluate it, or pass {name} as an array")
    Qh = check_covariance(stand_in(Q, "cov"), "Q", n, origin=origin)
    Fh = as_matrix(stand_in(F, "matrix"), "F", n, n, origin=origin)
    if not time_varying:
        return Fh, Qh, False
    for name, a in (("F", Fh), ("Q", Qh)):
        if a.ndim < 3 or a.shape[0] != T:
            raise ValueError(f"{name} must have shape (T, ..., {n}, {n}) with T = {T} steps (time first) when "
                             f"time_varying=True, got shape {a.shape}")
    return Fh, Qh, True


def kalman_filter(zs, x0, P0, F, Q, H, R, *, dt=None, times=None, time_varying: bool = False,
                  progress: bool = False, dtype=None, priors: bool = True, missing=None) -> FilterResult:
    r"""Filter a whole measurement sequence: at each step update with ``zs[k]``, then predict.

    A measurement row that is all NaN means "no measurement at this step": the filter only
    predicts across it (or say which rows are missing with ``missing=``). Validation happens
    once here; the loop runs unchecked kernels (:mod:`kftrack.kernels`) with one of the two
    drivers of :mod:`kftrack.engines`.

    The transition comes in one of three forms:

    * constant: ``F``, ``Q`` arrays ``(n, n)`` or ``(..., n, n)``, the same at every step;
    * irregular sampling: ``dt`` (or ``times``) given, ``F`` and ``Q`` callables of the interval
      (``model.F``, ``model.Q`` of :mod:`kftrack.models`), evaluated once per distinct interval;
      step ``k`` predicts with :math:`F(dt_k)`, :math:`Q(dt_k)`;
    * ``time_varying=True``: ``F``, ``Q`` stacks ``(T, ..., n, n)``, ``F[k]`` mapping step ``k`` to
      step ``k + 1``.

    .. math::

        x^-_{k+1} = F_k x_k,\quad P^-_{k+1} = F_k P_k F_k^\top + Q_k

    (the last ``F[T-1]``, ``dt[T-1]`` is not used: no step follows).

    Parameters
    ----------
    zs : (T, ..., m) measurements, time first; rows of NaN mark missing measurements.
    x0 : (..., n) prior mean for step 0 (before ``zs[0]``).
    P0 : (..., n, n) prior covariance for step 0.
    F, Q : the transition matrix and process-noise covariance in one of the forms above.
    H, R : (m, n) or (..., m, n) measurement matrix, (m, m) or (..., m, m) measurement noise
        (positive definite), constant over time.
    dt : None, or the intervals (s) after each step: a scalar, ``(T,)`` (``dt[k]`` from step ``k``
        to ``k + 1``, the last one unused, as in :func:`kftrack.imm.imm_filter`) or ``(T - 1,)``
        (``np.diff(t)`` of the timestamps); then ``F``, ``Q`` are callables.
    times : None, or instead of ``dt`` the timestamps ``(T,)`` (s, non-decreasing) of the
        measurements: ``dt = np.diff(times)``. ``dt`` and ``times`` exclude each other.
    time_varying : if True, ``F`` and ``Q`` carry a leading time axis ``T``.
    progress : show a progress bar (tqdm) over the time steps (NumPy engine only).
    dtype : None or ``"float64"`` (default), or ``"float32"``, an explicit choice that loses
        about nine decimal digits (round-off :math:`2^{-24}` relative per operation instead of
        :math:`2^{-53}`). With JAX arrays float64 needs ``jax_enable_x64``.
    priors : True (default): the result holds the predictions ``x_prior``, ``P_prior``.
        False: ``x_prior`` and ``P_prior`` are None in the result (:func:`rts_smoother` needs
        them), and neither engine stores them: with per-run covariances nearly half the output
        memory (``n + n²`` of the ``2n + 2n² + 2`` numbers per run and step; with shared
        covariances, which the NumPy engine stores once, the ``n`` of ``x_prior`` per run and step).
        ``x``, ``P``, ``nis``, ``loglik`` are the same (NumPy engine: the same bits).
    missing : which measurement rows are not used, known before the data are seen:

        * None (default): the rows of NaN of ``zs``;
        * False: none (every row of ``zs`` must then be finite);
        * a boolean NumPy array ``(T,)`` (the same steps for all runs) or ``(T, ...)`` (batch
          axes broadcasting to those of ``zs``): True where the row is not used, whatever it
          holds; the other rows must be finite.

        Inside your own ``jax.jit``, ``jax.grad`` or ``jax.vmap`` the values of ``zs`` are not
        known when the filter is traced, so with None the missing rows are found inside the
        trace, run by run, and the covariance recursion, which dominates the cost on small
        states, is repeated for every run (correct for any data). ``missing=False`` or a mask is
        static information: the traced call then takes the path of a direct call (covariances
        computed once for all runs), e.g. ``jax.jit(lambda z: kalman_filter(z, x0, P0, F, Q, H, R,
        missing=False).x)``. Inside a trace the values of ``zs`` cannot be checked: a NaN in a row
        used propagates.

    Returns
    -------
    FilterResult
        priors and posteriors ``(T, ..., n)``, ``(T, ..., n, n)`` (priors None with
        ``priors=False``); ``nis``, ``loglik`` ``(T, ...)``.
        JAX arrays if any input is a JAX array (the JAX engine, :func:`kftrack.engines.run_scan`),
        NumPy arrays otherwise. When no covariance input has batch axes and all runs miss the
        same rows, the covariance recursion is computed once for all runs (it does not depend on
        the data); the NumPy engine then returns ``P``, ``P_prior`` as read-only broadcast views.
        Inside ``jax.jit``, ``jax.grad`` and ``jax.vmap`` the inputs may be abstract: their
        shapes are checked, their values are not (see ``missing``); outputs you do not use are
        not computed (XLA drops them from the compiled program).

    Raises
    ------
    ValueError, TypeError
        On bad input, naming the argument.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.kalman import kalman_filter
    >>> from kftrack.models import ConstantVelocity
    >>> cv = ConstantVelocity(ndim=1, q=0.1)          # state [x, vx]
    >>> zs = np.array([[0.0], [1.1], [np.nan], [2.9], [4.2]])   # (T, m); a NaN row: no measurement
    >>> res = kalman_filter(zs, np.zeros(2), 10 * np.eye(2), cv.F(1.0), cv.Q(1.0), cv.H, np.eye(1))
    >>> res.x.shape, res.P.shape, np.isnan(res.nis).tolist()
    ((5, 2), (5, 2, 2), [False, False, True, False, False])
    >>> print(np.round(res.x[-1], 6))
    [4.077435 1.02663 ]
    >>> # irregular sampling: F and Q as functions of the interval, dt[k] from step k to k + 1
    >>> res = kalman_filter(zs, np.zeros(2), 10 * np.eye(2), cv.F, cv.Q, cv.H, np.eye(1), dt=[1.0, 0.5, 0.5, 1.0, 1.0])
    >>> print(np.round(res.x[-1], 6))
    [4.17199  1.419501]
    >>> same = kalman_filter(zs, np.zeros(2), 10 * np.eye(2), cv.F, cv.Q, cv.H, np.eye(1), times=[0.0, 1.0, 1.5, 2.0, 3.0])
    >>> bool(np.all(same.x == res.x))                 # the timestamps instead: the same intervals
    True
    >>> # 1000 Monte Carlo runs in one call: a batch axis after time
    >>> runs = np.random.default_rng(0).normal(size=(5, 1000, 1))
    >>> kalman_filter(runs, np.zeros(2), 10 * np.eye(2), cv.F(1.0), cv.Q(1.0), cv.H, np.eye(1)).x.shape
    (5, 1000, 2)
    """
    if not isinstance(priors, (bool, np.bool_)):
        raise TypeError(f"priors must be True or False, got {priors!r}")
    return _filter(zs, x0, P0, F, Q, H, R, dt, time_varying, times, missing, dtype, progress=progress, priors=priors)


def _filter(zs, x0, P0, F, Q, H, R, dt, time_varying, times, missing, dtype, *, progress=False, priors=True,
            total=False, checkpoint=None):
    """:func:`kalman_filter` after its check of ``priors``; with ``total`` the log-likelihood of each
    run summed over its measured steps, shape ``batch`` (``kftrack.engines.run_filter``), for
    :func:`kftrack.tuning.total_loglik`: on the JAX engine a loop that stores no sequence
    (``checkpoint``: its segments under ``jax.checkpoint``, validated by the caller)."""
    zs_h, gone = check_missing(zs, missing)
    T, m = zs_h.shape[0], zs_h.shape[-1]
    x0_h, P0_h, n = check_state(stand_in(x0, "vector"), stand_in(P0, "cov"), ("x0", "P0"))
    R_h = check_covariance(stand_in(R, "cov"), "R", m, positive_definite=True, origin=f"m = {m} from zs")
    F_h, Q_h, per_step = _transitions(F, Q, n, T, dt, time_varying, times=times)
    H_h = as_matrix(stand_in(H, "matrix"), "H", m, n, origin=f"m = {m} from zs, n = {n} from x0")
    tb = 1 if per_step else 0  # leading time axis of F, Q
    batch = broadcast_batch({"zs[k]": zs_h.shape[1:-1], "x0": x0_h.shape[:-1], "P0": P0_h.shape[:-2],
                             "F": F_h.shape[tb:-2], "Q": Q_h.shape[tb:-2], "H": H_h.shape[:-2], "R": R_h.shape[:-2]})
    transition = (Given(F, F_h), Given(Q, Q_h))
    return run_filter(Given(zs, zs_h), gone, Given(x0, x0_h), Given(P0, P0_h), batch, _KF_PREDICT, _KF_UPDATE,
                      pred_steps=transition if per_step else (), pred_args=() if per_step else transition,
                      upd_args=(Given(H, H_h), Given(R, R_h)),
                      cov_shapes=(P0_h.shape[:-2], F_h.shape[tb:-2], Q_h.shape[tb:-2], H_h.shape[:-2], R_h.shape[:-2]),
                      dtype=dtype, progress=progress, priors=priors, total=total, checkpoint=checkpoint)


_KF_PREDICT = Kernel(kf_predict)
_KF_UPDATE = Kernel(kf_update)


def _compact(a, nb: int):
    """A NumPy broadcast view ``(T, *batch, ...)`` with zero strides on the ``nb`` batch axes,
    reduced to ``(T, ...)`` (the shared covariances of :func:`kalman_filter`); ``None`` otherwise."""
    if isinstance(a, np.ndarray) and nb and all(st == 0 for st in a.strides[1:1 + nb]):
        return a[(slice(None),) + (0,) * nb]
    return None


def _smoother_transitions(F, dt, times, time_varying: bool, T: int, n: int, batch: tuple):
    """The transition of a smoother, checked against the filter's result (states ``n``, ``T``
    steps, batch axes ``batch``): ``(F_h, per_step)``, ``F_h`` ``(..., n, n)`` or, with
    ``per_step``, ``(T, ..., n, n)``, as :func:`_transitions` gives it (``Q``, which the
    smoother does not use, an identity), its batch axes broadcasting to ``batch``; else a
    ``ValueError`` naming ``F``. Shared by :func:`rts_smoother` and
    :func:`kftrack.parallel.parallel_smoother`."""
    eye = np.eye(n)
    timed = dt is not None or times is not None
    F_h, _, per_step = _transitions(F, (lambda d: eye) if timed else (eye if not time_varying else
                                    np.broadcast_to(eye, (T, n, n))), n, T, dt, time_varying, "the filter's states",
                                    times)
    tb = 1 if per_step else 0
    if broadcast_batch({"result": batch, "F": F_h.shape[tb:-2]}) != batch:
        raise ValueError(f"F must have shape ({n}, {n}) or the filter's batch axes {batch} + ({n}, {n}), "
                         f"got shape {F_h.shape}")
    return F_h, per_step


def rts_smoother(result: FilterResult, F, *, dt=None, times=None, time_varying: bool = False) -> SmootherResult:
    r"""Rauch–Tung–Striebel smoother over a :class:`FilterResult` (Särkkä 2013, Thm 8.2).

    .. math::

        G_k = P_k F_k^\top (P^-_{k+1})^{-1}, \quad
        x^s_k = x_k + G_k (x^s_{k+1} - x^-_{k+1}), \quad
        P^s_k = P_k + G_k (P^s_{k+1} - P^-_{k+1}) G_k^\top

    Parameters
    ----------
    result : the output of :func:`kalman_filter`, with its priors (the default ``priors=True``);
        JAX arrays run the smoother's JAX engine (:func:`kftrack.engines.run_smoother_scan`) and
        return JAX arrays.
    F : the transition used by the filter, in the same form: an ``(n, n)`` or ``(..., n, n)``
        matrix; a callable of ``dt`` (with ``dt``); or a ``(T, ..., n, n)`` stack
        (``time_varying=True``).
    dt : the filter's intervals, scalar, ``(T,)`` or ``(T - 1,)``, when ``F`` is a callable.
    times : instead of ``dt``, the filter's timestamps ``(T,)`` (s, non-decreasing).
    time_varying : if True, ``F`` carries a leading time axis ``T`` (``F[k]``: step ``k`` to ``k + 1``).

    Returns
    -------
    SmootherResult
        ``x`` ``(T, ..., n)``, ``P`` ``(T, ..., n, n)``, gains ``G`` ``(T-1, ..., n, n)``.

    Notes
    -----
    A singular prediction :math:`P^-_{k+1}` (a known start ``P0 = 0`` with ``Q = 0`` or a
    rank-deficient ``Q``) is handled on the NumPy engine with the pseudo-inverse,
    :math:`G_k = P_k F_k^\top (P^-_{k+1})^{+}`, the smoother gain in that case
    (:func:`kftrack.kernels.rts_step`); the JAX engine solves without that branch (inf/NaN there).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.kalman import kalman_filter, rts_smoother
    >>> from kftrack.models import ConstantVelocity
    >>> cv = ConstantVelocity(ndim=1, q=0.1)
    >>> zs = np.array([[0.0], [1.1], [np.nan], [2.9], [4.2]])
    >>> filt = kalman_filter(zs, np.zeros(2), 10 * np.eye(2), cv.F(1.0), cv.Q(1.0), cv.H, np.eye(1))
    >>> smooth = rts_smoother(filt, cv.F(1.0))
    >>> print(np.round(smooth.x[2], 6))               # the missing step, now from both sides
    [2.03797  1.009759]
    >>> bool(np.all(smooth.x[-1] == filt.x[-1]))      # the last step is the filter's
    True
    """
    if not isinstance(result, FilterResult):
        raise TypeError(f"result must be a FilterResult from kalman_filter, got {type(result).__name__}")
    if result.x_prior is None or result.P_prior is None:
        raise ValueError("result has no priors (x_prior, P_prior are None): the smoother needs them; run "
                         "kalman_filter with priors=True (the default)")
    jax_engine = use_jax(*result)
    n = result.x.shape[-1]
    T = result.x.shape[0]
    batch = result.x.shape[1:-1]
    F_h, per_step = _smoother_transitions(F, dt, times, time_varying, T, n, batch)
    tb = 1 if per_step else 0
    if jax_engine:  # the same step, rts_step, under a reversed jax.lax.scan
        if T < 2:
            return SmootherResult(result.x, result.P, result.P[:0])
        dt_ = result.x.dtype
        F_e = F if use_jax(F) else to_engine(F_h, True, dt_)
        return SmootherResult(*run_smoother_scan(result.x, result.P, result.x_prior, result.P_prior, F_e, per_step))
    P, P_prior = _compact(result.P, len(batch)), _compact(result.P_prior, len(batch))
    shared = P is not None and P_prior is not None and F_h.shape[tb:-2] == ()
    if not shared:
        P, P_prior = result.P, result.P_prior
    for name, a in (("x", result.x), ("P", P), ("x_prior", result.x_prior), ("P_prior", P_prior)):
        check_finite(np.asarray(a), f"result.{name}")
    xs = result.x.copy()
    Ps = P.copy()
    G = np.empty((max(T - 1, 0),) + P.shape[1:])
    for k in range(T - 2, -1, -1):
        Fk = F_h[k] if per_step else F_h
        try:
            xs[k], Ps[k], G[k] = rts_step(result.x[k], P[k], result.x_prior[k + 1], P_prior[k + 1], xs[k + 1],
                                          Ps[k + 1], Fk)
        except np.linalg.LinAlgError as exc:
            raise ValueError(f"result.P_prior[{k + 1}] cannot be used by the smoother ({exc}); pass the FilterResult "
                             "of kalman_filter run with this F") from None
    if shared:
        Ps = np.broadcast_to(Ps.reshape((T,) + (1,) * len(batch) + (n, n)), (T,) + batch + (n, n))
        G = np.broadcast_to(G.reshape((G.shape[0],) + (1,) * len(batch) + (n, n)), (G.shape[0],) + batch + (n, n))
    return SmootherResult(xs, Ps, G)


def _read_only(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def _same_bits(a: np.ndarray, b) -> bool:
    """True if ``b`` is ``a`` or an array with the same shape, memory layout and bytes (so every
    kernel computes the same bits from it; ``-0.0`` and ``0.0`` differ, NaN equals itself)."""
    return a is b or (b is not None and a.shape == b.shape and a.strides == b.strides and a.tobytes() == b.tobytes())


class KalmanStepper:
    r"""A linear Kalman filter stepped one call at a time, its inputs validated once.

    :meth:`predict` and :meth:`update` call the kernels of :mod:`kftrack.kernels`
    (:func:`~kftrack.kernels.kf_predict`, :func:`~kftrack.kernels.kf_gain`,
    :func:`~kftrack.kernels.kf_correct`, :func:`~kftrack.kernels.kf_score`) without checks:
    everything but the measurement is validated here, once, and a measurement only for its
    shape and finiteness. ``update(z)`` then ``predict()`` at every step gives what
    :func:`kalman_filter` gives for the same data, to the last bit.

    .. math::

        x^- = F x,\quad P^- = F P F^\top + Q;\qquad
        y = z - H x^-,\quad S = H P^- H^\top + R,\quad K = P^- H^\top S^{-1},\quad x^+ = x^- + K y,

        P^+ = (I - KH) P^- (I - KH)^\top + K R K^\top \;\text{(Joseph form)}

    **Reuse of the covariance recursion.** :math:`P`, :math:`S` and :math:`K` do not depend on
    the measurements. The stepper keeps the covariance each of its two kernels last started from
    and what it computed from it; when a step starts from a covariance with exactly the same bits
    (same shape, layout and bytes), the kernel would compute exactly the same bits again, so the
    stepper reuses them and computes the mean alone (:math:`Fx`; :math:`z - Hx`,
    :math:`x + Ky`). What is compared is the input of the covariance recursion, not its output:
    :math:`F, Q, H, R` and ``form`` are fixed at construction (private read-only copies), so the
    covariance a step starts from is its only input that can change. With constant matrices the
    rounded Riccati recursion typically settles on such a floating-point fixed point after some
    tens to a hundred steps (on the 2-D constant-velocity workload of ``benchmarks/filters.py``
    the benchmark reports the update, about the hundredth); from there on a step costs the mean
    recursion only. It need not settle (the rounded recursion may end in a short cycle instead,
    or :math:`P` may grow without bound for an undetectable model): then every step runs the
    full recursion, with the same results. A missing measurement changes the covariance, and
    the full recursion runs again until it repeats. ``reused_from`` says from which update on
    the covariances are reused.

    Parameters
    ----------
    x0 : (..., n) prior mean before the first measurement.
    P0 : (..., n, n) its covariance, symmetric positive semi-definite.
    F, Q : (n, n) or (..., n, n) transition matrix and process-noise covariance of one step; or,
        with ``dt``, callables of the interval such as ``model.F``, ``model.Q`` of
        :mod:`kftrack.models`, evaluated once at ``dt``.
    H : (m, n) or (..., m, n) measurement matrix.
    R : (m, m) or (..., m, m) measurement-noise covariance, positive definite.
    dt : None, or the sampling interval (s), a scalar ``>= 0``, when ``F`` and ``Q`` are callables.
    form : ``"joseph"`` (default) or ``"standard"``, the covariance update of :func:`update`.

    Attributes
    ----------
    steps : int, the number of :meth:`update` calls so far.
    reused_from : int or None, the index (0-based, counted in :meth:`update` calls) of the first
        update of the present unbroken run of updates that reused the covariances; None when the
        last update computed them or had no measurement.

    Raises
    ------
    ValueError, TypeError
        On bad input, naming the argument.

    Notes
    -----
    NumPy only, float64 (for JAX arrays use :func:`kalman_filter`, whose JAX engine compiles the
    whole loop). Batch axes broadcast as everywhere in :mod:`kftrack`: one stepper may carry many
    tracks, and the covariances stay shared when no covariance input has batch axes. A missing
    measurement is ``z=None`` or a ``z`` of NaN, for all tracks at once (a missing measurement in
    some tracks only: :func:`kalman_filter`). The covariance reuse is exact, never an
    approximation: where it applies, the arrays are the ones the kernels would return.
    :attr:`P`, :attr:`S`, :attr:`K` and :attr:`y` are read-only because the first three are
    shared with the cache (and :attr:`nis`, :attr:`loglik` are computed from :attr:`y` when
    read): copy them to change them; setting their ``writeable`` flag back defeats the check.
    The inputs are copied at construction, so changing the caller's arrays afterwards has no
    effect.

    Examples
    --------
    >>> from kftrack.models import ConstantVelocity
    >>> cv = ConstantVelocity(ndim=2, q=0.1)
    >>> kf = KalmanStepper(np.zeros(4), 100.0 * np.eye(4), cv.F, cv.Q, cv.H, 25.0 * np.eye(2), dt=1.0)
    >>> kf.update(np.array([1.0, 2.0])); kf.predict()
    >>> kf.x.shape, kf.P.shape
    ((4,), (4, 4))
    """

    def __init__(self, x0, P0, F, Q, H, R, *, dt=None, form: str = "joseph"):
        form = check_form(form)
        x0, P0, n = check_state(x0, P0, ("x0", "P0"))
        F, Q, _ = _transitions(F, Q, n, 1, dt, False)
        H = as_matrix(H, "H", None, n, origin=f"n = {n} from x0")
        m = H.shape[-2]
        R = check_covariance(R, "R", m, positive_definite=True, origin=f"m = {m} from H")
        batch = broadcast_batch({"x0": x0.shape[:-1], "P0": P0.shape[:-2], "F": F.shape[:-2], "Q": Q.shape[:-2],
                                 "H": H.shape[:-2], "R": R.shape[:-2]})
        self._F, self._Q, self._H, self._R = (_read_only(np.array(a, dtype=np.float64)) for a in (F, Q, H, R))
        self._form, self._m, self._batch, self._z_shape = form, m, batch, batch + (m,)
        self._x = np.array(np.broadcast_to(x0, batch + (n,)), dtype=np.float64)
        cov_batch = np.broadcast_shapes(P0.shape[:-2], F.shape[:-2], Q.shape[:-2], H.shape[:-2], R.shape[:-2])
        self._P = _read_only(np.array(np.broadcast_to(P0, cov_batch + (n, n)), dtype=np.float64))
        self._pred_in = self._pred_P = None  # the covariance predict() last started from, and its result
        self._gain_in = self._gain = None  # the covariance update() last started from, and its Gain
        self._last = None  # (innovation, Gain) of the last update; None after a missing measurement
        self._scored = None
        self.steps = 0
        self.reused_from = None

    # -- the two steps ------------------------------------------------------------------------
    def predict(self) -> None:
        r"""Time update :math:`x^- = F x`, :math:`P^- = F P F^\top + Q` (the covariance reused
        when :attr:`P` has the bits the last computed prediction started from)."""
        P = self._P
        if _same_bits(P, self._pred_in):
            self._pred_in = P
            self._x = kf_predict(self._x, None, self._F, self._Q)[0]
            self._P = self._pred_P
            return
        self._x, P_next = kf_predict(self._x, P, self._F, self._Q)
        self._pred_in, self._pred_P = P, _read_only(P_next)
        self._P = P_next

    def update(self, z) -> None:
        r"""Measurement update with ``z`` ``(..., m)``: :math:`y = z - Hx`, :math:`x^+ = x + Ky`
        and :math:`P^+` (Joseph form by default). ``z`` None or all NaN: no measurement, the
        state is kept and :attr:`nis`, :attr:`loglik` are NaN. A ``z`` of the wrong shape, with
        inf or only partly NaN raises a ``ValueError`` naming ``z``."""
        z = self._measurement(z)
        k = self.steps
        self.steps = k + 1
        self._scored = None
        if z is None:
            self._last = None
            self.reused_from = None
            return
        P = self._P
        if _same_bits(P, self._gain_in):
            g = self._gain
            if self.reused_from is None:
                self.reused_from = k
        else:
            g = kf_gain(P, self._H, self._R, self._form)
            for a in (g.S, g.K, g.P):
                _read_only(a)
            self._gain = g
            self.reused_from = None
        self._gain_in = P
        self._x, y = kf_correct(self._x, z, self._H, g.K)
        self._P = g.P
        self._last = (y, g)

    def _measurement(self, z):
        """``z`` checked (shape, finite) or None for a missing measurement."""
        if type(z) is np.ndarray and z.dtype == np.float64 and z.shape == self._z_shape and (
                all(map(math.isfinite, z.tolist())) if z.ndim == 1 else np.isfinite(z).all()):
            return z  # the fast path: a float64 array of the right shape, finite
        if z is None:
            return None
        z = as_vector(z, "z", self._m, allow_nan=True)
        if not _broadcasts_to(z.shape[:-1], self._batch):
            raise ValueError(f"z must have shape {self._z_shape} (batch axes of the state + (m,)), or broadcast "
                             f"to it, got shape {z.shape}")
        nan = np.isnan(z)
        if nan.all():
            return None
        if nan.any():
            raise ValueError("z is only partly NaN; a missing measurement is z=None or a z of NaN (all tracks "
                             "at once; for missing measurements in some tracks only use kalman_filter)")
        if np.isinf(z).any():
            raise ValueError("z must be finite, or None or NaN for a missing measurement, but it contains inf")
        return z

    # -- the state and the last update ------------------------------------------------------------
    @property
    def x(self) -> np.ndarray:
        """(..., n) the mean: the posterior after :meth:`update`, the prior after :meth:`predict`."""
        return self._x

    @property
    def P(self) -> np.ndarray:
        """(..., n, n) the covariance that goes with :attr:`x` (read-only)."""
        return self._P

    @property
    def y(self):
        """(..., m) the innovation of the last update (read-only); None if it had no measurement (or
        before any)."""
        if self._last is None:
            return None
        y = self._last[0]
        y.flags.writeable = False  # nis and loglik are computed from it when read
        return y

    @property
    def S(self):
        """(..., m, m) the innovation covariance of the last update (None as for :attr:`y`)."""
        return None if self._last is None else self._last[1].S

    @property
    def K(self):
        """(..., n, m) the Kalman gain of the last update (None as for :attr:`y`)."""
        return None if self._last is None else self._last[1].K

    def _score(self):
        if self._scored is None:
            nan = np.full(self._batch, np.nan)[()]
            self._scored = (nan, nan) if self._last is None else kf_score(*self._last)
        return self._scored

    @property
    def nis(self):
        r"""(...) the NIS :math:`y^\top S^{-1} y` of the last update (computed when read); NaN if it had
        no measurement (or before any)."""
        return self._score()[0]

    @property
    def loglik(self):
        r"""(...) the log-likelihood :math:`\log N(y; 0, S)` of the last update (computed when read);
        NaN as for :attr:`nis`."""
        return self._score()[1]


def _broadcasts_to(a: tuple, b: tuple) -> bool:
    """True if batch shape ``a`` broadcasts to ``b`` (without growing it)."""
    try:
        return np.broadcast_shapes(a, b) == b
    except ValueError:
        return False
