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

import functools
import math
from typing import NamedTuple

import numpy as np

from .adsb import category_of, refuse_test_flights
from .aircraft import REINIT_GAP_S, _accepted_rows, _columns, _flight_columns, _frame_of, _positive, _to_degrees

__all__ = ["cv_track", "cv_tuned_predictions", "fit_cv", "scan_cv", "tune_baselines", "cv_params_for", "CvTuning",
           "baseline_predictions", "imm_track", "imm_tuned_predictions", "fit_imm", "IMM_BASELINES", "IMM_TURN_DEG_S",
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
    score : {"CV (ML)", "CV (scan)", "CV (scan per category)", and the names of :data:`IMM_BASELINES`
        when tuned: geometric-mean RMSE (m) on the tuning flights}.
    reference : the name in ``score`` with the lowest value: the reference baseline.
    flights : the names of the flights tuned on.
    imm : {name of :data:`IMM_BASELINES`: (q_cv, q_turn, r, mean_loglik)} by :func:`fit_imm`
        (empty when not tuned).
    """

    ml: tuple
    ml_loglik: float
    scan: tuple
    by_category: dict
    score: dict
    reference: str
    flights: tuple
    imm: dict = {}


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


def tune_baselines(flights, imm: bool = True) -> CvTuning:
    """Tune the baselines on ``flights`` (the training flights; never a test flight) and name the
    reference baseline, the tuning with the lowest geometric-mean RMSE on them: the CV filter by
    maximum likelihood, by the RMSE scan over all of them and by the scan per category, and (with
    ``imm``) each IMM baseline of :data:`IMM_BASELINES` by maximum likelihood (:func:`fit_imm`)."""
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
    fitted = {}
    if imm:
        for kind in IMM_BASELINES:
            fitted[kind] = fit_imm(flights, kind)
            score[kind] = _imm_geo_mean_rmse(prep, kind, *fitted[kind][:3])
    ref = min(score, key=score.get)
    return CvTuning((q_ml, r_ml), ll, (q_s, r_s), by_cat, score, ref, names, fitted)


def baseline_predictions(tuning: CvTuning, method: str, flight):
    """One-step predictions ``(lat_pred_deg, lon_pred_deg)`` (K,) of the tuned baseline ``method`` (a
    key of ``tuning.score``) on ``flight`` (a :class:`kftrack.adsb.Flight`), for
    :func:`kftrack.flightscore.evaluate`."""
    if method in tuning.imm:
        return imm_tuned_predictions(flight.t_s, flight.lat_deg, flight.lon_deg, method, *tuning.imm[method][:3])
    return cv_tuned_predictions(flight.t_s, flight.lat_deg, flight.lon_deg, *cv_params_for(tuning, method, flight.name))


# ---------------------------------------------------------------- tuned IMM baselines
#: Turn rate of the IMM baselines' two known-rate turn modes, deg/s (the standard rate turn; the
#: chapter's IMM and issue 15's filterpy baseline, ``data/adsb/baseline.py``).
IMM_TURN_DEG_S = 3.0
#: The two IMM baselines (module docstring of the section): per name, ``noise`` ("discrete": ``q`` is
#: the direct-discrete variance sigma2, m²/s⁴; "continuous": the spectral density q, m²/s³),
#: ``tau`` (mean sojourn times, s, Markov matrix ``expm(Lambda dt)``) or ``pi_stay`` (a fixed
#: Markov matrix, stay probability on the diagonal, the rest shared), ``mu0`` (mode probabilities at
#: every track start) and ``combine`` ("predicted": the prediction is weighted by the predicted mode
#: probabilities; "posterior": by the previous posterior ones, as filterpy's ``IMMEstimator.x``
#: after ``predict``).
IMM_BASELINES = {
    "filterpy IMM (ML)": dict(noise="discrete", pi_stay=0.95, tau=None, mu0=(1 / 3, 1 / 3, 1 / 3),
                              combine="posterior"),
    "IMM (chapter, ML)": dict(noise="continuous", pi_stay=None, tau=(120.0, 60.0, 60.0), mu0=(0.8, 0.1, 0.1),
                              combine="predicted"),
}


_PAD = 1024          # sequences are padded to a multiple of this (one compilation per length class)


def _imm_sequence(kind, prep):
    """The inputs of :func:`_imm_scan` for the accepted rows (``place >= 1``) of the prepared flights
    ``prep``, one sequence (a flight's first row starts a track, so flights chain): per step ``op``
    (0 padding, 1 two-point start, 2 predict and update), ``z`` (2,), the start ``x`` (4,) and its
    covariance per unit ``r`` (4, 4), ``F``, ``Q`` per unit noise (3, 4, 4) and ``Pi`` (3, 3) at the
    step's interval (batched over the distinct intervals); and where each flight's steps lie."""
    from scipy.linalg import expm

    from .aircraft import two_point_init
    from .models import KnownTurn
    spec = IMM_BASELINES[kind]
    w = math.radians(IMM_TURN_DEG_S)
    key = "sigma2" if spec["noise"] == "discrete" else "q"
    models = [KnownTurn(omega=om, ndim=2, **{key: 1.0}) for om in (0.0, w, -w)]
    ops, zs, dts, x0s, P0s, where = [], [], [], [], [], []
    for t, enu, _, rows, place in prep:
        sel = np.flatnonzero(place >= 1)
        where.append((len(ops), rows[sel]))
        prev = rows[sel - 1]
        dt = t[rows[sel]] - t[prev]
        ops.extend(np.where(place[sel] == 1, 1, 2).tolist())
        zs.append(enu[rows[sel]])
        dts.append(dt)
        for a, b, d, pl in zip(prev.tolist(), rows[sel].tolist(), dt.tolist(), place[sel].tolist()):
            x, P = two_point_init(enu[a], enu[b], d, 1.0) if pl == 1 else (np.zeros(4), np.zeros((4, 4)))
            x0s.append(x)
            P0s.append(P)
    T = len(ops)
    L = max(_PAD, -(-T // _PAD) * _PAD)
    dt = np.concatenate(dts) if dts else np.zeros(0)
    uniq, inv = np.unique(np.where(np.asarray(ops) == 2, dt, 1.0), return_inverse=True) if T else (np.ones(1), [])
    F = np.stack([m.F(uniq) for m in models], axis=1)
    Q = np.stack([m.Q(uniq) for m in models], axis=1)
    if spec["tau"] is not None:
        tau = np.asarray(spec["tau"], float)
        lam = (1.0 / tau)[:, None] * (np.ones((3, 3)) - np.eye(3)) / 2.0
        Pi = np.stack([expm((lam - np.diag(lam.sum(axis=1))) * d) for d in uniq])
    else:
        s = spec["pi_stay"]
        Pi = np.broadcast_to(np.full((3, 3), (1.0 - s) / 2.0) + np.eye(3) * (s - (1.0 - s) / 2.0), (uniq.size, 3, 3))
    idx = np.zeros(L, int)
    idx[:T] = inv
    pad = lambda a, shape: np.concatenate([np.asarray(a, float).reshape((-1,) + shape),   # noqa: E731
                                           np.zeros((L - T,) + shape)])
    seq = dict(op=np.concatenate([np.asarray(ops, int), np.zeros(L - T, int)]),
               z=pad(np.concatenate(zs) if zs else np.zeros((0, 2)), (2,)), x0=pad(x0s, (4,)), P0=pad(P0s, (4, 4)),
               F=F[idx], Q=Q[idx], Pi=np.asarray(Pi)[idx])
    return seq, where


@functools.lru_cache(maxsize=None)
def _imm_scan_jit(posterior: bool):
    """The IMM baselines' time loop under ``jax.lax.scan`` (jitted), on the kernels of
    :mod:`kftrack.kernels` (one set of equations): mixing (:func:`kftrack.kernels.mixing_log_weights`,
    :func:`kftrack.kernels.moment_match`), :func:`kftrack.kernels.kf_predict`,
    :func:`kftrack.kernels.kf_update` for the three modes at once, with a two-point start where
    ``op == 1`` and nothing where ``op == 0``."""
    import jax

    from .kernels import kf_predict, kf_update, logsumexp, mixing_log_weights, moment_match
    jnp = jax.numpy

    def run(seq, qv, r, log_mu0):
        H = jnp.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
        R = r * jnp.eye(2)

        def step(carry, inp):
            log_mu, xs, Ps = carry
            logw, log_c = mixing_log_weights(log_mu, inp["Pi"])
            x0, P0 = moment_match(jnp.exp(logw).T, xs, Ps)               # the mixed start of each mode
            xp, Pp = kf_predict(x0, P0, inp["F"], inp["Q"] * qv[:, None, None])
            wts = jnp.exp(log_mu if posterior else log_c)
            pred = wts @ xp[:, jnp.array([0, 2])]
            u = kf_update(xp, Pp, inp["z"][None], H, R)
            joint = log_c + u.loglik
            ll = logsumexp(joint, axis=-1)
            upd = (joint - ll, u.x, u.P)
            start = (log_mu0, jnp.broadcast_to(inp["x0"], xs.shape), jnp.broadcast_to(r * inp["P0"], Ps.shape))
            op = inp["op"]
            new = jax.tree_util.tree_map(lambda a, b, c: jnp.where(op == 2, a, jnp.where(op == 1, b, c)),
                                         upd, start, carry)
            return new, (jnp.where(op == 2, pred, jnp.nan), jnp.where(op == 2, ll, 0.0))

        init = (log_mu0, jnp.zeros((3, 4)), jnp.broadcast_to(jnp.eye(4), (3, 4, 4)))
        _, (pred, ll) = jax.lax.scan(step, init, seq)
        return pred, ll

    return jax.jit(run)


def _imm_scan(kind, seq, q_cv, q_turn, r):
    """``(pred (L, 2), loglik (L,))`` of the IMM baseline ``kind`` over :func:`_imm_sequence`'s ``seq``
    (float64 JAX, NumPy results)."""
    import jax
    spec = IMM_BASELINES[kind]
    with jax.enable_x64(True):
        jnp = jax.numpy
        pred, ll = _imm_scan_jit(spec["combine"] == "posterior")(
            {k: jnp.asarray(v) for k, v in seq.items()}, jnp.array([q_cv, q_turn, q_turn], float),
            jnp.asarray(float(r)), jnp.log(jnp.asarray(spec["mu0"], float)))
        return np.asarray(pred), np.asarray(ll)


def _imm_kind(kind):
    if kind not in IMM_BASELINES:
        raise ValueError(f"kind must be one of {list(IMM_BASELINES)}, got {kind!r}")
    return kind


def _imm_flights(kind, prep, q_cv, q_turn, r, seq=None):
    """Per prepared flight ``(enu_pred (K, 2), loglik, n)`` of the IMM baseline ``kind``."""
    seq, where = _imm_sequence(kind, prep) if seq is None else seq
    pred, ll = _imm_scan(kind, seq, q_cv, q_turn, r)
    out = []
    for (t, _, _, _, _), (at, rows) in zip(prep, where):
        p = np.full((t.size, 2), np.nan)
        got = pred[at:at + rows.size]
        p[rows] = got
        out.append((p, float(np.sum(ll[at:at + rows.size])), int(np.sum(np.isfinite(got[:, 0])))))
    return out


def imm_track(t_s, lat_deg, lon_deg, kind: str, q_cv: float, q_turn: float, r: float):
    r"""Run an IMM baseline (:data:`IMM_BASELINES`) over one flight, on the rows of :func:`cv_track`.

    Three modes on ``[x, vx, y, vy]`` (east, north; m, m/s): constant velocity and two known-rate
    turns at :math:`\pm` :data:`IMM_TURN_DEG_S` (:class:`kftrack.models.KnownTurn`), ``R = r I``, a
    two-point start (:func:`kftrack.aircraft.two_point_init` with ``r``) and the mode probabilities
    ``mu0`` at every track start; the mixing and mode-matched updates of Blom & Bar-Shalom (1988),
    on the kernels of :mod:`kftrack.kernels` under ``jax.lax.scan`` (needs JAX, float64 inside). The
    log-likelihood is that of the mixture,
    :math:`\ell_k = \log\sum_j \bar c_{k,j}\,\mathcal N(z_k; H x^-_{k,j}, H P^-_{k,j} H^\top + R)`.

    Parameters
    ----------
    t_s, lat_deg, lon_deg : (K,) times (s) and WGS-84 degrees; bad rows are skipped.
    kind : a key of :data:`IMM_BASELINES`.
    q_cv, q_turn : float > 0, the noise of the CV mode and of the two turn modes: a discrete variance
        (m²/s⁴) for ``"filterpy IMM (ML)"``, a spectral density (m²/s³) for ``"IMM (chapter, ML)"``.
    r : float > 0, measurement variance per axis, m².

    Returns
    -------
    enu_pred : (K, 2) one-step predictions (m; NaN on the rows that are not scored).
    loglik : float, the summed mixture log-likelihood over the predicted rows; n : int, their number.
    """
    cols = _columns(t_s, lat_deg, lon_deg)
    kind, q_cv, q_turn, r = _imm_kind(kind), _positive(q_cv, "q_cv"), _positive(q_turn, "q_turn"), _positive(r, "r")
    return _imm_flights(kind, _prepared([cols]), q_cv, q_turn, r)[0]


def imm_tuned_predictions(t_s, lat_deg, lon_deg, kind: str, q_cv: float, q_turn: float, r: float):
    """The IMM baseline's one-step predictions ``(lat_pred_deg, lon_pred_deg)`` (K,) in degrees
    (NaN where none); arguments as in :func:`imm_track`."""
    cols = _columns(t_s, lat_deg, lon_deg)
    kind, q_cv, q_turn, r = _imm_kind(kind), _positive(q_cv, "q_cv"), _positive(q_turn, "q_turn"), _positive(r, "r")
    prep = _prepared([cols])
    pred, _, _ = _imm_flights(kind, prep, q_cv, q_turn, r)[0]
    return _to_degrees(pred, prep[0][2])


def fit_imm(flights, kind: str, x0=(1.0, 1.0, 100.0), xatol: float = 1e-2) -> tuple[float, float, float, float]:
    r"""Maximum-likelihood ``(q_cv, q_turn, r)`` of an IMM baseline (:func:`imm_track`) over
    ``flights`` jointly (never a test flight: ValueError), as :func:`fit_cv` does for the CV
    filter: Nelder–Mead in the logarithms from the simplex ``log x0``, ``log x0 + log(2) e_i``,
    stopping when the simplex spans less than ``xatol`` in each log coordinate.

    Returns
    -------
    q_cv, q_turn, r, mean_loglik : the fitted values (units of :func:`imm_track`) and the mean
    log-likelihood per predicted row (nats).
    """
    from scipy.optimize import minimize
    prep = _training(flights)
    kind = _imm_kind(kind)
    start = np.asarray(x0, dtype=float)
    if start.shape != (3,) or not np.all(np.isfinite(start)) or np.any(start <= 0):
        raise ValueError(f"x0 must be three positive numbers (q_cv, q_turn, r), got {x0!r}")
    xatol = _positive(xatol, "xatol")
    seq, _ = _imm_sequence(kind, prep)
    n = int(np.sum(seq["op"] == 2))
    if n == 0:
        raise ValueError("flights have no row to predict (at least three accepted rows per track)")

    def nll(u):
        q1, q2, r = (math.exp(v) for v in u)
        return -float(np.sum(_imm_scan(kind, seq, q1, q2, r)[1])) / n

    u0 = np.log(start)
    simplex = np.vstack([u0, u0 + math.log(2.0) * np.eye(3)])      # steps of a factor 2 (log 1 = 0 would give none)
    res = minimize(nll, u0, method="Nelder-Mead",
                   options={"xatol": xatol, "fatol": 1e-6, "initial_simplex": simplex})
    q1, q2, r = (float(math.exp(v)) for v in res.x)
    return q1, q2, r, float(-res.fun)


def _imm_geo_mean_rmse(prep, kind, q_cv, q_turn, r):
    logs = []
    for (_, enu, _, _, _), (pred, _, m) in zip(prep, _imm_flights(kind, prep, q_cv, q_turn, r)):
        if m:
            logs.append(0.5 * math.log(float(np.nanmean(np.sum((pred - enu) ** 2, axis=1)))))
    return math.exp(sum(logs) / len(logs))
