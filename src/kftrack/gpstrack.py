r"""The synthetic athletics-track world of chapter 13: two GPS receivers walked around an
IAAF 400 m track at Pato Branco, and the NMEA logs in ``data/gps_track/``.

The source study (Stahlschmidt 2018) has no raw data, so its setting is rebuilt:

* **Track.** IAAF standard 400 m track: straights of 84.39 m, inner-lane running line of radius
  36.80 m, lanes 1.22 m wide; the "outer lane" line is 6 lanes (7.32 m) further out. Laps are
  run counter-clockwise (inside on the left). The centre is placed at :data:`TRACK_ORIGIN`, near
  the UTFPR campus in Pato Branco (placed, not surveyed).
* **Runs.** Each run is one inner lap then one outer lap, walked at 1.5 m/s, fixes at 1 Hz,
  with 33 s between the laps to cross to the outer lane. 20 runs, 20 minutes apart.
* **Receivers** (:data:`RECEIVERS`). Each position error is a first-order Gauss–Markov process
  per axis (time constant ``tau``, stationary std ``sigma_gm``: bias-like, slowly varying)
  plus white noise ``sigma_white``; the velocity (hence speed and course) has white noise
  ``sigma_vel`` per axis. The Gauss–Markov errors of the two receivers are correlated with
  coefficient ``rho`` (same axis, same time), a parameter.

Layer: worlds (uses :mod:`kftrack.sensors.gps` for NMEA and geodesy; reads/writes ``data/``).
"""
from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .datasets import data_dir
from .ekf import wrap_angle
from .sensors.gps import (NmeaFixes, course_to_heading, enu_to_geodetic, format_gga, format_rmc,
                          geodetic_to_enu, heading_to_course, nmea_checksum, read_nmea_log)

__all__ = [
    "STRAIGHT", "INNER_RADIUS", "LANE_WIDTH", "LANE_SEPARATION", "TRACK_ORIGIN", "WALK_SPEED",
    "RUNS", "SEED", "RHO", "LOG_DATE", "Receiver", "RECEIVERS", "TrackRuns",
    "stadium_point", "lap_truth", "gauss_markov_errors", "simulate_track_runs", "error_covariance", "track_log_lines",
    "write_track_logs", "load_track_logs",
]

STRAIGHT = 84.39
"""Length of each straight (m), IAAF."""
INNER_RADIUS = 36.80
"""Radius of the inner-lane running line (m): kerb 36.50 m + 0.30 m."""
LANE_WIDTH = 1.22
"""IAAF lane width (m)."""
LANE_SEPARATION = 6 * LANE_WIDTH
"""Inner-to-outer lane distance measured in the thesis: 7.32 m (6 lanes)."""
TRACK_ORIGIN = (-26.1966, -52.6897)
"""Track centre (latitude, longitude in degrees), near UTFPR Pato Branco; placed, not surveyed."""
WALK_SPEED = 1.5
"""Walking speed (m/s); the thesis does not state it."""
RUNS = 20
SEED = 2018
"""Seed of the committed logs."""
RHO = -0.2
"""Correlation of the two receivers' Gauss–Markov errors in the committed logs (see chapter 13)."""
LOG_DATE = _dt.date(2018, 11, 1)
_START = 10 * 3600.0
_RUN_SPACING = 1200.0
_OUTER_OFFSET = 300.0
_VOID_EPOCHS = 3


class Receiver(NamedTuple):
    """A receiver's error model and NMEA output (``gga``: also writes GGA, not only RMC)."""

    name: str
    talker: str
    sigma_gm: float
    tau: float
    sigma_white: float
    sigma_vel: float
    gga: bool
    filename: str


