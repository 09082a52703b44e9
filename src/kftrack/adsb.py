"""Recorded ADS-B flights (The OpenSky Network, via the ``traffic`` samples) and the
geodetic-to-local conversion used to track them.

The flights are gzipped CSV files ``data/adsb/<group>/<name>.csv.gz`` (provenance, units,
licences and the resampling found in each file: ``data/README.md``; regenerate them with
``python data/adsb/extract.py``). Each holds one aircraft's records in file order, with the
columns ``t_s`` (unix seconds), ``lat_deg``, ``lon_deg``, ``alt_m`` (barometric altitude, or
geometric where the sample has it), ``groundspeed_mps``, ``track_deg`` (as recorded: in most
``calibration`` samples an integer wrapped to [-128, 127]) and ``vertical_rate_mps``.

Three sets of flights:

- :data:`CHAPTER_FLIGHTS`: the flights a chapter may look at and tune on;
- :data:`NOISY_FLIGHTS`: flights with known defects (held positions, spoofing, time jumps,
  missing fields), for the robustness of a tracking recipe;
- :data:`UNSEEN_FLIGHTS`: held out; a recipe is judged on them and nothing may be tuned on them.

:func:`load_flight` reads a bundled flight by name or a user's own file in the same format by
path; it keeps every row it can read, duplicates and time reversals included (ordering and
deduplication are the tracker's job), and skips and counts the rows it cannot use.
:func:`to_enu` / :func:`from_enu` convert between WGS 84 geodetic coordinates (degrees,
the only place degrees enter) and a local East-North-Up frame in metres (``pymap3d``);
:func:`from_enu_horizontal` takes a filter's east-north prediction back to degrees as the point
on the ellipsoid (height 0, like the fixes), not on the tangent plane.
"""
from __future__ import annotations

import gzip
import math
import os
import zlib
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pymap3d

from ._validate import as_float_array, finite_scalar, positive_scalar
from .datasets import data_path

__all__ = ["CHAPTER_FLIGHTS", "NOISY_FLIGHTS", "UNSEEN_FLIGHTS", "TRAINING_FLIGHTS", "TEST_FLIGHTS",
           "ROBUSTNESS_FLIGHTS", "split_of", "category_of", "refuse_test_flights", "COLUMNS", "Flight", "load_flight",
           "to_enu", "from_enu", "from_enu_horizontal", "TRAFFIC_FILE", "TRAFFIC_COLUMNS", "RADAR_SITE", "MAX_GAP_S",
           "TrafficWindow", "load_traffic"]

#: Flights a chapter may look at and tune on.
CHAPTER_FLIGHTS: tuple[str, ...] = (
    "calibration/toulouse", "calibration/munich", "calibration/london_heathrow", "calibration/lisbon",
    "gliders/alpi_italiane", "gliders/cevennes", "featured/belevingsvlucht")
#: Flights with known defects, for robustness checks.
NOISY_FLIGHTS: tuple[str, ...] = (
    "noisy/noisy_landing", "noisy/noisy_spoofing", "noisy/noisy_time_issue", "noisy/noisy_takeoff",
    "noisy/noisy_ground")
#: Held-out flights (every other ``calibration`` and ``gliders`` sample of traffic 2.13).
UNSEEN_FLIGHTS: tuple[str, ...] = (
    "calibration/ajaccio", "calibration/bornholm", "calibration/brussels_ils", "calibration/brussels_vor",
    "calibration/cardiff", "calibration/funchal", "calibration/guatemala", "calibration/kingston",
    "calibration/kiruna", "calibration/kota_kinabalu", "calibration/liege_sprimont",
    "calibration/london_gatwick", "calibration/monastir", "calibration/montreal", "calibration/nice",
    "calibration/noumea", "calibration/perth", "calibration/sydney", "calibration/vancouver",
    "calibration/vienna", "gliders/alto_adige", "gliders/danube_valley", "gliders/franconia",
    "gliders/luberon", "gliders/oxford_cambridge", "gliders/sisteron")
#: The split (issue 26; data/README.md). Training: the seven chapter flights, the only flights any
#: constant, rule or baseline of chapter 18 is tuned on. Test: the 26 unseen flights, on which the
#: methods are judged and nothing is tuned. Robustness: the five noisy flights, for "never fails"
#: checks (finite, causal, plausible), not for scores. No flight moves between sets.
TRAINING_FLIGHTS: tuple[str, ...] = CHAPTER_FLIGHTS
#: The test flights of the split: the 26 unseen flights (judged on, never tuned on).
TEST_FLIGHTS: tuple[str, ...] = UNSEEN_FLIGHTS
#: The robustness flights of the split: the five noisy flights (finite, causal, plausible checks only).
ROBUSTNESS_FLIGHTS: tuple[str, ...] = NOISY_FLIGHTS
#: Column names of a flight file, in order.
COLUMNS: tuple[str, ...] = ("t_s", "lat_deg", "lon_deg", "alt_m", "groundspeed_mps", "track_deg",
                            "vertical_rate_mps")

_ALL = CHAPTER_FLIGHTS + NOISY_FLIGHTS + UNSEEN_FLIGHTS


