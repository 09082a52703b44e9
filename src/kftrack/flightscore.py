r"""Judging tracking methods on recorded flights (chapter 18, issue 26): every method on the same rows.

:func:`evaluate` scores each method's one-step predictions on the rows of
:func:`kftrack.aircraft.scored_rows` (one rule for all methods), in the flight's ENU frame
(origin the first finite fix, metres): per flight and method the one-step RMSE
:math:`\sqrt{\tfrac1N\sum_k \lVert \hat z_k - z_k\rVert^2}`, the median error (robust to the
heavy tails), and the RMSE ratio to a reference method,
:math:`\rho = \mathrm{RMSE}_{m}/\mathrm{RMSE}_{\mathrm{ref}}`, with a **moving-block bootstrap**
interval (Künsch 1989): the scored rows, in time order, are cut into all overlapping blocks of
``L`` consecutive rows; a replicate draws :math:`\lceil N/L\rceil` block starts uniformly, and
:math:`\rho^* = \sqrt{\sum e^{*2}_m / \sum e^{*2}_{\mathrm{ref}}}` over the drawn rows (the same
rows for both methods: the pairing is kept). The interval is the percentile interval of
:math:`\rho^*`. The errors of consecutive rows are correlated (one manoeuvre, one long
interpolated segment spans many rows), so ``L`` must exceed their correlation length:
:func:`block_length` takes it from the data, per flight. The percentile interval of a moving-block
bootstrap is too narrow when a flight holds few blocks: on an AR(1) series with coefficient 0.9
(2500 rows, about 40 blocks) it covers the true ratio in about 87 % of trials at a nominal 95 %
(single-row resampling: 35 %; ``tests/test_aircraft_split.py``), so a verdict near the edge of
its interval is weaker than its level says; :func:`intervals` recomputes the intervals with a
fixed, longer block to show how the verdicts move.

A **win** of a method is a flight whose interval lies entirely below 1, a **loss** one whose
interval lies entirely above 1 (the reference is better beyond its bootstrap interval).
"""
from __future__ import annotations

import math
import zlib
from typing import Callable, NamedTuple

import numpy as np

from .aircraft import _flight_columns, _frame_of, scored_rows

__all__ = ["FlightScores", "evaluate", "intervals", "block_length", "block_bootstrap_ratio", "wins_losses",
           "category_summary", "MIN_BLOCK", "N_BOOT"]

#: Shortest block (rows) of the bootstrap.
MIN_BLOCK = 10
#: Bootstrap replicates: the 2.5 % and 97.5 % percentiles of 2000 replicates move by about
#: 0.005 in the ratio between seeds on the chapter flights (Monte Carlo error well below the widths).
N_BOOT = 2000


