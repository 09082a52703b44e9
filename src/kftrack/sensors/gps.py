r"""GPS receivers: NMEA 0183 sentences, logs, and the geodesy that turns fixes into metres.

Reading. Sentences are decoded by `pynmeagps <https://pypi.org/project/pynmeagps/>`_ (pinned in
``requirements.txt``), chosen over ``pynmea2`` because it is actively maintained, knows the
NMEA 4.x fields (the RMC ``posMode`` indicator) and every talker ID (``GP``, ``GN``, ``GL``,
``GA``, ``GB``, ...), verifies the checksum itself, and returns typed values (``datetime.time``
and ``date``, signed decimal degrees). pynmeagps is lenient with broken fields (an unparsable
latitude becomes ``''``), so this module adds the checks a filter needs: a fix must have a time, a latitude and a longitude.

:func:`read_nmea_log` reads a whole log (a path, bytes or an iterable of lines) and returns a tidy
table, one row per epoch, with RMC and GGA of the same epoch merged, and a :class:`SkipReport`
of every line it did not use and why. No line stops the read. The reasons are

* ``non_utf8``: the line is not valid UTF-8 (or ASCII);
* ``truncated``: it starts with ``$`` but does not end with ``*hh`` (two hex digits);
* ``bad_checksum``: the XOR of the characters between ``$`` and ``*`` differs from ``hh``;
* ``malformed``: it is not a sentence (no ``$``), or a required field is missing or invalid
  (under a valid checksum too: minutes of latitude or longitude >= 60, a hemisphere other than
  ``N``/``S`` or ``E``/``W``, a negative speed over ground, a date that does not exist);
* ``no_fix``: RMC status ``V`` (void) or GGA quality 0, a valid sentence without a position;
* ``unsupported``: a valid sentence of another type (GSV, VTG, ...), ignored.

Geodesy. Geodetic (WGS 84) latitude/longitude to a local East-North-Up frame with
`pymap3d <https://pypi.org/project/pymap3d/>`_ and to UTM with `utm <https://pypi.org/project/utm/>`_.

Units and angles. Degrees exist only at this edge: the table gives latitude and longitude in
degrees (what geodesy libraries take) and everything else in SI: speed in m/s (NMEA knots times
1852/3600, :func:`knots_to_mps`) and course in radians. The NMEA *course over ground* :math:`\chi`
is measured from North, clockwise; the book's heading :math:`h` is measured from the +x (East)
axis, counter-clockwise, so :math:`h = \pi/2 - \chi` (:func:`course_to_heading`, the one place
this conversion is done).
"""
from __future__ import annotations

import datetime as _dt
import os
import re
from collections import Counter
from collections.abc import Iterable
from typing import NamedTuple

import numpy as np
import pymap3d
import utm
from pynmeagps import VALCKSUM, NMEAParseError, NMEAReader
from pynmeagps.nmeahelpers import calc_checksum

from .._validate import as_float_array
from ..ekf import wrap_angle as _wrap

__all__ = [
    "KNOT", "SKIP_REASONS", "NmeaFixes", "SkipReport",
    "nmea_checksum", "parse_sentence", "read_nmea_log", "format_rmc", "format_gga",
    "knots_to_mps", "mps_to_knots", "course_to_heading", "heading_to_course",
    "geodetic_to_enu", "enu_to_geodetic", "geodetic_to_utm", "utm_to_geodetic",
]

KNOT = 1852.0 / 3600.0
"""One knot in m/s (one nautical mile, 1852 m, per hour): 0.514444... m/s."""

SKIP_REASONS = ("non_utf8", "truncated", "bad_checksum", "malformed", "no_fix", "unsupported")
"""Every reason :func:`read_nmea_log` can give for not using a line."""

_TAIL = re.compile(r"\*([0-9A-Fa-f]{2})$")
_GGA_QUALITY_FROM_POSMODE = {"A": 1, "D": 2, "P": 3, "R": 4, "F": 5, "E": 6, "M": 7, "S": 8}


