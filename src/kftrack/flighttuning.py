r"""Tuned baselines for recorded flights (chapter 18, issue 26): a constant-velocity filter whose
``q`` and ``r`` are fitted on the training flights only.

The baseline is the plainest tracker a reader would write: per track, a constant-velocity Kalman
filter on the state ``[x, vx, y, vy]`` (east, north; m, m/s) of the flight's ENU frame (origin
the first finite fix, as in :func:`kftrack.aircraft.track_flight`), **continuous** white
acceleration of spectral density :math:`q` (m²/s³) per axis,

.. math::

    F = \begin{bmatrix}1 & \Delta t\\ 0 & 1\end{bmatrix},\qquad
    Q = q\begin{bmatrix}\Delta t^3/3 & \Delta t^2/2\\ \Delta t^2/2 & \Delta t\end{bmatrix},\qquad
    R = r I,

on the rows :func:`kftrack.aircraft.scored_rows` accepts (finite, time after the last accepted
row, a new position; held reports are not measurements), a two-point start
(:func:`kftrack.aircraft.two_point_init`) at every track start (a step longer than
:data:`kftrack.aircraft.REINIT_GAP_S`). No gate. Its one-step predictions exist on exactly the
scored rows. With ``R = r I`` and the same ``P`` on both axes the filter separates into two
identical 2-state filters sharing one covariance, which is how :func:`cv_track` runs it.

Two tunings, both on flights passed as data (never looked up by name) and both refusing a test
flight (:func:`kftrack.adsb.refuse_test_flights`):

* :func:`fit_cv`: maximum likelihood of :math:`(q, r)` over all flights jointly (the chapter's
  tuning, chapter 10), :math:`\ell = \sum_k \log\mathcal N(y_k; 0, S_k)` over the scored rows;
* :func:`scan_cv`: the grid point of :math:`(q, r)` with the lowest geometric mean of the
  per-flight one-step RMSE (the score the chapter reports), over all flights or per category
  (:func:`kftrack.adsb.category_of`: airliner ``calibration`` streams, ``gliders``, ...).

:func:`tune_baselines` runs them and names the reference baseline: the tuning with the lowest
geometric-mean RMSE on the flights it was given (the training flights), chosen before any
test flight is scored. :func:`cv_params_for` gives the ``(q, r)`` a tuning uses on a flight.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .adsb import category_of, refuse_test_flights
from .aircraft import REINIT_GAP_S, _accepted_rows, _columns, _flight_columns, _frame_of, _positive, _to_degrees

__all__ = ["cv_track", "cv_tuned_predictions", "fit_cv", "scan_cv", "tune_baselines", "cv_params_for", "CvTuning",
           "Q_GRID", "R_GRID"]

#: Grid of q (m²/s³) for :func:`scan_cv`: 0.001 to 1000, three points per decade.
Q_GRID = tuple(float(v) for v in np.logspace(-3, 3, 19))
#: Grid of r (m²) for :func:`scan_cv`: 0.01 to 10 000, three points per decade.
R_GRID = tuple(float(v) for v in np.logspace(-2, 4, 19))


def _cv_core(t, enu, rows, place, q, r):
    """One-step predictions (K, 2) and (sum, count) of the log-likelihood of the CV filter."""
    pred = np.full((t.size, 2), np.nan)
    tt, ee, nn = t[rows].tolist(), enu[rows, 0].tolist(), enu[rows, 1].tolist()
    pl = place.tolist()
    ll, n = 0.0, 0
    two_pi = 2.0 * math.pi
    for i in range(len(tt)):
        if pl[i] == 0:
            continue
        if pl[i] == 1:                     # two-point start from the previous accepted row
            dt = tt[i] - tt[i - 1]
            pe, pn = ee[i], nn[i]
            ve, vn = (ee[i] - ee[i - 1]) / dt, (nn[i] - nn[i - 1]) / dt
            p00, p01, p11 = r, r / dt, 2.0 * r / dt ** 2
            continue
        dt = tt[i] - tt[i - 1]
        pe, pn = pe + dt * ve, pn + dt * vn
        a00 = p00 + 2.0 * dt * p01 + dt * dt * p11 + q * dt ** 3 / 3.0
        a01 = p01 + dt * p11 + q * dt * dt / 2.0
        a11 = p11 + q * dt
        k = rows[i]
        pred[k, 0], pred[k, 1] = pe, pn
        S = a00 + r
        ye, yn = ee[i] - pe, nn[i] - pn
        ll -= math.log(two_pi * S) + (ye * ye + yn * yn) / (2.0 * S)
        n += 1
        k0, k1 = a00 / S, a01 / S
        pe, pn, ve, vn = pe + k0 * ye, pn + k0 * yn, ve + k1 * ye, vn + k1 * yn
        p00, p01, p11 = a00 - k0 * a00, a01 - k0 * a01, a11 - k1 * a01
    return pred, ll, n


def _prepared(cols, gap_s=REINIT_GAP_S):
    """Per flight ``(t, enu (K, 2), origin, rows, place)`` of validated columns."""
    out = []
    for t, lat, lon in cols:
        enu, origin, _ = _frame_of(t, lat, lon)
        rows, place = _accepted_rows(t, lat, lon, gap_s)
        out.append((t, enu, origin, rows, place))
    return out


def cv_track(t_s, lat_deg, lon_deg, q: float, r: float):
    r"""Run the baseline CV filter (module docstring) over one flight.

    Parameters
    ----------
    t_s, lat_deg, lon_deg : (K,) times (s) and WGS-84 degrees; bad rows are skipped.
    q : float > 0, continuous white-acceleration spectral density, m²/s³.
    r : float > 0, measurement variance per axis, m².

    Returns
    -------
    enu_pred : (K, 2) one-step predictions (m, the frame of :func:`kftrack.aircraft.track_flight`;
        NaN on the rows that are not scored).
    loglik : float, :math:`\sum_k \log\mathcal N(y_k; 0, (P^-_{xx} + r) I_2)` over the predicted rows.
    n : int, the number of predicted rows.
    """
    cols = _columns(t_s, lat_deg, lon_deg)
    q, r = _positive(q, "q"), _positive(r, "r")
    (t, enu, _, rows, place), = _prepared([cols])
    return _cv_core(t, enu, rows, place, q, r)


def cv_tuned_predictions(t_s, lat_deg, lon_deg, q: float, r: float):
    """The baseline's one-step predictions ``(lat_pred_deg, lon_pred_deg)`` (K,) in degrees
    (NaN where none), for :func:`kftrack.flightscore.evaluate`; ``q``, ``r`` as in :func:`cv_track`."""
    cols = _columns(t_s, lat_deg, lon_deg)
    q, r = _positive(q, "q"), _positive(r, "r")
    (t, enu, origin, rows, place), = _prepared([cols])
    pred, _, _ = _cv_core(t, enu, rows, place, q, r)
    return _to_degrees(pred, origin)


def _training(flights):
    """Validated, prepared training flights (refusing test flights)."""
    cols = _flight_columns(flights)
    refuse_test_flights(flights)
    return _prepared(cols)


def fit_cv(flights, x0=(1.0, 100.0), xatol: float = 1e-3) -> tuple[float, float, float]:
    r"""Maximum-likelihood ``(q, r)`` of the baseline CV filter over ``flights`` jointly.

    Maximises the summed innovation log-likelihood of :func:`cv_track` over all flights, in
    :math:`u = \log(q, r)` (``scipy.optimize.minimize``, Nelder–Mead from ``log x0``, stopping when
    the simplex spans less than ``xatol`` in each log coordinate).

    Parameters
    ----------
    flights : sequence of :class:`kftrack.adsb.Flight` (anything with ``t_s``, ``lat_deg``,
        ``lon_deg``), never a test flight (ValueError).
    x0 : (q, r) start, both > 0 (m²/s³, m²).
    xatol : positive tolerance in log units.

    Returns
    -------
    q, r, mean_loglik : the fitted values and the mean log-likelihood per predicted row (nats).
    """
    from scipy.optimize import minimize
    prep = _training(flights)
    start = np.asarray(x0, dtype=float)
    if start.shape != (2,) or not np.all(np.isfinite(start)) or np.any(start <= 0):
        raise ValueError(f"x0 must be two positive numbers (q, r), got {x0!r}")
    xatol = _positive(xatol, "xatol")

    def nll(u):
        q, r = math.exp(u[0]), math.exp(u[1])
        tot = n = 0
        for t, enu, _, rows, place in prep:
            _, ll, m = _cv_core(t, enu, rows, place, q, r)
            tot, n = tot + ll, n + m
        if n == 0:
            raise ValueError("flights have no row to predict (at least three accepted rows per track)")
        return -tot / n

    res = minimize(nll, np.log(start), method="Nelder-Mead", options={"xatol": xatol, "fatol": 1e-7})
    return float(math.exp(res.x[0])), float(math.exp(res.x[1])), float(-res.fun)


def _geo_mean_rmse(prep, q, r):
    logs = []
    for t, enu, _, rows, place in prep:
        pred, _, m = _cv_core(t, enu, rows, place, q, r)
        if m:
            d = pred - enu
            logs.append(0.5 * math.log(float(np.nanmean(np.sum(d * d, axis=1)))))
    if not logs:
        raise ValueError("flights have no row to predict (at least three accepted rows per track)")
    return math.exp(sum(logs) / len(logs))


def scan_cv(flights, q_grid=Q_GRID, r_grid=R_GRID) -> tuple[float, float, float]:
    """The grid point ``(q, r)`` whose CV filter has the lowest geometric mean of the per-flight
    one-step RMSE over ``flights`` (never a test flight: ValueError).

    Returns
    -------
    q, r, score : the chosen point (m²/s³, m²) and its geometric-mean RMSE (m).
    """
    prep = _training(flights)
    qs = [_positive(v, "q_grid") for v in np.atleast_1d(np.asarray(q_grid, dtype=float))]
    rs = [_positive(v, "r_grid") for v in np.atleast_1d(np.asarray(r_grid, dtype=float))]
    best = min(((_geo_mean_rmse(prep, q, r), q, r) for q in qs for r in rs))
    return best[1], best[2], best[0]


class CvTuning(NamedTuple):
    """Output of :func:`tune_baselines`.

    Attributes
    ----------
    ml : (q, r) by maximum likelihood (:func:`fit_cv`); ml_loglik its mean log-likelihood per row.
    scan : (q, r) by the RMSE scan over all flights (:func:`scan_cv`).
    by_category : {category: (q, r)} by the RMSE scan over the flights of each category.
    score : {"CV (ML)", "CV (scan)", "CV (scan per category)": geometric-mean RMSE (m) on the
        tuning flights}.
    reference : the name in ``score`` with the lowest value: the reference baseline.
    flights : the names of the flights tuned on.
    """

    ml: tuple
    ml_loglik: float
    scan: tuple
    by_category: dict
    score: dict
    reference: str
    flights: tuple


def cv_params_for(tuning: CvTuning, method: str, name: str) -> tuple[float, float]:
    """``(q, r)`` that the tuning ``method`` (a key of ``tuning.score``) uses on the flight ``name``:
    per category, the category's scan (the pooled scan for a category not tuned on)."""
    if method == "CV (ML)":
        return tuning.ml
    if method == "CV (scan)":
        return tuning.scan
    if method == "CV (scan per category)":
        return tuning.by_category.get(category_of(name), tuning.scan)
    raise ValueError(f"method must be one of {list(tuning.score)}, got {method!r}")


