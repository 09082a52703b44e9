r"""Monte Carlo comparison of several filters on one scenario.

Numerics layer: pure functions, no plotting, no printing. The pattern of a case-study chapter
(11: the drone, 12: the 3-D radar targets) is

1. one truth, ``N`` independent noise realisations, **time first**: ``zs`` ``(T, N, m)``
   (:func:`noisy_runs`);
2. each filter runs **once** over all the runs (the batch axis of :mod:`kftrack.kalman`,
   :mod:`kftrack.ekf`, :mod:`kftrack.imm`): :func:`run_filters`;
3. one error number per run and filter (:func:`per_run_error`: the time-averaged squared
   Euclidean error, study 000's "EQM", or its square root, the RMSE), collected in a
   :class:`Comparison`;
4. statements backed by statistics: the mean and its standard error, **paired** differences
   between filters run by run (:func:`paired_difference`: the same noise for both, so the
   run-to-run spread of the scenario cancels), and where a single published run falls in the
   distribution of single runs (:meth:`Comparison.percentile`).

Shapes: ``estimate`` ``(T, ..., n)``, ``truth`` ``(T, n)`` or ``(T, ..., n)``; per-run values
``(...)``, typically ``(N,)``.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import NamedTuple

import numpy as np

from ._validate import as_float_array, as_vector, check_finite, check_rng

__all__ = ["noisy_runs", "per_run_error", "PairedDifference", "paired_difference", "Comparison", "compare",
           "run_filters", "RunningMoments", "Moments", "run_generators", "chunked_study"]


def noisy_runs(rng: np.random.Generator, clean, sigma, runs: int) -> np.ndarray:
    r"""``runs`` independent noisy copies of a clean measurement sequence, time first:
    :math:`z_k^{(i)} = h_k + \sigma\,w_k^{(i)}`, :math:`w \sim N(0, I)` white in time and run.

    Parameters
    ----------
    rng : the random generator.
    clean : (T, m) noise-free measurements (e.g. the true positions).
    sigma : noise standard deviation, scalar or (m,) per component (same unit as ``clean``).
    runs : number of Monte Carlo runs ``N`` (>= 1).

    Returns
    -------
    (T, N, m) measurements.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.montecarlo import noisy_runs
    >>> clean = np.zeros((50, 2))                    # (T, m) noise-free positions
    >>> noisy_runs(np.random.default_rng(0), clean, sigma=[1.0, 2.0], runs=200).shape   # (T, N, m)
    (50, 200, 2)
    """
    check_rng(rng)
    clean = as_vector(clean, "clean")
    if clean.ndim != 2:
        raise ValueError(f"clean must have shape (T, m), time first, got shape {clean.shape}")
    s = check_finite(as_float_array(sigma, "sigma"), "sigma")
    if s.ndim > 1 or (s.ndim == 1 and s.shape != clean.shape[-1:]) or np.any(s < 0):
        raise ValueError(f"sigma must be a scalar or have shape ({clean.shape[-1]},), with sigma >= 0; "
                         f"got {np.asarray(sigma)!r}")
    if isinstance(runs, bool) or not isinstance(runs, (int, np.integer)) or runs < 1:
        raise ValueError(f"runs must be an integer >= 1, got {runs!r}")
    T, m = clean.shape
    return clean[:, None, :] + s * rng.standard_normal((T, int(runs), m))


def per_run_error(truth, estimate, components: Sequence[int] | None = None, *, start: int = 0,
                  root: bool = False) -> np.ndarray:
    r"""Time-averaged squared Euclidean error of each run,

    .. math:: \mathrm{EQM} = \frac{1}{T - k_0}\sum_{k=k_0}^{T-1}\lVert \hat x_k - x_k\rVert^2

    over the selected state components (study 000's eq. 73, in m² for positions), or its square
    root, the per-run RMSE, with ``root=True``.

    Arguments in the order of :mod:`kftrack.metrics`: ``(truth, estimate, ...)``.

    Parameters
    ----------
    truth : (T, n') (shared by all runs) or (T, ..., n'); ``n' = n`` unless ``components``
        is given (the estimate may hold more, e.g. a turn rate ``omega`` last).
    estimate : (T, ..., n) estimates, time first.
    components : indices of the state to compare (e.g. ``[0, 2]`` for the positions of
        ``[x, vx, y, vy]``), the same in ``estimate`` and ``truth``; default all.
    start : first step counted (skips a start-up transient), ``0 <= start < T``.
    root : return the RMSE instead of the mean squared error.

    Returns
    -------
    (...) one value per run.
    """
    est = as_vector(estimate, "estimate")
    tru = as_vector(truth, "truth", None if components is not None else est.shape[-1])
    if tru.ndim > est.ndim:
        raise ValueError(f"truth has more axes than estimate (shapes {tru.shape} and {est.shape}); the order is "
                         "per_run_error(truth, estimate, ...): truth (T, n') or (T, ..., n'), estimate (T, ..., n)")
    if est.ndim < 2 or tru.shape[0] != est.shape[0]:
        raise ValueError(f"estimate (T, ..., n) and truth (T, n) must share the time axis first, got shapes "
                         f"{est.shape} and {tru.shape}")
    T = est.shape[0]
    if tru.ndim == 2 and est.ndim > 2:
        tru = tru.reshape((T,) + (1,) * (est.ndim - 2) + tru.shape[-1:])
    if components is not None:
        idx = np.asarray(components, dtype=int)
        n = min(est.shape[-1], tru.shape[-1])
        if idx.ndim != 1 or idx.size == 0 or idx.min() < 0 or idx.max() >= n:
            raise ValueError(f"components must be a non-empty list of indices in [0, {n - 1}] (components held "
                             f"by both estimate and truth), got {components!r}")
        est, tru = est[..., idx], tru[..., idx]
    if isinstance(start, bool) or not isinstance(start, (int, np.integer)) or not 0 <= start < T:
        raise ValueError(f"start must be an integer step in [0, {T - 1}], got {start!r}")
    try:
        sq = np.sum((est[start:] - tru[start:]) ** 2, axis=-1)
    except ValueError:
        raise ValueError(f"estimate and truth must broadcast, got shapes {est.shape} and {tru.shape}") from None
    mse = sq.mean(axis=0)
    return np.sqrt(mse) if root else mse


class PairedDifference(NamedTuple):
    """Run-by-run difference ``a - b`` of two filters' per-run errors on the same noise.

    Attributes
    ----------
    mean : mean difference over the runs.
    se : its standard error, ``std(ddof=1) / sqrt(runs)``.
    z : ``mean / se``: how many standard errors ``a`` is above ``b`` (negative: ``a`` better).
        Over ``runs >= 30`` independent runs it is close to standard normal when the two
        filters are equally good.
    runs : number of runs.
    """

    mean: float
    se: float
    z: float
    runs: int


def paired_difference(a, b) -> PairedDifference:
    """:class:`PairedDifference` of per-run values ``a`` and ``b`` (same shape, >= 2 runs).

    Examples
    --------
    >>> from kftrack.montecarlo import paired_difference
    >>> d = paired_difference([1.0, 2.0, 3.0, 4.0], [1.5, 1.5, 2.5, 4.5])   # per-run errors of a and b
    >>> print(round(d.mean, 6), round(d.se, 6), d.runs)
    0.0 0.288675 4
    """
    a = np.ravel(check_finite(as_float_array(a, "a"), "a"))
    b = np.ravel(check_finite(as_float_array(b, "b"), "b"))
    if a.shape != b.shape or a.size < 2:
        raise ValueError(f"a and b must hold the same number (>= 2) of per-run values, got {a.size} and {b.size}")
    d = a - b
    mean, se = float(d.mean()), float(d.std(ddof=1) / np.sqrt(d.size))
    z = mean / se if se > 0 else (0.0 if mean == 0 else np.copysign(np.inf, mean))
    return PairedDifference(mean, se, float(z), int(d.size))


@dataclass(frozen=True)
class Comparison:
    """Per-run errors of several filters on the same Monte Carlo runs.

    Attributes
    ----------
    values : mapping filter name -> (N,) per-run error (read-only), in insertion order.
    """

    values: Mapping[str, np.ndarray]

    def __post_init__(self):
        vals = {}
        sizes = set()
        for name, v in dict(self.values).items():
            arr = np.ravel(check_finite(as_float_array(v, f"values[{name!r}]"), f"values[{name!r}]")).copy()
            arr.setflags(write=False)
            vals[name] = arr
            sizes.add(arr.size)
        if not vals or len(sizes) != 1 or sizes.pop() < 1:
            raise ValueError("values must map at least one filter name to per-run errors, the same number of runs "
                             f"for every filter; got sizes { {k: v.size for k, v in vals.items()} }")
        object.__setattr__(self, "values", MappingProxyType(vals))

    @property
    def names(self) -> tuple[str, ...]:
        """Filter names, in insertion order."""
        return tuple(self.values)

    @property
    def runs(self) -> int:
        """Number of Monte Carlo runs."""
        return next(iter(self.values.values())).size

    def _get(self, name: str) -> np.ndarray:
        if name not in self.values:
            raise ValueError(f"name must be one of {self.names}, got {name!r}")
        return self.values[name]

    def mean(self, name: str) -> float:
        """Mean of the per-run errors."""
        return float(self._get(name).mean())

    def std(self, name: str) -> float:
        """Run-to-run standard deviation (ddof = 1): the spread of a single run's value."""
        v = self._get(name)
        return float(v.std(ddof=1)) if v.size > 1 else float("nan")

    def sem(self, name: str) -> float:
        """Standard error of :meth:`mean`, ``std / sqrt(runs)``."""
        return self.std(name) / np.sqrt(self.runs)

    def paired(self, a: str, b: str) -> PairedDifference:
        """Run-by-run difference ``a - b`` (:func:`paired_difference`)."""
        return paired_difference(self._get(a), self._get(b))

    def percentile(self, name: str, value: float) -> float:
        """Fraction of the runs whose error is ``<= value``: where a single run with error
        ``value`` (e.g. a study's published one) falls in the distribution of single runs."""
        return float(np.mean(self._get(name) <= float(value)))

    def ranking(self) -> tuple[str, ...]:
        """Filter names from the lowest to the highest mean error."""
        return tuple(sorted(self.names, key=self.mean))


def compare(truth, estimates: Mapping[str, np.ndarray], components: Sequence[int] | None = None, *,
            start: int = 0, root: bool = False) -> Comparison:
    """:class:`Comparison` of estimates ``(T, N, n)`` (one per filter name) against ``truth``
    with :func:`per_run_error` (same ``components``, ``start``, ``root`` for every filter).
    Arguments in the order of :mod:`kftrack.metrics`: ``(truth, estimates, ...)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.kalman import kalman_filter
    >>> from kftrack.models import ConstantVelocity
    >>> from kftrack.montecarlo import compare, noisy_runs, run_filters
    >>> t = np.arange(50.0)
    >>> truth = np.stack([2.0 * t, np.full(50, 2.0)], axis=-1)        # [x, vx], 2 m/s
    >>> zs = noisy_runs(np.random.default_rng(0), truth[:, :1], sigma=1.0, runs=200)   # (T, N, 1)
    >>> def kf(q):
    ...     m = ConstantVelocity(ndim=1, q=q)
    ...     return lambda z: kalman_filter(z, np.zeros(2), 100 * np.eye(2), m.F(1.0), m.Q(1.0), m.H, np.eye(1))
    >>> est = run_filters({"q=0.01": kf(0.01), "q=10": kf(10.0)}, zs)
    >>> c = compare(truth, est, components=[0], start=10, root=True)   # position RMSE per run, after step 10
    >>> c.ranking(), c.runs
    (('q=0.01', 'q=10'), 200)
    >>> bool(c.paired("q=0.01", "q=10").z < -3)       # on the same noise, by many standard errors
    True
    """
    if isinstance(truth, Mapping):
        raise TypeError("truth must be an array (T, n') or (T, ..., n'), got a mapping; the order is "
                        "compare(truth, estimates, ...) with estimates a mapping name -> (T, N, n) array")
    if not isinstance(estimates, Mapping) or not estimates:
        raise TypeError(f"estimates must be a non-empty mapping name -> (T, N, n) array, got {type(estimates).__name__}")
    return Comparison({name: per_run_error(truth, x, components, start=start, root=root)
                       for name, x in estimates.items()})


def run_filters(filters: Mapping[str, Callable], zs) -> dict[str, np.ndarray]:
    """Run each filter once on all the Monte Carlo runs: ``filters[name](zs)`` returns the
    estimates ``(T, N, n)`` or a result with an ``x`` attribute (``FilterResult``,
    ``IMMResult``); returns name -> estimates, ready for :func:`compare`."""
    if not isinstance(filters, Mapping) or not filters:
        raise TypeError(f"filters must be a non-empty mapping name -> callable(zs), got {type(filters).__name__}")
    out = {}
    for name, fn in filters.items():
        if not callable(fn):
            raise TypeError(f"filters[{name!r}] must be callable(zs), got {type(fn).__name__}")
        res = fn(zs)
        out[name] = np.asarray(getattr(res, "x", res), dtype=float)
    return out


# --------------------------------------------------------------------------------------------
# studies larger than memory: chunks of runs reduced to running moments
# --------------------------------------------------------------------------------------------
class Moments(NamedTuple):
    """Summary of per-run values: ``count`` runs, their ``mean``, variance ``var`` (ddof = 1;
    NaN for one run) and the standard error of the mean ``sem = sqrt(var / count)``. ``mean``,
    ``var``, ``sem`` have the shape of one run's value."""

    count: int
    mean: np.ndarray
    var: np.ndarray
    sem: np.ndarray


class RunningMoments:
    r"""Mean and variance of values arriving in batches, in constant memory (Welford 1962;
    Chan, Golub & LeVeque 1983, the parallel combination).

    A batch of :math:`n_b` values is reduced by two passes to its mean :math:`\bar x_b` and
    :math:`M_{2,b} = \sum (x - \bar x_b)^2`, then combined with the running :math:`(n_a, \bar x_a,
    M_{2,a})`:

    .. math::

        n = n_a + n_b,\quad \delta = \bar x_b - \bar x_a,\quad
        \bar x = \bar x_a + \delta\,\frac{n_b}{n},\quad
        M_2 = M_{2,a} + M_{2,b} + \delta^2\,\frac{n_a n_b}{n},

    and :math:`s^2 = M_2/(n - 1)`. The result depends on how the values were split into batches
    only through round-off. Elementwise over the shape of one value (e.g. a per-step error curve).
    """

    def __init__(self):
        self.count, self.mean_, self.m2 = 0, None, None

    def update(self, values) -> "RunningMoments":
        """Add a batch ``values`` ``(n_b, ...)`` (runs first); returns ``self``."""
        v = np.asarray(values, dtype=float)
        if v.ndim < 1 or v.shape[0] < 1:
            raise ValueError(f"values must have shape (n_b, ...) with n_b >= 1 runs first, got shape {v.shape}")
        if self.mean_ is not None and v.shape[1:] != self.mean_.shape:
            raise ValueError(f"values must keep the shape of one run's value {self.mean_.shape} after the run "
                             f"axis, got shape {v.shape}")
        nb = v.shape[0]
        mb = v.mean(axis=0)
        m2b = ((v - mb) ** 2).sum(axis=0)
        if self.mean_ is None:
            self.count, self.mean_, self.m2 = nb, mb, m2b
            return self
        na, n = self.count, self.count + nb
        delta = mb - self.mean_
        self.mean_ = self.mean_ + delta * (nb / n)
        self.m2 = self.m2 + m2b + delta ** 2 * (na * nb / n)
        self.count = n
        return self

    def moments(self) -> Moments:
        """The current :class:`Moments`."""
        if self.mean_ is None:
            raise ValueError("no values yet: call update first")
        var = self.m2 / (self.count - 1) if self.count > 1 else np.full_like(self.m2, np.nan)
        return Moments(self.count, self.mean_.copy(), var, np.sqrt(var / self.count))


def run_generators(rng: np.random.Generator, runs: int):
    """One independent generator per run index, made on demand for a range of runs.

    Run ``i`` gets ``default_rng(SeedSequence(entropy, spawn_key=(i,)))``, the entropy (four 63-bit words)
    drawn once from ``rng`` (the children of one ``SeedSequence`` are independent streams, NumPy's
    ``SeedSequence.spawn`` scheme), so it draws the same numbers whatever chunk it falls in.

    Parameters
    ----------
    rng : the generator the entropy is drawn from (advanced by four draws).
    runs : the number of runs, >= 1.

    Returns
    -------
    callable
        ``gens(start, stop) -> list`` of ``stop - start`` generators for runs ``start .. stop - 1``
        (``0 <= start <= stop <= runs``, else ``ValueError``).
    """
    check_rng(rng)
    runs = _positive_int(runs, "runs")
    entropy = [int(e) for e in rng.integers(0, 2**63, size=4)]

    def gens(start: int, stop: int) -> list[np.random.Generator]:
        if not (0 <= start <= stop <= runs):
            raise ValueError(f"start, stop must satisfy 0 <= start <= stop <= runs = {runs}, got {start}, {stop}")
        return [np.random.default_rng(np.random.SeedSequence(entropy, spawn_key=(i,))) for i in range(start, stop)]

    return gens


def _to_numpy(obj):
    """NumPy view of a filter's output: arrays (NumPy, JAX, anything with ``__array__``) through
    ``np.asarray``; tuples (named too), lists and dicts field by field; anything else unchanged."""
    if isinstance(obj, np.ndarray):
        return obj
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):
        return type(obj)(*(_to_numpy(v) for v in obj))
    if isinstance(obj, (tuple, list)):
        return type(obj)(_to_numpy(v) for v in obj)
    if isinstance(obj, Mapping):
        return {k: _to_numpy(v) for k, v in obj.items()}
    if hasattr(obj, "__array__"):
        return np.asarray(obj)
    return obj