def split_of(name: str) -> str | None:
    """``"training"``, ``"test"`` or ``"robustness"`` for a bundled flight name; None for any other name
    (a user's file)."""
    if not isinstance(name, str):
        raise TypeError(f"name must be a flight name (str), got {type(name).__name__}")
    for label, names in (("training", TRAINING_FLIGHTS), ("test", TEST_FLIGHTS), ("robustness", ROBUSTNESS_FLIGHTS)):
        if name in names:
            return label
    return None


def category_of(name: str) -> str:
    """The group of a bundled flight (``"calibration"``, ``"gliders"``, ``"featured"``, ``"noisy"``),
    ``"user"`` for any other name (a user's file)."""
    if not isinstance(name, str):
        raise TypeError(f"name must be a flight name (str), got {type(name).__name__}")
    return name.split("/")[0] if name in _ALL else "user"


def refuse_test_flights(flights, argname: str = "flights") -> None:
    """Raise ValueError if any record of ``flights`` is a test flight (its ``name`` in ``TEST_FLIGHTS``).

    Every tuning function of chapter 18 calls this at its boundary, so that nothing is fitted,
    scanned or chosen on the flights the methods are judged on. Records without a ``name`` (arrays
    wrapped by a user) pass.
    """
    bad = [str(getattr(fl, "name", None)) for fl in flights
           if isinstance(getattr(fl, "name", None), str) and fl.name in TEST_FLIGHTS]
    if bad:
        raise ValueError(f"{argname} must not hold test flights (kftrack.adsb.TEST_FLIGHTS: nothing is tuned on "
                         f"them), got {', '.join(bad)}")


class Flight(NamedTuple):
    """One aircraft's records, in file order (shape ``(K,)`` each; NaN where a field is missing).

    Attributes
    ----------
    name : str
        The flight's name, e.g. ``"calibration/toulouse"``, or the path of a user's file.
    t_s : numpy.ndarray
        Time, unix seconds (not necessarily increasing or unique).
    lat_deg, lon_deg : numpy.ndarray
        WGS 84 latitude and longitude, degrees (finite and in range in every kept row).
    alt_m : numpy.ndarray
        Altitude, metres: barometric (pressure altitude), except in ``noisy/noisy_landing``,
        whose file holds geometric altitude (its comment header says which).
    groundspeed_mps : numpy.ndarray
        Ground speed, m/s.
    track_deg : numpy.ndarray
        Track angle as recorded, degrees clockwise from north (see ``data/README.md`` for the
        wrapped integer tracks of the calibration samples).
    vertical_rate_mps : numpy.ndarray
        Vertical rate, m/s, positive up.
    skipped : dict[str, int]
        Number of rows skipped, by reason.
    """

    name: str
    t_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray
    groundspeed_mps: np.ndarray
    track_deg: np.ndarray
    vertical_rate_mps: np.ndarray
    skipped: dict[str, int]


def _parse_row(line: str) -> tuple[tuple[float, ...] | None, str | None]:
    """The values of one data line, or ``(None, reason)``; an empty optional cell is NaN."""
    fields = line.split(",")
    if len(fields) != len(COLUMNS):
        return None, f"wrong number of fields (expected {len(COLUMNS)})"
    if not all(f.strip() for f in fields[:3]):
        return None, "missing time, latitude or longitude"
    try:
        values = tuple(float(f) if f.strip() else math.nan for f in fields)
    except ValueError:
        return None, "non-numeric field"
    t, lat, lon = values[:3]
    if not math.isfinite(t):
        return None, "non-finite time"
    if not (math.isfinite(lat) and math.isfinite(lon)):
        return None, "non-finite latitude or longitude"
    if not -90.0 <= lat <= 90.0:
        return None, "latitude outside [-90, 90]"
    if not -180.0 <= lon <= 180.0:
        return None, "longitude outside [-180, 180]"
    if any(math.isinf(v) for v in values[3:]):
        return None, "infinite altitude, speed, track or vertical rate"
    return values, None


def _flight_file(name) -> tuple[str, Path, bool]:
    """``(flight name, file path, gzipped)`` of a bundled flight name or a user's file path."""
    if isinstance(name, os.PathLike) or (isinstance(name, str) and name not in _ALL
                                         and name.lower().endswith((".csv", ".csv.gz"))):
        path = Path(name)
        if not path.name.lower().endswith((".csv", ".csv.gz")):
            raise ValueError(f"name must be a flight file ending in .csv or .csv.gz, got {str(name)!r}")
        if not path.is_file():
            raise FileNotFoundError(f"name: no flight file {str(path)!r}")
        return str(name), path, path.name.lower().endswith(".gz")
    if not isinstance(name, str):
        raise TypeError(f"name must be a flight name (str) or a file path (str or os.PathLike), "
                        f"got {type(name).__name__}")
    if name not in _ALL:
        raise ValueError(f"name must be one of the ADS-B flights {', '.join(_ALL)}, or the path of a .csv or "
                         f".csv.gz file; got {name!r}")
    return name, data_path(f"adsb/{name}.csv.gz"), True