def block_length(*errors_sq) -> int:
    r"""Block length (rows) for the moving-block bootstrap of ratios of sums of squared errors.

    For each series :math:`s_k = e_k^2` (one per method), the sample autocorrelation
    :math:`\hat\rho(\ell)` is computed; its correlation length is the first lag at which
    :math:`\hat\rho(\ell)` falls inside the white-noise band :math:`\pm 1.96/\sqrt N`. The block is
    twice the longest correlation length over the series, at least :data:`MIN_BLOCK` and at most
    :math:`N/5` (so that a replicate draws at least five blocks).

    Parameters
    ----------
    *errors_sq : (N,) arrays of squared errors on the same rows.
    """
    n = min(np.size(s) for s in errors_sq)
    longest = 1
    for s in errors_sq:
        x = np.asarray(s, float) - np.mean(s)
        den = float(np.dot(x, x))
        if den == 0.0:
            continue
        nfft = 1 << (2 * n - 1).bit_length()
        f = np.fft.rfft(x, nfft)
        acf = np.fft.irfft(f * np.conj(f), nfft)[:n] / den
        inside = np.flatnonzero(np.abs(acf[1:]) < 1.96 / math.sqrt(n))
        longest = max(longest, int(inside[0]) + 1 if inside.size else n)
    return int(max(MIN_BLOCK, min(2 * longest, n // 5)))


def block_bootstrap_ratio(ea2, eb2, block: int, rng: np.random.Generator, n_boot: int = N_BOOT,
                          level: float = 0.95) -> tuple[float, float]:
    r"""Percentile interval of :math:`\sqrt{\sum e_a^2/\sum e_b^2}` by a moving-block bootstrap of the
    paired squared errors ``ea2``, ``eb2`` (N,) with blocks of ``block`` rows (module docstring)."""
    ea2, eb2 = np.asarray(ea2, float), np.asarray(eb2, float)
    n = ea2.size
    block = int(min(max(1, block), n))
    ca, cb = np.concatenate([[0.0], np.cumsum(ea2)]), np.concatenate([[0.0], np.cumsum(eb2)])
    sa, sb = ca[block:] - ca[:-block], cb[block:] - cb[:-block]      # block sums, n - block + 1 starts
    starts = rng.integers(0, n - block + 1, size=(n_boot, -(-n // block)))
    ratio = np.sqrt(sa[starts].sum(axis=1) / sb[starts].sum(axis=1))
    lo, hi = np.quantile(ratio, [(1.0 - level) / 2.0, (1.0 + level) / 2.0])
    return float(lo), float(hi)


class FlightScores(NamedTuple):
    """Output of :func:`evaluate`: F flights, M methods.

    Attributes
    ----------
    flights : (F,) names; categories : (F,) their groups (:func:`kftrack.adsb.category_of`).
    methods : (M,) names; reference : the reference method's name.
    n_rows : (F,) scored rows per flight; block : (F,) bootstrap block length (rows).
    rmse, median : (F, M) one-step RMSE and median error, m.
    ratio : (F, M) RMSE ratio to the reference; ci : (F, M, 2) its bootstrap interval.
    level, n_boot, seed : the bootstrap's settings.
    errors_sq : (F,) tuple of (M, n_rows[f]) squared errors (m²), scored rows in time order, for
        :func:`intervals` with another block length.
    """

    flights: tuple
    categories: tuple
    methods: tuple
    reference: str
    n_rows: np.ndarray
    block: np.ndarray
    rmse: np.ndarray
    median: np.ndarray
    ratio: np.ndarray
    ci: np.ndarray
    level: float
    n_boot: int
    seed: int
    errors_sq: tuple


def evaluate(flights, methods: dict[str, Callable], reference: str, *, seed: int = 26,
             n_boot: int = N_BOOT, level: float = 0.95) -> FlightScores:
    """Score every method on the same rows of every flight, with ratios to ``reference``.

    Parameters
    ----------
    flights : sequence of :class:`kftrack.adsb.Flight` (``name``, ``t_s``, ``lat_deg``, ``lon_deg``).
    methods : {name: callable(flight) -> (lat_pred_deg, lon_pred_deg)}, each (K,) one-step
        predictions of the flight's rows, in degrees; they must be finite on every scored row.
    reference : a key of ``methods``.
    seed : seed of the bootstrap: flight ``name`` uses ``numpy.random.default_rng([seed, crc32(name)])``,
        so a flight's interval does not depend on which other flights are scored.
    n_boot, level : bootstrap replicates and interval level.

    Returns
    -------
    FlightScores
    """
    from .adsb import category_of, to_enu
    cols = _flight_columns(flights)
    if not isinstance(methods, dict) or not methods or not all(callable(f) for f in methods.values()):
        raise TypeError(f"methods must be a non-empty dict of name -> callable, got {type(methods).__name__}")
    if reference not in methods:
        raise ValueError(f"reference must be one of the methods {list(methods)}, got {reference!r}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must lie in (0, 1), got {level!r}")
    names = tuple(methods)
    iref = names.index(reference)
    F, M = len(cols), len(names)
    rmse, med, ratio = np.empty((F, M)), np.empty((F, M)), np.empty((F, M))
    ci, n_rows, block = np.empty((F, M, 2)), np.empty(F, int), np.empty(F, int)
    fnames, errs = [], []
    for i, (fl, (t, lat, lon)) in enumerate(zip(flights, cols)):
        name = str(getattr(fl, "name", f"flight {i}"))
        fnames.append(name)
        m = scored_rows(t, lat, lon)
        if not m.any():
            raise ValueError(f"flights[{i}] ({name}) has no scored row")
        enu, origin, _ = _frame_of(t, lat, lon)
        e2 = np.empty((M, int(m.sum())))
        for j, meth in enumerate(names):
            la, lo = methods[meth](fl)
            p = to_enu(np.asarray(la, float), np.asarray(lo, float), origin=origin)[0][:, :2]
            d = p[m] - enu[m]
            if not np.all(np.isfinite(d)):
                raise ValueError(f"method {meth!r} has no finite prediction on {int(np.sum(~np.isfinite(d[:, 0])))} "
                                 f"scored rows of {name}")
            e2[j] = np.sum(d * d, axis=1)
        errs.append(e2)
        n_rows[i] = e2.shape[1]
        block[i] = block_length(*e2)
        rmse[i] = np.sqrt(e2.mean(axis=1))
        med[i] = np.median(np.sqrt(e2), axis=1)
        ratio[i] = rmse[i] / rmse[i, iref]
        ci[i] = _flight_intervals(e2, iref, block[i], name, seed, n_boot, level)
    return FlightScores(tuple(fnames), tuple(category_of(n) for n in fnames), names, reference, n_rows, block,
                        rmse, med, ratio, ci, float(level), int(n_boot), int(seed), tuple(errs))


def _flight_intervals(e2, iref, block, name, seed, n_boot, level):
    """(M, 2) intervals of one flight; its generator is seeded by ``[seed, crc32(name)]``, so a
    flight's interval does not depend on which other flights are scored."""
    rng = np.random.default_rng([int(seed), zlib.crc32(name.encode())])
    return np.array([(1.0, 1.0) if j == iref else block_bootstrap_ratio(e2[j], e2[iref], block, rng, n_boot, level)
                     for j in range(e2.shape[0])])


def intervals(scores: FlightScores, block: int) -> np.ndarray:
    """(F, M, 2) bootstrap intervals of ``scores`` recomputed with a fixed ``block`` (rows; at most
    N/5 per flight), to show how much the verdicts depend on the block length."""
    iref = scores.methods.index(scores.reference)
    return np.stack([_flight_intervals(e2, iref, int(min(block, max(1, e2.shape[1] // 5))), f, scores.seed,
                                       scores.n_boot, scores.level)
                     for f, e2 in zip(scores.flights, scores.errors_sq)])


def wins_losses(scores: FlightScores, method: str) -> tuple[int, int]:
    """``(wins, losses)`` of ``method`` against the reference: flights whose ratio interval lies
    entirely below 1, entirely above 1."""
    j = scores.methods.index(method)
    return int(np.sum(scores.ci[:, j, 1] < 1.0)), int(np.sum(scores.ci[:, j, 0] > 1.0))


def category_summary(scores: FlightScores) -> dict:
    """Per category and method: ``{"n": flights, "median_ratio", "geo_mean_ratio", "wins", "losses"}``
    (``"all"`` for every flight)."""
    out = {}
    cats = sorted(set(scores.categories)) + ["all"]
    for c in cats:
        sel = np.array([c in ("all", k) for k in scores.categories])
        out[c] = {}
        for j, meth in enumerate(scores.methods):
            r, lo, hi = scores.ratio[sel, j], scores.ci[sel, j, 0], scores.ci[sel, j, 1]
            out[c][meth] = {"n": int(sel.sum()), "median_ratio": float(np.median(r)),
                            "geo_mean_ratio": float(np.exp(np.mean(np.log(r)))),
                            "wins": int(np.sum(hi < 1.0)), "losses": int(np.sum(lo > 1.0))}
    return out
