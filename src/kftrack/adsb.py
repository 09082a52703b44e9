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
    """Raise ValueError if any record of ``flights`` is a test flight, by name or by content.

    Every tuning function of chapter 18 calls this at its boundary, so that nothing is fitted,
    scanned or chosen on the flights the methods are judged on. A record (anything with ``t_s``,
    ``lat_deg``, ``lon_deg`` arrays of shape ``(K,)``, a ``name`` optional) is a test flight if

    - its ``name`` is in :data:`TEST_FLIGHTS`, or
    - at least half of its finite rows (``t_s``, ``lat_deg``, ``lon_deg`` all finite) match one
      test flight: a row matches if its time lies in that flight's span :math:`[t_0, t_1]` and its
      position lies within that flight's tolerance :math:`\\delta` of its stored track
      :math:`(\\hat\\varphi(t), \\hat\\lambda(t))` at the same time,
      :math:`R\\sqrt{(\\varphi - \\hat\\varphi)^2 + \\cos^2\\varphi\\,(\\lambda - \\hat\\lambda)^2} \\le \\delta`
      (radians, :math:`R` = 6371 km).

    The stored tracks (``_TEST_FLIGHT_TRACKS``, no file is read: tuning code never opens a test
    flight) hold each test flight's position every 600 s, linearly interpolated in time;
    :math:`\\delta` is the largest distance of that flight's own rows from its track plus 1 km
    (6.5 to 38.6 km). So a test flight renamed, sliced or copied into a record without a name
    is refused (all its rows match), while no row of a training or robustness flight matches any
    (the nearest, ``gliders/alpi_italiane``, stays 18.5 km from the track of ``gliders/alto_adige``,
    whose :math:`\\delta` is 9.4 km; ``tests/test_adsb.py`` checks both). A record whose rows mostly
    lie elsewhere in space or time, named or not, passes; so does one in which a test flight's rows
    are fewer than half (e.g. appended to a longer flight). Cost: a few vector operations per test
    flight (under 10 ms for 3000 rows).

    Parameters
    ----------
    flights : iterable of records (:class:`Flight` or alike)
        The flights a tuning function was given; records without the three columns are left to
        the caller's own validation.
    argname : str
        The argument's name, for the message.

    Raises
    ------
    ValueError
        Naming ``argname[i]`` of every refused record and the test flight it is (or matches).

    Examples
    --------
    >>> from kftrack.adsb import COLUMNS, load_flight, refuse_test_flights
    >>> fl = load_flight("gliders/luberon")                                   # a test flight
    >>> mine = fl._replace(name="mine.csv", **{k: getattr(fl, k)[500:600] for k in COLUMNS})
    >>> refuse_test_flights([load_flight("gliders/cevennes"), mine], argname="train")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ValueError: train must not hold test flights ..., got train[1] (name 'mine.csv': 100 of its 100
    finite rows match gliders/luberon)
    """
    bad = []
    for i, fl in enumerate(flights):
        name = getattr(fl, "name", None)
        if isinstance(name, str) and name in TEST_FLIGHTS:
            bad.append(f"{argname}[{i}] ({name})")
            continue
        match = _matched_test_flight(fl)
        if match is not None:
            test, k, n = match
            label = f"name {name!r}" if isinstance(name, str) else "no name"
            bad.append(f"{argname}[{i}] ({label}: {k} of its {n} finite rows match {test})")
    if bad:
        raise ValueError(f"{argname} must not hold test flights (kftrack.adsb.TEST_FLIGHTS: nothing is tuned on "
                         f"them; a record is one if its name is a test flight's, or if at least half of its "
                         f"finite rows lie in a test flight's time span and within its tolerance of that "
                         f"flight's stored track), got {', '.join(bad)}")


#: Seconds between the stored points of a test flight's track (``_TEST_FLIGHT_TRACKS``).
_TRACK_STEP_S = 600.0
#: km added to the largest distance of a test flight's own rows from its stored track: a copy of
#: the flight rounded to 0.001 deg (0.1 km) or coarser still matches.
_TRACK_MARGIN_KM = 1.0
_KM_PER_DEG = 6371.0 * math.pi / 180.0   # km per degree of arc on the mean sphere (R = 6371 km)