def load_flight(name: str | os.PathLike) -> Flight:
    """Load one recorded flight, skipping and counting the rows it cannot use.

    Parameters
    ----------
    name : str or os.PathLike
        Either ``"<group>/<name>"``, one of :data:`CHAPTER_FLIGHTS`, :data:`NOISY_FLIGHTS` or
        :data:`UNSEEN_FLIGHTS` (the file ``data/adsb/<name>.csv.gz``, found with
        :func:`kftrack.datasets.data_path`), or the path of a user's own file (an
        ``os.PathLike``, or a str ending in ``.csv`` or ``.csv.gz``; ``.gz`` means gzipped).

        File format (UTF-8 text): any number of lines starting with ``#`` (comments), then the
        header line ``t_s,lat_deg,lon_deg,alt_m,groundspeed_mps,track_deg,vertical_rate_mps``
        (:data:`COLUMNS`), then one record per line, comma-separated, in these units: unix
        seconds, WGS 84 degrees, metres, m/s, degrees clockwise from north, m/s up. ``nan`` or an
        empty cell is a missing value; time, latitude and longitude are required.

    Returns
    -------
    Flight
        The kept rows in file order (shape ``(K,)`` per column); ``Flight.name`` is ``name``
        (as a str). A row is skipped, and counted in ``Flight.skipped`` under its reason, if it
        has the wrong number of fields, a non-numeric field, a missing (empty) or non-finite
        time, latitude or longitude, a latitude outside [-90, 90] or longitude outside
        [-180, 180] degrees, or an infinite value in another column (which :func:`to_enu`
        would refuse). A missing field in the other columns (empty or ``nan``) is kept as NaN.
        Duplicated and decreasing times are kept. Undecodable bytes become U+FFFD and make the
        row non-numeric. No bad row raises.

    Raises
    ------
    TypeError
        If ``name`` is neither a str nor an ``os.PathLike``.
    ValueError
        If ``name`` is not a known flight nor a ``.csv``/``.csv.gz`` path (the message lists the
        flights); or, naming the file, if its header is not the expected column list, or a
        ``.gz`` file is not gzip, is corrupt, or is truncated (no partial flight is returned).
    FileNotFoundError
        If a user's path does not exist.

    Examples
    --------
    >>> from kftrack.adsb import CHAPTER_FLIGHTS, load_flight
    >>> flight = load_flight("calibration/toulouse")   # a bundled flight (CHAPTER_FLIGHTS, ...)
    >>> flight.t_s.shape, flight.lat_deg.shape, flight.skipped
    ((2492,), (2492,), {})
    >>> import pathlib, tempfile                       # a file of your own, in the same format
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "mine.csv"
    >>> with open(path, "w") as f:
    ...     print("t_s,lat_deg,lon_deg,alt_m,groundspeed_mps,track_deg,vertical_rate_mps", file=f)
    ...     print("0,52.0,4.00,1000,100,90,0", file=f)
    ...     print("5,52.0,4.01,1000,100,90,0", file=f)
    ...     print("10,95.0,4.02,1000,100,90,0", file=f)   # latitude 95: a bad row
    >>> mine = load_flight(path)
    >>> mine.t_s.tolist(), mine.skipped                # a bad row is skipped and counted, never fatal
    ([0.0, 5.0], {'latitude outside [-90, 90]': 1})
    """
    name, path, gzipped = _flight_file(name)
    rows: list[tuple[float, ...]] = []
    skipped: dict[str, int] = {}
    header_seen = False
    opener = gzip.open if gzipped else open
    try:
        with opener(path, "rt", encoding="utf-8", errors="replace", newline="") as fh:
            for raw in fh:
                line = raw.strip()
                if not line or line.startswith("#"):
                    continue
                if not header_seen:
                    if tuple(line.split(",")) != COLUMNS:
                        raise ValueError(f"{path}: header must be {','.join(COLUMNS)!r}, got {line[:200]!r}")
                    header_seen = True
                    continue
                values, reason = _parse_row(line)
                if values is None:
                    skipped[reason] = skipped.get(reason, 0) + 1
                else:
                    rows.append(values)
    except gzip.BadGzipFile as exc:
        raise ValueError(f"{path}: not a valid gzip file ({exc}); a flight file ending in .gz must be "
                         "gzip-compressed CSV") from exc
    except EOFError as exc:
        raise ValueError(f"{path}: truncated gzip stream (the file ends before the end-of-stream marker, "
                         f"after {len(rows)} data rows); no partial flight is returned") from exc
    except zlib.error as exc:
        raise ValueError(f"{path}: corrupt gzip data ({exc})") from exc
    if not header_seen:
        raise ValueError(f"{path}: no header line {','.join(COLUMNS)!r}")
    table = np.array(rows, dtype=float).reshape(len(rows), len(COLUMNS))
    return Flight(name, *(np.ascontiguousarray(table[:, j]) for j in range(len(COLUMNS))), skipped=skipped)


def _check_origin(origin) -> tuple[float, float, float]:
    arr = as_float_array(origin, "origin")
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"origin must be three finite numbers (lat0_deg, lon0_deg, h0_m), got {origin!r}")
    if not -90.0 <= arr[0] <= 90.0 or not -180.0 <= arr[1] <= 180.0:
        raise ValueError(f"origin latitude must be in [-90, 90] and longitude in [-180, 180] degrees, "
                         f"got {tuple(arr.tolist())}")
    return float(arr[0]), float(arr[1]), float(arr[2])