RECEIVERS = (
    Receiver("MAX-8", "GN", sigma_gm=1.44, tau=120.0, sigma_white=0.30, sigma_vel=0.10, gga=True,
             filename="max8.nmea"),
    Receiver("NEO-6", "GP", sigma_gm=1.85, tau=120.0, sigma_white=0.40, sigma_vel=0.10, gga=False,
             filename="neo6.nmea"),
)
"""Two receivers standing in for the thesis's u-blox MAX-8 (multi-GNSS, talker GN) and NEO-6
(GPS only, talker GP). Standard deviations in m and m/s, ``tau`` in s.

Calibration (the thesis gives no error model): ``tau``, the white and the velocity noise are
assumed; the two ``sigma_gm`` were then set so that the *expected* per-run lane RMSE of the raw
receivers (2000 simulated runs from ``default_rng(777)``, nearest-point pairing) equals the
thesis's means: 1.886 m and 2.438 m (Monte Carlo standard error 0.012 and 0.016 m) for 1.8873
and 2.4352 m; and :data:`RHO`
so that the expected lane RMSE of the stacked filter with the thesis's tuning is 1.402 m for
1.4012 m. Chapter 13 checks this expectation on fresh runs; the committed 20-run logs are one
sample of the model, not a fit."""


class TrackRuns(NamedTuple):
    """Truth and measurements of the runs, local East-North frame about :data:`TRACK_ORIGIN`.

    ``truth_inner`` ``(Ti, 4)`` and ``truth_outer`` ``(To, 4)``: ``[x, y, v, h]`` (m, m, m/s, rad,
    heading counter-clockwise from East); the same for every run. ``inner`` ``(runs, Ti, r, 4)`` and
    ``outer`` ``(runs, To, r, 4)``: what each of the ``r`` receivers reported, in the same units.
    ``receivers``: the names, in order.
    """

    truth_inner: np.ndarray
    truth_outer: np.ndarray
    inner: np.ndarray
    outer: np.ndarray
    receivers: tuple