class NmeaFixes(NamedTuple):
    """A tidy table of fixes, one row per epoch, sorted by time; every column has shape ``(N,)``.

    Attributes
    ----------
    time : seconds (UTC) since midnight of the first date in the log (RMC dates; GGA carries
        none and takes the last RMC date seen, or day 0).
    lat, lon : geodetic latitude and longitude in degrees (north and east positive).
    speed : speed over ground in m/s (NaN where no RMC was read for the epoch).
    course : course over ground in radians, clockwise from North, in [0, 2 pi)
        (NaN where the field was empty or no RMC was read).
    quality : GGA fix quality (1 GPS, 2 DGPS, 4 RTK fixed, ...); from the RMC mode indicator when
        the epoch has no GGA (``A`` -> 1, ``D`` -> 2, ...; 1 when the field is absent).
    """

    time: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    speed: np.ndarray
    course: np.ndarray
    quality: np.ndarray


class SkipReport(NamedTuple):
    """The lines :func:`read_nmea_log` did not use.

    Attributes
    ----------
    counts : number of skipped lines per reason; every key of :data:`SKIP_REASONS` is present.
    lines : ``(line_number, reason)`` for each skipped line, 1-based line numbers.
    total : number of non-blank lines read.
    """

    counts: dict
    lines: list
    total: int

    @property
    def skipped(self) -> int:
        """Number of lines not used (all reasons)."""
        return sum(self.counts.values())


def nmea_checksum(body: str) -> str:
    """The NMEA checksum of ``body`` (the text between ``$`` and ``*``): XOR of its characters,
    as two upper-case hex digits. ``nmea_checksum("GPRMC,123519,...,W") == "6A"``."""
    if not isinstance(body, str):
        raise TypeError(f"body must be a str (the text between '$' and '*'), got {type(body).__name__}")
    return calc_checksum(body)


def _as_float(value) -> float:
    if value == "" or value is None:
        return float("nan")
    return float(value)


#: Field index (in the comma-split body, address = 0) of latitude, its hemisphere, longitude and
#: its hemisphere, per sentence type; the RMC date is field :data:`_RMC_DATE`.
_FIELDS = {"RMC": (3, 4, 5, 6), "GGA": (2, 3, 4, 5)}
_RMC_DATE = 9


def _minutes_valid(field: str) -> bool:
    """Whether an NMEA ``(d)ddmm.mmmm`` field is unsigned digits whose minutes are below 60."""
    if not field.replace(".", "", 1).isdigit():
        return False
    point = field.find(".")
    head = field if point < 0 else field[:point]
    return float(head[-2:] + field[len(head):]) < 60.0


def _position_fields_valid(fields: list[str], kind: str) -> bool:
    """The checks pynmeagps does not make on the raw position fields: hemisphere letters and
    minutes below 60 (it reads ``01175.000`` as 11 deg + 75/60 and ``Q`` as North)."""
    i_lat, i_ns, i_lon, i_ew = _FIELDS[kind]
    if len(fields) <= i_ew or fields[i_ns] not in ("N", "S") or fields[i_ew] not in ("E", "W"):
        return False
    return _minutes_valid(fields[i_lat]) and _minutes_valid(fields[i_lon])


def _seconds(t) -> float:
    return t.hour * 3600.0 + t.minute * 60.0 + t.second + t.microsecond * 1e-6


