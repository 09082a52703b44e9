r"""The two time-loop drivers of the whole-sequence filters: one set of equations, two engines.

The filter equations live once, in :mod:`kftrack.kernels`, written against an array namespace
(the array API standard). This module runs them over time:

* :func:`run_sequence`, the **NumPy engine**: a Python loop over the steps, what the chapters
  show and step through;
* :func:`run_scan`, the **JAX engine**: the same step function under ``jax.lax.scan``,
  compiled with ``jax.jit``, for speed, accelerators and gradients.

Both call the *same* kernels with the *same* arguments; neither holds an equation of its own.
The public filters (:func:`kftrack.kalman.kalman_filter`, :func:`kftrack.ekf.extended_kalman_filter`,
:func:`kftrack.ukf.unscented_kalman_filter`) validate their inputs once, then make one call,
:func:`run_filter`, where the engine is chosen (:func:`choose_engine`): any JAX array among the
caller's inputs selects the JAX engine, which returns JAX arrays; NumPy input keeps the NumPy
engine. :func:`kftrack.imm.imm_filter` chooses with :func:`choose_engine` too.

**The caller's functions** (``f``, ``h``, their Jacobians) are checked on the NumPy engine right
after each call (:class:`Checked`): NaN or inf raises a ``ValueError`` naming the function and
the step. Inside the JAX engine's compiled loop values cannot be checked: NaN propagates.

**One step** (both engines): at step ``k`` update with ``zs[k]`` unless the row is missing
(then the prior is kept and ``nis``, ``loglik`` are NaN), then predict to step ``k + 1``.
The kernels are :class:`Kernel` objects (a kernel function and its static, hashable options),
called as ``predict(x, P, *pred_args, *pred_steps[k])`` and
``update(x, P, z, *upd_args, *upd_steps[k])``: ``*_args`` are constant arrays, ``*_steps``
arrays with a leading time axis (a transition matrix per step, for irregular sampling).

**Shared covariances.** When the covariances do not depend on the run (no batch axes on
``P0``, ``F``, ``Q``, ``H``, ``R`` and one missing-row pattern for all runs), the recursion of
``P``, ``S`` and ``K`` does not depend on the data: the drivers then carry ``P`` without
batch axes (``cov_batch = ()``), so the kernels compute it once per step and apply the gain to
every run's mean; ``nis`` and ``loglik`` stay per run. The NumPy engine returns the
covariances as read-only broadcast views of the one ``(T, n, n)`` sequence.

**The missing-row pattern is static.** Whether the covariances can be shared is decided when
the loop is built, so the pattern must be known then; it comes from the filter's ``missing=``
argument (``kftrack._validate.check_missing``): ``None`` (default) takes the rows of NaN of
a concrete ``zs``; ``False`` says no measurement is missing; a concrete boolean array
``(T,)`` or ``(T, ...)`` marks the rows not to use. Inside the caller's ``jax.jit``,
``jax.grad`` or ``jax.vmap`` the values of ``zs`` are not known: with ``missing=None`` the
pattern is then derived inside the trace, run by run (``isnan(zs).all(-1)``, correct for any
data, but the covariances are per run); with ``missing=False`` or a concrete mask the traced
call takes the same path as the direct one (shared covariances; with no row missing, no
selection in the loop either). Under ``jax.vmap`` a covariance recursion that depends on no
mapped input stays unbatched.

**Composition.** A filter called inside the caller's ``jax.jit``, ``jax.grad`` or ``jax.vmap``
validates the shapes of the abstract values (:func:`stand_in`; their values cannot be checked
there), then traces the same compiled loop as a direct call: the loop is an inner ``jax.jit``,
inlined into the caller's program, so outputs the caller does not use (``x_prior``, ``P``,
...) are dropped from the compiled program by dead-code elimination (``tests/test_compose.py``
checks its memory: ``jit(lambda z: kalman_filter(...).x)`` compiles to the same program with
``priors=True`` and ``priors=False``), and no Python runs per call beyond the tracing.

**Outputs.** Both drivers return the predictions ``x_prior``, ``P_prior``, the posteriors ``x``,
``P`` and ``nis``, ``loglik`` of every step; with ``priors=False`` neither stores the
predictions (``x_prior``, ``P_prior`` are None; the JAX engine's compiled loop then has no such
outputs): per run and step the linear filter then writes n + n² + 2 numbers instead of
2n + 2n² + 2 (per-run covariances). Writing the results, not the arithmetic, bounds the JAX
engine on small states.

**The log-likelihood alone.** When only the total log-likelihood is wanted (what ``jax.grad``
differentiates: :func:`kftrack.tuning.total_loglik`, :func:`kftrack.imm.imm_loglik` with
``sequence=False``), :func:`run_total_scan` and :func:`run_imm_total_scan` run the same step
under a plain ``jax.lax.scan`` whose carry is the state and the running sum, with no per-run
output per step: the stored loop of the sequence would carry its whole output buffers, and under reverse
mode their cotangents, through every step. For the linear filter :func:`run_total_scan` runs the
covariance recursion first, in a loop of its own that also forms :math:`S_k^{-1}` once per step,
then the means, whose score :math:`y^\top S_k^{-1} y` leaves reverse mode two vectors per run
and step (:math:`y` and :math:`S_k^{-1} y`) and one reduction over the runs per step. Reverse mode
still keeps residuals for every step, memory O(T); ``total_loglik(..., checkpoint=c)`` runs the
steps in segments of ``c`` under ``jax.checkpoint`` (``_segmented``): O(T/c + c), for about one
more forward pass.

**Precision.** Both engines compute in float64 unless ``float32`` is chosen explicitly. JAX
computes in float32 unless ``jax_enable_x64`` is on; the JAX engine does not switch it on for
you (that would change every other JAX computation in the session): with float64 requested and
x64 off it raises a ``ValueError`` that says how to enable it, or to pass ``dtype="float32"``.
"""
from __future__ import annotations

import math
import sys
from collections.abc import Callable
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from ._validate import as_float_array, check_finite, is_tracer, stand_in
from .kernels import (_NUMPY, kf_correct, kf_gain, kf_predict, kf_update, logsumexp, moment_match, mv, rts_step,
                      solve_spd, sym)
from .results import FilterResult

__all__ = ["Kernel", "Checked", "NonFiniteOutput", "PerDt", "check_dts", "use_jax", "is_tracer", "check_dtype",
           "choose_engine", "to_engine", "stand_in", "Given", "run_filter", "run_sequence", "run_scan",
           "run_total_scan", "run_imm_scan", "run_imm_total_scan", "run_smoother_scan", "run_imm_smoother_scan"]


# --------------------------------------------------------------------------------------------
# sampling intervals
# --------------------------------------------------------------------------------------------
class PerDt:
    """Cache of ``fn(dt)`` for the few distinct sampling intervals of a run (``fn`` is called
    once per distinct ``dt``; at most 65 entries are kept)."""

    def __init__(self, fn: Callable):
        self.fn, self.cache = fn, {}

    def __call__(self, dt):
        key = float(dt)
        if key not in self.cache:
            if len(self.cache) > 64:
                self.cache.clear()
            self.cache[key] = self.fn(key)
        return self.cache[key]