def _check_degrees(value, name: str, bound: float) -> np.ndarray:
    arr = as_float_array(value, name)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array of shape (K,), got shape {arr.shape}")
    finite = arr[np.isfinite(arr)]
    if np.any(np.abs(finite) > bound) or np.any(np.isinf(arr)):
        raise ValueError(f"{name} must lie in [-{bound:g}, {bound:g}] degrees (NaN allowed)")
    return arr


def to_enu(lat_deg, lon_deg, alt_m=None, origin=None) -> tuple[np.ndarray, tuple[float, float, float]]:
    """Geodetic WGS 84 coordinates to a local East-North-Up frame, in metres.

    The fixes are mapped to Earth-centred Earth-fixed coordinates and rotated into the tangent
    plane at the origin,
    :math:`[e, n, u]^T = R(\\varphi_0, \\lambda_0)\\,(p_{ECEF}(\\varphi, \\lambda, h) - p_{ECEF}(\\varphi_0, \\lambda_0, h_0))`
    (``pymap3d.geodetic2enu``, vectorised).

    Parameters
    ----------
    lat_deg, lon_deg : array_like, shape (K,)
        Latitude in [-90, 90] and longitude in [-180, 180], degrees. NaN propagates to the row.
    alt_m : array_like, shape (K,), optional
        Height in metres (taken as height above the ellipsoid); zeros when omitted.
    origin : tuple (lat0_deg, lon0_deg, h0_m), optional
        Origin of the frame; default the first row whose latitude, longitude (and altitude, if
        given) are all finite.

    Returns
    -------
    enu : numpy.ndarray, shape (K, 3)
        East, north, up, metres.
    origin : tuple (lat0_deg, lon0_deg, h0_m)
        The origin used, to pass to :func:`from_enu`.
    """
    lat = _check_degrees(lat_deg, "lat_deg", 90.0)
    lon = _check_degrees(lon_deg, "lon_deg", 180.0)
    if lon.shape != lat.shape:
        raise ValueError(f"lon_deg must have the shape of lat_deg {lat.shape}, got {lon.shape}")
    if alt_m is None:
        alt = np.zeros_like(lat)
    else:
        alt = as_float_array(alt_m, "alt_m")
        if alt.shape != lat.shape:
            raise ValueError(f"alt_m must have the shape of lat_deg {lat.shape}, got {alt.shape}")
        if np.any(np.isinf(alt)):
            raise ValueError("alt_m must be finite or NaN, but it contains inf")
    if origin is None:
        good = np.flatnonzero(np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt))
        if good.size == 0:
            raise ValueError("origin cannot default to the first fix: no row of lat_deg, lon_deg"
                             + ("" if alt_m is None else ", alt_m") + " is finite; pass origin")
        k = int(good[0])
        origin = (float(lat[k]), float(lon[k]), float(alt[k]))
    lat0, lon0, h0 = _check_origin(origin)
    e, n, u = pymap3d.geodetic2enu(lat, lon, alt, lat0, lon0, h0, deg=True)
    enu = np.stack([np.asarray(e, float), np.asarray(n, float), np.asarray(u, float)], axis=-1)
    return enu.reshape(lat.shape[0], 3), (lat0, lon0, h0)