def _track_times(t0: float, t1: float, n: int) -> np.ndarray:
    """The ``n`` times of a stored track: ``t0 + k * _TRACK_STEP_S``, the last one ``t1``."""
    return np.minimum(t0 + _TRACK_STEP_S * np.arange(n), t1)


def _track_distance_km(t, lat, lon, track_t, track_lat, track_lon) -> np.ndarray:
    """Distance (km, equirectangular) of the rows ``(t, lat, lon)`` (K,) from the track linearly
    interpolated at their times."""
    plat, plon = np.interp(t, track_t, track_lat), np.interp(t, track_t, track_lon)
    dlon = (lon - plon + 180.0) % 360.0 - 180.0
    return _KM_PER_DEG * np.hypot(lat - plat, dlon * np.cos(np.radians(lat)))


def _test_flight_tracks() -> dict[str, tuple]:
    """``{name: (t0, t1, tol_km, lat, lon)}`` of every test flight, computed from its file.

    ``t0``, ``t1``: the first and last time (s, floor and ceiling); ``lat``, ``lon``: the flight's
    position (deg, rounded to 0.001) at :func:`_track_times`, interpolated in time between its rows
    sorted by time; ``tol_km``: the largest distance of its rows from that track plus
    ``_TRACK_MARGIN_KM``, rounded up to 0.1 km. Only ``tests/test_adsb.py`` and the regeneration of
    ``_TEST_FLIGHT_TRACKS`` (``print(_format_tracks(_test_flight_tracks()))``, pasted at the end of
    this module) call it: tuning code never reads a test flight.
    """
    out = {}
    for name in TEST_FLIGHTS:
        fl = load_flight(name)
        order = np.argsort(fl.t_s, kind="stable")
        t, lat, lon = fl.t_s[order], fl.lat_deg[order], fl.lon_deg[order]
        t0, t1 = math.floor(t[0]), math.ceil(t[-1])
        grid = _track_times(t0, t1, math.ceil((t1 - t0) / _TRACK_STEP_S) + 1)
        glat, glon = np.round(np.interp(grid, t, lat), 3), np.round(np.interp(grid, t, lon), 3)
        dev = float(np.max(_track_distance_km(t, lat, lon, grid, glat, glon)))
        out[name] = (t0, t1, math.ceil(10.0 * (dev + _TRACK_MARGIN_KM)) / 10.0, tuple(glat.tolist()),
                     tuple(glon.tolist()))
    return out


def _format_tracks(table: dict[str, tuple]) -> str:
    """The Python source of ``_TEST_FLIGHT_TRACKS = table`` (lines of at most 110 characters)."""
    import textwrap

    def numbers(values, end: str) -> str:
        return "\n".join(textwrap.wrap("(" + ", ".join(repr(v) for v in values) + end, 110,
                                        initial_indent=" " * 8, subsequent_indent=" " * 9, break_on_hyphens=False))

    lines = ["_TEST_FLIGHT_TRACKS: dict[str, tuple] = {"]
    for name, (t0, t1, tol, lat, lon) in table.items():
        lines += [f"    {name!r}: ({t0!r}, {t1!r}, {tol!r},", numbers(lat, "),"), numbers(lon, ")),")]
    return "\n".join(lines + ["}"])


@lru_cache(maxsize=1)
def _test_tracks() -> tuple[tuple, ...]:
    """``_TEST_FLIGHT_TRACKS`` as arrays: ``(name, t0, t1, tol_km, times, lat, lon)`` per flight."""
    return tuple((name, float(t0), float(t1), float(tol), _track_times(t0, t1, len(lat)), np.array(lat),
                  np.array(lon)) for name, (t0, t1, tol, lat, lon) in _TEST_FLIGHT_TRACKS.items())