def check_dts(dt, T: int, times=None) -> np.ndarray:
    """Sampling intervals ``(T,)``, ``dt[k]`` the interval (s) from step ``k`` to ``k + 1`` (the last
    one is not used), from exactly one of

    * ``dt``: a scalar (repeated), ``(T,)`` or ``(T - 1,)`` (the ``np.diff`` of the timestamps;
      the unused last interval is then taken equal to the one before, so no new interval
      appears), finite and ``>= 0``;
    * ``times``: the timestamps ``(T,)`` (s) of the steps, finite and non-decreasing;
      ``dt = np.diff(times)`` as above.

    A ``ValueError`` (``TypeError`` for non-numbers) names the argument and gives the shape
    received, not the values.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.engines import check_dts
    >>> check_dts(0.5, T=3)                           # one interval after each of T steps
    array([0.5, 0.5, 0.5])
    >>> check_dts(None, T=3, times=[0.0, 1.0, 3.0])   # from timestamps; the unused last copies the one before
    array([1., 2., 2.])
    """
    if times is not None:
        if dt is not None:
            raise ValueError("dt and times exclude each other: give the intervals dt (s) or the timestamps "
                             "times (s), not both")
        t = check_finite(as_float_array(times, "times"), "times")
        if t.shape != (T,):
            raise ValueError(f"times must have shape ({T},) (the timestamp of each of the T = {T} steps, s), "
                             f"got shape {t.shape}")
        d = np.diff(t)
        if np.any(d < 0):
            k = int(np.argmax(d < 0))
            raise ValueError(f"times must be non-decreasing, but times[{k + 1}] < times[{k}] "
                             f"({t[k + 1]:g} < {t[k]:g} s)")
        return np.append(d, d[-1]) if T > 1 else np.zeros(T)
    if dt is None:
        raise TypeError("dt must be given (a scalar, or the intervals after each step), or the timestamps times=")
    d = check_finite(as_float_array(dt, "dt"), "dt")
    if d.ndim == 0:
        d = np.full(T, float(d))
    if d.shape not in ((T,), (T - 1,)):
        raise ValueError(f"dt must be a scalar or have shape ({T},) (one interval after each step) or ({T - 1},) "
                         f"(np.diff of the {T} timestamps), got shape {d.shape}")
    if np.any(d < 0):
        k = int(np.argmax(d < 0))
        raise ValueError(f"dt must be >= 0 (intervals in s), but dt[{k}] = {d[k]:g}")
    if d.shape == (T - 1,):
        d = np.append(d, d[-1]) if T > 1 else np.zeros(T)
    return d


# --------------------------------------------------------------------------------------------
# engine choice and precision
# --------------------------------------------------------------------------------------------
def _jax():
    import jax  # imported only when JAX arrays are given

    return jax


def use_jax(*arrays) -> bool:
    """True if any argument is a JAX array (or a JAX tracer, inside ``jit``/``grad``)."""
    jax = sys.modules.get("jax")
    if jax is None:  # nobody imported jax, so nothing can be a JAX array
        return False
    return any(isinstance(a, jax.Array) for a in arrays)


def check_dtype(dtype, jax_engine: bool):
    """The floating dtype of a computation: ``None`` or ``"float64"`` (the default), or
    ``"float32"`` (explicit, with its loss of about 9 decimal digits: relative round-off
    ``2**-24`` instead of ``2**-53`` per operation). For the JAX engine float64 needs
    ``jax_enable_x64``."""
    try:
        dt = np.dtype("float64" if dtype is None else dtype)
    except TypeError:
        raise TypeError(f"dtype must be None, 'float64' or 'float32', got {dtype!r}") from None
    if dt not in (np.dtype("float64"), np.dtype("float32")):
        raise ValueError(f"dtype must be None, 'float64' or 'float32', got {dtype!r}")
    if jax_engine and dt == np.float64 and not _jax().config.jax_enable_x64:
        raise ValueError(
            "dtype: the JAX engine computes in float64 by default, but JAX has float64 disabled; run "
            "jax.config.update('jax_enable_x64', True) before creating your arrays, or pass "
            "dtype='float32' to accept float32 round-off (relative 6e-8 per operation instead of 1e-16)")
    return dt


def to_engine(a, jax_engine: bool, dtype):
    """``a`` as an array of the engine (NumPy or JAX) in ``dtype`` (booleans stay boolean)."""
    if jax_engine:
        jnp = _jax().numpy
        kind = a.dtype if hasattr(a, "dtype") else np.asarray(a).dtype
        return jnp.asarray(a) if kind == bool else jnp.asarray(a, dtype=dtype)
    a = np.asarray(a)
    return a if a.dtype == bool or a.dtype == dtype else a.astype(dtype)


def choose_engine(*arrays, dtype=None) -> tuple[bool, np.dtype]:
    """The engine and the precision of a computation: ``(jax_engine, dtype)``, the JAX engine if any
    of ``arrays`` is a JAX array (:func:`use_jax`), the dtype checked by :func:`check_dtype`."""
    jax_engine = use_jax(*arrays)
    return jax_engine, check_dtype(dtype, jax_engine)


class Given(NamedTuple):
    """An array argument of a filter as the caller gave it (``raw``) and as checked at the boundary
    (``checked``, a NumPy array; for an abstract JAX value the :func:`stand_in` of its shape).
    The JAX engine runs on ``raw`` when it is a JAX array (tracers keep flowing: ``jit``, ``grad``),
    on ``checked`` otherwise; the NumPy engine always on ``checked``."""

    raw: object
    checked: object


def _value(a, jax_engine: bool):
    if type(a) is not Given:
        return a
    return a.raw if jax_engine and use_jax(a.raw) else a.checked


