r"""A simulated rotating surveillance radar over recorded traffic: scans of range-bearing plots.

The radar sits at the origin of the east/north frame of a :class:`kftrack.adsb.TrafficWindow`
(the trajectories are real, the sensor is simulated). Its antenna turns **clockwise** at a constant
rate, one turn per ``period`` seconds; scan ``j`` starts at :math:`t_j = t_{start} + j\,T` with the
beam pointing north. The beam's compass azimuth (clockwise from north) is
:math:`\alpha(t) = 2\pi (t - t_j)/T`, so a target at compass azimuth :math:`\alpha` is seen at

.. math::

    t = t_j + T\,\frac{\alpha(p(t))}{2\pi}, \qquad \alpha(p) = (\pi/2 - \operatorname{atan2}(p_y, p_x)) \bmod 2\pi,

solved by fixed-point iteration on the target's interpolated position :math:`p(t)`: it contracts by
the ratio of the target's angular rate to the beam's, :math:`v/(r\,2\pi/T)`, below 0.1 for 250 m/s
at 2 km with T = 4.8 s, so ten iterations leave less than :math:`0.1^{10}\,T` s. Each aircraft
present and inside the coverage annulus ``min_range <= r <= max_range`` at that time is detected
with probability ``P_D``; its plot is
:math:`z = [r, \theta] + w`, :math:`\theta = \operatorname{atan2}(p_y, p_x)` (the math convention of
:class:`kftrack.sensors.radar.RangeBearing`), :math:`w \sim N(0, \operatorname{diag}(\sigma_r^2, \sigma_\theta^2))`,
the bearing wrapped to :math:`(-\pi, \pi]`. The range is horizontal (the 2-D model ignores the
aircraft's height). False alarms: a Poisson number with mean ``clutter_rate`` per scan, uniform over the
annulus (area :math:`\pi(r_{max}^2 - r_{min}^2)`), each at the time the beam passes its azimuth.
A target crossing north during a scan is seen twice (moving anticlockwise) or not at all (clockwise)
in that scan by a real antenna; here it is reported at most once per scan: at one solution of the
equation above, or not at all when there is none.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .._validate import check_rng, finite_scalar, positive_scalar
from ..ekf import wrap_angle

__all__ = ["Scan", "SurveillanceRadar", "truth_at_scan", "compass_azimuth"]

_TIME_TOL = 1e-6   # s: a detection time solves its equation to this (the iteration reaches ~1e-10 s)


class Scan(NamedTuple):
    """One antenna revolution's plots, sorted by time.

    Attributes
    ----------
    time : float
        Scan start, s (the beam points north).
    times : numpy.ndarray, shape (m,)
        Each detection's time, s, in ``[time, time + period)``.
    z : numpy.ndarray, shape (m, 2)
        ``[range m, bearing rad]`` (bearing counter-clockwise from east, in (-pi, pi]).
    origin : numpy.ndarray of int, shape (m,)
        Index into the window's ``ids`` of the aircraft that made the plot, -1 for clutter
        (for evaluation only; a tracker never reads it).
    """

    time: float
    times: np.ndarray
    z: np.ndarray
    origin: np.ndarray


def compass_azimuth(xy) -> np.ndarray:
    r"""Compass azimuth (clockwise from north, in :math:`[0, 2\pi)`) of east/north points ``xy`` ``(..., 2)``."""
    xy = np.asarray(xy, float)
    return np.mod(np.pi / 2 - np.arctan2(xy[..., 1], xy[..., 0]), 2 * np.pi)


def _probability(value, name: str, low_open: bool) -> float:
    v = finite_scalar(value, name)
    if not (0.0 < v <= 1.0 if low_open else 0.0 <= v <= 1.0):
        raise ValueError(f"{name} must be in {'(0, 1]' if low_open else '[0, 1]'}, got {value!r}")
    return v


class SurveillanceRadar:
    r"""A rotating 2-D surveillance radar at the origin (clockwise antenna, one turn per ``period``).

    Parameters
    ----------
    period : float
        Scan period T, s (> 0); default 4.8 s (an airport surveillance radar's 12.5 rpm).
    sigmas : (float, float)
        Standard deviations of range (m) and bearing (rad); default 50 m and 0.1 degree.
    P_D : float
        Detection probability of an aircraft in coverage, in (0, 1]; default 0.9.
    clutter_rate : float, optional
        Mean number of false alarms per scan (>= 0). Give this or ``clutter_density``; default 10.
    clutter_density : float, optional
        Mean number of false alarms per scan per m^2 of coverage (>= 0); then
        ``clutter_rate = clutter_density * pi (max_range^2 - min_range^2)``.
    max_range, min_range : float
        The coverage annulus, m; default 100 km and 2 km (0 <= min_range < max_range).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.adsb import load_traffic
    >>> from kftrack.sensors.surveillance import SurveillanceRadar
    >>> radar = SurveillanceRadar(period=4.8, sigmas=(50.0, np.deg2rad(0.1)), P_D=0.9, clutter_rate=10.0)
    >>> scans = radar.scans(load_traffic(), np.random.default_rng(0), t_start=0.0, t_end=60.0)
    >>> len(scans), scans[0].z.shape[1], bool(np.all(np.diff(scans[0].times) >= 0))
    (13, 2, True)
    >>> radar.measurement_model.sigmas == radar.sigmas
    True
    """

    def __init__(self, period: float = 4.8, sigmas=(50.0, math.radians(0.1)), P_D: float = 0.9,
                 clutter_rate: float | None = None, clutter_density: float | None = None,
                 max_range: float = 100e3, min_range: float = 2e3):
        self.period = positive_scalar(period, "period", "s")
        from .radar import RangeBearing   # imported here: importing this module does not import SymPy

        self.measurement_model = RangeBearing(sigmas=sigmas)   # validates sigmas (m, rad)
        self.sigmas = self.measurement_model.sigmas
        self.P_D = _probability(P_D, "P_D", low_open=True)
        self.max_range = positive_scalar(max_range, "max_range", "m")
        self.min_range = finite_scalar(min_range, "min_range")
        if not 0.0 <= self.min_range < self.max_range:
            raise ValueError(f"min_range must be in [0, max_range={self.max_range:g}) m, got {min_range!r}")
        self.area = math.pi * (self.max_range**2 - self.min_range**2)
        if clutter_rate is not None and clutter_density is not None:
            raise ValueError("give clutter_rate or clutter_density, not both")
        if clutter_density is not None:
            dens = finite_scalar(clutter_density, "clutter_density")
            if dens < 0:
                raise ValueError(f"clutter_density must be >= 0 (false alarms per scan per m^2), "
                                 f"got {clutter_density!r}")
            self.clutter_rate = dens * self.area
        else:
            rate = 10.0 if clutter_rate is None else finite_scalar(clutter_rate, "clutter_rate")
            if rate < 0:
                raise ValueError(f"clutter_rate must be >= 0 (false alarms per scan), got {clutter_rate!r}")
            self.clutter_rate = rate
        #: false alarms per scan per m^2 of coverage (the tracker's clutter intensity per scan)
        self.clutter_density = self.clutter_rate / self.area

    def __repr__(self) -> str:
        return (f"SurveillanceRadar(period={self.period:g}, sigmas=({self.sigmas[0]:g}, {self.sigmas[1]:g}), "
                f"P_D={self.P_D:g}, clutter_rate={self.clutter_rate:g}, max_range={self.max_range:g}, "
                f"min_range={self.min_range:g})")

    def in_coverage(self, xy) -> np.ndarray:
        """Boolean ``(k,)``: the points ``xy`` ``(k, 2)`` inside the annulus ``min_range <= r <= max_range``."""
        r = np.hypot(*np.asarray(xy, float).reshape(-1, 2).T)
        return (r >= self.min_range) & (r <= self.max_range)

    def detection_times(self, window, t_scan, iterations: int = 10):
        r"""Each present aircraft's beam-crossing time in the scans starting at ``t_scan`` (scalar or (n,)).

        Returns ``(scan (k,), index (k,), times (k,), xy (k, 2))``: the scan's position in
        ``t_scan``, aircraft indices into ``window.ids``, the times solving
        :math:`t = t_j + T\alpha(p(t))/2\pi`, and the true positions then. An aircraft absent at
        the scan start, or at an iterate (it left the window or is in a gap), is not detected.
        """
        t_scan = np.atleast_1d(np.asarray(t_scan, float))
        n_air = len(window.ids)
        scan = np.repeat(np.arange(t_scan.size), n_air)
        index = np.tile(np.arange(n_air), t_scan.size)
        present, xy, _ = window.states_at(index, t_scan[scan])
        scan, index, xy = scan[present], index[present], xy[present]
        for _ in range(iterations):
            t = t_scan[scan] + self.period * compass_azimuth(xy) / (2 * np.pi)
            present, xy, _ = window.states_at(index, t)
            scan, index, t, xy = scan[present], index[present], t[present], xy[present]
        t = t_scan[scan] + self.period * compass_azimuth(xy) / (2 * np.pi)
        present, xy, _ = window.states_at(index, t)
        scan, index, t, xy = scan[present], index[present], t[present], xy[present]
        # an aircraft crossing north clockwise during the scan has no solution (the iteration
        # jumps between the scan's two ends): the beam misses it in this scan
        solved = np.abs(t_scan[scan] + self.period * compass_azimuth(xy) / (2 * np.pi) - t) <= _TIME_TOL
        return scan[solved], index[solved], t[solved], xy[solved]

    def _simulate(self, window, rng: np.random.Generator, t_scan: np.ndarray) -> list[Scan]:
        """The scans starting at ``t_scan`` (n,), simulated together (vectorised over scans and aircraft)."""
        scan, index, t, xy = self.detection_times(window, t_scan)
        seen = self.in_coverage(xy) & (rng.random(index.size) < self.P_D)
        scan, index, t, xy = scan[seen], index[seen], t[seen], xy[seen]
        z = np.column_stack([np.hypot(xy[:, 0], xy[:, 1]), np.arctan2(xy[:, 1], xy[:, 0])])
        z = z + rng.standard_normal(z.shape) * np.asarray(self.sigmas)
        n_c = rng.poisson(self.clutter_rate, size=t_scan.size).astype(np.intp)  # int32 on WebAssembly: np.repeat needs intp
        scan_c = np.repeat(np.arange(t_scan.size), n_c)
        r_c = np.sqrt(rng.uniform(self.min_range**2, self.max_range**2, scan_c.size))
        az_c = rng.uniform(0.0, 2 * np.pi, scan_c.size)      # compass azimuth
        scans = np.concatenate([scan, scan_c])
        times = np.concatenate([t, t_scan[scan_c] + self.period * az_c / (2 * np.pi)])
        zz = np.concatenate([z, np.column_stack([r_c, np.pi / 2 - az_c])]).reshape(-1, 2)
        zz[:, 1] = wrap_angle(zz[:, 1])
        origin = np.concatenate([index, np.full(scan_c.size, -1)]).astype(np.int64)
        order = np.lexsort((times, scans))
        scans, times, zz, origin = scans[order], times[order], zz[order], origin[order]
        cuts = np.searchsorted(scans, np.arange(1, t_scan.size))
        return [Scan(float(ts), tj, zj, oj) for ts, tj, zj, oj in
                zip(t_scan, np.split(times, cuts), np.split(zz, cuts), np.split(origin, cuts))]

    def scan(self, window, rng: np.random.Generator, t_scan: float) -> Scan:
        """One scan starting at ``t_scan`` (see :meth:`scans`)."""
        return self._simulate(window, check_rng(rng), np.array([finite_scalar(t_scan, "t_scan")]))[0]

    def scans(self, window, rng: np.random.Generator, t_start: float | None = None,
              t_end: float | None = None) -> list[Scan]:
        r"""Simulate the scans starting at :math:`t_j = t_{start} + jT < t_{end}` over a traffic window.

        Parameters
        ----------
        window : kftrack.adsb.TrafficWindow
            The true trajectories (east/north m, the radar at the origin).
        rng : numpy.random.Generator
        t_start, t_end : float, optional
            s from the window start; default ``window.t0`` and ``window.t1 - period`` (so every scan
            ends inside the window).

        Returns
        -------
        list of Scan
            One per revolution; plots sorted by time (see the module docstring for the model).
        """
        if not hasattr(window, "truth_at") or not hasattr(window, "states_at"):
            raise TypeError(f"window must be a kftrack.adsb.TrafficWindow, got {type(window).__name__}")
        rng = check_rng(rng)
        t_start = window.t0 if t_start is None else finite_scalar(t_start, "t_start")
        t_end = window.t1 - self.period if t_end is None else finite_scalar(t_end, "t_end")
        if not t_end > t_start:
            raise ValueError(f"t_end must be > t_start, got t_start={t_start!r}, t_end={t_end!r}")
        n = int(math.ceil((t_end - t_start) / self.period - 1e-12))
        return self._simulate(window, rng, t_start + np.arange(n) * self.period)

    def truth_at_scan(self, window, scan: Scan) -> tuple[np.ndarray, np.ndarray]:
        """The aircraft present and in coverage at the scan start: ``(ids (k,) int into window.ids, xy (k, 2))``."""
        ids, xy, _ = window.truth_at(scan.time)
        inside = self.in_coverage(xy)
        return ids[inside], xy[inside]


def truth_at_scan(window, scan: Scan, radar: SurveillanceRadar | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The aircraft present at ``scan.time`` (in ``radar``'s coverage if given): ``(ids (k,), xy (k, 2))``."""
    if radar is not None:
        return radar.truth_at_scan(window, scan)
    ids, xy, _ = window.truth_at(scan.time)
    return ids, xy