def tune_baselines(flights) -> CvTuning:
    """Tune the CV baseline on ``flights`` (the training flights; never a test flight) by maximum
    likelihood, by the RMSE scan over all of them and by the scan per category, and name the
    reference baseline, the tuning with the lowest geometric-mean RMSE on them."""
    prep = _training(flights)
    flights = list(flights)
    names = tuple(str(getattr(fl, "name", "")) for fl in flights)
    q_ml, r_ml, ll = fit_cv(flights)
    q_s, r_s, _ = scan_cv(flights)
    cats = [category_of(n) for n in names]
    by_cat = {}
    for c in sorted(set(cats)):
        q_c, r_c, _ = scan_cv([fl for fl, k in zip(flights, cats) if k == c])
        by_cat[c] = (q_c, r_c)
    logs = [math.log(_geo_mean_rmse([p], *by_cat[c])) for p, c in zip(prep, cats)]
    score = {"CV (ML)": _geo_mean_rmse(prep, q_ml, r_ml), "CV (scan)": _geo_mean_rmse(prep, q_s, r_s),
             "CV (scan per category)": math.exp(sum(logs) / len(logs))}
    ref = min(score, key=score.get)
    return CvTuning((q_ml, r_ml), ll, (q_s, r_s), by_cat, score, ref, names)