def run_filter(zs, gone, x0, P0, batch: tuple, predict, update, *, pred_args=(), pred_steps=(), upd_args=(),
               upd_steps=(), sources=(), cov_shapes=None, dtype=None, progress: bool = False,
               priors: bool = True, total: bool = False, checkpoint: int | None = None):
    """The one call of a whole-sequence filter after its validation: choose the engine, convert the
    arrays to it and run the time loop (:func:`run_sequence` or :func:`run_scan`).

    Parameters
    ----------
    zs, x0, P0, pred_args, pred_steps, upd_args, upd_steps : the arrays of :func:`run_sequence`,
        each checked (NumPy) or a :class:`Given` pair ``(caller's value, checked value)``.
    gone : (T, ...) bool, the rows not to use (``kftrack._validate.check_missing``), a
        concrete NumPy array; or None when only the trace knows them (an abstract ``zs`` with
        ``missing=None``): then ``isnan(zs).all(-1)`` of the caller's ``zs``, per run.
    batch : the batch shape of the means.
    predict, update : :class:`Kernel` objects.
    sources : further caller's values that choose the engine (with the raw values of the
        :class:`Given` arguments: any JAX array selects the JAX engine).
    cov_shapes : None (the covariances are per run: ``cov_batch = batch``), or the batch shapes
        of the inputs the covariance recursion depends on (``P0``, ``F``, ``Q``, ``H``, ``R``):
        then it is computed once for all runs where they and the missing rows allow it.
    dtype : None, ``"float64"`` or ``"float32"`` (:func:`check_dtype`).
    progress, priors : as in :func:`run_sequence`.
    total : if True, return only the log-likelihood of each run summed over its measured steps,
        ``batch`` shaped (:func:`run_total_scan` on the JAX engine: no sequence is stored, so
        ``jax.grad`` differentiates a loop that carries ``(x, P, sum)`` and nothing else; the
        NumPy engine's ``nansum`` over time of ``loglik``).
    checkpoint : with ``total`` on the JAX engine, None or a validated int ``c >= 1``: segments of
        ``c`` steps under ``jax.checkpoint`` (:func:`run_total_scan`); ignored otherwise.

    Returns
    -------
    kftrack.results.FilterResult, or with ``total`` an array ``batch``
        NumPy arrays (NumPy engine) or JAX arrays (JAX engine).
    """
    raws = [a.raw for a in (zs, x0, P0, *pred_args, *pred_steps, *upd_args, *upd_steps) if type(a) is Given]
    jax_engine, dt = choose_engine(*raws, *sources, dtype=dtype)
    if gone is None:  # the missing rows are known only inside the trace: derived there, run by run
        zs_raw = zs.raw if type(zs) is Given else zs
        gone = _jax().numpy.isnan(zs_raw).all(-1)
    elif cov_shapes is not None and gone.ndim > 1:
        T = gone.shape[0]
        flat = gone.reshape(T, -1)
        if (flat == flat[:, :1]).all():  # one pattern for every run: keep the covariances shared
            gone = flat[:, 0]
    cov_batch = batch if cov_shapes is None else np.broadcast_shapes(*cov_shapes, tuple(gone.shape[1:]))
    conv = lambda a: to_engine(_value(a, jax_engine), jax_engine, dt)  # noqa: E731
    if jax_engine and type(gone) is np.ndarray and not gone.any():
        gone_e = None  # no row missing (static): the compiled loop updates without selecting
    else:
        gone_e = conv(gone)
    if total:
        args = (conv(zs), gone_e, conv(x0), conv(P0), tuple(batch), tuple(cov_batch), predict, update)
        kw = dict(pred_args=tuple(map(conv, pred_args)), pred_steps=tuple(map(conv, pred_steps)),
                  upd_args=tuple(map(conv, upd_args)), upd_steps=tuple(map(conv, upd_steps)))
        if jax_engine:
            return run_total_scan(*args, **kw, checkpoint=checkpoint)
        return np.nansum(run_sequence(*args, **kw, progress=progress, priors=False).loglik, axis=0)
    return (run_scan if jax_engine else run_sequence)(
        conv(zs), gone_e, conv(x0), conv(P0), tuple(batch), tuple(cov_batch), predict, update,
        pred_args=tuple(map(conv, pred_args)), pred_steps=tuple(map(conv, pred_steps)),
        upd_args=tuple(map(conv, upd_args)), upd_steps=tuple(map(conv, upd_steps)), progress=progress,
        priors=bool(priors))


# --------------------------------------------------------------------------------------------
# the step
# --------------------------------------------------------------------------------------------
class NonFiniteOutput(ValueError):
    """A function of the caller returned NaN or inf (raised by a checked call on the NumPy engine;
    :func:`run_sequence` turns it into a ``ValueError`` that names the function and the step)."""

    def __init__(self, name: str, bad: str, shape: tuple):
        super().__init__(f"{name} returned {bad} (on an input of shape {shape})")
        self.name, self.bad, self.shape = name, bad, shape


class Checked:
    """A function of the caller, ``fn``, with its output checked right after each call: NaN or inf
    raises :class:`NonFiniteOutput` naming ``name`` (the boundary between the caller's code and
    the package, on the NumPy engine; one ``np.isfinite`` over the output per call)."""

    __slots__ = ("fn", "name")

    def __init__(self, fn: Callable, name: str):
        self.fn, self.name = fn, name

    def __call__(self, x):
        out = self.fn(x)
        a = np.asarray(out)
        if not np.isfinite(a).all():
            raise NonFiniteOutput(self.name, "NaN" if np.isnan(a).any() else "inf", tuple(np.shape(x)))
        return out


class Kernel(NamedTuple):
    """A kernel of :mod:`kftrack.kernels` with its static options bound, hashable so that the JAX
    engine compiles once per kernel and options: ``Kernel(kf_update, (("form", "joseph"),))``.
    ``user`` pairs ``(option, name)`` mark the options that are the caller's functions (``f``,
    ``h``, their Jacobians): the NumPy engine checks their outputs after each call
    (:meth:`checked`); inside a JAX trace values cannot be checked, and NaN propagates."""

    fn: Callable
    static: tuple = ()
    user: tuple = ()

    def __call__(self, *args):
        return self.fn(*args, **dict(self.static))

    def checked(self) -> Kernel:
        """The kernel with the caller's functions wrapped in :class:`Checked`."""
        if not self.user:
            return self
        names = dict(self.user)
        return self._replace(static=tuple((k, Checked(v, names[k]) if k in names else v) for k, v in self.static))


def _step(xp, predict, update, x, P, z, g, pred_args, pk, upd_args, uk, last):
    """One step of every whole-sequence filter, on either engine: update with ``z`` where ``g``
    (missing) is False, keep the prior where it is True, then predict unless ``last``. ``g``
    None: no row is missing (known statically), the update is taken as it is.
    Returns ``(x_post, P_post, nis, loglik, x_next, P_next)``."""
    if g is None:
        u = update(x, P, z, *upd_args, *uk)
        x_post, P_post, nis, ll = u.x, u.P, u.nis, u.loglik
    else:
        gx = g[..., None]
        u = update(x, P, xp.where(gx, xp.zeros((), dtype=z.dtype), z), *upd_args, *uk)
        nan = xp.asarray(float("nan"), dtype=x.dtype)
        x_post = xp.where(gx, x, u.x)
        P_post = xp.where(gx[..., None], P, u.P)
        nis, ll = xp.where(g, nan, u.nis), xp.where(g, nan, u.loglik)
    if last:
        return x_post, P_post, nis, ll, x_post, P_post
    x_next, P_next = predict(x_post, P_post, *pred_args, *pk)
    return x_post, P_post, nis, ll, x_next, P_next


