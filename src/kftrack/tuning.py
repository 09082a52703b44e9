r"""Noise parameters by maximum likelihood: the innovation log-likelihood of a linear-Gaussian
state-space model as a function of log noise parameters, and its maximisation.

For a model with parameters :math:`\theta` (e.g. the spectral density :math:`q` of the white
acceleration and the measurement variance :math:`r`), the Kalman filter factorises the
likelihood of the measurements into its innovations (prediction-error decomposition,
Harvey 1989, ch. 3; Särkkä 2013, §12.3):

.. math::

    \ell(\theta) = \log p(z_{0:T-1} \mid \theta)
    = \sum_{k\,:\,z_k \text{ measured}} \log \mathcal N\!\left(y_k;\, 0,\, S_k(\theta)\right)
    = -\tfrac12 \sum_k \left(y_k^\top S_k^{-1} y_k + \log\det(2\pi S_k)\right),

with :math:`y_k`, :math:`S_k` the innovation and its covariance of
:func:`kftrack.kalman.kalman_filter` (steps without a measurement add nothing). The
parameters enter through their logarithms, :math:`\phi = \log\theta`, so that every
:math:`\phi \in \mathbb R^d` is a valid model and the search is unconstrained.

:func:`total_loglik` evaluates :math:`\ell(e^\phi)` with the NumPy engine for NumPy input and
with the JAX engine for a JAX ``log_params``, so that ``jax.grad`` and ``jax.hessian``
give its exact derivatives (on the JAX engine only the sum is computed, by a loop that stores no
per-step sequence: ``kftrack.engines.run_total_scan``, so the reverse pass carries the states
alone). :func:`fit_noise` maximises it either with
``scipy.optimize.minimize`` (NumPy engine, derivatives by finite differences or none) or
by Newton's method with the exact gradient and Hessian from JAX and step halving.
:func:`white_noise_build` makes the model of the common case
:math:`Q_k = q\,\bar Q(dt_k)`, :math:`R = r I`.

At the maximum, the observed information :math:`-\nabla^2 \ell(\hat\phi)` estimates the Fisher
information: asymptotically :math:`\hat\phi \sim \mathcal N(\phi, (-\nabla^2\ell)^{-1})`
(Harvey 1989, ch. 4), the basis of ``NoiseFit.cov_log_params``.

The JAX engine computes in float64 and needs ``jax.config.update("jax_enable_x64", True)``
(see ``kftrack.engines``).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from ._validate import as_float_array, check_finite, check_missing
from .engines import _jax, check_dts, use_jax
from .kalman import _filter, kalman_filter

__all__ = ["NoiseFit", "WhiteNoiseBuild", "total_loglik", "fit_noise", "white_noise_build"]

_EPS = float(np.finfo(float).eps)
_TINY = float(np.finfo(float).tiny)


# --------------------------------------------------------------------------------------------
# the model of the common case
# --------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class WhiteNoiseBuild:
    r"""The model :math:`F_k = F(dt_k)`, :math:`Q_k = q\,\bar Q(dt_k)`, :math:`H`,
    :math:`R = r I_m`, as a ``build`` for :func:`total_loglik` and :func:`fit_noise`.

    Made by :func:`white_noise_build`. Called with ``params = (q, r)`` (NumPy or JAX), it returns
    ``(F, q * Qbar, H, r * I)``.

    Attributes
    ----------
    F : (T, n, n) per-step transition matrices (``time_varying``), or (n, n).
    Qbar : (T, n, n) or (n, n) process noise for ``q = 1``.
    H : (m, n) measurement matrix.
    time_varying : True when ``F``, ``Q`` have the leading time axis (``dt`` an array).
    names : the parameter names, ``("q", "r")``: ``q`` the spectral density of the model's
        white noise (m²/s³ for white acceleration), ``r`` the measurement variance per axis (m²).
    """

    F: np.ndarray
    Qbar: np.ndarray
    H: np.ndarray
    time_varying: bool
    names: tuple[str, ...] = ("q", "r")

    def __call__(self, params):
        q, r = params[0], params[1]
        return self.F, q * self.Qbar, self.H, r * np.eye(self.H.shape[0])


def white_noise_build(model, dt) -> WhiteNoiseBuild:
    r"""The build of the model :math:`Q_k = q\,\bar Q(dt_k)`, :math:`R = r I` for a model of
    :mod:`kftrack.models` driven by continuous white noise, its positions measured.

    For :class:`kftrack.models.ConstantVelocity` with spectral density ``q`` (m²/s³), per axis
    :math:`Q(dt) = q\,[[dt^3/3, dt^2/2], [dt^2/2, dt]]`: linear in ``q``, so
    :math:`\bar Q(dt) = Q(dt)|_{q=1}` (Bar-Shalom, Li & Kirubarajan 2001, ch. 6). The
    measurement is ``model.H`` (the positions, state order ``[x, vx, y, vy, ...]``) with
    :math:`R = r I_m`, ``r`` the variance of each position axis (m²). The parameters are
    ``params = (q, r)``, one ``q`` for all axes.

    Parameters
    ----------
    model : a dataclass model of :mod:`kftrack.models` given by its spectral density ``q``
        (``ConstantVelocity(ndim, q=...)``, ``ConstantAcceleration``, ``KnownTurn``, ...) whose
        ``Q(dt)`` is linear in ``q`` (checked). The value of ``model.q`` is not used.
    dt : a scalar interval (s), or ``(T,)`` the interval after each step (``dt[k]`` from step
        ``k`` to ``k + 1``; the last one is not used), as in :func:`kftrack.kalman.kalman_filter`.

    Returns
    -------
    WhiteNoiseBuild
        ``F``, ``Qbar`` of shape ``(T, n, n)`` (``time_varying=True``) for an array ``dt``, or
        ``(n, n)`` for a scalar.

    Raises
    ------
    TypeError, ValueError
        If ``model`` has no continuous spectral density ``q`` in which ``Q`` is linear, or ``dt``
        is not finite and ``>= 0``.
    """
    if not (dataclasses.is_dataclass(model) and not isinstance(model, type)
            and any(f.name == "q" for f in dataclasses.fields(model)) and callable(getattr(model, "Q", None))):
        raise TypeError(f"model must be a model of kftrack.models with a spectral density q "
                        f"(e.g. ConstantVelocity(ndim=2, q=1.0)), got {type(model).__name__}")
    if getattr(model, "noise", "continuous") != "continuous" or model.q is None:
        raise ValueError(f"model must be given by its continuous spectral density q, not a discrete variance; "
                         f"got {model!r}")
    d = check_finite(as_float_array(dt, "dt"), "dt")
    if d.ndim == 0:
        d = check_dts(d, 1)[0]
    elif d.ndim != 1 or np.any(d < 0):
        raise ValueError(f"dt must be a scalar or have shape (T,) with dt >= 0, got shape {d.shape}")
    try:
        one, two = dataclasses.replace(model, q=1.0), dataclasses.replace(model, q=2.0)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"model: cannot set its spectral density q ({exc})") from None
    Qbar = np.asarray(one.Q(d), dtype=float)
    # Q linear in q: Q(q=2) = 2 Q(q=1) up to a few roundings of each entry (relative 8 eps)
    if not np.all(np.abs(np.asarray(two.Q(d)) - 2.0 * Qbar) <= 8 * _EPS * np.abs(Qbar) + _TINY):
        raise ValueError(f"model: its Q(dt) is not linear in q (other noise parameters?), got {model!r}")
    F = np.asarray(model.F(d), dtype=float)
    return WhiteNoiseBuild(F=F, Qbar=Qbar, H=np.asarray(model.H, dtype=float), time_varying=d.ndim == 1)



# --------------------------------------------------------------------------------------------
# the objective
# --------------------------------------------------------------------------------------------
def _check_log_params(log_params):
    """``(log_params, jax_engine)``: a 1-D float vector (JAX arrays stay JAX)."""
    if use_jax(log_params):
        shape = tuple(log_params.shape)
        if len(shape) != 1 or shape[0] == 0:
            raise ValueError(f"log_params must have shape (d,) with d >= 1, got shape {shape}")
        return log_params, True
    lp = check_finite(as_float_array(log_params, "log_params"), "log_params")
    if lp.ndim != 1 or lp.size == 0:
        raise ValueError(f"log_params must have shape (d,) with d >= 1, got shape {lp.shape}")
    return lp, False


def _check_build(build) -> None:
    if not callable(build):
        raise TypeError(f"build must be a callable params -> (F, Q, H, R), got {type(build).__name__}")


def _time_varying(build, time_varying) -> bool:
    if time_varying is None:
        return bool(getattr(build, "time_varying", False))
    if not isinstance(time_varying, (bool, np.bool_)):
        raise TypeError(f"time_varying must be None, True or False, got {time_varying!r}")
    return bool(time_varying)


def _check_zs(zs, missing=None) -> None:
    """At least one measured row (known for a concrete ``zs`` or a ``missing`` mask; the values of a
    JAX tracer cannot be inspected)."""
    _, gone = check_missing(zs, missing)
    if gone is not None and gone.all():
        raise ValueError("zs has no measured row (every row is NaN, or marked in missing): the likelihood is not "
                         "defined")


def _check_checkpoint(checkpoint) -> int | None:
    """None, or a positive int (a NumPy integer too; not a bool)."""
    if checkpoint is None:
        return None
    if isinstance(checkpoint, (bool, np.bool_)) or not isinstance(checkpoint, (int, np.integer)):
        got = f" of shape {tuple(checkpoint.shape)}" if hasattr(checkpoint, "shape") else f" {checkpoint!r}"
        raise TypeError(f"checkpoint must be None or a positive int (steps per segment), got "
                        f"{type(checkpoint).__name__}{got}")
    if checkpoint < 1:
        raise ValueError(f"checkpoint must be a positive int (steps per segment), got {int(checkpoint)}")
    return int(checkpoint)


def total_loglik(log_params, build: Callable, zs, x0, P0, *, time_varying: bool | None = None, missing=None,
                 checkpoint: int | None = None):
    r"""Total innovation log-likelihood :math:`\ell(e^\phi)` of the measurements (nats).

    .. math::

        \ell = \sum_{k\,:\,z_k \text{ measured}} \log \mathcal N(y_k; 0, S_k),
        \qquad (F, Q, H, R) = \mathrm{build}(e^{\phi})

    summed over the steps with a measurement (and over the runs, for batched input): the
    ``nansum`` of ``loglik`` of :class:`kftrack.kalman.FilterResult`.

    Parameters
    ----------
    log_params : (d,) the logarithms :math:`\phi` of the parameters. A NumPy array (or list)
        runs the NumPy engine and returns a float; a JAX array runs the JAX engine and returns
        a JAX scalar, so ``jax.grad`` and ``jax.hessian`` apply (float64 needs
        ``jax_enable_x64``).
    build : callable ``params -> (F, Q, H, R)`` with ``params = exp(log_params)`` of shape
        ``(d,)``, in the forms :func:`kftrack.kalman.kalman_filter` accepts (constant, or ``F``,
        ``Q`` stacks ``(T, ..., n, n)`` with ``time_varying``). Written with operators only
        (``params[0] * Qbar``), it works on both engines; see :func:`white_noise_build`.
    zs : (T, ..., m) measurements, time first; rows of NaN are missing (add nothing).
    x0 : (..., n) prior mean for step 0.
    P0 : (..., n, n) prior covariance for step 0.
    time_varying : whether ``F``, ``Q`` carry a leading time axis ``T``; default (None) the
        ``time_varying`` attribute of ``build`` if it has one (:class:`WhiteNoiseBuild`), else
        False.
    missing : None (the rows of NaN of ``zs`` are missing), False (none is) or a boolean mask of
        the rows not to use, as in :func:`kftrack.kalman.kalman_filter`: inside your own
        ``jax.jit`` of batched data, False or a mask keeps the covariances shared by the runs.
    checkpoint : None (default) or a positive int ``c``: trade compute for memory under
        ``jax.grad`` (JAX engine; the NumPy engine ignores it). Reverse mode stores the
        residuals of every step: memory :math:`M \approx T\,b` for ``T`` steps of ``b`` bytes
        each (per run, the state and the innovations, plus the gains the runs share, one set per step). With ``c`` the ``T`` steps run as
        :math:`\lfloor T/c \rfloor` segments of ``c`` steps, each under ``jax.checkpoint``
        (rematerialised: its forward pass is run again in the reverse pass), so only the state at
        each segment's start is kept: :math:`M \approx (T/c)\,b_0 + c\,b` (``b_0`` the
        bytes of a state), smallest at :math:`c = \sqrt{T b_0 / b}`, near :math:`\sqrt{T}`, for
        about one more forward pass of compute. When ``c`` does not divide ``T`` the :math:`T \bmod c` last steps run as one
        plain segment (no padding); ``c >= T`` is one plain segment, as None. The value is the
        same bit for bit (``tests/test_compose.py``: shared-covariance path, CPU); the gradient differs by the order in which the contributions of the
        steps are summed (round-off; ``tests/test_compose.py`` states the bound).

    Returns
    -------
    float or jax.Array
        :math:`\ell`, a Python float (NumPy engine) or a 0-d JAX array (JAX engine).

    Raises
    ------
    ValueError, TypeError
        On bad input, naming the argument (the filter's own checks name ``F``, ``Q``, ``H``,
        ``R``, ``zs``, ``x0``, ``P0``).
    """
    lp, jax_engine = _check_log_params(log_params)
    checkpoint = _check_checkpoint(checkpoint)
    _check_build(build)
    tv = _time_varying(build, time_varying)
    _check_zs(zs, missing)
    if jax_engine:
        jnp = _jax().numpy
        zs, x0, P0 = (a if use_jax(a) else jnp.asarray(np.asarray(a, dtype=float)) for a in (zs, x0, P0))
        params = jnp.exp(lp)
    else:
        params = np.exp(lp)
    out = build(params)
    if not (isinstance(out, tuple) and len(out) == 4):
        raise TypeError(f"build must return a tuple (F, Q, H, R), got {type(out).__name__}"
                        + (f" of length {len(out)}" if isinstance(out, tuple) else ""))
    F, Q, H, R = out
    expect = np.broadcast_shapes(tuple(np.shape(zs)[1:-1]), tuple(np.shape(x0)[:-1]))
    if jax_engine:  # the sum alone: a loop that stores no sequence (kftrack.engines.run_total_scan)
        ell = _filter(zs, x0, P0, F, Q, H, R, None, tv, None, missing, None, total=True, checkpoint=checkpoint)
        batch = tuple(ell.shape)
    else:
        res = kalman_filter(zs, x0, P0, F, Q, H, R, time_varying=tv, priors=False, missing=missing)  # only loglik
        batch = tuple(res.loglik.shape[1:])
    if batch != expect:
        raise ValueError(f"build: F, Q, H or R add batch axes {batch} to those of zs and x0 "
                         f"{expect}; for per-step F, Q of shape (T, n, n) pass time_varying=True")
    if jax_engine:
        return _jax().numpy.sum(ell)
    return float(np.nansum(res.loglik))


# --------------------------------------------------------------------------------------------
# the maximisation
# --------------------------------------------------------------------------------------------
class NoiseFit(NamedTuple):
    r"""The result of :func:`fit_noise`.

    Attributes
    ----------
    method : ``"scipy"`` or ``"newton"``.
    log_params : (d,) the maximiser :math:`\hat\phi` (logarithms of the parameters).
    params : (d,) :math:`e^{\hat\phi}`.
    loglik : :math:`\ell(e^{\hat\phi})`, nats.
    iterations : optimiser iterations (``scipy``: its ``nit``; ``newton``: Newton steps taken).
    evaluations : evaluations of :math:`\ell` (``scipy``: every call, finite-difference ones
        included; ``newton``: calls of the compiled value-gradient-Hessian, one per trial point of
        the step halving).
    converged : True if the stopping test was met (``scipy``: its ``success``; ``newton``:
        :math:`\|\nabla\ell\|_\infty \le` ``gtol``).
    gradient : (d,) :math:`\nabla\ell` at the result (``scipy``: its finite-difference estimate,
        or None without one; ``newton``: exact).
    hessian : (d, d) :math:`\nabla^2\ell` at the result (``newton``; None for ``scipy``).
    """

    method: str
    log_params: np.ndarray
    params: np.ndarray
    loglik: float
    iterations: int
    evaluations: int
    converged: bool
    gradient: np.ndarray | None
    hessian: np.ndarray | None

    @property
    def cov_log_params(self) -> np.ndarray:
        r"""Asymptotic covariance of :math:`\hat\phi`, the inverse observed information
        :math:`(-\nabla^2\ell(\hat\phi))^{-1}`, ``(d, d)`` (``newton`` fits only)."""
        if self.hessian is None:
            raise ValueError("cov_log_params needs the Hessian: fit with method='newton'")
        return np.linalg.inv(-self.hessian)


_METHODS = ("scipy", "newton")


def fit_noise(log_params0, build: Callable, zs, x0, P0, *, method: str = "scipy", time_varying: bool | None = None,
              gtol: float = 1e-4, max_iter: int = 100, scipy_method: str = "L-BFGS-B") -> NoiseFit:
    r"""Maximise :func:`total_loglik` over the log parameters :math:`\phi`.

    * ``method="scipy"``: ``scipy.optimize.minimize`` of :math:`-\ell` with the NumPy engine;
      ``scipy_method="L-BFGS-B"`` (default) with central-difference gradients (``jac="3-point"``)
      and the stopping test :math:`\|\nabla\ell\|_\infty \le` ``gtol`` on them, or
      ``"Nelder-Mead"`` (no derivatives; stops when the simplex is within ``xatol = gtol`` in
      :math:`\phi` and ``fatol = gtol`` in :math:`\ell`).
    * ``method="newton"``: Newton's method with the exact gradient and Hessian of the JAX
      engine (forward-mode ``jax.jacfwd`` twice: the derivatives ``jax.grad`` and
      ``jax.hessian`` give, with value, gradient and Hessian in one function compiled with
      ``jax.jit``, which compiles faster through ``lax.scan`` than reverse mode),

      .. math::

          \phi_{j+1} = \phi_j + t_j\, d_j,\qquad d_j = \bigl(-\nabla^2\ell(\phi_j)\bigr)^{-1}\nabla\ell(\phi_j),

      where the eigenvalues of :math:`-\nabla^2\ell` are replaced by their absolute values
      (floored at :math:`10^{-8}` of the largest) so that :math:`d_j` ascends where the Hessian is
      not negative definite, and :math:`t_j = 1, 1/2, 1/4, \dots` is halved until
      :math:`\ell(\phi_j + t_j d_j) \ge \ell(\phi_j) + 10^{-4}\, t_j\, \nabla\ell^\top d_j`
      (Armijo; Nocedal & Wright 2006, §3.1, §3.4). Stops when
      :math:`\|\nabla\ell\|_\infty \le` ``gtol``. Needs JAX with ``jax_enable_x64`` and a
      ``build`` that JAX can trace.

    Near the maximum, a gradient :math:`g` left by the stopping test puts :math:`\hat\phi` within
    about :math:`\|(-\nabla^2\ell)^{-1}\|_2\,\|g\|_2` of the exact maximiser.

    Parameters
    ----------
    log_params0 : (d,) starting point :math:`\phi_0`.
    build, zs, x0, P0, time_varying : the model and data, as in :func:`total_loglik`.
    method : ``"scipy"`` (default) or ``"newton"``.
    gtol : tolerance on :math:`\|\nabla\ell\|_\infty` (nats per unit of :math:`\log\theta`), > 0.
    max_iter : at most this many iterations, >= 1.
    scipy_method : ``"L-BFGS-B"`` or ``"Nelder-Mead"`` (``method="scipy"`` only).

    Returns
    -------
    NoiseFit
        The maximiser, :math:`\ell` there, iteration and evaluation counts, and (Newton) the
        exact gradient and Hessian.

    Raises
    ------
    ValueError, TypeError
        On bad input, naming the argument.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.models import ConstantVelocity
    >>> from kftrack.tuning import fit_noise, white_noise_build
    >>> cv = ConstantVelocity(ndim=1, q=1.0)           # simulate 400 steps with q = 1 m²/s³, r = 4 m²
    >>> rng, L = np.random.default_rng(0), np.linalg.cholesky(cv.Q(1.0))
    >>> x, zs = np.zeros(2), []
    >>> for k in range(400):
    ...     zs.append(x[:1] + 2.0 * rng.standard_normal(1))
    ...     x = cv.F(1.0) @ x + L @ rng.standard_normal(2)
    >>> fit = fit_noise(np.log([0.1, 1.0]), white_noise_build(cv, 1.0), np.array(zs), np.zeros(2), 100 * np.eye(2))
    >>> print(np.round(fit.params, 1), fit.converged)   # (q, r) by maximum likelihood, from one record
    [1.  3.9] True
    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    if scipy_method not in ("L-BFGS-B", "Nelder-Mead"):
        raise ValueError(f"scipy_method must be 'L-BFGS-B' or 'Nelder-Mead', got {scipy_method!r}")
    if isinstance(gtol, bool) or not isinstance(gtol, (int, float)) or not (math.isfinite(gtol) and gtol > 0):
        raise ValueError(f"gtol must be a finite number > 0, got {gtol!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")
    lp0 = np.array(_check_log_params(np.asarray(log_params0))[0], dtype=float)
    _check_build(build)
    tv = _time_varying(build, time_varying)
    _check_zs(zs)
    if method == "scipy":
        return _fit_scipy(lp0, build, zs, x0, P0, tv, float(gtol), int(max_iter), scipy_method)
    return _fit_newton(lp0, build, zs, x0, P0, tv, float(gtol), int(max_iter))