def parse_sentence(line: str | bytes) -> tuple[str, dict | None]:
    """Classify and decode one NMEA line.

    Parameters
    ----------
    line : one sentence, with or without the trailing CR LF.

    Returns
    -------
    (status, fields)
        ``status`` is ``"ok"`` or one of :data:`SKIP_REASONS`. For ``"ok"``, ``fields`` is a dict
        with ``type`` (``"RMC"`` or ``"GGA"``), ``talker``, ``time`` (seconds of the UTC day),
        ``date`` (a ``datetime.date`` or None), ``lat``, ``lon`` (degrees), ``speed`` (m/s,
        NaN for GGA), ``course`` (rad clockwise from North, NaN if empty or GGA) and ``quality``
        (int, None for RMC without mode field). Otherwise ``fields`` is None.

    A sentence with a valid checksum is still ``"malformed"`` if a field cannot be a reading:
    minutes of latitude or longitude >= 60, a hemisphere other than ``N``/``S`` (``E``/``W``), a
    negative speed over ground, or an RMC date that does not exist (31 February).

    Never raises for bad content; raises ``TypeError`` only if ``line`` is not str or bytes.

    Examples
    --------
    >>> from kftrack.sensors.gps import parse_sentence
    >>> status, fix = parse_sentence("$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A")
    >>> status, fix["type"], fix["time"], round(fix["lat"], 6), round(fix["lon"], 6)   # s of the UTC day, degrees
    ('ok', 'RMC', 45319.0, 48.1173, 11.516667)
    >>> round(fix["speed"], 6), round(fix["course"], 6)   # m/s (from 22.4 kn), rad clockwise from North
    (11.523556, 1.473058)
    >>> parse_sentence("$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6B")[0]
    'bad_checksum'
    """
    if isinstance(line, (bytes, bytearray)):
        try:
            line = bytes(line).decode("ascii")
        except UnicodeDecodeError:
            try:
                line = bytes(line).decode("utf-8")
            except UnicodeDecodeError:
                return "non_utf8", None
    elif not isinstance(line, str):
        raise TypeError(f"line must be str or bytes, got {type(line).__name__}")
    line = line.strip()
    if not line.startswith("$"):
        return "malformed", None
    tail = _TAIL.search(line)
    if tail is None:
        return "truncated", None
    if not line.isascii():
        return "malformed", None
    body = line[1:tail.start()]
    if calc_checksum(body) != tail.group(1).upper():
        return "bad_checksum", None
    fields = body.split(",")
    address = fields[0]
    if len(address) != 5 or not address.isalpha():
        return "malformed", None
    kind = address[2:]
    if kind not in ("RMC", "GGA"):
        return "unsupported", None
    try:
        msg = NMEAReader.parse(line, validate=VALCKSUM)
    except (NMEAParseError, ValueError, TypeError, IndexError, KeyError, AttributeError):
        return "malformed", None
    if msg is None:
        return "malformed", None
    t = getattr(msg, "time", "")
    if not isinstance(t, _dt.time):
        return "malformed", None
    if kind == "RMC":
        status = getattr(msg, "status", "")
        if status == "V":
            return "no_fix", None
        if status != "A":
            return "malformed", None
        quality = _GGA_QUALITY_FROM_POSMODE.get(getattr(msg, "posMode", ""), None)
        date = getattr(msg, "date", "")
        if not isinstance(date, _dt.date):
            if len(fields) > _RMC_DATE and fields[_RMC_DATE].strip():  # a date that does not exist
                return "malformed", None
            date = None
    else:
        quality = getattr(msg, "quality", "")
        if not isinstance(quality, int):
            return "malformed", None
        if quality == 0:
            return "no_fix", None
        date = None
    lat, lon = getattr(msg, "lat", ""), getattr(msg, "lon", "")
    if not isinstance(lat, (int, float)) or not isinstance(lon, (int, float)):
        return "malformed", None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        return "malformed", None
    if not _position_fields_valid(fields, kind):
        return "malformed", None
    speed = course = float("nan")
    if kind == "RMC":
        try:
            speed = _as_float(getattr(msg, "spd", "")) * KNOT
            course = np.deg2rad(_as_float(getattr(msg, "cog", ""))) % (2 * np.pi)
        except (TypeError, ValueError):
            return "malformed", None
        if np.isnan(speed) or speed < 0:
            return "malformed", None
    return "ok", {"type": kind, "talker": address[:2], "time": _seconds(t), "date": date,
                  "lat": float(lat), "lon": float(lon), "speed": float(speed), "course": float(course),
                  "quality": quality}


def _lines(source) -> Iterable[bytes | str]:
    if isinstance(source, str) and (source.lstrip().startswith("$") or "\n" in source or "\r" in source):
        raise ValueError(f"source must be a path, the log's bytes or an iterable of lines, but got a str that "
                         f"is log text, not a path ({source[:40]!r}...); pass a list of sentences ([sentence]) "
                         "or the text as bytes (text.encode())")
    if isinstance(source, (str, os.PathLike)):
        with open(source, "rb") as fh:
            data = fh.read()
        return data.splitlines()
    if isinstance(source, (bytes, bytearray)):
        return bytes(source).splitlines()
    if isinstance(source, Iterable):
        return source
    raise TypeError(f"source must be a path, bytes or an iterable of lines, got {type(source).__name__}")