def _matched_test_flight(fl) -> tuple[str, int, int] | None:
    """``(test flight, matching rows, finite rows)`` for the test flight the most finite rows of
    ``fl`` match, if at least half do (rule of :func:`refuse_test_flights`); else None."""
    try:
        t, lat, lon = (np.asarray(getattr(fl, a), dtype=float) for a in ("t_s", "lat_deg", "lon_deg"))
    except (AttributeError, TypeError, ValueError):
        return None
    if t.ndim != 1 or lat.shape != t.shape or lon.shape != t.shape:
        return None
    finite = np.isfinite(t) & np.isfinite(lat) & np.isfinite(lon)
    n = int(np.count_nonzero(finite))
    if n == 0:
        return None
    t, lat, lon = t[finite], lat[finite], lon[finite]
    best = None
    for name, t0, t1, tol, track_t, track_lat, track_lon in _test_tracks():
        span = (t >= t0) & (t <= t1)
        if 2 * int(np.count_nonzero(span)) < n:
            continue
        d = _track_distance_km(t[span], lat[span], lon[span], track_t, track_lat, track_lon)
        k = int(np.count_nonzero(d <= tol))
        if 2 * k >= n and (best is None or k > best[1]):
            best = (name, k, n)
    return best


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


# The stored tracks of the test flights (rule: refuse_test_flights), {name: (t0 s, t1 s, tolerance km,
# lat deg, lon deg)}: written by print(_format_tracks(_test_flight_tracks())), checked against the
# files by tests/test_adsb.py.
_TEST_FLIGHT_TRACKS: dict[str, tuple] = {
    'calibration/ajaccio': (1515748470, 1515761610, 32.4,
        (41.891, 41.843, 41.815, 41.569, 41.51, 42.003, 41.711, 41.896, 41.811, 41.331, 41.665, 42.23, 42.862,
         43.108, 42.855, 42.32, 41.809, 41.293, 41.604, 41.625, 41.387, 41.695, 41.922),
        (8.78, 8.786, 8.7, 9.006, 8.535, 8.501, 8.687, 8.28, 8.712, 8.97, 8.821, 8.826, 8.897, 8.296, 7.965,
         8.368, 8.746, 8.713, 8.589, 8.397, 7.968, 8.63, 8.795)),
    'calibration/bornholm': (1543225095, 1543237950, 17.2,
        (55.061, 55.042, 54.974, 55.054, 54.906, 55.099, 54.818, 54.993, 54.979, 55.054, 55.007, 54.973,
         55.059, 55.039, 55.022, 55.013, 55.004, 55.017, 55.038, 55.03, 55.04, 54.995, 55.059),
        (14.767, 14.84, 14.989, 14.913, 14.863, 15.242, 15.246, 15.249, 14.88, 14.767, 14.831, 14.973, 14.923,
         14.855, 14.921, 14.953, 14.96, 14.811, 14.858, 14.77, 14.851, 14.946, 14.778)),
    'calibration/brussels_ils': (1544274475, 1544283995, 21.9,
        (50.909, 51.051, 50.983, 50.88, 51.069, 51.019, 50.968, 51.114, 51.062, 50.951, 50.976, 51.008,
         51.016, 51.061, 51.023, 50.994, 50.898),
        (4.491, 4.549, 4.411, 4.654, 4.575, 4.546, 4.525, 4.696, 4.5, 4.518, 4.528, 4.541, 4.545, 4.564,
         4.547, 4.535, 4.47)),
    'calibration/brussels_vor': (1544260265, 1544267725, 15.1,
        (50.908, 50.999, 50.584, 50.852, 51.199, 51.171, 50.802, 50.708, 51.11, 51.046, 50.653, 50.976,
         50.901, 50.897),
        (4.488, 4.028, 4.396, 5.061, 4.772, 4.232, 4.031, 4.789, 4.764, 4.22, 4.493, 4.887, 4.493, 4.469)),
    'calibration/cardiff': (1550222725, 1550232975, 22.1,
        (51.394, 51.54, 51.529, 51.403, 51.416, 51.521, 51.414, 51.381, 51.43, 51.384, 51.375, 51.346, 51.372,
         51.301, 51.359, 51.322, 51.406, 51.394, 51.394),
        (-3.335, -3.391, -3.616, -3.542, -3.561, -3.625, -3.463, -3.336, -3.449, -3.203, -3.275, -3.087,
         -3.266, -3.317, -3.084, -3.29, -3.38, -3.345, -3.346)),
    'calibration/funchal': (1542966250, 1542980025, 23.9,
        (32.696, 32.811, 32.789, 32.647, 32.907, 32.581, 32.88, 32.678, 32.748, 32.835, 32.612, 32.914,
         32.595, 32.854, 32.553, 32.415, 32.588, 32.973, 32.934, 32.762, 32.646, 32.888, 32.689, 32.693),
        (-16.776, -16.523, -16.897, -16.547, -16.761, -16.732, -16.587, -16.886, -16.507, -16.874, -16.591,
         -16.712, -16.787, -16.554, -16.818, -16.882, -16.807, -16.562, -16.594, -16.654, -16.802, -16.595,
         -16.785, -16.781)),
    'calibration/guatemala': (1522081475, 1522090745, 29.7,
        (14.591, 15.054, 15.043, 15.077, 15.013, 14.968, 15.145, 14.755, 14.994, 15.38, 14.973, 15.055,
         14.921, 15.115, 15.038, 14.542, 14.594),
        (-90.525, -90.356, -90.413, -90.202, -90.512, -90.479, -90.19, -90.406, -90.488, -90.443, -90.642,
         -90.309, -90.613, -90.338, -90.461, -90.574, -90.526)),
    'calibration/kingston': (1530033130, 1530040400, 20.9,
        (17.935, 18.164, 17.908, 17.954, 17.91, 17.973, 18.032, 18.091, 18.097, 17.864, 18.025, 18.02, 17.935,
         17.936),
        (-76.786, -76.937, -76.848, -77.082, -77.132, -76.874, -76.92, -76.888, -76.848, -77.033, -76.992,
         -76.983, -76.779, -76.778)),
    'calibration/kiruna': (1548836125, 1548844575, 25.1,
        (67.831, 67.907, 67.905, 67.929, 67.973, 68.0, 68.033, 67.922, 67.956, 67.974, 68.079, 68.149, 67.955,
         67.789, 67.824, 67.825),
        (20.352, 20.487, 20.39, 20.623, 20.709, 20.716, 20.441, 20.628, 20.571, 21.116, 22.17, 21.233, 21.578,
         20.324, 20.337, 20.333)),
    'calibration/kota_kinabalu': (1488936615, 1488941205, 33.6,
        (5.94, 5.997, 6.074, 5.986, 6.154, 6.225, 6.171, 6.219, 5.941),
        (116.052, 115.767, 116.023, 115.875, 115.948, 116.075, 116.146, 116.144, 116.053)),
    'calibration/liege_sprimont': (1556352555, 1556364575, 20.1,
        (50.896, 50.909, 50.828, 50.747, 50.604, 50.344, 50.728, 50.628, 50.338, 50.706, 50.552, 50.278,
         50.655, 50.649, 50.276, 50.554, 50.628, 50.45, 50.847, 50.646, 50.671, 50.664),
        (4.468, 4.498, 4.511, 5.411, 6.105, 5.655, 5.388, 6.099, 5.698, 5.363, 6.013, 5.511, 5.302, 5.951,
         5.707, 5.238, 5.849, 5.302, 5.234, 5.86, 5.497, 5.486)),
    'calibration/london_gatwick': (1551313690, 1551324965, 20.9,
        (51.15, 51.106, 51.217, 51.149, 51.116, 51.243, 51.226, 51.131, 51.209, 51.165, 51.152, 51.121,
         51.095, 51.192, 51.131, 51.084, 51.135, 51.123, 51.142, 51.153),
        (-0.177, -0.091, 0.083, 0.003, -0.232, -0.064, 0.389, -0.149, 0.069, -0.071, -0.017, -0.233, -0.187,
         -0.309, -0.205, -0.212, -0.516, -0.136, -0.163, -0.195)),
    'calibration/monastir': (1542794990, 1542805395, 20.2,
        (35.754, 35.727, 35.682, 35.722, 35.706, 35.742, 35.785, 35.746, 35.779, 35.741, 35.739, 35.704,
         35.726, 35.746, 35.879, 35.521, 35.685, 35.738, 35.759),
        (10.736, 10.649, 10.618, 10.593, 10.567, 10.686, 10.689, 10.706, 10.851, 10.682, 10.706, 10.636,
         10.622, 10.654, 10.485, 10.524, 10.297, 10.672, 10.754)),
    'calibration/montreal': (1544540290, 1544549995, 29.3,
        (45.471, 45.701, 45.665, 45.664, 45.451, 45.671, 45.647, 45.621, 45.675, 45.677, 45.707, 45.876,
         45.844, 45.799, 45.758, 45.388, 45.471, 45.47),
        (-73.723, -73.206, -73.283, -73.273, -73.832, -74.067, -74.115, -74.217, -74.13, -74.235, -74.094,
         -73.763, -73.844, -73.918, -73.818, -74.056, -73.721, -73.72)),
    'calibration/nice': (1576068400, 1576080850, 23.8,
        (43.656, 43.554, 43.55, 43.537, 43.496, 43.595, 43.607, 43.655, 43.564, 43.533, 43.533, 43.656,
         43.607, 43.529, 43.395, 43.544, 43.47, 43.512, 43.497, 43.619, 43.65, 43.656),
        (7.206, 7.191, 7.008, 7.118, 7.126, 7.228, 7.272, 7.25, 7.183, 7.101, 7.078, 7.214, 7.217, 7.147,
         7.188, 6.791, 6.976, 7.187, 7.165, 7.234, 7.243, 7.206)),
    'calibration/noumea': (1509844535, 1509850410, 23.3,
        (-22.039, -22.276, -22.249, -22.249, -22.317, -22.419, -22.326, -22.135, -22.125, -22.134, -21.955),
        (166.22, 166.422, 166.484, 166.485, 166.502, 166.53, 166.466, 166.562, 166.627, 166.324, 166.13)),
    'calibration/perth': (1548188465, 1548203965, 26.1,
        (-31.942, -31.865, -31.821, -32.039, -32.089, -31.671, -31.27, -31.456, -31.985, -31.602, -31.586,
         -31.74, -31.646, -31.535, -31.56, -31.7, -31.428, -31.701, -31.748, -31.677, -31.556, -31.531,
         -31.576, -31.706, -31.709, -31.899, -31.931),
        (115.965, 115.98, 115.989, 115.675, 116.072, 116.507, 116.141, 115.602, 115.692, 115.996, 115.994,
         115.986, 116.044, 116.135, 115.894, 116.021, 115.988, 115.845, 115.849, 115.92, 116.13, 116.142,
         116.046, 115.962, 115.887, 116.041, 115.96)),
    'calibration/sydney': (1541810960, 1541825690, 22.6,
        (-33.965, -33.809, -33.763, -33.828, -33.817, -33.897, -33.907, -33.935, -33.855, -33.681, -33.846,
         -33.917, -33.945, -33.814, -33.82, -33.812, -33.923, -33.755, -33.921, -33.926, -33.942, -33.863,
         -33.669, -33.938, -33.946, -33.946),
        (151.192, 151.152, 151.239, 151.162, 151.175, 151.175, 151.177, 151.185, 151.161, 151.279, 151.162,
         151.181, 151.264, 151.232, 151.315, 151.278, 151.063, 151.314, 151.181, 151.182, 151.186, 151.166,
         151.232, 151.264, 151.187, 151.187)),
    'calibration/vancouver': (1538840575, 1538849965, 38.6,
        (49.929, 49.732, 49.453, 49.165, 49.176, 49.18, 49.155, 49.203, 49.183, 49.173, 49.163, 49.142,
         49.266, 49.274, 49.5, 49.773, 49.966),
        (-119.374, -120.48, -122.089, -122.984, -123.087, -123.108, -122.948, -123.326, -123.231, -123.354,
         -123.193, -121.976, -120.233, -118.633, -118.347, -119.415, -119.379)),
    'calibration/vienna': (1542756885, 1542770570, 24.9,
        (48.109, 48.129, 48.13, 48.072, 48.074, 48.099, 48.057, 48.077, 48.096, 48.198, 48.009, 47.99, 48.111,
         48.089, 48.031, 48.098, 48.099, 48.052, 47.983, 48.027, 48.041, 47.958, 48.151, 48.111),
        (16.575, 16.505, 16.512, 16.596, 16.684, 16.608, 16.618, 16.673, 16.53, 16.744, 16.712, 16.677,
         16.568, 16.542, 16.715, 16.609, 16.506, 16.885, 16.836, 17.056, 16.684, 16.82, 16.707, 16.58)),
    'gliders/alto_adige': (1558600726, 1558631793, 9.4,
        (46.017, 46.087, 46.137, 46.146, 46.154, 46.209, 46.302, 46.39, 46.476, 46.606, 46.705, 46.781, 46.77,
         46.721, 46.697, 46.664, 46.656, 46.64, 46.588, 46.647, 46.681, 46.696, 46.713, 46.714, 46.737,
         46.748, 46.801, 46.844, 46.87, 46.762, 46.69, 46.629, 46.539, 46.552, 46.579, 46.622, 46.595, 46.638,
         46.681, 46.687, 46.622, 46.611, 46.456, 46.29, 46.069, 45.892, 45.816, 45.888, 46.052, 46.107,
         46.157, 45.999, 46.018),
        (11.125, 11.245, 11.305, 11.354, 11.376, 11.451, 11.565, 11.627, 11.818, 11.942, 12.033, 12.249,
         12.497, 12.644, 12.894, 13.147, 13.409, 13.553, 13.709, 13.511, 13.291, 13.171, 12.954, 12.815,
         12.546, 12.305, 12.13, 11.827, 11.697, 11.654, 11.538, 11.361, 11.111, 11.137, 11.186, 11.314,
         11.597, 11.759, 12.061, 12.134, 11.92, 11.764, 11.557, 11.437, 11.287, 11.186, 11.131, 11.2, 11.297,
         11.351, 11.355, 11.302, 11.123)),
    'gliders/danube_valley': (1558601548, 1558631334, 7.1,
        (49.794, 49.837, 49.812, 49.755, 49.594, 49.483, 49.497, 49.377, 49.259, 49.139, 49.03, 48.971,
         48.923, 48.815, 48.827, 48.838, 48.823, 48.77, 48.726, 48.715, 48.655, 48.731, 48.728, 48.762,
         48.815, 48.874, 48.862, 48.889, 48.92, 49.021, 49.03, 49.07, 49.019, 48.917, 48.885, 48.955, 49.06,
         49.174, 49.246, 49.289, 49.392, 49.469, 49.537, 49.558, 49.583, 49.604, 49.712, 49.684, 49.755,
         49.794, 49.792),
        (11.136, 11.218, 11.394, 11.511, 11.587, 11.76, 12.007, 12.17, 12.226, 12.294, 12.117, 11.957, 11.776,
         11.527, 11.366, 11.217, 10.932, 10.664, 10.439, 10.239, 9.952, 9.96, 10.204, 10.549, 10.831, 11.079,
         11.39, 11.53, 11.769, 12.032, 12.118, 12.429, 12.602, 12.868, 12.933, 12.83, 12.745, 12.579, 12.349,
         12.217, 12.092, 12.024, 11.987, 11.898, 11.803, 11.654, 11.474, 11.517, 11.277, 11.137, 11.128)),
    'gliders/franconia': (1558605772, 1558632799, 7.8,
        (49.794, 49.801, 49.773, 49.785, 49.812, 49.831, 49.854, 49.891, 49.916, 49.891, 49.815, 49.699,
         49.601, 49.562, 49.604, 49.649, 49.716, 49.748, 49.799, 49.813, 49.906, 49.945, 49.989, 49.97, 50.03,
         50.133, 50.188, 50.183, 50.204, 50.339, 50.278, 50.237, 50.141, 50.062, 49.916, 49.854, 49.808,
         49.847, 49.838, 49.759, 49.783, 49.807, 49.807, 49.799, 49.787, 49.794, 49.793),
        (11.137, 11.229, 11.348, 11.544, 11.694, 11.923, 12.073, 12.304, 12.477, 12.737, 12.815, 12.926,
         13.045, 13.018, 12.913, 12.725, 12.595, 12.48, 12.29, 12.197, 12.047, 11.843, 11.705, 11.567, 11.421,
         11.345, 11.186, 11.042, 10.955, 10.937, 10.894, 11.005, 11.024, 11.112, 11.244, 11.233, 11.077,
         10.942, 10.801, 10.694, 10.773, 10.994, 11.045, 11.184, 11.263, 11.133, 11.13)),
    'gliders/luberon': (1558607668, 1558633957, 6.5,
        (43.769, 43.755, 43.742, 43.759, 43.819, 43.806, 43.815, 43.836, 43.892, 43.934, 43.95, 44.024,
         44.036, 44.046, 44.047, 44.033, 44.061, 44.108, 44.094, 44.063, 44.073, 44.089, 44.135, 44.1, 44.076,
         44.068, 44.114, 44.094, 44.047, 44.028, 43.993, 43.932, 43.866, 43.775, 43.729, 43.736, 43.735,
         43.735, 43.748, 43.81, 43.849, 43.809, 43.766, 43.766, 43.766),
        (4.894, 4.916, 4.948, 5.051, 5.149, 5.332, 5.495, 5.608, 5.832, 5.998, 6.077, 6.11, 6.193, 6.222,
         6.173, 6.14, 6.057, 5.968, 6.004, 6.035, 6.048, 6.008, 5.95, 5.979, 5.994, 6.036, 5.978, 5.987,
         6.031, 6.019, 5.996, 5.956, 5.863, 5.793, 5.774, 5.785, 5.786, 5.787, 5.761, 5.512, 5.188, 4.963,
         4.894, 4.893, 4.893)),
    'gliders/oxford_cambridge': (1558609291, 1558633826, 8.1,
        (51.87, 51.97, 52.061, 52.157, 52.311, 52.401, 52.485, 52.583, 52.693, 52.799, 52.782, 52.747, 52.72,
         52.659, 52.525, 52.442, 52.374, 52.386, 52.354, 52.308, 52.217, 52.099, 52.066, 52.05, 51.913,
         51.817, 51.755, 51.651, 51.589, 51.501, 51.462, 51.456, 51.496, 51.515, 51.613, 51.77, 51.783,
         51.797, 51.926, 51.873, 51.868, 51.87),
        (-0.542, -0.624, -0.487, -0.323, -0.026, 0.186, 0.348, 0.459, 0.668, 0.757, 0.73, 0.681, 0.549, 0.385,
         0.22, 0.031, -0.17, -0.18, -0.363, -0.493, -0.632, -0.752, -0.751, -0.795, -1.025, -1.179, -1.248,
         -1.437, -1.498, -1.712, -1.836, -1.782, -1.686, -1.491, -1.275, -1.208, -1.173, -1.139, -0.846,
         -0.549, -0.547, -0.547)),
    'gliders/sisteron': (1558609124, 1558632076, 12.1,
        (44.283, 44.244, 44.27, 44.269, 44.358, 44.38, 44.386, 44.433, 44.526, 44.612, 44.599, 44.609, 44.612,
         44.695, 44.721, 44.671, 44.634, 44.643, 44.706, 44.601, 44.477, 44.422, 44.375, 44.272, 44.19,
         44.118, 44.137, 44.145, 44.234, 44.364, 44.233, 44.283, 44.283, 44.284, 44.284, 44.284, 44.284,
         44.284, 44.284, 44.284),
        (5.93, 6.048, 6.089, 6.146, 6.101, 6.038, 5.947, 5.846, 5.912, 5.904, 5.821, 5.763, 5.713, 5.629,
         5.55, 5.687, 5.812, 5.99, 5.965, 5.844, 5.651, 5.522, 5.687, 5.783, 5.868, 5.903, 5.712, 5.84, 5.848,
         5.931, 5.928, 5.929, 5.929, 5.93, 5.93, 5.931, 5.931, 5.932, 5.932, 5.932)),
}