def _fit_scipy(lp0, build, zs, x0, P0, tv, gtol, max_iter, scipy_method) -> NoiseFit:
    from scipy.optimize import minimize

    calls = [0]

    def neg(phi):
        calls[0] += 1
        return -total_loglik(phi, build, zs, x0, P0, time_varying=tv)

    if scipy_method == "L-BFGS-B":
        # ftol at a few eps so that the gradient test (gtol) decides
        res = minimize(neg, lp0, method="L-BFGS-B", jac="3-point",
                       options=dict(gtol=gtol, ftol=4 * _EPS, maxiter=max_iter))
        grad = -np.asarray(res.jac, dtype=float)
    else:
        res = minimize(neg, lp0, method="Nelder-Mead",
                       options=dict(xatol=gtol, fatol=gtol, maxiter=max_iter * lp0.size * 50))
        grad = None
    lp = np.asarray(res.x, dtype=float)
    return NoiseFit("scipy", lp, np.exp(lp), float(-res.fun), int(res.nit), calls[0], bool(res.success), grad, None)


@lru_cache(maxsize=1)
def _fgh_jit():
    """The compiled value, gradient and Hessian of :func:`total_loglik` in ``phi``, as
    ``(hessian, (value, gradient))``: ``(dynamic, static)``, the first taking the arrays
    ``(F, Qbar, H)`` of a :class:`WhiteNoiseBuild` as traced arguments (the build is re-made
    inside, so no JAX pytree registration, no global side effect), the second any other
    ``build`` as a static (hashable) argument."""
    jax = _jax()

    def fgh_arrays(phi, arrays, zs, x0, P0, tv):
        return fgh(phi, WhiteNoiseBuild(*arrays, time_varying=tv), zs, x0, P0, tv)

    def fgh(phi, build, zs, x0, P0, tv):
        def ell(p):
            v = total_loglik(p, build, zs, x0, P0, time_varying=tv)
            return v, v

        def grad_aux(p):
            g, v = jax.jacfwd(ell, has_aux=True)(p)
            return g, (v, g)

        return jax.jacfwd(grad_aux, has_aux=True)(phi)

    # Forward-mode differentiation, twice: the derivatives jax.grad / jax.hessian give; through
    # lax.scan it compiles faster than reverse mode. A fit calls this about ten times, so
    # compiling dominates: XLA's backend optimisation level 0 compiles in about half the time
    # (measured on a shared 2-core machine: 5 s instead of 9-12 s, 400 steps of a 2-D CV model)
    # and ran no slower here.
    opts = {"xla_backend_optimization_level": 0}
    return (jax.jit(fgh_arrays, static_argnames=("tv",), compiler_options=opts),
            jax.jit(fgh, static_argnames=("build", "tv"), compiler_options=opts))