def stadium_point(s, radius: float, straight: float = STRAIGHT) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point at arc length ``s`` (m) along a stadium-shaped lane of bend ``radius`` run counter-clockwise.

    The straights are parallel to East, the bend centres at ``(+-straight/2, 0)``; ``s = 0`` is the
    start of the southern straight (heading East). Returns ``(east, north, heading)`` in m, m, rad.
    """
    s = np.mod(np.asarray(s, dtype=float), 2 * straight + 2 * np.pi * radius)
    half, arc = straight / 2, np.pi * radius
    e, n, h = np.empty_like(s), np.empty_like(s), np.empty_like(s)
    seg1 = s < straight
    seg2 = (s >= straight) & (s < straight + arc)
    seg3 = (s >= straight + arc) & (s < 2 * straight + arc)
    seg4 = s >= 2 * straight + arc
    e[seg1], n[seg1], h[seg1] = -half + s[seg1], -radius, 0.0
    phi = (s[seg2] - straight) / radius - np.pi / 2
    e[seg2], n[seg2], h[seg2] = half + radius * np.cos(phi), radius * np.sin(phi), phi + np.pi / 2
    u = s[seg3] - straight - arc
    e[seg3], n[seg3], h[seg3] = half - u, radius, np.pi
    phi = (s[seg4] - 2 * straight - arc) / radius + np.pi / 2
    e[seg4], n[seg4], h[seg4] = -half + radius * np.cos(phi), radius * np.sin(phi), phi + np.pi / 2
    return e, n, wrap_angle(h)


def lap_truth(radius: float, speed: float = WALK_SPEED, dt: float = 1.0) -> np.ndarray:
    """One lap at constant ``speed``, sampled every ``dt`` s from ``s = 0`` until the lap closes.
    Returns ``(T, 4)`` rows ``[x, y, v, h]``; ``T = ceil(lap length / (speed dt))``."""
    if not speed > 0 or not dt > 0 or not radius > 0:
        raise ValueError(f"radius, speed and dt must be positive, got {radius!r}, {speed!r}, {dt!r}")
    length = 2 * STRAIGHT + 2 * np.pi * radius
    s = np.arange(int(np.ceil(length / (speed * dt)))) * speed * dt
    e, n, h = stadium_point(s, radius)
    return np.stack([e, n, np.full_like(s, speed), h], -1)


def gauss_markov_errors(rng: np.random.Generator, n_steps: int, sigma, tau, rho: float = 0.0,
                        dt: float = 1.0, size: tuple = ()) -> np.ndarray:
    r"""Stationary first-order Gauss–Markov errors of ``r`` correlated sources.

    :math:`b_{k+1} = \phi b_k + \sqrt{1-\phi^2}\,\sigma\,w_k`, :math:`\phi = e^{-\Delta T/\tau}`, started
    from the stationary law; the driving noises (and the start) of sources i and j have correlation
    ``rho``, so :math:`\operatorname{corr}(b_i, b_j) = \rho` when the ``tau`` are equal.

    Parameters
    ----------
    sigma, tau : (r,) stationary standard deviations and time constants.
    size : leading shape (e.g. ``(runs,)``); the last axis of the result indexes the source.

    Returns
    -------
    ``(*size, n_steps, r)``
    """
    sigma = np.atleast_1d(np.asarray(sigma, dtype=float))
    tau = np.broadcast_to(np.asarray(tau, dtype=float), sigma.shape)
    r = sigma.size
    if not -1.0 / max(r - 1, 1) <= rho <= 1.0:
        raise ValueError(f"rho must be in [-1/(r-1), 1] for r={r} sources, got {rho!r}")
    C = np.full((r, r), rho) + (1 - rho) * np.eye(r)
    L = np.linalg.cholesky(C + 1e-12 * np.eye(r))
    w = rng.standard_normal(tuple(size) + (n_steps, r)) @ L.T
    phi = np.exp(-dt / tau)
    b = np.empty_like(w)
    b[..., 0, :] = sigma * w[..., 0, :]
    drive = np.sqrt(1 - phi**2) * sigma
    for k in range(1, n_steps):
        b[..., k, :] = phi * b[..., k - 1, :] + drive * w[..., k, :]
    return b


def _measure(truth, pos_err, vel_err):
    """Receiver outputs [x, y, v, h] from truth (T, 4) and errors (..., T, r, 2)."""
    t = truth[:, None, :]
    vx = t[..., 2] * np.cos(t[..., 3]) + vel_err[..., 0]
    vy = t[..., 2] * np.sin(t[..., 3]) + vel_err[..., 1]
    return np.stack([t[..., 0] + pos_err[..., 0], t[..., 1] + pos_err[..., 1], np.hypot(vx, vy),
                     np.arctan2(vy, vx)], -1)


def simulate_track_runs(rng: np.random.Generator, runs: int = RUNS, rho: float = RHO,
                        receivers=RECEIVERS, speed: float = WALK_SPEED) -> TrackRuns:
    """Simulate ``runs`` (inner lap, outer lap) pairs seen by ``receivers``, in local metres.

    The Gauss–Markov error runs continuously through a run (inner lap, 33 s crossing, outer lap);
    runs are independent. No NMEA: :func:`track_log_lines` formats these numbers.
    """
    truth_in = lap_truth(INNER_RADIUS, speed)
    truth_out = lap_truth(INNER_RADIUS + LANE_SEPARATION, speed)
    Ti, To = len(truth_in), len(truth_out)
    n_steps = int(_OUTER_OFFSET) + To
    sig = np.array([r.sigma_gm for r in receivers])
    tau = np.array([r.tau for r in receivers])
    white = np.array([r.sigma_white for r in receivers])[:, None]
    svel = np.array([r.sigma_vel for r in receivers])[:, None]
    nr = len(receivers)
    gm = np.stack([gauss_markov_errors(rng, n_steps, sig, tau, rho, size=(runs,)) for _ in range(2)], -1)
    pos = gm + white * rng.standard_normal((runs, n_steps, nr, 2))
    vel = svel * rng.standard_normal((runs, n_steps, nr, 2))
    off = int(_OUTER_OFFSET)
    inner = _measure(truth_in, pos[:, :Ti], vel[:, :Ti])
    outer = _measure(truth_out, pos[:, off:off + To], vel[:, off:off + To])
    return TrackRuns(truth_in, truth_out, inner, outer, tuple(r.name for r in receivers))


def error_covariance(receivers=RECEIVERS, rho: float = RHO, speed: float = WALK_SPEED) -> np.ndarray:
    r"""Covariance ``(4 r, 4 r)`` of the stacked receiver errors in ``[x, y, v, h]`` per receiver.

    Position: :math:`\sigma_{gm}^2 + \sigma_{white}^2` per axis, cross-receiver
    :math:`\rho\,\sigma_{gm,i}\sigma_{gm,j}`; speed :math:`\sigma_{vel}^2`; heading
    :math:`(\sigma_{vel}/v)^2` (small-angle, at walking ``speed``). This is the *marginal* covariance:
    the Gauss–Markov part is correlated in time, which a Kalman filter with this ``R`` ignores.
    """
    r = len(receivers)
    R = np.zeros((4 * r, 4 * r))
    for i, a in enumerate(receivers):
        for j, b in enumerate(receivers):
            c = a.sigma_gm**2 + a.sigma_white**2 if i == j else rho * a.sigma_gm * b.sigma_gm
            R[4 * i, 4 * j] = R[4 * i + 1, 4 * j + 1] = c
        R[4 * i + 2, 4 * i + 2] = a.sigma_vel**2
        R[4 * i + 3, 4 * i + 3] = (a.sigma_vel / speed) ** 2
    return R


def _corrupt(rng: np.random.Generator, line: str, kind: str) -> str | bytes:
    if kind == "bad_checksum":
        last = line[-1]
        return line[:-1] + ("0" if last != "0" else "1")
    if kind == "truncated":
        return line[: int(rng.integers(8, len(line) - 4))]
    if kind == "non_utf8":
        raw = bytearray(line.encode("ascii"))
        raw[int(rng.integers(1, len(raw) - 3))] = 0xFF
        return bytes(raw)
    if kind == "malformed_field":  # checksum right, latitude unreadable
        fields = line[1:line.index("*")].split(",")
        idx = 3 if fields[0].endswith("RMC") else 2
        fields[idx] = fields[idx][:2] + "x" + fields[idx][3:]
        body = ",".join(fields)
        return f"${body}*{nmea_checksum(body)}"
    return "GARBAGE " + line[1:20]  # malformed: not a sentence


_CORRUPTIONS = ("bad_checksum", "bad_checksum", "truncated", "truncated", "non_utf8", "malformed_field", "garbage")
"""Corrupted copies injected in each log, after randomly chosen valid lines."""


def track_log_lines(rng: np.random.Generator, data: TrackRuns | None = None, receivers=RECEIVERS) -> dict:
    """The NMEA lines of each receiver (``{filename: [str | bytes, ...]}``) for simulated runs.

    Per run: ``_VOID_EPOCHS`` (3) void epochs before the first fix (RMC status V, GGA quality 0),
    one GSV sentence (unsupported, ignored), then an RMC (and a GGA for receivers with ``gga``)
    per fix. Then the corrupted copies of ``_CORRUPTIONS`` are inserted. ``data`` defaults to
    :func:`simulate_track_runs` with ``rng``.
    """
    if data is None:
        data = simulate_track_runs(rng, receivers=receivers)
    lat0, lon0 = TRACK_ORIGIN
    runs = data.inner.shape[0]
    out = {}
    for j, rec in enumerate(receivers):
        lines: list = []
        for run in range(runs):
            t0 = _START + _RUN_SPACING * run
            for k in range(_VOID_EPOCHS, 0, -1):
                lines.append(format_rmc(t0 - k, 0, 0, 0, 0, LOG_DATE, rec.talker, status="V"))
                if rec.gga:
                    lines.append(format_gga(t0 - k, *TRACK_ORIGIN, quality=0, talker=rec.talker, num_sv=0,
                                            hdop=99.9))
            body = f"{rec.talker[:1]}PGSV,1,1,04"
            lines.append(f"${body}*{nmea_checksum(body)}")
            for lap, start in ((data.inner, t0), (data.outer, t0 + _OUTER_OFFSET)):
                z = lap[run, :, j]
                lat, lon, _ = enu_to_geodetic(z[:, 0], z[:, 1], lat0, lon0)
                course = heading_to_course(z[:, 3])
                for k in range(len(z)):
                    lines.append(format_rmc(start + k, lat[k], lon[k], z[k, 2], course[k], LOG_DATE, rec.talker))
                    if rec.gga:
                        lines.append(format_gga(start + k, lat[k], lon[k], 1, rec.talker, num_sv=9, hdop=1.1,
                                                alt_m=760.0, sep_m=2.0))
        valid = [i for i, s in enumerate(lines) if ",A," in s or ("GGA" in s and ",1,09," in s)]
        where = np.sort(rng.choice(valid, size=len(_CORRUPTIONS), replace=False))[::-1]
        for i, kind in zip(where, rng.permutation(_CORRUPTIONS)):
            lines.insert(int(i) + 1, _corrupt(rng, lines[i], str(kind)))
        out[rec.filename] = lines
    return out


def _directory(directory) -> Path:
    return Path(directory) if directory is not None else data_dir() / "gps_track"


def write_track_logs(directory: str | os.PathLike, seed: int = SEED) -> list[Path]:
    """Generate the logs with ``numpy.random.default_rng(seed)`` and write one file per receiver
    (CR LF line ends, as receivers send them) into ``directory``, created if missing. The folder
    is required, never the installed package's data: the committed files are
    ``write_track_logs("data/gps_track")`` from the repository's root (checked by a unit test).
    Returns the paths."""
    if not isinstance(directory, (str, os.PathLike)):
        raise TypeError(f"directory must be the folder to write into (str or os.PathLike), "
                        f"got {type(directory).__name__}")
    folder = Path(directory)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, lines in track_log_lines(np.random.default_rng(seed)).items():
        raw = b"".join((s if isinstance(s, bytes) else s.encode("ascii")) + b"\r\n" for s in lines)
        path = folder / name
        path.write_bytes(raw)
        paths.append(path)
    return paths


def _lap_rows(fixes: NmeaFixes, start: np.ndarray, n: int) -> np.ndarray:
    """Rows [x, y, v, h] for times start[run] + k, k < n; NaN where a fix is missing."""
    lat0, lon0 = TRACK_ORIGIN
    e, nn, _ = geodetic_to_enu(fixes.lat, fixes.lon, lat0, lon0)
    table = np.stack([e, nn, fixes.speed, course_to_heading(fixes.course)], -1)
    want = (start[:, None] + np.arange(n)[None, :]).ravel()
    idx = np.searchsorted(fixes.time, want)
    idx = np.clip(idx, 0, len(fixes.time) - 1)
    hit = np.abs(fixes.time[idx] - want) < 1e-3
    rows = np.where(hit[:, None], table[idx], np.nan)
    return rows.reshape(len(start), n, 4)


def load_track_logs(directory=None, receivers=RECEIVERS, speed: float = WALK_SPEED) -> tuple[TrackRuns, dict]:
    """Read the receivers' logs and cut them into runs and laps by the schedule.

    Returns ``(TrackRuns, {receiver name: SkipReport})``; the measurements are projected to the
    local East-North frame about :data:`TRACK_ORIGIN` (:func:`kftrack.sensors.gps.geodetic_to_enu`),
    speed in m/s and heading in the book's convention. An epoch missing from a log is a row of NaN.

    Examples
    --------
    >>> from kftrack.gpstrack import load_track_logs
    >>> runs, reports = load_track_logs()              # the two receivers' NMEA logs of data/gps_track/
    >>> runs.receivers, runs.inner.shape               # (runs, epochs of a lap, receivers, [x, y, v, h])
    (('MAX-8', 'NEO-6'), (20, 267, 2, 4))
    >>> sorted(reports)                                # one SkipReport per receiver
    ['MAX-8', 'NEO-6']
    """
    folder = _directory(directory)
    truth_in = lap_truth(INNER_RADIUS, speed)
    truth_out = lap_truth(INNER_RADIUS + LANE_SEPARATION, speed)
    inner, outer, reports = [], [], {}
    for rec in receivers:
        path = folder / rec.filename
        if not path.exists():
            raise FileNotFoundError(f"log {path} not found; write it with kftrack.gpstrack.write_track_logs(folder) "
                                    "(data/README.md)")
        fixes, report = read_nmea_log(path)
        reports[rec.name] = report
        n_runs = int(round((fixes.time.max() - _START) // _RUN_SPACING)) + 1 if len(fixes.time) else 0
        start = _START + _RUN_SPACING * np.arange(n_runs)
        inner.append(_lap_rows(fixes, start, len(truth_in)))
        outer.append(_lap_rows(fixes, start + _OUTER_OFFSET, len(truth_out)))
    runs = TrackRuns(truth_in, truth_out, np.stack(inner, 2), np.stack(outer, 2), tuple(r.name for r in receivers))
    return runs, reports