def read_nmea_log(source) -> tuple[NmeaFixes, SkipReport]:
    """Read an NMEA 0183 log into a table of fixes; bad lines are skipped and counted.

    RMC and GGA sentences from any talker are used. Sentences of the same epoch (same UTC time
    of day and date) are merged into one row: position from the first sentence of the epoch,
    speed and course from RMC, quality from GGA. Dates come from RMC; the day counter also
    advances when the time of day steps back by more than 12 h (a midnight without RMC).

    Parameters
    ----------
    source : path of a log file (str or os.PathLike), its bytes, or an iterable of lines (str or
        bytes). A str is always a path: a str that is a sentence or several lines (it starts with
        ``$`` or holds a line break) raises ``ValueError``; wrap one sentence in a list.

    Returns
    -------
    (NmeaFixes, SkipReport)

    Examples
    --------
    >>> from kftrack.sensors.gps import read_nmea_log
    >>> lines = ["$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A", "garbage"]
    >>> fixes, report = read_nmea_log(lines)           # a path, bytes, or lines
    >>> len(fixes.time), report.total, report.counts["malformed"], report.lines
    (1, 2, 1, [(2, 'malformed')])
    """
    rows: dict[float, dict] = {}
    counts = Counter({r: 0 for r in SKIP_REASONS})
    skipped: list[tuple[int, str]] = []
    total = 0
    first_date = current_date = None
    day = 0
    last_tod = None
    for number, raw in enumerate(_lines(source), start=1):
        if isinstance(raw, (bytes, bytearray)):
            if not bytes(raw).strip():
                continue
        elif isinstance(raw, str):
            if not raw.strip():
                continue
        total += 1
        status, f = parse_sentence(raw)
        if status != "ok":
            counts[status] += 1
            skipped.append((number, status))
            continue
        if f["date"] is not None:
            if first_date is None:
                first_date = f["date"]
            current_date = f["date"]
            day = (current_date - first_date).days
        elif last_tod is not None and f["time"] < last_tod - 43200.0:
            day += 1
        last_tod = f["time"]
        key = round(day * 86400.0 + f["time"], 3)
        row = rows.setdefault(key, {"lat": f["lat"], "lon": f["lon"], "speed": np.nan,
                                    "course": np.nan, "quality": None, "gga": False})
        if f["type"] == "RMC":
            row["speed"], row["course"] = f["speed"], f["course"]
            if not row["gga"] and f["quality"] is not None:
                row["quality"] = f["quality"]
        else:
            row["quality"], row["gga"] = f["quality"], True
    keys = sorted(rows)
    col = {k: np.array([rows[t][k] for t in keys], dtype=float) for k in ("lat", "lon", "speed", "course")}
    quality = np.array([1 if rows[t]["quality"] is None else rows[t]["quality"] for t in keys], dtype=int)
    fixes = NmeaFixes(np.array(keys, dtype=float), col["lat"], col["lon"], col["speed"], col["course"], quality)
    return fixes, SkipReport(dict(counts), skipped, total)


def _dmm(value: float, width: int) -> tuple[str, bool]:
    """Degrees to NMEA ``(d)ddmm.mmmmm`` and whether the value is negative."""
    neg = value < 0
    minutes_total = round(abs(value) * 60.0, 5)
    deg, minutes = divmod(minutes_total, 60.0)
    return f"{int(deg):0{width}d}{minutes:08.5f}", neg


def _hhmmss(time_s: float) -> str:
    tod = float(time_s) % 86400.0
    h, rem = divmod(round(tod, 2), 3600.0)
    m, s = divmod(rem, 60.0)
    return f"{int(h):02d}{int(m):02d}{s:05.2f}"


def _sentence(body: str) -> str:
    return f"${body}*{calc_checksum(body)}"