def from_enu(enu, origin) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local East-North-Up coordinates (metres) back to WGS 84 geodetic coordinates.

    The inverse of :func:`to_enu` (``pymap3d.enu2geodetic``; the ECEF-to-geodetic step is the
    non-iterative method of You 2000). ``to_enu(*from_enu(enu, origin), origin=origin)``
    returns ``enu`` to round-off: ``tests/test_adsb.py`` bounds the error by
    :math:`50\\,\\lVert p_{ECEF}\\rVert\\,\\varepsilon \\approx 7\\times 10^{-8}` m within
    300 km of the origin and up to 15 km height (about 1e-8 m measured).

    Parameters
    ----------
    enu : array_like, shape (K, 3)
        East, north, up, metres (NaN propagates to the row).
    origin : tuple (lat0_deg, lon0_deg, h0_m)
        The frame's origin, as returned by :func:`to_enu`.

    Returns
    -------
    lat_deg, lon_deg, alt_m : numpy.ndarray, shape (K,)
        Latitude and longitude in degrees, height above the ellipsoid in metres.
    """
    arr = as_float_array(enu, "enu")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"enu must have shape (K, 3), got shape {arr.shape}")
    if np.any(np.isinf(arr)):
        raise ValueError("enu must be finite or NaN, but it contains inf")
    if origin is None:
        raise TypeError("origin must be (lat0_deg, lon0_deg, h0_m), the origin returned by to_enu; got None")
    lat0, lon0, h0 = _check_origin(origin)
    lat, lon, alt = pymap3d.enu2geodetic(arr[:, 0], arr[:, 1], arr[:, 2], lat0, lon0, h0, deg=True)
    return (np.asarray(lat, float).reshape(-1), np.asarray(lon, float).reshape(-1),
            np.asarray(alt, float).reshape(-1))


def from_enu_horizontal(en, origin, tol_m: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    r"""East-North positions (metres) of points **on the ellipsoid** (height 0) back to degrees.

    The inverse of the horizontal part of :func:`to_enu` without altitude,
    ``to_enu(lat, lon, origin=origin)[0][:, :2]``: a filter that tracks east and north only
    (the recorded fixes at height 0) predicts ``(e, n)``, and the point it means is the one on
    the ellipsoid with these coordinates, below the tangent plane by about
    :math:`(e^2 + n^2)/2R`. Taking ``up = 0`` instead (a point on the tangent plane) and
    projecting it down moves it horizontally by about :math:`d^3/2R^2` (12 m at 100 km from the
    origin). The up coordinate is found by the fixed-point iteration
    :math:`u_{j+1} = \mathrm{up}(\mathrm{geodetic}(e, n, u_j)\,\text{ at height } 0)`, which
    contracts by a factor of order :math:`d/R` or smaller per step; it stops when the horizontal residual is below
    ``tol_m``.

    Parameters
    ----------
    en : array_like, shape (K, 2)
        East, north, metres (NaN propagates to the row).
    origin : tuple (lat0_deg, lon0_deg, h0_m)
        The frame's origin, as returned by :func:`to_enu`.
    tol_m : float
        Horizontal tolerance of the round trip, metres (> 0).

    Returns
    -------
    lat_deg, lon_deg : numpy.ndarray, shape (K,)
    """
    arr = as_float_array(en, "en")
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"en must have shape (K, 2), got shape {arr.shape}")
    if np.any(np.isinf(arr)):
        raise ValueError("en must be finite or NaN, but it contains inf")
    tol_m = positive_scalar(tol_m, "tol_m", "m")
    up = np.zeros(arr.shape[0])
    good = np.isfinite(arr).all(axis=1)
    for _ in range(20):
        lat, lon, _alt = from_enu(np.column_stack([arr, up]), origin)
        back, _ = to_enu(np.where(good, lat, np.nan), np.where(good, lon, np.nan), origin=origin)
        if not good.any() or np.max(np.abs(back[good, :2] - arr[good])) <= tol_m:
            return lat, lon
        up = np.where(good, back[:, 2], 0.0)
    raise RuntimeError("from_enu_horizontal did not converge (points farther than ~1000 km from the origin?)")


# --------------------------------------------------------------------------------------------
# many aircraft at once: one recorded window of traffic (issue 28)
# --------------------------------------------------------------------------------------------
#: The bundled traffic window: ``data/adsb/traffic/quickstart_1400.csv.gz``, the airborne records of
#: traffic 2.13's ``collections/quickstart`` (OpenSky, around Paris) from 2021-10-07 14:00:01 to
#: 14:20:01 UTC (``data/README.md``).
TRAFFIC_FILE: str = "adsb/traffic/quickstart_1400.csv.gz"
#: Column names of a traffic file, in order: the aircraft's ``icao24`` and ``callsign``, then :data:`COLUMNS`.
TRAFFIC_COLUMNS: tuple[str, ...] = ("icao24", "callsign") + COLUMNS
#: The stated radar site (lat_deg, lon_deg, h_m): 48.91 N, 2.47 E, the median airborne position of the
#: whole quickstart recording rounded to 0.01 degree (north-east Paris, between Le Bourget and the city).
RADAR_SITE: tuple[float, float, float] = (48.91, 2.47, 0.0)
#: An aircraft is absent (not interpolated) across a gap between two of its reports longer than this, s.
MAX_GAP_S: float = 10.0
_MIN_OVERLAP_S = 60.0   # s: a synthetic copy made by TrafficWindow.shifted spans at least this inside the window


def _rotate(xy: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.column_stack([c * xy[:, 0] - s * xy[:, 1], s * xy[:, 0] + c * xy[:, 1]])


class TrafficWindow:
    r"""Real trajectories of many aircraft over one time window, in the radar site's east/north frame.

    Built by :func:`load_traffic` (or :meth:`shifted`); times are seconds from the window start
    ``start_unix``, positions metres east/north of ``site`` (``pymap3d`` geodetic to ENU of the
    fixes at height 0, as for single flights), velocities m/s in the same frame.

    Between two consecutive reports :math:`(t_k, p_k)`, :math:`(t_{k+1}, p_{k+1})` of one aircraft
    at most :data:`MAX_GAP_S` apart, :meth:`truth_at` interpolates linearly,
    :math:`p(t) = p_k + \frac{t - t_k}{t_{k+1} - t_k}(p_{k+1} - p_k)` (exact at the reports); the
    velocity likewise interpolates the recorded ground speed and track, rotated from the
    aircraft's local east/north into the site's frame (``pymap3d`` ENU to ECEF to ENU, which
    includes the meridian convergence, about 0.75 degree at 1 degree of longitude). An aircraft is
    present at ``t`` only inside such an interval (or exactly at a report).

    ``TrafficWindow(ids, callsigns, aircraft, t, xy, v, t1=, start_unix=, site=, skipped=)`` builds one
    from reports in any order (``aircraft`` (K,) indices into ``ids``; ``t`` (K,); ``xy``, ``v`` (K, 2)).

    Attributes
    ----------
    ids : list of str, length n
        The aircraft: icao24 (``"<icao24>+<k>"`` for a synthetic copy made by :meth:`shifted`).
    callsigns : list of str, length n
    t0, t1 : float
        Window bounds, s from ``start_unix`` (``t0 = 0``).
    start_unix : float
        The window start, unix s.
    site : tuple (lat_deg, lon_deg, h_m)
        The origin of the east/north frame (the radar site).
    skipped : dict[str, int]
        Rows of the file skipped, by reason.
    synthetic : bool
        True for a window made by :meth:`shifted` with time-shifted, rotated copies.
    aircraft, t, xy, v : numpy.ndarray, shapes (K,), (K,), (K, 2), (K, 2)
        Every kept report, sorted by aircraft index (into ``ids``) then time.
    """

    def __init__(self, ids, callsigns, aircraft, t, xy, v, *, t1, start_unix, site, skipped, synthetic=False):
        aircraft, t = np.asarray(aircraft), np.asarray(t, float)
        xy, v = (np.asarray(a, float) for a in (xy, v))
        xy, v = (a.reshape(0, 2) if a.size == 0 else a for a in (xy, v))
        if aircraft.ndim != 1 or t.shape != aircraft.shape or xy.shape != (t.size, 2) or v.shape != (t.size, 2):
            raise ValueError(f"aircraft and t must have shape (K,), xy and v shape (K, 2); got aircraft {aircraft.shape}, "
                             f"t {t.shape}, xy {xy.shape}, v {v.shape}")
        if len(callsigns) != len(ids) or (aircraft.size and not (0 <= aircraft.min() and aircraft.max() < len(ids))):
            raise ValueError(f"aircraft must index ids (length {len(ids)}) and callsigns must match ids "
                             f"(length {len(callsigns)})")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(xy)) and np.all(np.isfinite(v))):
            raise ValueError("t, xy and v must be finite")
        order = np.lexsort((t, aircraft))
        self.ids, self.callsigns = list(ids), list(callsigns)
        self.aircraft = np.asarray(aircraft, dtype=np.int64)[order]
        self.t = np.asarray(t, float)[order]
        self.xy = np.asarray(xy, float)[order]
        self.v = np.asarray(v, float)[order]
        self.t0, self.t1 = 0.0, float(t1)
        self.start_unix, self.site = float(start_unix), tuple(site)
        self.skipped, self.synthetic = dict(skipped), bool(synthetic)
        for arr in (self.aircraft, self.t, self.xy, self.v):
            arr.flags.writeable = False
        # one sorted key per report: aircraft index * span + time, for a vectorised search
        self._span = 4.0 * (float(np.max(np.abs(self.t))) + self.t1 + 1.0) if self.t.size else 1.0
        self._key = self.aircraft * self._span + self.t
        nxt_same = np.zeros(self.t.size, bool)
        nxt_same[:-1] = self.aircraft[1:] == self.aircraft[:-1]
        gap = np.full(self.t.size, np.inf)
        gap[:-1] = np.diff(self.t)
        #: report k starts an interpolation interval to report k+1
        self._interval = nxt_same & (gap <= MAX_GAP_S)

    def __repr__(self) -> str:
        return (f"TrafficWindow({len(self.ids)} aircraft, {self.t.size} reports, t in [{self.t0:g}, {self.t1:g}] s"
                f"{', synthetic' if self.synthetic else ''})")

    def states_at(self, index, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Interpolated ``(present (m,) bool, xy (m, 2), v (m, 2))`` of aircraft ``index[j]`` at time ``t[j]``.

        ``index`` and ``t`` broadcast to shape ``(m,)``; rows not present are NaN.
        """
        index, t = np.broadcast_arrays(np.asarray(index, np.int64).reshape(-1), np.asarray(t, float).reshape(-1))
        xy = np.full((index.size, 2), np.nan)
        v = np.full((index.size, 2), np.nan)
        if self.t.size == 0 or index.size == 0:
            return np.zeros(index.size, bool), xy, v
        k = np.searchsorted(self._key, index * self._span + t, side="right") - 1
        kc = np.clip(k, 0, self.t.size - 1)
        mine = (k >= 0) & (self.aircraft[kc] == index)
        at_report = mine & (self.t[kc] == t)
        k1 = np.minimum(kc + 1, self.t.size - 1)
        inside = mine & self._interval[kc] & (t <= self.t[k1])
        present = at_report | inside
        w = np.where(inside & ~at_report, (t - self.t[kc]) / np.where(inside, self.t[k1] - self.t[kc], 1.0), 0.0)
        w = w[:, None]
        xy[present] = ((1 - w) * self.xy[kc] + w * self.xy[k1])[present]
        v[present] = ((1 - w) * self.v[kc] + w * self.v[k1])[present]
        return present, xy, v

    def truth_at(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The aircraft present at time ``t`` (s from the window start) and their interpolated states.

        Returns
        -------
        ids_present : numpy.ndarray of int, shape (k,)
            Indices into ``ids`` (the ``origin`` labels of a :class:`kftrack.sensors.surveillance.Scan`).
        xy : numpy.ndarray, shape (k, 2)
            East, north, m.
        v : numpy.ndarray, shape (k, 2)
            Velocity east, north, m/s.

        Examples
        --------
        >>> from kftrack.adsb import load_traffic
        >>> window = load_traffic()
        >>> ids, xy, v = window.truth_at(600.0)
        >>> len(ids), xy.shape, v.shape
        (32, (32, 2), (32, 2))
        """
        t = finite_scalar(t, "t")
        present, xy, v = self.states_at(np.arange(len(self.ids)), t)
        idx = np.flatnonzero(present)
        return idx, xy[idx], v[idx]

    def shifted(self, n_aircraft: int, seed=0) -> TrafficWindow:
        r"""A window of ``n_aircraft`` trajectories, synthesised from the recorded ones (for scaling studies).

        If ``n_aircraft`` is at most the number recorded, a random subset of the recorded aircraft
        (unchanged: real). Beyond that, every recorded aircraft plus synthetic copies: copy ``c`` of
        recorded aircraft ``a`` is shifted in time by a uniform :math:`s` and rotated about
        the site by :math:`\phi \sim U(0, 2\pi)` (positions and velocities), so copies neither
        coincide with their original nor with each other. Only aircraft recorded for at least 120 s
        are copied (in turn), and :math:`s` is uniform over the shifts that leave at least 60 s of
        the copy's recorded span inside the window. The result is marked ``synthetic``; its aircraft
        are real trajectories but their times and places are not.

        Parameters
        ----------
        n_aircraft : int
            Number of trajectories, >= 1.
        seed : int or numpy.random.Generator
            Randomness of the subset, shifts and rotations.

        Examples
        --------
        >>> from kftrack.adsb import load_traffic
        >>> big = load_traffic().shifted(200, seed=1)
        >>> len(big.ids), big.synthetic
        (200, True)
        """
        if isinstance(n_aircraft, bool) or not isinstance(n_aircraft, (int, np.integer)) or n_aircraft < 1:
            raise ValueError(f"n_aircraft must be an integer >= 1, got {n_aircraft!r}")
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        n_rec = len(self.ids)
        if n_rec == 0:
            raise ValueError("shifted needs a window with at least one aircraft")
        if n_aircraft <= n_rec:
            keep = np.sort(rng.choice(n_rec, size=int(n_aircraft), replace=False))
            sel = np.isin(self.aircraft, keep)
            new_index = np.full(n_rec, -1)
            new_index[keep] = np.arange(keep.size)
            return TrafficWindow([self.ids[i] for i in keep], [self.callsigns[i] for i in keep],
                                 new_index[self.aircraft[sel]], self.t[sel], self.xy[sel], self.v[sel],
                                 t1=self.t1, start_unix=self.start_unix, site=self.site, skipped=self.skipped,
                                 synthetic=self.synthetic)
        ids, calls = list(self.ids), list(self.callsigns)
        parts = [(self.aircraft, self.t, self.xy, self.v)]
        first = np.array([self.t[self.aircraft == a].min() for a in range(n_rec)])
        last = np.array([self.t[self.aircraft == a].max() for a in range(n_rec)])
        eligible = np.flatnonzero(last - first >= 2 * _MIN_OVERLAP_S)
        if eligible.size == 0:
            raise ValueError(f"shifted needs an aircraft recorded for at least {2 * _MIN_OVERLAP_S:g} s to copy")
        for j in range(int(n_aircraft) - n_rec):
            a = int(eligible[j % eligible.size])
            rows = self.aircraft == a
            # last + s >= t0 + 60 s and first + s <= t1 - 60 s: at least 60 s of the copy's span inside
            s = rng.uniform(self.t0 + _MIN_OVERLAP_S - last[a], self.t1 - _MIN_OVERLAP_S - first[a])
            phi = rng.uniform(0.0, 2 * np.pi)
            ids.append(f"{self.ids[a]}+{j // eligible.size + 1}")
            calls.append(self.callsigns[a])
            parts.append((np.full(int(rows.sum()), len(ids) - 1), self.t[rows] + s, _rotate(self.xy[rows], phi),
                          _rotate(self.v[rows], phi)))
        cat = [np.concatenate([p[i] for p in parts]) for i in range(4)]
        return TrafficWindow(ids, calls, *cat, t1=self.t1, start_unix=self.start_unix, site=self.site,
                             skipped=self.skipped, synthetic=True)


def _velocity_enu(lat, lon, gs, track_deg, site) -> np.ndarray:
    """Ground velocity (ground speed, track clockwise from north) in the site's east/north frame, (K, 2)."""
    tr = np.deg2rad(track_deg)
    ve, vn = gs * np.sin(tr), gs * np.cos(tr)
    u, v, w = pymap3d.enu2uvw(ve, vn, np.zeros_like(ve), lat, lon, deg=True)
    e, n, _ = pymap3d.uvw2enu(u, v, w, site[0], site[1], deg=True)
    return np.column_stack([np.asarray(e, float), np.asarray(n, float)])


@lru_cache(maxsize=2)
def _bundled_traffic(path: str) -> TrafficWindow:
    """The bundled window at ``path`` (where ``data_path`` finds it), read once per process (read-only arrays)."""
    return load_traffic(Path(path))


def load_traffic(path: str | os.PathLike | None = None) -> TrafficWindow:
    """Load a window of recorded traffic (many aircraft), skipping and counting the rows it cannot use.

    Parameters
    ----------
    path : str or os.PathLike, optional
        A traffic file (gzipped if its name ends in ``.gz``); default the bundled window
        :data:`TRAFFIC_FILE` (OpenSky, Paris, 2021-10-07 14:00:01-14:20:01 UTC, airborne reports
        of 63 aircraft). Format: ``#`` comment lines (a line containing ``window unix [a, b)``
        sets the window, else it spans the reports), the header :data:`TRAFFIC_COLUMNS`, then one
        report per line: the flight columns of :func:`load_flight` after ``icao24,callsign``.

    Returns
    -------
    TrafficWindow
        Positions in the east/north frame of :data:`RADAR_SITE`. A row is skipped and counted in
        ``skipped`` under its reason: the reasons of :func:`load_flight`, a missing ``icao24``,
        a time outside the window, a time not after the aircraft's previous report (duplicate or
        reversal), a missing ground speed or track, or a position equal to the aircraft's
        previous report (a held, stale position: OpenSky's 1 s state vectors repeat the last
        received position when no new one came).

    Examples
    --------
    >>> from kftrack.adsb import load_traffic
    >>> window = load_traffic()
    >>> window
    TrafficWindow(61 aircraft, 32036 reports, t in [0, 1200] s)
    >>> window.skipped
    {'position held from the previous report': 2542, 'missing ground speed or track': 293}
    """
    if path is None:
        return _bundled_traffic(str(data_path(TRAFFIC_FILE)))
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a traffic file path (str or os.PathLike) or None, got {type(path).__name__}")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no traffic file {str(path)!r}")
    opener = gzip.open if path.name.lower().endswith(".gz") else open
    skipped: dict[str, int] = {}
    window = None
    rows, who, calls = [], [], {}
    header_seen = False

    def skip(reason):
        skipped[reason] = skipped.get(reason, 0) + 1

    try:
        with opener(path, "rt", encoding="utf-8", errors="replace", newline="") as fh:
            for raw in fh:
                line = raw.strip()
                if not line:
                    continue
                if line.startswith("#"):
                    if "window unix [" in line and window is None:
                        a, b = line.split("window unix [", 1)[1].split(")", 1)[0].split(",")
                        window = (float(a), float(b))
                    continue
                if not header_seen:
                    if tuple(line.split(",")) != TRAFFIC_COLUMNS:
                        raise ValueError(f"{path}: header must be {','.join(TRAFFIC_COLUMNS)!r}, got {line[:200]!r}")
                    header_seen = True
                    continue
                fields = line.split(",")
                if len(fields) != len(TRAFFIC_COLUMNS):
                    skip(f"wrong number of fields (expected {len(TRAFFIC_COLUMNS)})")
                    continue
                if not fields[0].strip():
                    skip("missing icao24")
                    continue
                values, reason = _parse_row(",".join(fields[2:]))
                if values is None:
                    skip(reason)
                    continue
                rows.append(values)
                who.append(fields[0].strip())
                calls.setdefault(fields[0].strip(), fields[1].strip())
    except gzip.BadGzipFile as exc:
        raise ValueError(f"{path}: not a valid gzip file ({exc})") from exc
    except (EOFError, zlib.error) as exc:
        raise ValueError(f"{path}: truncated or corrupt gzip data ({exc})") from exc
    if not header_seen:
        raise ValueError(f"{path}: no header line {','.join(TRAFFIC_COLUMNS)!r}")
    table = np.array(rows, dtype=float).reshape(len(rows), len(COLUMNS))
    if window is None:
        window = (math.floor(table[:, 0].min()), math.ceil(table[:, 0].max())) if len(rows) else (0.0, 0.0)
    ids = list(dict.fromkeys(who))
    index = {k: i for i, k in enumerate(ids)}
    keep = np.ones(len(rows), bool)
    last: dict[str, tuple[float, float, float]] = {}
    for j, k in enumerate(who):   # file order: each report against its aircraft's previous kept report
        t, lat, lon = table[j, :3]
        gs, trk = table[j, 4], table[j, 5]
        prev = last.get(k)
        reason = None
        if not window[0] <= t <= window[1]:
            reason = "time outside the window"
        elif prev is not None and t <= prev[0]:
            reason = "time not after the aircraft's previous report"
        elif not (math.isfinite(gs) and math.isfinite(trk)):
            reason = "missing ground speed or track"
        elif prev is not None and (lat, lon) == prev[1:]:
            reason = "position held from the previous report"
        if reason is None:
            last[k] = (t, lat, lon)
        else:
            keep[j] = False
            skip(reason)
    table = table[keep]
    who_kept = [k for k, ok in zip(who, keep) if ok]
    ids = [k for k in ids if k in last]
    index = {k: i for i, k in enumerate(ids)}
    aircraft = np.array([index[k] for k in who_kept], dtype=np.int64)
    if table.shape[0]:
        enu, _ = to_enu(table[:, 1], table[:, 2], origin=RADAR_SITE)
        xy = enu[:, :2]
        v = _velocity_enu(table[:, 1], table[:, 2], table[:, 4], table[:, 5], RADAR_SITE)
    else:
        xy = v = np.zeros((0, 2))
    return TrafficWindow(ids, [calls[k] for k in ids], aircraft, table[:, 0] - window[0], xy, v,
                         t1=window[1] - window[0], start_unix=window[0], site=RADAR_SITE, skipped=skipped)
