"""Reproduce the maximum-likelihood fit quoted in ``kftrack.aircraft``'s provenance paragraph.

Fits :func:`kftrack.aircraft.fit_recipe` (cruise and manoeuvre ``q``, the lag scale and the
white floor ``r_0``) on the seven chapter flights: first on the first 2000 rows of each flight
from the module's constants, then on all rows from that result (about 15 minutes on one core),
and prints the fitted values, the mean log-likelihood per row and the one-step RMSE ratios to
the filterpy and CV baselines (scored as ``tests/test_aircraft.py`` does). The module's
constants are not changed by it: they come from a scan of the one-step RMSE (see the module
docstring). Run: ``python data/adsb/ml_fit.py``.
"""
from __future__ import annotations

import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

from kftrack import aircraft as A
from kftrack.adsb import CHAPTER_FLIGHTS, load_flight, to_enu

spec = importlib.util.spec_from_file_location("adsb_baseline", Path(__file__).with_name("baseline.py"))
baseline = importlib.util.module_from_spec(spec)
spec.loader.exec_module(baseline)


def mean_loglik(flights, x):
    return A.innovation_loglik(flights, (x[0], x[1]) + tuple(A.Q_MODES[2:]), A.SOJOURN_S, x[2], x[3])


def ratios(flight, x):
    res = A.track_flight(flight.t_s, flight.lat_deg, flight.lon_deg, q=(x[0], x[1]) + tuple(A.Q_MODES[2:]),
                         lag_scale=x[2], r_floor=x[3])
    m = A.scored_rows(flight.t_s, flight.lat_deg, flight.lon_deg)
    _, la, lo = baseline.read_cache(flight.name)
    zf = to_enu(la, lo, origin=res.origin)[0][:, :2]
    zc = to_enu(*A.cv_predictions(flight.t_s, flight.lat_deg, flight.lon_deg), origin=res.origin)[0][:, :2]
    rmse = [float(np.sqrt(np.mean(np.sum((p[m] - res.enu[m]) ** 2, axis=-1)))) for p in (res.enu_pred, zf, zc)]
    return rmse[0] / rmse[1], rmse[0] / rmse[2]


def main() -> int:
    flights = [load_flight(n) for n in CHAPTER_FLIGHTS]
    head = [f._replace(**{k: getattr(f, k)[:2000] for k in ("t_s", "lat_deg", "lon_deg")}) for f in flights]
    x_scan = (A.Q_MODES[0], A.Q_MODES[1], A.LAG_SCALE, A.R_FLOOR)
    t0 = time.perf_counter()
    x_head = A.fit_recipe(head, x0=x_scan)
    x_full = A.fit_recipe(flights, x0=x_head)
    print(f"fit time {time.perf_counter() - t0:.0f} s")
    for label, x in (("scan (the module's constants)", x_scan), ("fit, first 2000 rows", x_head), ("fit, all rows", x_full)):
        print(f"{label}: q = ({x[0]:.3g}, {x[1]:.4g}) m^2/s^3, lag scale {x[2]:.3g}, r0 = {x[3]:.3g} m^2, "
              f"mean log-likelihood per row {mean_loglik(flights, x):.3f}")
        for f in flights:
            fp, cv = ratios(f, x)
            print(f"    {f.name:28s} recipe / filterpy {fp:.3f}   recipe / CV {cv:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