def _check_talker(talker: str) -> str:
    if not (isinstance(talker, str) and len(talker) == 2 and talker.isalpha() and talker.isupper()):
        raise ValueError(f"talker must be two upper-case letters such as 'GP' or 'GN', got {talker!r}")
    return talker


def _check_latlon(lat_deg: float, lon_deg: float) -> tuple[float, float]:
    lat, lon = float(lat_deg), float(lon_deg)
    if not -90.0 <= lat <= 90.0:
        raise ValueError(f"lat_deg must be in [-90, 90] degrees, got {lat_deg!r}")
    if not -180.0 <= lon <= 180.0:
        raise ValueError(f"lon_deg must be in [-180, 180] degrees, got {lon_deg!r}")
    return lat, lon


def format_rmc(time_s: float, lat_deg: float, lon_deg: float, speed_mps: float, course_rad: float,
               date: _dt.date = _dt.date(2018, 11, 1), talker: str = "GP", status: str = "A") -> str:
    """One RMC sentence (without CR LF), with its checksum.

    Position to 1e-5 arc-minute (about 2 cm), speed to 0.001 kn, course to 0.01 degree.
    ``status="V"`` writes a void sentence with empty position, speed and course fields.
    ``course_rad`` is clockwise from North (NaN writes an empty field). NMEA 2.3 mode
    indicator ``A`` (autonomous) is appended.
    """
    _check_talker(talker)
    if status not in ("A", "V"):
        raise ValueError(f"status must be 'A' (valid) or 'V' (void), got {status!r}")
    date_s = f"{date.day:02d}{date.month:02d}{date.year % 100:02d}"
    if status == "V":
        return _sentence(f"{talker}RMC,{_hhmmss(time_s)},V,,,,,,,{date_s},,,N")
    lat, lon = _check_latlon(lat_deg, lon_deg)
    lat_s, south = _dmm(lat, 2)
    lon_s, west = _dmm(lon, 3)
    course = "" if np.isnan(course_rad) else f"{np.rad2deg(course_rad) % 360.0:.2f}"
    body = (f"{talker}RMC,{_hhmmss(time_s)},A,{lat_s},{'S' if south else 'N'},{lon_s},{'W' if west else 'E'},"
            f"{mps_to_knots(speed_mps):.3f},{course},{date_s},,,A")
    return _sentence(body)


def format_gga(time_s: float, lat_deg: float, lon_deg: float, quality: int = 1, talker: str = "GP",
               num_sv: int = 8, hdop: float = 1.0, alt_m: float = 0.0, sep_m: float = 0.0) -> str:
    """One GGA sentence (without CR LF), with its checksum; position as in :func:`format_rmc`."""
    _check_talker(talker)
    if not isinstance(quality, (int, np.integer)) or not 0 <= quality <= 8:
        raise ValueError(f"quality must be an integer GGA fix quality 0..8, got {quality!r}")
    lat, lon = _check_latlon(lat_deg, lon_deg)
    lat_s, south = _dmm(lat, 2)
    lon_s, west = _dmm(lon, 3)
    body = (f"{talker}GGA,{_hhmmss(time_s)},{lat_s},{'S' if south else 'N'},{lon_s},{'W' if west else 'E'},"
            f"{int(quality)},{int(num_sv):02d},{hdop:.1f},{alt_m:.1f},M,{sep_m:.1f},M,,")
    return _sentence(body)


def knots_to_mps(knots):
    """Speed in knots to m/s: multiply by :data:`KNOT` = 1852/3600 = 0.514444... (exact)."""
    return as_float_array(knots, "knots") * KNOT


def mps_to_knots(mps):
    """Speed in m/s to knots (inverse of :func:`knots_to_mps`)."""
    return as_float_array(mps, "mps") / KNOT


def course_to_heading(course):
    r"""Course over ground :math:`\chi` (rad, clockwise from North) to the book's heading
    :math:`h = \pi/2 - \chi` (rad, counter-clockwise from +x = East), wrapped to (-pi, pi].

    The velocity is then :math:`(v\cos h, v\sin h) = (v\sin\chi, v\cos\chi)` in (East, North).
    """
    return _wrap(np.pi / 2 - as_float_array(course, "course"))


