"""Peer baseline of chapter 18: filterpy's IMMEstimator on every chapter and unseen ADS-B flight.

Writes the baseline's one-step predictions to ``data/adsb/baseline/<group>/<name>.csv.gz``
(one line per row of the flight file, in file order; deterministic gzip, mtime 0), because
filterpy runs at about 0.9 ms per step and the chapter cannot afford ~30 000 steps inside its
30 s budget. ``tests/test_aircraft.py`` re-runs :func:`filterpy_baseline` on every chapter flight
(and a few hundred rows of each unseen flight) and checks the cache against it.

The baseline (issue 15): an IMM of three linear modes on the state ``[x, vx, y, vy]`` (east,
north; m, m/s) of the flight's ENU frame (origin the first finite fix, as in
:func:`kftrack.aircraft.track_flight`):

* constant velocity, ``kftrack.models.ConstantVelocity(ndim=2, sigma2=0.05)``;
* two known-rate turns at +3 and -3 deg/s, ``kftrack.models.KnownTurn(omega, sigma2=0.5)``;

``sigma2`` is the **discrete** white-acceleration variance (m^2/s^4, direct-discrete
``Gamma = [T^2/2, T]`` per axis), so ``Q = sigma2 * [[T^4/4, T^3/2], [T^3/2, T^2]]`` per axis;
``F`` and ``Q`` are rebuilt for each step's ``dt``; ``R = 25 I`` m^2; fixed
``Pi = 0.95 I + 0.025 (1 - I)``; initial mode probabilities 1/3 each; two-point initialisation
(:func:`kftrack.aircraft.two_point_init` with ``r = 25``) from the first two usable rows.
Usable rows: finite latitude and longitude and a time after the last usable row (filterpy
cannot step back in time); every other row gets no prediction (NaN) and no update. A repeated
(held) position is used as a measurement: this is the naive baseline.

Usage: ``python data/adsb/baseline.py [--check]`` (``--check`` compares instead of writing).
Needs filterpy (test-only dependency, pinned in requirements.txt).
"""
from __future__ import annotations

import gzip
import io
import sys
from pathlib import Path

import numpy as np

R_BASELINE = 25.0          # m^2 per axis
SIGMA2_CV = 0.05           # m^2/s^4, discrete white acceleration of the CV mode
SIGMA2_TURN = 0.5          # m^2/s^4, of the two turn modes
OMEGA_TURN = np.deg2rad(3.0)  # rad/s
PI_DIAGONAL = 0.95
HERE = Path(__file__).resolve().parent


def filterpy_baseline(t_s, lat_deg, lon_deg):
    """One-step predictions ``(lat_pred_deg, lon_pred_deg)`` (K,) of the filterpy IMM baseline."""
    from filterpy.kalman import IMMEstimator, KalmanFilter

    from kftrack.adsb import from_enu_horizontal
    from kftrack.aircraft import _frame_of, two_point_init
    from kftrack.models import ConstantVelocity, KnownTurn

    t = np.asarray(t_s, dtype=float)
    enu, origin, ok = _frame_of(t, lat_deg, lon_deg)
    K = t.size
    pred = np.full((K, 2), np.nan)
    models = [ConstantVelocity(ndim=2, sigma2=SIGMA2_CV), KnownTurn(omega=OMEGA_TURN, sigma2=SIGMA2_TURN),
              KnownTurn(omega=-OMEGA_TURN, sigma2=SIGMA2_TURN)]
    H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    Pi = np.full((3, 3), (1.0 - PI_DIAGONAL) / 2.0) + np.eye(3) * (PI_DIAGONAL - (1.0 - PI_DIAGONAL) / 2.0)
    rows = [k for k in np.flatnonzero(ok)]
    usable, last = [], -np.inf
    for k in rows:                       # usable rows: increasing time
        if t[k] > last:
            usable.append(k)
            last = t[k]
    if len(usable) >= 2:
        k0, k1 = usable[0], usable[1]
        x0, P0 = two_point_init(enu[k0], enu[k1], t[k1] - t[k0], R_BASELINE)
        filters = []
        for _ in models:
            f = KalmanFilter(dim_x=4, dim_z=2)
            f.H, f.R, f.x, f.P = H.copy(), np.eye(2) * R_BASELINE, x0.copy(), P0.copy()
            filters.append(f)
        imm = IMMEstimator(filters, np.full(3, 1.0 / 3.0), Pi)
        cache = {}
        tl = t[k1]
        for k in usable[2:]:
            dt = t[k] - tl
            if dt not in cache:
                cache[dt] = [(m.F(dt), m.Q(dt)) for m in models]
            for f, (F, Q) in zip(filters, cache[dt]):
                f.F, f.Q = F, Q
            imm.predict()
            pred[k] = imm.x[[0, 2]]
            imm.update(enu[k])
            tl = t[k]
    lat_p, lon_p = np.full(K, np.nan), np.full(K, np.nan)
    good = np.isfinite(pred[:, 0])
    if good.any():  # the predicted east-north on the ellipsoid, like the fixes (not on the tangent plane)
        lat_p[good], lon_p[good] = from_enu_horizontal(pred[good], origin)
    return lat_p, lon_p


def cache_path(name: str) -> Path:
    """``data/adsb/baseline/<group>/<name>.csv.gz`` for a flight ``<group>/<name>``."""
    return HERE / "baseline" / f"{name}.csv.gz"


def format_cache(name: str, t_s, lat_p, lon_p) -> bytes:
    """The gzipped CSV bytes: a comment, a header, one line per row (``repr`` floats, exact)."""
    buf = io.StringIO()
    buf.write(f"# filterpy IMMEstimator baseline of {name} (data/adsb/baseline.py); one line per row of the "
              "flight file; nan = no prediction\n")
    buf.write("t_s,lat_pred_deg,lon_pred_deg\n")
    for ti, a, b in zip(np.asarray(t_s, float), lat_p, lon_p):
        buf.write(f"{float(ti)!r},{float(a)!r},{float(b)!r}\n")
    raw = io.BytesIO()
    with gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0) as gz:
        gz.write(buf.getvalue().encode("utf-8"))
    return raw.getvalue()


def read_cache(name: str):
    """``(t_s, lat_pred_deg, lon_pred_deg)`` (K,) from the cache of flight ``name``."""
    from kftrack.datasets import data_path
    with gzip.open(data_path(f"adsb/baseline/{name}.csv.gz"), "rt", encoding="utf-8") as fh:
        arr = np.loadtxt(fh, delimiter=",", comments="#", skiprows=2, ndmin=2)
    return arr[:, 0], arr[:, 1], arr[:, 2]


def main(argv=None) -> int:
    from kftrack.adsb import CHAPTER_FLIGHTS, UNSEEN_FLIGHTS, load_flight
    argv = sys.argv[1:] if argv is None else argv
    check = "--check" in argv
    bad = 0
    for name in CHAPTER_FLIGHTS + UNSEEN_FLIGHTS:
        fl = load_flight(name)
        lat_p, lon_p = filterpy_baseline(fl.t_s, fl.lat_deg, fl.lon_deg)
        data = format_cache(name, fl.t_s, lat_p, lon_p)
        path = cache_path(name)
        if check:
            same = path.exists() and path.read_bytes() == data
            bad += not same
            print(name, "same" if same else "DIFFERENT")
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
            print(name, len(fl.t_s), "rows", flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