def run_sequence(zs, gone, x0, P0, batch: tuple, cov_batch: tuple, predict, update, pred_args=(), pred_steps=(),
                 upd_args=(), upd_steps=(), progress: bool = False, priors: bool = True):
    """The NumPy engine: the time loop in Python, one broadcast kernel call per step for all runs.

    Parameters
    ----------
    zs : (T, ..., m) measurements (missing rows may hold anything; they are not used).
    gone : (T, ...) bool, True where the measurement of a run is missing; its batch axes must
        broadcast to ``cov_batch`` (shape ``(T,)`` when all runs share the pattern).
    x0, P0 : prior of step 0, broadcast to ``batch + (n,)`` and ``cov_batch + (n, n)``.
    batch, cov_batch : batch shape of the means and of the covariances (``cov_batch`` is ``()``
        when the covariance recursion is shared by all runs).
    predict, update : :class:`Kernel` objects (see the module docstring).
    pred_args, upd_args : constant array arguments of the kernels.
    pred_steps, upd_steps : array arguments with a leading time axis ``T``; step ``k`` gets ``a[k]``.
    progress : show a tqdm bar over the steps.
    priors : if False, the predictions are not stored: ``x_prior`` and ``P_prior`` of the result
        are None (n + n² fewer numbers per run and step for the linear filter).

    Returns
    -------
    kftrack.results.FilterResult
    """
    T, n = zs.shape[0], x0.shape[-1]
    dtype = x0.dtype
    x = np.broadcast_to(x0, batch + (n,)).copy()
    P = np.broadcast_to(P0, cov_batch + (n, n)).copy()
    out_x = np.empty((T,) + batch + (n,), dtype)
    out_P = np.empty((T,) + cov_batch + (n, n), dtype)
    out_xp, out_Pp = (np.empty_like(out_x), np.empty_like(out_P)) if priors else (None, None)
    out_nis = np.full((T,) + batch, np.nan, dtype)
    out_ll = np.full((T,) + batch, np.nan, dtype)
    steps = range(T)
    if progress:
        from tqdm.auto import tqdm  # only when asked for

        steps = tqdm(steps, desc="filter", unit="step")
    xp = _np_namespace()
    if isinstance(predict, Kernel):  # the caller's functions checked after each call
        predict = predict.checked()
    if isinstance(update, Kernel):
        update = update.checked()
    k = 0
    try:
        for k in steps:
            if priors:
                out_xp[k], out_Pp[k] = x, P
            pk, uk = tuple(a[k] for a in pred_steps), tuple(a[k] for a in upd_steps)
            g = gone[k]
            if g.all():  # nothing to update: predict only
                out_x[k], out_P[k] = x, P
                if k < T - 1:
                    x, P = predict(x, P, *pred_args, *pk)
                continue
            if not g.any():  # every run measured: no selection needed
                u = update(x, P, zs[k], *upd_args, *uk)
                x, P = u.x, u.P
                out_nis[k], out_ll[k] = u.nis, u.loglik
                out_x[k], out_P[k] = x, P
                if k < T - 1:
                    x, P = predict(x, P, *pred_args, *pk)
                continue
            out_x[k], out_P[k], out_nis[k], out_ll[k], x, P = _step(xp, predict, update, x, P, zs[k], g,
                                                                    pred_args, pk, upd_args, uk, k == T - 1)
    except NonFiniteOutput as e:
        raise ValueError(f"{e.name} returned {e.bad} at step {k} (called on an input of shape {e.shape}): check "
                         f"{e.name} where the filter's state has gone (the NumPy engine checks the output of your "
                         "functions after each call)") from None
    if cov_batch != batch:  # shared covariances: read-only views of the one sequence
        out_Pp, out_P = (None if a is None else _batch_view(a, np, batch, cov_batch) for a in (out_Pp, out_P))
    return FilterResult(out_xp, out_Pp, out_x, out_P, out_nis, out_ll)


def _batch_view(P, xp, batch: tuple, cov_batch: tuple):
    """A shared covariance sequence ``(T, *cov_batch, n, n)`` broadcast to ``(T, *batch, n, n)``
    (NumPy: a read-only view)."""
    T, n = P.shape[0], P.shape[-1]
    return xp.broadcast_to(P.reshape((T,) + (1,) * (len(batch) - len(cov_batch)) + P.shape[1:]),
                           (T,) + batch + (n, n))


@lru_cache(maxsize=1)
def _np_namespace():
    return _NUMPY  # numpy itself (NumPy >= 2), else array_api_compat's wrapper


# --------------------------------------------------------------------------------------------
# the JAX engine
# --------------------------------------------------------------------------------------------
def _stored_loop(step, carry, T: int):
    """``lax.scan(step, carry, jnp.arange(T))`` for ``step(k, carry) -> (carry, out)``, with the
    outputs stored from the loop's carry: the loop carries the output of step ``k - 1`` and stores
    it at step ``k`` (the last one after the loop). An output that is also used inside the step
    (a posterior, which the prediction reads) would otherwise let XLA fuse its whole computation a
    second time into the store (measured on CPU: the Joseph form computed twice per step); a
    carried value is computed once, and its store is a copy. Same numbers, bit for bit.
    Returns ``(carry, stacked outputs)``, time first; a ``None`` among the outputs (an empty pytree)
    has no buffer, is never stored, and stays ``None``."""
    jax = _jax()
    jnp, lax, tree = jax.numpy, jax.lax, jax.tree_util
    put = lambda buf, v, k: lax.dynamic_update_index_in_dim(buf, v, k, 0)  # noqa: E731
    shapes = jax.eval_shape(step, 0, carry)[1]
    out0 = tree.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
    bufs = tree.tree_map(lambda s: jnp.zeros((T,) + s.shape, s.dtype), shapes)

    def body(k, state):
        carry, prev, bufs = state  # at k = 0 the placeholder goes to index -1, clamped to 0, then overwritten
        bufs = tree.tree_map(lambda b, v: put(b, v, k - 1), bufs, prev)
        return step(k, carry) + (bufs,)

    carry, last, bufs = lax.fori_loop(0, T, body, (carry, out0, bufs))
    return carry, tree.tree_map(lambda b, v: put(b, v, T - 1), bufs, last)


def _scan_impl(zs, gone, x0, P0, pred_args, pred_steps, upd_args, upd_steps, *, batch, cov_batch, predict, update,
               priors):
    jax = _jax()
    jnp = jax.numpy
    at = lambda a, k: jax.lax.dynamic_index_in_dim(a, k, 0, keepdims=False)  # noqa: E731
    n, T = x0.shape[-1], zs.shape[0]
    x = jnp.broadcast_to(x0, batch + (n,))
    P = jnp.broadcast_to(P0, cov_batch + (n, n))

    def step(k, carry):
        x, P = carry
        g = None if gone is None else at(gone, k)
        x_post, P_post, nis, ll, x_next, P_next = _step(jnp, predict, update, x, P, at(zs, k), g,
                                                        pred_args, tuple(at(a, k) for a in pred_steps), upd_args,
                                                        tuple(at(a, k) for a in upd_steps), False)
        out = ((x, P) if priors else (None, None)) + (  # None: not a loop output, nothing stored
            jnp.broadcast_to(x_post, x.shape), jnp.broadcast_to(P_post, P.shape),
            jnp.broadcast_to(nis, batch), jnp.broadcast_to(ll, batch))
        return (jnp.broadcast_to(x_next, x.shape), jnp.broadcast_to(P_next, P.shape)), out

    _, (xp_, Pp, xs, Ps, nis, ll) = _stored_loop(step, (x, P), T)
    if cov_batch != batch:
        Pp, Ps = (None if a is None else _batch_view(a, jnp, batch, cov_batch) for a in (Pp, Ps))
    return xp_, Pp, xs, Ps, nis, ll