def _fit_newton(lp0, build, zs, x0, P0, tv, gtol, max_iter) -> NoiseFit:
    jax = _jax()
    jnp = jax.numpy
    if not jax.config.jax_enable_x64:
        raise ValueError("method='newton' computes in float64 with JAX, which has float64 disabled: run "
                         "jax.config.update('jax_enable_x64', True) first, or use method='scipy'")
    zs_j, x0_j, P0_j = (jnp.asarray(np.asarray(a, dtype=float)) for a in (zs, x0, P0))
    dynamic, static = _fgh_jit()
    if type(build) is WhiteNoiseBuild:  # its arrays are arguments: one compilation per shapes
        arrays = (build.F, build.Qbar, build.H)
        call = lambda phi: dynamic(phi, arrays, zs_j, x0_j, P0_j, tv)  # noqa: E731
    else:  # any other callable is a static argument: one compilation per build
        call = lambda phi: static(phi, build, zs_j, x0_j, P0_j, tv)  # noqa: E731

    def fgh(phi):
        Hm, (v, g) = call(jnp.asarray(phi))
        Hm = np.asarray(Hm, dtype=float)
        return float(v), np.asarray(g, dtype=float), 0.5 * (Hm + Hm.T)

    phi = lp0.copy()
    f, g, Hm = fgh(phi)
    evals, steps = 1, 0
    if not (np.isfinite(f) and np.all(np.isfinite(g)) and np.all(np.isfinite(Hm))):
        raise ValueError(f"log_params0: the log-likelihood or its derivatives are not finite at {phi}")
    while np.max(np.abs(g)) > gtol and steps < max_iter:
        w, V = np.linalg.eigh(-Hm)
        w = np.maximum(np.abs(w), 1e-8 * np.max(np.abs(w)) + _TINY)
        d = V @ ((V.T @ g) / w)
        t, slope = 1.0, float(g @ d)
        for _ in range(60):
            trial = fgh(phi + t * d)
            evals += 1
            if np.isfinite(trial[0]) and np.all(np.isfinite(trial[1])) and trial[0] >= f + 1e-4 * t * slope:
                break
            t *= 0.5
        else:  # no ascent along d even at t = 2**-60: stop where we are
            break
        phi = phi + t * d
        steps += 1
        f, g, Hm = trial
    return NoiseFit("newton", phi, np.exp(phi), f, steps, evals, bool(np.max(np.abs(g)) <= gtol), g, Hm)