def _positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


def chunked_study(simulate: Callable, estimate: Callable, score: Callable, runs: int, chunk: int,
                  rng: np.random.Generator, *, progress: bool = False) -> dict[str, Moments]:
    r"""A Monte Carlo study of ``runs`` runs, done ``chunk`` runs at a time in constant memory:
    for each chunk, simulate, estimate, score, fold the per-run scores into running moments
    (:class:`RunningMoments`), and drop the chunk.

    Results do not depend on ``chunk`` beyond round-off: run ``i`` always draws from its own
    generator (:func:`run_generators`), and the moments combine exactly (Chan et al. 1983).
    Memory is that of one chunk plus the moments, whatever ``runs``.

    Parameters
    ----------
    simulate : ``simulate(rngs) -> data`` for ``len(rngs)`` runs, one generator per run (draw
        run ``i``'s noise from ``rngs[i]`` only, e.g. ``np.stack([g.standard_normal((T, m)) for g
        in rngs], axis=1)`` for ``(T, n, m)``).
    estimate : ``estimate(data) -> estimates``, any filter over the batch, e.g.
        ``lambda d: kalman_filter(d.zs, ...)``. JAX arrays (or named tuples, tuples, dicts of
        them) are converted with ``np.asarray`` before scoring.
    score : ``score(data, estimates)`` -> per-run values with the **run axis first**, ``(n, ...)``
        (e.g. :func:`per_run_error`, which gives ``(n,)``; a per-step curve ``(T, n)`` needs
        ``.T``), or a mapping name -> such arrays. Paired comparisons: score the difference
        run by run (``a - b``); its ``mean / sem`` is :class:`PairedDifference`'s ``z``.
        Non-finite values propagate into the moments (a diverged run shows as inf or NaN).
    runs : total number of runs (>= 1).
    chunk : runs per chunk (>= 1; larger than ``runs`` means one chunk).
    rng : the generator the per-run seeds are drawn from.
    progress : show a tqdm bar over the runs.

    Returns
    -------
    dict
        name -> :class:`Moments` (``"score"`` when ``score`` returns a single array).
    """
    for name, fn in (("simulate", simulate), ("estimate", estimate), ("score", score)):
        if not callable(fn):
            raise TypeError(f"{name} must be callable, got {type(fn).__name__}")
    runs = _positive_int(runs, "runs")
    chunk = min(_positive_int(chunk, "chunk"), runs)
    gens = run_generators(rng, runs)
    acc: dict[str, RunningMoments] = {}
    bar = None
    if progress:
        from tqdm.auto import tqdm  # only when asked for

        bar = tqdm(total=runs, desc="Monte Carlo", unit="run")
    try:
        for start in range(0, runs, chunk):
            stop = min(start + chunk, runs)
            data = simulate(gens(start, stop))
            scores = score(data, _to_numpy(estimate(data)))
            single = not isinstance(scores, Mapping)
            scores = {"score": scores} if single else dict(scores)
            if acc and set(scores) != set(acc):
                raise ValueError(f"score must return the same names for every chunk, got {sorted(scores)} after "
                                 f"{sorted(acc)}")
            for name, v in scores.items():
                v = np.asarray(_to_numpy(v), dtype=float)
                if v.ndim < 1 or v.shape[0] != stop - start:
                    raise ValueError(f"score must return per-run values with the run axis first, shape "
                                     f"({stop - start}, ...) for this chunk, got shape {v.shape} for {name!r}")
                acc.setdefault(name, RunningMoments()).update(v)
            del data, scores
            if bar is not None:
                bar.update(stop - start)
    finally:
        if bar is not None:
            bar.close()
    return {name: a.moments() for name, a in acc.items()}