@lru_cache(maxsize=1)
def _scan_jit():
    jax = _jax()
    return jax.jit(_scan_impl, static_argnames=("batch", "cov_batch", "predict", "update", "priors"))


def run_scan(zs, gone, x0, P0, batch: tuple, cov_batch: tuple, predict, update, pred_args=(), pred_steps=(),
             upd_args=(), upd_steps=(), progress: bool = False, priors: bool = True):
    """The JAX engine: the step of :func:`run_sequence` under ``jax.lax.scan``, compiled with
    ``jax.jit`` (once per kernel, options and shapes). Same arguments and result as
    :func:`run_sequence`, as JAX arrays; ``progress`` is ignored (the loop runs compiled).
    Every step runs the update on all runs and selects the prior where a row is missing
    (``gone`` None: no row is missing, no selection).
    With ``priors=False`` the predictions are not outputs of the loop (the compiled program
    neither stores nor returns them; ``x_prior``, ``P_prior`` are None)."""
    out = _scan_jit()(zs, gone, x0, P0, tuple(pred_args), tuple(pred_steps), tuple(upd_args), tuple(upd_steps),
                      batch=tuple(batch), cov_batch=tuple(cov_batch), predict=predict, update=update,
                      priors=bool(priors))
    return FilterResult(*out)


def _total_impl(zs, gone, x0, P0, pred_args, pred_steps, upd_args, upd_steps, *, batch, cov_batch, predict,
                update, checkpoint=None):
    jax = _jax()
    jnp = jax.numpy
    at = lambda a, k: jax.lax.dynamic_index_in_dim(a, k, 0, keepdims=False)  # noqa: E731
    n = x0.shape[-1]
    x = jnp.broadcast_to(x0, batch + (n,))
    P = jnp.broadcast_to(P0, cov_batch + (n, n))
    s0, zero = jnp.zeros(batch, x0.dtype), jnp.zeros((), x0.dtype)
    if predict.fn is kf_predict and update.fn is kf_update and not upd_steps:
        segment = _total_linear(jax, at, zs, gone, zero, pred_args, pred_steps, upd_args, predict,
                                dict(update.static))
    else:
        def step(carry, k):
            x, P, s = carry
            g = None if gone is None else at(gone, k)
            _, _, _, ll, x_next, P_next = _step(jnp, predict, update, x, P, at(zs, k), g, pred_args,
                                                tuple(at(a, k) for a in pred_steps), upd_args,
                                                tuple(at(a, k) for a in upd_steps), False)
            ll = jnp.broadcast_to(ll if g is None else jnp.where(g, zero, ll), batch)
            return (jnp.broadcast_to(x_next, x.shape), jnp.broadcast_to(P_next, P.shape), s + ll), None

        segment = lambda carry, ks: jax.lax.scan(step, carry, ks)[0]  # noqa: E731
    _, _, s = _segmented(jax, segment, (x, P, s0), zs.shape[0], checkpoint)
    return s


def _segmented(jax, segment, carry, T: int, checkpoint):
    r"""``segment(carry, arange(T))`` for ``segment(carry, ks) -> carry``, a loop over the steps
    ``ks``; with ``checkpoint = c`` (``1 <= c < T``) the same steps as an outer ``lax.scan`` over
    :math:`\lfloor T/c \rfloor` segments of ``c`` steps whose body is ``jax.checkpoint(segment)``,
    then the :math:`T \bmod c` remaining steps as one plain segment. Under reverse mode the outer
    loop keeps only the carry at each segment's start and each segment's forward pass is run again
    when its reverse pass needs its residuals: memory :math:`O(T/c + c)` per-step states instead of
    :math:`O(T)`, for about one more forward pass (Griewank & Walther 2008, ch. 12). The steps run
    the same arithmetic in the same order, so the value is the same bit for bit (checked in
    ``tests/test_compose.py`` on the shared-covariance path, CPU); only the sums that reverse mode accumulates over the steps (the
    cotangents of inputs shared by every step) are added segment by segment, a round-off
    difference."""
    jnp = jax.numpy
    ks = jnp.arange(T)
    if checkpoint is None or checkpoint >= T:
        return segment(carry, ks)
    nseg = T // checkpoint
    body = jax.checkpoint(lambda c, seg: (segment(c, seg), None), prevent_cse=False)  # inside a scan: no CSE
    carry, _ = jax.lax.scan(body, carry, ks[:nseg * checkpoint].reshape(nseg, checkpoint))
    if T > nseg * checkpoint:  # the remainder, fewer than c steps: residuals of the size of one segment
        carry = segment(carry, ks[nseg * checkpoint:])
    return carry


