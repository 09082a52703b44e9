r"""Scoring a multi-target tracker against the truth over time: GOSPA per scan with its split
into localisation, missed and false targets, and track-level metrics (track breaks, identity
switches, false tracks, missed targets, time to confirm).

Both take the same input, a sequence of ``K`` times with, at each time ``k``,

* ``truth[k] = (ids, xy)``: the identities ``(n_k,)`` (any hashable values: str icao24, int)
  and positions ``(n_k, d)`` of the targets present (in coverage) at ``times[k]``;
* ``estimates[k] = (ids, xy)``: the track identities ``(m_k,)`` and estimated positions
  ``(m_k, d)`` of the (confirmed) tracks reported at ``times[k]``.

**Assignment.** At each time, truths and estimates are matched by the optimal GOSPA assignment
(:func:`kftrack.association.gospa_assignment`, cut-off ``c``, order ``p``): a truth and a track
are *assigned* at time ``k`` when they form a pair of that assignment (distance below ``c``).
Writing :math:`a_k(i)` for the track assigned to truth ``i`` at time ``k`` (none when ``i`` is
unassigned), the track-level metrics are (after Rothrock & Drummond 2000 and the track-label
errors of Ristic, Vo, Clark & Vo 2011):

* **identity switch**: a truth ``i`` whose assigned track changes, :math:`a_k(i) = b` after its
  previous assignment :math:`a_{k'}(i) = a \ne b` (``k' < k`` its last assigned time, any gap
  between), while track ``a`` is still reported at time ``k`` (it went to another target or to
  nothing);
* **track break** (fragmentation): the same change :math:`a \to b` when track ``a`` is no
  longer reported at time ``k`` (it ended, and ``b`` took over, usually after a gap). Each change
  of a truth's assigned track is exactly one of the two; the same track taking the truth again
  after a gap is neither;
* **false track**: a track assigned to some truth at fewer than ``min_fraction`` (default 1/2)
  of the times it is reported;
* **missed target**: a truth assigned to some track at fewer than ``min_fraction`` of the times
  it is present;
* **time to confirm** of a truth: the first time it is assigned minus the first time it is
  present (NaN if never assigned). Since ``estimates`` hold confirmed tracks only, this is the
  delay from appearance in coverage to a confirmed track on it.

GOSPA (Rahmathullah, García-Fernández & Svensson 2017, :math:`\alpha = 2`):
:math:`d^p = \sum_{\text{pairs}} d_{ij}^p + \tfrac{c^p}{2}(\text{missed} + \text{false})`.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._validate import as_float_array, finite_scalar
from .association import _check_sets, _gospa

__all__ = ["GOSPATimeline", "gospa_over_time", "TrackMetrics", "track_metrics"]


class GOSPATimeline(NamedTuple):
    """GOSPA per time, ``(K,)`` arrays: ``distance``, ``localisation`` (the sum of
    :math:`d^p` over the assigned pairs), ``missed`` and ``false`` (int counts), with
    ``distance**p = localisation + c**p / 2 * (missed + false)``; ``times`` (K,)."""

    times: np.ndarray
    distance: np.ndarray
    localisation: np.ndarray
    missed: np.ndarray
    false: np.ndarray


class TrackMetrics(NamedTuple):
    """Track-level metrics (definitions in the module docstring).

    Attributes
    ----------
    breaks, switches, false_tracks, missed_targets : int counts.
    truth_ids : (n,) the truths, in order of first appearance; ``time_to_confirm`` (n,) s
        (NaN if never assigned); ``coverage`` (n,) the fraction of its present times each truth
        is assigned.
    track_ids : (t,) the tracks, in order of first report; ``track_coverage`` (t,) the fraction
        of its reported times each track is assigned.
    """

    breaks: int
    switches: int
    false_tracks: int
    missed_targets: int
    truth_ids: list
    time_to_confirm: np.ndarray
    coverage: np.ndarray
    track_ids: list
    track_coverage: np.ndarray


def _check_series(times, truth, estimates, c, p):
    times = as_float_array(times, "times")
    if times.ndim != 1:
        raise ValueError(f"times must have shape (K,), got shape {times.shape}")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise ValueError("times must be finite and strictly increasing")
    K = len(times)
    truth, estimates = list(truth), list(estimates)
    if len(truth) != K or len(estimates) != K:
        raise ValueError(f"truth and estimates must hold one (ids, xy) pair per time ({K} from times), "
                         f"got {len(truth)} and {len(estimates)}")
    c = finite_scalar(c, "c")
    p = finite_scalar(p, "p")
    out = []
    for k in range(K):
        sets = []
        for name, item in (("truth", truth[k]), ("estimates", estimates[k])):
            try:
                ids, xy = item
            except (TypeError, ValueError):
                raise ValueError(f"{name}[{k}] must be a pair (ids, xy), got {type(item).__name__}") from None
            ids = list(np.asarray(ids).reshape(-1).tolist()) if np.size(ids) else []
            if len(set(ids)) != len(ids):
                raise ValueError(f"{name}[{k}] ids must be distinct at one time, got {len(ids)} ids, "
                                 f"{len(set(ids))} distinct")
            sets.append((ids, xy))
        (ti, txy), (ei, exy) = sets
        X, Y = _check_sets(txy, exy, c, p)
        if len(X) != len(ti) or len(Y) != len(ei):
            raise ValueError(f"at time {k}: ids and xy must have the same length, got truth {len(ti)} ids for "
                             f"{len(X)} points and estimates {len(ei)} ids for {len(Y)} points")
        out.append((ti, X, ei, Y))
    return times, out, c, p


def gospa_over_time(times, truth, estimates, *, c: float, p: float = 2.0) -> GOSPATimeline:
    r"""GOSPA (:math:`\alpha = 2`) at each time, split into localisation, missed and false.

    Parameters
    ----------
    times : (K,) increasing times (s).
    truth, estimates : K pairs ``(ids, xy)`` each (see the module docstring; ids are not used).
    c : cut-off distance (m); ``p`` the order (>= 1).

    Examples
    --------
    >>> from kftrack.trackeval import gospa_over_time
    >>> g = gospa_over_time([0.0, 1.0], [(["a"], [[0.0, 0.0]]), (["a"], [[1.0, 0.0]])],
    ...                     [([7], [[3.0, 4.0]]), ([], [])], c=10.0)
    >>> g.distance.round(4).tolist(), g.missed.tolist()        # 5 m off; then missed: sqrt(100 / 2)
    ([5.0, 7.0711], [0, 1])
    """
    times, series, c, p = _check_series(times, truth, estimates, c, p)
    res = [_gospa(X, Y, c, p)[0] for _, X, _, Y in series]
    return GOSPATimeline(times, np.array([r.distance for r in res]), np.array([r.localisation for r in res]),
                         np.array([r.missed for r in res], dtype=int), np.array([r.false for r in res], dtype=int))


def track_metrics(times, truth, estimates, *, c: float, p: float = 2.0, min_fraction: float = 0.5) -> TrackMetrics:
    r"""Track breaks, identity switches, false tracks, missed targets and time to confirm.

    Parameters
    ----------
    times : (K,) increasing times (s).
    truth, estimates : K pairs ``(ids, xy)`` each (see the module docstring).
    c : cut-off distance of the per-time assignment (m); ``p`` its order.
    min_fraction : a track assigned at fewer than this fraction of its reported times is false; a
        truth assigned at fewer than this fraction of its present times is missed. In (0, 1].

    Examples
    --------
    >>> from kftrack.trackeval import track_metrics
    >>> truth = [(["A", "B"], [[0.0, 0.0], [100.0, 0.0]])] * 2
    >>> est = [([1, 2], [[1.0, 0.0], [101.0, 0.0]]), ([1, 2], [[101.0, 0.0], [1.0, 0.0]])]   # tracks swap
    >>> m = track_metrics([0.0, 1.0], truth, est, c=10.0)
    >>> m.switches, m.breaks, m.false_tracks, m.missed_targets
    (2, 0, 0, 0)
    """
    min_fraction = finite_scalar(min_fraction, "min_fraction")
    if not 0.0 < min_fraction <= 1.0:
        raise ValueError(f"min_fraction must lie in (0, 1], got {min_fraction!r}")
    times, series, c, p = _check_series(times, truth, estimates, c, p)
    first_seen, n_present, n_assigned = {}, {}, {}
    first_assigned, last_track = {}, {}
    t_reported, t_assigned = {}, {}
    breaks = switches = 0
    for k, (ti, X, ei, Y) in enumerate(series):
        pairs = _gospa(X, Y, c, p)[1]
        alive = set(ei)
        for i in ti:
            first_seen.setdefault(i, times[k])
            n_present[i] = n_present.get(i, 0) + 1
        for j in ei:
            t_reported[j] = t_reported.get(j, 0) + 1
        for a, b in pairs:
            i, j = ti[a], ei[b]
            n_assigned[i] = n_assigned.get(i, 0) + 1
            t_assigned[j] = t_assigned.get(j, 0) + 1
            first_assigned.setdefault(i, times[k])
            prev = last_track.get(i)
            if prev is not None and prev != j:
                if prev in alive:
                    switches += 1
                else:
                    breaks += 1
            last_track[i] = j
    truth_ids, track_ids = list(first_seen), list(t_reported)
    coverage = np.array([n_assigned.get(i, 0) / n_present[i] for i in truth_ids])
    track_cov = np.array([t_assigned.get(j, 0) / t_reported[j] for j in track_ids])
    ttc = np.array([first_assigned.get(i, np.nan) - first_seen[i] for i in truth_ids])
    return TrackMetrics(breaks, switches, int(np.sum(track_cov < min_fraction)), int(np.sum(coverage < min_fraction)),
                        truth_ids, ttc, coverage, track_ids, track_cov)