def heading_to_course(heading):
    r"""Inverse of :func:`course_to_heading`: :math:`\chi = \pi/2 - h`, wrapped to [0, 2 pi)."""
    return np.mod(np.pi / 2 - as_float_array(heading, "heading"), 2 * np.pi)


def _latlon_arrays(lat_deg, lon_deg, name_lat="lat_deg", name_lon="lon_deg"):
    lat = as_float_array(lat_deg, name_lat)
    lon = as_float_array(lon_deg, name_lon)
    if np.any(np.abs(lat) > 90):
        raise ValueError(f"{name_lat} must be in [-90, 90] degrees, got values up to {np.max(np.abs(lat))!r}")
    if np.any(np.abs(lon) > 180):
        raise ValueError(f"{name_lon} must be in [-180, 180] degrees, got values up to {np.max(np.abs(lon))!r}")
    return lat, lon


def geodetic_to_enu(lat_deg, lon_deg, lat0_deg: float, lon0_deg: float, h=0.0, h0: float = 0.0):
    """WGS 84 geodetic coordinates to local East-North-Up metres about ``(lat0, lon0, h0)``.

    Uses ``pymap3d.geodetic2enu`` (exact, through ECEF). Returns ``(east, north, up)`` arrays
    with the broadcast shape of the inputs.
    """
    lat, lon = _latlon_arrays(lat_deg, lon_deg)
    _latlon_arrays(lat0_deg, lon0_deg, "lat0_deg", "lon0_deg")
    e, n, u = pymap3d.geodetic2enu(lat, lon, h, lat0_deg, lon0_deg, h0, deg=True)
    return np.asarray(e, dtype=float), np.asarray(n, dtype=float), np.asarray(u, dtype=float)


def enu_to_geodetic(east, north, lat0_deg: float, lon0_deg: float, up=0.0, h0: float = 0.0):
    """Inverse of :func:`geodetic_to_enu`: returns ``(lat_deg, lon_deg, h)``."""
    e = as_float_array(east, "east")
    n = as_float_array(north, "north")
    _latlon_arrays(lat0_deg, lon0_deg, "lat0_deg", "lon0_deg")
    lat, lon, h = pymap3d.enu2geodetic(e, n, up, lat0_deg, lon0_deg, h0, deg=True)
    return np.asarray(lat, dtype=float), np.asarray(lon, dtype=float), np.asarray(h, dtype=float)


def geodetic_to_utm(lat_deg, lon_deg, zone: int | None = None):
    """WGS 84 latitude/longitude (degrees) to UTM ``(easting, northing, zone, letter)`` in metres.

    Uses the ``utm`` package (Krüger series). Arrays must lie in one zone; ``zone`` forces a
    zone number (the hemisphere follows the sign of the first latitude). Pato Branco
    (26.2 S, 52.7 W) is in zone 22 J: false easting 500 km, false northing 10 000 km.
    """
    lat, lon = _latlon_arrays(lat_deg, lon_deg)
    if lat.ndim and lat.size and np.ptp(lat) > 0 and (lat.min() < 0 <= lat.max()):
        raise ValueError("lat_deg must not straddle the equator in one call (UTM hemispheres differ)")
    letter = None
    if zone is not None:
        letter = utm.latitude_to_zone_letter(float(np.ravel(lat)[0]))
    e, n, zn, zl = utm.from_latlon(lat, lon, force_zone_number=zone, force_zone_letter=letter)
    return np.asarray(e, dtype=float), np.asarray(n, dtype=float), int(zn), zl


def utm_to_geodetic(easting, northing, zone: int, letter: str):
    """Inverse of :func:`geodetic_to_utm`: returns ``(lat_deg, lon_deg)``."""
    e = as_float_array(easting, "easting")
    n = as_float_array(northing, "northing")
    if not isinstance(zone, (int, np.integer)) or not 1 <= zone <= 60:
        raise ValueError(f"zone must be an integer 1..60, got {zone!r}")
    lat, lon = utm.to_latlon(e, n, int(zone), letter, strict=False)
    return np.asarray(lat, dtype=float), np.asarray(lon, dtype=float)