def _total_linear(jax, at, zs, gone, zero, pred_args, pred_steps, upd_args, predict, opts):
    r"""The segment ``(x, P, s), ks -> (x, P, s)`` of the log-likelihood of the linear Kalman filter
    over the steps ``ks`` (:func:`_segmented`), in two loops. First the covariance
    recursion, which does not depend on the data (:func:`kftrack.kernels.kf_gain`, ``kf_predict``;
    batch ``cov_batch``, so computed once for all runs on the shared path), storing per step the
    gain ``K``, :math:`S^{-1}` (:func:`kftrack.kernels.solve_spd` of ``S`` and the identity, made
    exactly symmetric by ``sym``) and :math:`\log\det S`; then the means (:func:`kftrack.kernels.kf_correct`, ``kf_predict`` of the
    mean alone) with :math:`\log N(y; 0, S) = -\tfrac12 (y^\top S^{-1} y + \log\det S + m \log 2\pi)`
    (the equation of :func:`kftrack.kernels.innovation_score`).

    Why not the kernels' score: it solves :math:`S^{-1} y` by triangular solves against the
    entries of the unrolled Cholesky factor of ``S``, which on the shared path are scalars
    broadcast over the runs. Reverse mode then treats each factor entry as its own variable: per
    step it stores one residual ``(N,)`` per entry and reduces one product over the ``N`` runs per
    entry (the jaxpr of ``jax.grad`` for the 2-D CV filter, ``m = 2``: six residuals
    ``(T, N, 1)`` besides the innovations, six reductions over the runs per step in the compiled
    reverse loop), per-run work for a quantity that is shared. With :math:`S^{-1}` formed once per
    step and the derivative of :math:`y^\top S^{-1} y` written with matrix products
    (:func:`_quadratic_form`), the reverse pass keeps per run and step two vectors of ``m``
    numbers (``y`` and :math:`S^{-1} y`) and reduces one product,
    :math:`\sum_i \bar\ell_i\, y_i y_i^\top`, per step (a side-by-side run while developing it,
    not stored, found ``jax.grad`` of the sum faster and the forward pass unchanged within its
    spread; the benchmark's grad rows are measured after it). The value agrees with the one-loop score to the round-off
    of the two solves, :math:`O(m\,\kappa(S)\,\varepsilon)` relative per term.

    The covariance step runs under ``jax.checkpoint``: its reverse pass recomputes the step from
    ``P`` (the only residual kept per step) instead of reading residuals stored by the forward
    loop. The unrolled products and factor (:func:`kftrack.kernels.mm`, ``solve_spd``) leave some
    seventy small residuals per step, each written by its own kernel in the compiled forward
    loop (71 kernels per step against 13 with the checkpoint, 2-D CV filter), and their
    recomputation fuses into a few kernels of the reverse step. The forward arithmetic is the
    same, so the value is the same bit for bit; the gradient differs at most by the round-off of
    the recomputation's fusion (side-by-side runs while developing it, not stored: ``jax.grad`` of
    the sum faster on the shared path and with per-run covariances, the gradient bit for bit on
    the benchmark's shared-path setup; the benchmark's grad rows are measured after it)."""
    jnp = jax.numpy
    H, R = upd_args
    n, m = H.shape[-1], H.shape[-2]
    x_dummy = jnp.zeros((n,), zero.dtype)  # the mean of kf_predict in the covariance loop: unused, dropped
    eye, log_2pi_m, quadratic = jnp.eye(m, dtype=zero.dtype), m * math.log(2.0 * math.pi), _quadratic_form()

    def cov_step(P, k):
        gain = kf_gain(P, H, R, **opts)
        P_post = gain.P if gone is None else jnp.where(at(gone, k)[..., None, None], P, gain.P)
        _, P_next = predict(x_dummy, P_post, *pred_args, *(at(a, k) for a in pred_steps))
        return jnp.broadcast_to(P_next, P.shape), (gain.K, sym(solve_spd(gain.S, eye)), gain.logdet)

    def mean_step(carry, inp):
        x, s = carry
        k, (K, S_inv, logdet) = inp
        z = at(zs, k)
        if gone is not None:
            g = at(gone, k)
            z = jnp.where(g[..., None], zero, z)  # a missing row may hold NaN: kept out of the gradient too
        x_post, y = kf_correct(x, z, H, K)
        ll = -0.5 * (quadratic(S_inv, y) + logdet + log_2pi_m)
        if gone is not None:
            x_post, ll = jnp.where(g[..., None], x, x_post), jnp.where(g, zero, ll)
        x_next, _ = predict(x_post, None, *pred_args, *(at(a, k) for a in pred_steps))
        return (jnp.broadcast_to(x_next, x.shape), s + jnp.broadcast_to(ll, s.shape)), None

    def segment(carry, ks):
        x, P, s = carry
        P, gains = jax.lax.scan(jax.checkpoint(cov_step, prevent_cse=False), P, ks)
        (x, s), _ = jax.lax.scan(mean_step, (x, s), (ks, gains))
        return x, P, s

    return segment


@lru_cache(maxsize=1)
def _quadratic_form():
    r"""``q(A, y)`` :math:`= y^\top A y` over the batch axes, for a symmetric ``A`` (..., m, m) and
    ``y`` (..., m), as a ``jax.custom_jvp``: the value as :math:`\sum_{ij} A_{ij} y_i y_j`, scalar
    products that XLA fuses with the rest of the step into one loop over the runs; the derivative
    :math:`\dot q = 2\,\dot y^\top A y + y^\top \dot A y` written with matrix products, so that
    its transpose (the reverse pass) reduces :math:`\bar q\,y y^\top` over the runs in one
    product. Differentiating the scalar form instead would give each entry :math:`A_{ij}`, shared
    by the runs, a reduction over the runs of its own. :math:`A y`, which depends on the primals
    alone (a residual of the reverse pass), is formed with elementwise products, so XLA fuses it
    into the loop that stores it (``mv``'s product ``y A^T`` was a kernel of its own per step)."""
    jax = _jax()
    jnp = jax.numpy

    def value(A, y):
        m = y.shape[-1]
        return sum(A[..., i, j] * y[..., i] * y[..., j] for i in range(m) for j in range(m))

    q = jax.custom_jvp(value)

    @q.defjvp
    def _(primals, tangents):
        (A, y), (dA, dy) = primals, tangents
        m = y.shape[-1]
        Ay = sum(A[..., :, j] * y[..., j, None] for j in range(m))
        return value(A, y), jnp.sum(2.0 * dy * Ay + y * mv(dA, y), axis=-1)

    return q


@lru_cache(maxsize=1)
def _total_jit():
    return _jax().jit(_total_impl, static_argnames=("batch", "cov_batch", "predict", "update", "checkpoint"))


def run_total_scan(zs, gone, x0, P0, batch: tuple, cov_batch: tuple, predict, update, pred_args=(), pred_steps=(),
                   upd_args=(), upd_steps=(), checkpoint: int | None = None):
    r"""The JAX engine for the log-likelihood alone: the step of :func:`run_scan` under a plain
    ``jax.lax.scan`` whose carry is ``(x, P, s)``, ``s`` the running sum over the measured steps
    of ``loglik`` (:math:`\ell = \sum_k \log N(y_k; 0, S_k)`), with no per-run output per step
    (the linear filter's covariance loop keeps one set of gains per step, shared by the runs).
    Under ``jax.grad`` the loop's per-run residuals are then the states of each step: a stored
    sequence (``_stored_loop``) would carry its whole output buffers, and their cotangents,
    through every step of the reverse pass. With the linear kernels (``kf_predict``,
    ``kf_update``) two loops, covariances then means (``_total_linear``: the reverse pass of the
    score touches per run the innovations alone). Same arguments as :func:`run_scan` (no
    ``priors``), and ``checkpoint``: None, or an int ``c >= 1`` (validated by the caller): the
    steps in segments of ``c`` under ``jax.checkpoint`` (``_segmented``; with the linear
    kernels both loops run per segment, so the gains stored are those of one segment). Returns
    ``s`` of shape ``batch``."""
    return _total_jit()(zs, gone, x0, P0, tuple(pred_args), tuple(pred_steps), tuple(upd_args), tuple(upd_steps),
                        batch=tuple(batch), cov_batch=tuple(cov_batch), predict=predict, update=update,
                        checkpoint=checkpoint)


def _imm_cycle(H, R, batch, mixing_weights):
    """The step of the IMM's JAX engine, ``step(k, carry, zs, gone, Pis, Fs, Qs) -> (carry, parts)``
    with ``carry = (log_mu, xs, Ps)`` and ``parts = (prior, post, loglik, g, xs, Ps)``: the combined
    prior and posterior ``(mu, x, P)``, the mode likelihoods ``loglik`` (..., r) (not masked), the
    missing flags ``g`` (...) and the mode-matched posteriors of step ``k``."""
    jax = _jax()
    jnp = jax.numpy
    r, nb = H.shape[0], len(batch)
    per_mode = lambda a: jnp.reshape(a, (r,) + (1,) * nb + a.shape[1:])  # noqa: E731  mode axis first
    H, R = per_mode(H), per_mode(R)
    at = lambda a, k: jax.lax.dynamic_index_in_dim(a, k, 0, keepdims=False)  # noqa: E731

    def combine(log_mu, xs, Ps):
        mu = jnp.exp(log_mu)
        x, P = moment_match(mu, xs, Ps)
        return mu, x, P

    def step(k, carry, zs, gone, Pis, Fs, Qs):
        log_mu, xs, Ps = carry  # (..., r), (r, ..., n), (r, ..., n, n)
        z, g, Pi, F, Q = (at(a, k) for a in (zs, gone, Pis, Fs, Qs))
        prior = combine(log_mu, xs, Ps)
        u = kf_update(xs, Ps, jnp.where(g[..., None], jnp.zeros((), z.dtype), z)[None], H, R)  # every mode at once
        loglik = jnp.moveaxis(jnp.broadcast_to(u.loglik, (r,) + batch), 0, -1)
        joint = log_mu + loglik
        gm = g[..., None]
        log_mu = jnp.where(gm, log_mu, joint - logsumexp(joint, axis=-1, keepdims=True))
        xs = jnp.where(gm[None], xs, u.x)
        Ps = jnp.where(gm[None, ..., None], Ps, u.P)
        post = combine(log_mu, xs, Ps)
        w, log_cbar = mixing_weights(log_mu, Pi)  # (..., r_i, r_j)
        x0, P0 = moment_match(jnp.moveaxis(w, -1, 0), xs, Ps)  # (r_j, ..., n): the mixed start of each mode
        xs_n, Ps_n = kf_predict(x0, P0, per_mode(F), per_mode(Q))
        carry = (jnp.broadcast_to(log_cbar, log_mu.shape), jnp.broadcast_to(xs_n, xs.shape),
                 jnp.broadcast_to(Ps_n, Ps.shape))
        return carry, (prior, post, loglik, g, xs, Ps)

    return step


def _imm_impl(zs, gone, log_mu0, xs0, Ps0, Pis, Fs, Qs, H, R, *, batch, mixing_weights):
    jnp = _jax().numpy
    r = H.shape[0]
    nan = jnp.asarray(jnp.nan, dtype=xs0.dtype)
    cycle = _imm_cycle(H, R, batch, mixing_weights)

    def step(k, carry):
        carry, (prior, post, loglik, g, xs, Ps) = cycle(k, carry, zs, gone, Pis, Fs, Qs)
        return carry, prior + post + (jnp.where(g[..., None], nan, loglik), xs, Ps)

    _, out = _stored_loop(step, (log_mu0, xs0, Ps0), zs.shape[0])
    mu_p, x_p, P_p, mu, x, P, ll, xs, Ps = out
    xs = tuple(xs[:, i] for i in range(r))
    Ps = tuple(Ps[:, i] for i in range(r))
    return x_p, P_p, mu_p, x, P, mu, ll, xs, Ps


def _imm_total_impl(zs, gone, log_mu0, xs0, Ps0, Pis, Fs, Qs, H, R, *, batch, mixing_weights):
    jax = _jax()
    jnp = jax.numpy
    cycle = _imm_cycle(H, R, batch, mixing_weights)
    zero = jnp.zeros((), xs0.dtype)

    def step(carry, k):
        state, s = carry
        log_mu = state[0]  # the predicted mode probabilities (log) of step k
        state, (_, _, loglik, g, _, _) = cycle(k, state, zs, gone, Pis, Fs, Qs)
        term = logsumexp(log_mu + jnp.where(g[..., None], zero, loglik), axis=-1)
        return (state, s + jnp.where(g, zero, term)), None

    (_, s), _ = jax.lax.scan(step, ((log_mu0, xs0, Ps0), jnp.zeros(batch, xs0.dtype)), jnp.arange(zs.shape[0]))
    return s


@lru_cache(maxsize=1)
def _imm_total_jit():
    return _jax().jit(_imm_total_impl, static_argnames=("batch", "mixing_weights"))


def run_imm_total_scan(zs, gone, log_mu0, xs0, Ps0, Pis, Fs, Qs, H, R, *, batch: tuple, mixing_weights):
    r"""The log-likelihood alone of :func:`run_imm_scan` (same arguments): the IMM's cycle under a
    plain ``jax.lax.scan`` whose carry is the state ``(log_mu, xs, Ps)`` and the running sum

    .. math:: \ell = \sum_{k\ \text{measured}} \log \sum_j \bar c_{k,j}\, \Lambda_{k,j}

    (:func:`kftrack.imm.imm_loglik`), with no per-step output, so that ``jax.grad`` carries no
    stored sequence through the reverse pass (:func:`run_total_scan`). Returns ``ell`` (...)."""
    return _imm_total_jit()(zs, gone, log_mu0, xs0, Ps0, Pis, Fs, Qs, H, R, batch=tuple(batch),
                            mixing_weights=mixing_weights)


@lru_cache(maxsize=1)
def _imm_jit():
    return _jax().jit(_imm_impl, static_argnames=("batch", "mixing_weights"))


def run_imm_scan(zs, gone, log_mu0, xs0, Ps0, Pis, Fs, Qs, H, R, *, batch: tuple, mixing_weights):
    """The JAX engine of the IMM (and GPB1) with linear Kalman modes that share one state: the cycle
    of :meth:`kftrack.imm.IMM.update` and :meth:`kftrack.imm.IMM.predict` under
    ``jax.lax.scan``, with the mode axis as a batch axis of the kernels (one
    :func:`kftrack.kernels.kf_update`, one :func:`kftrack.kernels.moment_match` and one
    :func:`kftrack.kernels.kf_predict` call per step for all modes and runs).

    Parameters
    ----------
    zs : (T, ..., m) measurements; ``gone`` (T, ...) missing rows.
    log_mu0 : (..., r) log mode probabilities; ``xs0``, ``Ps0`` (r, ..., n), (r, ..., n, n).
    Pis : (T, r, r) Markov matrix of the step after ``k``; ``Fs``, ``Qs`` (T, r, n, n).
    H, R : (r, m, n), (r, m, m) per mode.
    batch : the batch shape; ``mixing_weights`` the estimator's ``(log_mu, Pi) -> (w, log_cbar)``.

    Returns
    -------
    tuple
        ``(x_prior, P_prior, mu_prior, x, P, mu, loglik, xs, Ps)``, time first; ``xs``, ``Ps`` the
        mode-matched posteriors, tuples of r arrays ``(T, ..., n)``, ``(T, ..., n, n)``.
    """
    return _imm_jit()(zs, gone, log_mu0, xs0, Ps0, Pis, Fs, Qs, H, R, batch=tuple(batch),
                      mixing_weights=mixing_weights)


def _smooth_impl(x, P, x_prior, P_prior, F, *, per_step):
    jax = _jax()
    jnp = jax.numpy
    T = x.shape[0]
    Fseq = F[:-1] if per_step else jnp.broadcast_to(F, (T - 1,) + F.shape)

    def body(carry, inp):
        xs_next, Ps_next = carry
        xk, Pk, xpn, Ppn, Fk = inp
        xs, Ps, G = rts_step(xk, Pk, xpn, Ppn, xs_next, Ps_next, Fk)
        xs, Ps = jnp.broadcast_to(xs, xs_next.shape), jnp.broadcast_to(Ps, Ps_next.shape)
        return (xs, Ps), (xs, Ps, jnp.broadcast_to(G, Ps_next.shape))

    _, (xs, Ps, G) = jax.lax.scan(body, (x[-1], P[-1]), (x[:-1], P[:-1], x_prior[1:], P_prior[1:], Fseq),
                                  reverse=True)
    return jnp.concatenate([xs, x[-1:]]), jnp.concatenate([Ps, P[-1:]]), G


@lru_cache(maxsize=1)
def _smooth_jit():
    return _jax().jit(_smooth_impl, static_argnames=("per_step",))


def run_smoother_scan(x, P, x_prior, P_prior, F, per_step: bool):
    """The JAX engine of the Rauch–Tung–Striebel smoother: :func:`kftrack.kernels.rts_step`
    under a reversed ``jax.lax.scan``. ``x``, ``P``, ``x_prior``, ``P_prior`` as in
    :class:`kftrack.kalman.FilterResult`; ``F`` one transition ``(..., n, n)`` or, with
    ``per_step``, a stack ``(T, ..., n, n)``. Returns ``(x_s, P_s, G)``."""
    return _smooth_jit()(x, P, x_prior, P_prior, F, per_step=bool(per_step))


def _imm_smooth_impl(mu, x, P, xs, Ps, Pis, Fs, Qs, *, backward_weights):
    jax = _jax()
    jnp = jax.numpy
    nb = mu.ndim - 2  # batch axes
    r = Pis.shape[-1]
    xs_f, Ps_f = jnp.stack(xs, axis=1), jnp.stack(Ps, axis=1)  # (T, r, ..., n), (T, r, ..., n, n)
    log_mu = jnp.log(mu)
    per_mode = lambda a: jnp.reshape(a, (r,) + (1,) * nb + (1,) + a.shape[1:])  # noqa: E731  (r_j, ..., 1, n, n)

    def body(carry, inp):
        log_ms, xs_s, Ps_s = carry  # smoothed at k + 1: (..., r), (r, ..., n), (r, ..., n, n)
        log_mu_f, x_f, P_f, Pi, F, Q = inp  # filtered at k; the transition from k to k + 1
        cond, log_ms = backward_weights(log_mu_f, Pi, log_ms)  # (..., r_i, r_j), (..., r_i)
        # every pair (i at k, j at k + 1) at once: j on the leading axis, i last of the batch axes
        x_i, P_i = jnp.moveaxis(x_f, 0, -2)[None], jnp.moveaxis(P_f, 0, -3)[None]  # (1, ..., r_i, n[, n])
        F_j = per_mode(F)
        x_pred, P_pred = kf_predict(x_i, P_i, F_j, per_mode(Q))
        x_ij, P_ij, _ = rts_step(x_i, P_i, x_pred, P_pred, xs_s[:, ..., None, :], Ps_s[:, ..., None, :, :], F_j)
        x_new, P_new = moment_match(cond, x_ij, P_ij)  # merged over j: (..., r_i, n[, n])
        xs_s, Ps_s = jnp.moveaxis(x_new, -2, 0), jnp.moveaxis(P_new, -3, 0)
        mu_s = jnp.exp(log_ms)
        x_c, P_c = moment_match(mu_s, xs_s, Ps_s)
        return (log_ms, xs_s, Ps_s), (mu_s, x_c, P_c, xs_s, Ps_s)

    last = log_mu[-1]
    init = (last - logsumexp(last, axis=-1, keepdims=True), xs_f[-1], Ps_f[-1])
    _, (mu_s, x_s, P_s, xs_s, Ps_s) = jax.lax.scan(
        body, init, (log_mu[:-1], xs_f[:-1], Ps_f[:-1], Pis[:-1], Fs[:-1], Qs[:-1]), reverse=True)
    cat = lambda a, b: jnp.concatenate([a, b[-1:]])  # noqa: E731  the last step: the filter's own arrays
    return (cat(x_s, x), cat(P_s, P), cat(mu_s, mu), tuple(cat(xs_s[:, i], xs[i]) for i in range(r)),
            tuple(cat(Ps_s[:, i], Ps[i]) for i in range(r)))


@lru_cache(maxsize=1)
def _imm_smooth_jit():
    return _jax().jit(_imm_smooth_impl, static_argnames=("backward_weights",))


def run_imm_smoother_scan(mu, x, P, xs, Ps, Pis, Fs, Qs, *, backward_weights):
    r"""The JAX engine of :func:`kftrack.imm.imm_smoother` for linear Kalman modes that share one
    state: Kim's backward recursion under a reversed ``jax.lax.scan`` over ``k = T-2, ..., 0``,
    every pair (mode ``i`` at ``k``, mode ``j`` at ``k + 1``) in one call of
    :func:`kftrack.kernels.kf_predict` and :func:`kftrack.kernels.rts_step` (the pair axis a batch
    axis of the kernels), merged over ``j`` and combined by :func:`kftrack.kernels.moment_match`.

    Parameters
    ----------
    mu, x, P : (T, ..., r), (T, ..., n), (T, ..., n, n) the filter's mode probabilities and
        combined posteriors; ``xs``, ``Ps`` tuples of r arrays (T, ..., n), (T, ..., n, n), the
        mode-matched posteriors (:class:`kftrack.imm.IMMResult`).
    Pis : (T, r, r) Markov matrix of the step after ``k``; ``Fs``, ``Qs`` (T, r, n, n) (the last
        row unused).
    backward_weights : ``(log_mu_k, Pi, log_ms_next) -> (w, log_ms_k)``, the smoother's weights
        :math:`P\{M_{k+1} = j \mid M_k = i, Z^T\}` (..., r, r) and the smoothed log mode
        probabilities of step ``k`` (a static, hashable function of the caller's).

    Returns
    -------
    tuple
        ``(x, P, mu, xs, Ps)`` smoothed, time first; at ``T - 1`` the inputs themselves.
    """
    return _imm_smooth_jit()(mu, x, P, tuple(xs), tuple(Ps), Pis, Fs, Qs, backward_weights=backward_weights)

