r"""Multi-target tracking of many targets in clutter: track initiation, confirmation and deletion
around global nearest neighbour (GNN) or joint probabilistic data association (JPDA), scan by scan.

A **scan** is any object with ``time`` (scan start, s), ``times`` ``(m,)`` (each detection's own
time, e.g. when a rotating antenna passed the target) and ``z`` ``(m, d)`` (detections in the
sensor's frame, e.g. ``[range, bearing]`` of :class:`kftrack.sensors.radar.RangeBearing`), such
as :class:`kftrack.sensors.surveillance.Scan`; any other attribute (``origin``) is never read.
States are interleaved, ``[x, vx, y, vy]``.

Per scan and track (Bar-Shalom, Willett & Tian 2011, ch. 3, 6, 8; Blackman & Popoli 1999, ch. 6):

* **prediction** with the motion model (``F(dt)``, ``Q(dt)``) from the track's last time, the
  EKF measurement :math:`\hat z = h(x)`, :math:`H = \partial h/\partial x`,
  :math:`S = HPH^\top + R`, innovation :math:`\nu = z \ominus \hat z` (bearing wrapped);
* **gate** :math:`\nu^\top S^{-1}\nu \le \gamma = \chi^2_m{}^{-1}(P_G)`, after a coarse test
  per component (:math:`|\nu_k| \le \sqrt{\gamma S_{kk}}` is necessary, since
  :math:`\nu^\top S^{-1}\nu \ge \nu_k^2/S_{kk}`; the windows are widened by 1.5 for the
  linearisation) on range-sorted detections, so that no Python loop runs over track-detection
  pairs and only a few per cent of the pairs reach the exact gate;
* **GNN**: a track that shares no gated detection takes its cheapest one; the others go to one
  :func:`kftrack.association.gnn_assignment` with cost :math:`d^2 + \log|S|` and a per-track
  miss cost at the gate's edge :math:`\gamma + \max\log|S|` (over the track's pairs); then the
  EKF update (:func:`kftrack.kernels.ekf_update`) of each assigned track;
* **JPDA**: :func:`kftrack.association.jpda_update`, in one batched call for the tracks that share
  no gated detection (each its own run: the PDAF) and one call per gating cluster of the others
  (exact marginals; the EKF linearisation offset :math:`h(x) - Hx` carried by an augmented state
  ``[x, 1]`` so that the scan is shared);
  a cluster over the ``max_events`` guard falls back to *cheap JPDA* (Fitzgerald 1985),
  :math:`\beta_{tj} = G_{tj}/(\sum_{j'} G_{tj'} + \sum_{t'} G_{t'j} - G_{tj} + 1)` with
  :math:`G_{tj} = L_{tj}/L_{t0}` the likelihood ratio of the pair against a miss (exact for an
  isolated target: it is then the PDAF), counted in :attr:`Tracks.fallbacks`;
* **initiation**: detections left unassociated in two consecutive scans start a tentative track by
  two-point differencing (:func:`kftrack.trackmanagement.two_point_initiation`) of their
  Cartesian conversions (``sensor.to_cartesian``) when closer than
  :math:`v_{max}\,\Delta t + \sqrt{\gamma\,\mathrm{tr}(C_1 + C_2)}`, one to one by
  :func:`~kftrack.association.gnn_assignment` on the distance;
* **confirmation and deletion**: M-of-N (:func:`kftrack.trackmanagement.m_of_n_confirm` on the
  last ``N`` scans' hits) or the sequential track score
  (:func:`~kftrack.trackmanagement.score_increment`, :func:`~kftrack.trackmanagement.sprt_thresholds`);
  a confirmed track is deleted after ``M`` misses in its last ``N`` scans (M-of-N) or when its
  score falls ``|log(beta/(1-alpha))|`` below its peak (score), and any track whose position
  standard deviation :math:`\sqrt{P_{xx} + P_{yy}}` exceeds ``max_std``.

**Per-detection times.** Each track is first predicted to the scan's mean detection time for the
coarse test (widened by the range and bearing rates times the largest offset of a detection time
from that mean, and by the covariance grown over that offset). GNN then predicts the track to
each candidate detection's own time, gates and costs the pair there, and updates the assigned
track at its detection's time: exact. JPDA needs one prediction per track and cluster: the track
is predicted to the mean time of its candidate detections. With a rotating antenna the detections
near one target share its azimuth and hence nearly its time (a gate of a few tenths of a degree is
a few milliseconds of a 4 s scan), so the approximation costs far less than the noise. A track
with no detection in its gate keeps its prediction at the scan's mean detection time.

Python loops run over the births of a scan and the multi-target JPDA clusters only; the cost per
scan grows with the number of tracks and detections through vectorised array operations.
"""
from __future__ import annotations

import time as _time
from typing import NamedTuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from . import association as _assoc
from . import kernels as _k
from ._validate import as_float_array
from .trackmanagement import m_of_n_confirm, score_increment, sprt_thresholds, two_point_initiation

__all__ = ["TrackState", "Track", "Tracks", "MultiTargetTracker", "track_scans"]

_METHODS = ("gnn", "jpda", "phd")
_CSV_HEADER = ["id", "time", "confirmed", "end", "x", "vx", "y", "vy"] + [f"P{i}{j}" for i in range(4) for j in range(4)]


class TrackState(NamedTuple):
    """A track after a scan: ``id``, ``time`` of the state, ``x`` (4,), ``P`` (4, 4), ``confirmed``."""

    id: int
    time: float
    x: np.ndarray
    P: np.ndarray
    confirmed: bool


class Track(NamedTuple):
    """One track's history, one row per scan it lived through: ``id``, ``times`` (k,), ``x`` (k, 4),
    ``P`` (k, 4, 4) and ``confirmed`` (k,) bool (its status after that scan)."""

    id: int
    times: np.ndarray
    x: np.ndarray
    P: np.ndarray
    confirmed: np.ndarray


class Tracks:
    """The tracks of a scan sequence.

    Attributes
    ----------
    tracks : list of :class:`Track`, by id.
    ends : dict id -> time the track was deleted (``inf`` if alive after the last scan).
    fallbacks : number of JPDA clusters over the ``max_events`` guard, updated by cheap JPDA.
    seconds : (K,) wall-clock time of each scan's step (s).
    motion : the motion model (``F(dt)``, ``Q(dt)``), needed by :meth:`snapshot`.
    steps : the GM-PHD intensities (list of :class:`kftrack.phd.PHDStep`) with ``method="phd"``.
    """

    def __init__(self, tracks, ends, motion=None, fallbacks: int = 0, seconds=()):
        self.tracks = list(tracks)
        self.ends = dict(ends)
        self.motion = motion
        self.fallbacks = int(fallbacks)
        self.seconds = np.asarray(seconds, dtype=float)
        self.steps = None
        self._rows = None

    def __len__(self) -> int:
        return len(self.tracks)

    def __iter__(self):
        return iter(self.tracks)

    def __repr__(self) -> str:
        n_conf = sum(bool(t.confirmed.any()) for t in self.tracks)
        return f"Tracks({len(self.tracks)} tracks, {n_conf} ever confirmed, {self.fallbacks} JPDA fall-backs)"

    def snapshot(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Confirmed tracks at time ``t``: each track's latest state at or before ``t``, predicted
        to ``t`` with the motion model, if it was confirmed then and not deleted by ``t``.

        Returns ``ids`` (j,) int and ``x`` (j, 4)."""
        t = float(as_float_array(t, "t"))
        if self.motion is None:
            raise ValueError("snapshot needs the motion model: pass motion= to Tracks.from_csv")
        if not self.tracks:
            return np.zeros(0, dtype=int), np.zeros((0, 4))
        if self._rows is None:  # all rows, by track then time, built once
            n = np.array([len(tr.times) for tr in self.tracks])
            ids = np.repeat([tr.id for tr in self.tracks], n)
            times = np.concatenate([tr.times for tr in self.tracks])
            last = np.zeros(len(ids), dtype=bool)
            last[np.cumsum(n) - 1] = True
            until = np.append(times[1:], np.inf)  # the track's next row ...
            until[last] = [self.ends.get(int(tr.id), np.inf) for tr in self.tracks]  # ... or its deletion
            self._rows = (ids, times, np.concatenate([tr.x for tr in self.tracks]),
                          np.concatenate([tr.confirmed for tr in self.tracks]).astype(bool), until)
        ids, times, x, conf, until = self._rows
        # the row in force at t: at or before t, and before the track's next row (or its deletion)
        k = np.flatnonzero((times <= t) & (t < until) & conf)
        return ids[k], _k.mv(self.motion.F(t - times[k]), x[k])

    def to_csv(self, path) -> None:
        """Write one row per track and scan: ``id, time, confirmed, end, x, vx, y, vy, P00 .. P33``
        (``end`` the deletion time, ``inf`` if alive at the end). Read back with :meth:`from_csv`."""
        rows = [np.column_stack([np.full(len(tr.times), tr.id), tr.times, tr.confirmed.astype(float),
                                 np.full(len(tr.times), self.ends.get(tr.id, np.inf)), tr.x, tr.P.reshape(-1, 16)])
                for tr in self.tracks]
        data = np.concatenate(rows) if rows else np.zeros((0, len(_CSV_HEADER)))
        fmt = ["%d", "%.17g", "%d"] + ["%.17g"] * (len(_CSV_HEADER) - 3)
        np.savetxt(path, data, fmt=fmt, delimiter=",", header=",".join(_CSV_HEADER), comments="")

    @classmethod
    def from_csv(cls, path, motion=None) -> "Tracks":
        """Read a file written by :meth:`to_csv` (``motion`` for :meth:`snapshot`)."""
        with open(path) as fh:
            header = fh.readline().strip().split(",")
        if header != _CSV_HEADER:
            raise ValueError(f"path must be a CSV written by Tracks.to_csv (header {','.join(_CSV_HEADER[:5])},...), "
                             f"got header {','.join(header[:5])},...")
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        tracks, ends = [], {}
        for i in np.unique(data[:, 0]).astype(int):
            d = data[data[:, 0] == i]
            tracks.append(Track(int(i), d[:, 1], d[:, 4:8], d[:, 8:].reshape(-1, 4, 4), d[:, 2] > 0.5))
            ends[int(i)] = float(d[0, 3])
        return cls(tracks, ends, motion)


# --------------------------------------------------------------------------------------------
# argument checks (once, at the public boundary)
# --------------------------------------------------------------------------------------------
def _check_logic(value, name, kinds):
    if isinstance(value, tuple) and len(value) == 2 and "m_of_n" in kinds:
        value = ("m_of_n",) + value
    if not (isinstance(value, tuple) and len(value) == 3 and value[0] in kinds):
        raise ValueError(f"{name} must be (M, N), ('m_of_n', M, N) or ('score', alpha, beta), got {value!r}")
    if value[0] == "m_of_n":
        M, N = value[1], value[2]
        if isinstance(M, bool) or int(M) != M or int(N) != N or not 1 <= M <= N:
            raise ValueError(f"{name} must have integers 1 <= M <= N (M-of-N logic), got {value!r}")
        return ("m_of_n", int(M), int(N))
    a, b = float(value[1]), float(value[2])
    sprt_thresholds(a, b)
    return ("score", a, b)


def _check_sensor(sensor):
    for attr in ("h", "jacobian", "R", "to_cartesian"):
        if not hasattr(sensor, attr):
            raise TypeError(f"sensor must be a measurement model such as kftrack.sensors.radar.RangeBearing "
                            f"(with h, jacobian, R, to_cartesian), got {type(sensor).__name__} without {attr!r}")
    R = np.asarray(sensor.R, dtype=float)
    if R.ndim != 2 or R.shape[0] != R.shape[1]:
        raise ValueError(f"sensor.R must be a square (m, m) matrix, got shape {R.shape}")
    return R, tuple(getattr(sensor, "angle_components", ()))


def _check_motion(motion):
    if not (callable(getattr(motion, "F", None)) and callable(getattr(motion, "Q", None))):
        raise TypeError(f"motion must be a motion model with F(dt) and Q(dt), e.g. "
                        f"kftrack.models.ConstantVelocity(ndim=2, q=...), got {type(motion).__name__}")
    F = np.asarray(motion.F(1.0))
    if F.shape != (4, 4):
        raise ValueError(f"motion must have the state [x, vx, y, vy] (F(dt) of shape (4, 4)), got shape {F.shape}")


def _positive(value, name, what, allow_none=False):
    if value is None and allow_none:
        return None
    v = float(as_float_array(value, name))
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{name} ({what}) must be finite and > 0, got {value!r}")
    return v


# --------------------------------------------------------------------------------------------
# the tracker
# --------------------------------------------------------------------------------------------
class MultiTargetTracker:
    r"""Scan-by-scan multi-target tracker (streaming form of :func:`track_scans`).

    Parameters
    ----------
    method : ``"gnn"`` or ``"jpda"`` (``"phd"``: use :func:`track_scans`).
    sensor : measurement model with ``h(x)`` (..., m), ``jacobian(x)`` (..., m, 4), ``R`` (m, m),
        ``angle_components`` and ``to_cartesian(z) -> (p, C)``, e.g.
        :class:`kftrack.sensors.radar.RangeBearing`.
    motion : ``F(dt)``, ``Q(dt)`` broadcasting over an array of ``dt``, e.g.
        :class:`kftrack.models.ConstantVelocity` ``(ndim=2, q=...)``.
    P_D : detection probability in (0, 1].
    clutter_density : expected false alarms per scan per m² of Cartesian coverage (uniform in
        the plane, as :mod:`kftrack.phd` takes it), > 0; the tracker uses its density in
        measurement space, :math:`\lambda r` per m rad for a sensor with an angle component
        (the area element :math:`r\,dr\,d\theta`), :math:`\lambda` for a linear position sensor.
        Or a callable ``f(z (..., m)) -> (...)`` giving the density per unit measurement volume
        directly. Used by JPDA and the score; GNN with M-of-N logic does not need it (``None``).
    P_G : gate probability in (0, 1).
    confirmation : ``(M, N)`` (M hits in the last N scans confirm a tentative track; a tentative
        track not confirmed within N scans of its birth is deleted) or ``("score", alpha, beta)``
        (Wald's SPRT on the track score; ``alpha`` false-confirmation, ``beta`` true-deletion
        probability).
    deletion : ``(M, N)``: a confirmed track with M misses in its last N scans is deleted (with
        score-based confirmation the score's drop from its peak deletes instead).
    max_std : delete a track whose position standard deviation :math:`\sqrt{P_{xx}+P_{yy}}` (m)
        exceeds this (default: no limit).
    v_max : the largest speed (m/s) of a target, for the two-point initiation gate.
    initiate : start tracks from unassociated detections (False: only ``initial_tracks``).
    initial_tracks : list of ``(t, x (4,), P (4, 4))`` known starts, confirmed from the start.
    max_events : JPDA guard, the largest number of joint events of one cluster enumerated exactly.
    """

    def __init__(self, *, method: str = "gnn", sensor, motion, P_D: float, clutter_density=None,
                 P_G: float = 0.99, confirmation=(2, 3), deletion=(3, 3), max_std: float | None = None,
                 v_max: float = 400.0, initiate: bool = True, initial_tracks=(), max_events: int = 10_000):
        if method not in ("gnn", "jpda"):
            raise ValueError(f"method must be 'gnn' or 'jpda' for MultiTargetTracker ('phd' via track_scans), got {method!r}")
        self.R, self.angles = _check_sensor(sensor)
        _check_motion(motion)
        self.method, self.sensor, self.motion = method, sensor, motion
        self.P_D = _assoc._check_prob_detect(P_D)
        self.P_G = _assoc._check_prob_gate(P_G)
        self.confirmation = _check_logic(confirmation, "confirmation", ("m_of_n", "score"))
        self.deletion = _check_logic(deletion, "deletion", ("m_of_n",))
        if callable(clutter_density):
            self._lam = clutter_density
        elif clutter_density is None:
            if method == "jpda" or self.confirmation[0] == "score":
                raise ValueError(f"clutter_density must be given (> 0) for method={method!r} with "
                                 f"confirmation={confirmation!r}, got None")
            self._lam = None
        else:
            lam = _positive(clutter_density, "clutter_density", "false alarms per scan per m^2")
            if self.angles:  # range-bearing: the area element r dr dtheta
                self._lam = lambda z, lam=lam: lam * np.maximum(np.asarray(z)[..., 0], 0.0)
            else:
                self._lam = lambda z, lam=lam: np.full(np.shape(z)[:-1], lam)
        self.max_std = _positive(max_std, "max_std", "largest position standard deviation, m", allow_none=True)
        self.v_max = _positive(v_max, "v_max", "largest target speed, m/s")
        if isinstance(max_events, bool) or int(max_events) != max_events or max_events < 1:
            raise ValueError(f"max_events must be a positive integer, got {max_events!r}")
        self.max_events = int(max_events)
        self.initiate = bool(initiate)
        self.m = self.R.shape[0]
        self.gamma = _assoc.gate_threshold(self.P_G, self.m)
        if self.confirmation[0] == "score":
            self._sprt = sprt_thresholds(self.confirmation[1], self.confirmation[2])
        self._L = max(self.confirmation[2] if self.confirmation[0] == "m_of_n" else 1, self.deletion[2])
        # track arrays
        self._x = np.zeros((0, 4))
        self._P = np.zeros((0, 4, 4))
        self._t = np.zeros(0)
        self._id = np.zeros(0, dtype=int)
        self._conf = np.zeros(0, dtype=bool)
        self._hist = np.zeros((0, self._L), dtype=np.int8)  # 1 hit, 0 miss, -1 before birth
        self._age = np.zeros(0, dtype=int)
        self._score = np.zeros(0)
        self._peak = np.zeros(0)
        self._next_id = 0
        self._cand = (np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0))  # unassociated, last scan
        self._last_time = -np.inf
        self._records: list[tuple] = []
        self._ends: dict[int, float] = {}
        self.fallbacks = 0
        self._seconds: list[float] = []
        for k, item in enumerate(initial_tracks):
            try:
                t0, x0, P0 = item
            except (TypeError, ValueError):
                raise ValueError(f"initial_tracks[{k}] must be (t, x (4,), P (4, 4)), got {item!r}") from None
            x0 = as_float_array(x0, f"initial_tracks[{k}] x")
            P0 = as_float_array(P0, f"initial_tracks[{k}] P")
            if x0.shape != (4,) or P0.shape != (4, 4):
                raise ValueError(f"initial_tracks[{k}] must be (t, x (4,), P (4, 4)), got x of shape {x0.shape} "
                                 f"and P of shape {P0.shape}")
            self._add(x0[None], P0[None], np.array([float(t0)]), confirmed=True)
            self._last_time = max(self._last_time, float(t0))

    # ---------------------------------------------------------------------------------------
    def _add(self, x, P, t, confirmed):
        k = len(t)
        self._x = np.concatenate([self._x, x])
        self._P = np.concatenate([self._P, P])
        self._t = np.concatenate([self._t, t])
        self._id = np.concatenate([self._id, self._next_id + np.arange(k)])
        self._next_id += k
        self._conf = np.concatenate([self._conf, np.full(k, confirmed)])
        self._hist = np.concatenate([self._hist, np.full((k, self._L), -1, dtype=np.int8)])
        self._age = np.concatenate([self._age, np.zeros(k, dtype=int)])
        self._score = np.concatenate([self._score, np.zeros(k)])
        self._peak = np.concatenate([self._peak, np.zeros(k)])

    def _keep(self, keep, t_end):
        for i in self._id[~keep]:
            self._ends[int(i)] = t_end
        for name in ("_x", "_P", "_t", "_id", "_conf", "_hist", "_age", "_score", "_peak"):
            setattr(self, name, getattr(self, name)[keep])

    def _predict(self, idx, t):
        """Tracks ``idx`` (k,) predicted to times ``t`` (k,) from their last states."""
        dt = t - self._t[idx]
        return _k.kf_predict(self._x[idx], self._P[idx], self.motion.F(dt), self.motion.Q(dt))

    def _check_scan(self, scan):
        try:
            t_scan, times, z = scan.time, scan.times, scan.z
        except AttributeError:
            raise TypeError(f"scan must have attributes time, times (m,) and z (m, {self.m}) (e.g. a "
                            f"kftrack.sensors.surveillance.Scan), "
                            f"got {type(scan).__name__}") from None
        z = as_float_array(z, "scan.z")
        if z.size == 0:
            z = z.reshape(0, self.m)
        times = np.atleast_1d(as_float_array(times, "scan.times"))
        if times.size == 0:
            times = times.reshape(0)
        if z.ndim != 2 or z.shape[1] != self.m:
            raise ValueError(f"scan.z must have shape (m, {self.m}) (m = {self.m} from sensor.R), got shape {z.shape}")
        if times.shape != (len(z),):
            raise ValueError(f"scan.times must have shape ({len(z)},) (one time per row of scan.z), got shape {times.shape}")
        t_scan = float(as_float_array(t_scan, "scan.time"))
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(times)) and np.isfinite(t_scan)):
            raise ValueError("scan.time, scan.times and scan.z must be finite")
        first = min(t_scan, times.min(initial=np.inf))
        if first < self._last_time:
            raise ValueError(f"scans must be in time order: scan.time/scan.times start at {first!r}, before the "
                             f"previous scan's last time {self._last_time!r}")
        return t_scan, times, z

    # ---------------------------------------------------------------------------------------
    def step(self, scan) -> list[TrackState]:
        """Process one scan; returns the tracks alive after it (tentative and confirmed)."""
        return self._run(*self._check_scan(scan))

    def _run(self, t_scan, times, z) -> list[TrackState]:
        start = _time.perf_counter()
        self._step(t_scan, times, z)
        self._seconds.append(_time.perf_counter() - start)
        return [TrackState(int(i), float(t), x, P, bool(c))
                for i, t, x, P, c in zip(self._id, self._t, self._x, self._P, self._conf)]

    def tracks(self) -> Tracks:
        """All tracks so far, as :class:`Tracks`."""
        ends = dict(self._ends)
        for i in self._id:
            ends[int(i)] = np.inf
        if not self._records:
            return Tracks([], ends, self.motion, self.fallbacks, self._seconds)
        ids, ts, xs, Ps, cs = (np.concatenate(a) for a in zip(*self._records))
        order = np.argsort(ids, kind="stable")
        ids, ts, xs, Ps, cs = ids[order], ts[order], xs[order], Ps[order], cs[order]
        cut = np.flatnonzero(np.diff(ids)) + 1
        tracks = [Track(int(i[0]), t, x, P, c) for i, t, x, P, c in
                  zip(*(np.split(a, cut) for a in (ids, ts, xs, Ps, cs)))]
        return Tracks(tracks, ends, self.motion, self.fallbacks, self._seconds)

    def _step(self, t_scan, times, z):
        M, T = len(z), len(self._t)
        t_ref = float(times.mean()) if M else t_scan
        hit = np.zeros(T, dtype=bool)
        logN = np.zeros(T)
        used = np.zeros(M, dtype=bool)  # detections associated (GNN) or gated (JPDA)
        x_new, P_new, t_new = None, None, np.full(T, t_ref)
        if T:
            x_new, P_new = self._predict(np.arange(T), np.full(T, t_ref))
        if T and M:
            ti, dj = self._candidates(x_new, P_new, times, z, t_ref)
            if self.method == "gnn":
                self._gnn(ti, dj, times, z, x_new, P_new, t_new, hit, logN, used)
            else:
                self._jpda(ti, dj, times, z, x_new, P_new, t_new, hit, logN, used)
        if T:
            self._x, self._P, self._t = x_new, P_new, t_new
            self._manage(hit, logN, t_ref)
        self._last_time = max(t_scan, times.max(initial=-np.inf), self._last_time)
        if self.initiate:
            self._births(times[~used], z[~used])
        if len(self._t):
            self._records.append((self._id.copy(), self._t.copy(), self._x.copy(), self._P.copy(), self._conf.copy()))

    def _candidates(self, xr, Pr, times, z, t_ref):
        """Coarse test: pairs (track, detection) within per-component windows, vectorised."""
        T = len(xr)
        delta = float(np.max(np.abs(times - t_ref)))
        F, Q = self.motion.F(delta), self.motion.Q(delta)
        _, P_far = _k.kf_predict(xr, Pr, F, Q)  # covariance grown over the largest time offset
        zr, H = self.sensor.h(xr), self.sensor.jacobian(xr)
        S_far = _k.sym(_k.mm(_k.mm(H, P_far), _k.matrix_transpose(H))) + self.R
        S_now = _k.mm(_k.mm(H, Pr), _k.matrix_transpose(H)) + self.R
        var = np.maximum(np.diagonal(S_far, axis1=-2, axis2=-1), np.diagonal(S_now, axis1=-2, axis2=-1))
        xdot = np.zeros_like(xr)
        xdot[:, 0], xdot[:, 2] = xr[:, 1], xr[:, 3]
        zdot = _k.mv(H, xdot)
        half = 1.5 * np.sqrt(self.gamma * var) + np.abs(zdot) * delta  # (T, m); 1.5: linearisation margin
        order = np.argsort(z[:, 0], kind="stable")
        r_sorted = z[order, 0]
        lo = np.searchsorted(r_sorted, zr[:, 0] - half[:, 0], side="left")
        hi = np.searchsorted(r_sorted, zr[:, 0] + half[:, 0], side="right")
        counts = np.maximum(hi - lo, 0)
        ti = np.repeat(np.arange(T), counts)
        offs = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        dj = order[np.repeat(lo, counts) + offs]
        d = _k.residual(z[dj], zr[ti], self.angles)
        ok = np.all(np.abs(d) <= half[ti], axis=-1)
        return ti[ok], dj[ok]

    def _fine(self, ti, dj, tau, z):
        """Per pair: prediction to ``tau`` (k,), the EKF innovation, gain, NIS and log-likelihood."""
        xp, Pp = self._predict(ti, tau)
        H = self.sensor.jacobian(xp)
        y = _k.residual(z[dj], self.sensor.h(xp), self.angles)
        g = _k.kf_gain(Pp, H, self.R)
        nis, loglik = _k.kf_score(y, g)
        return xp, Pp, H, y, g, nis, loglik

    def _gnn(self, ti, dj, times, z, x_new, P_new, t_new, hit, logN, used):
        xp, Pp, _, _, g, nis, loglik = self._fine(ti, dj, times[dj], z)
        inside = nis <= self.gamma
        ti, dj, xp, Pp, nis, loglik, logdet = (a[inside] for a in (ti, dj, xp, Pp, nis, loglik, g.logdet))
        if not len(ti):
            return
        cost = nis + logdet
        T, M = len(x_new), len(z)
        # a track sharing no gated detection with another is a problem of its own; the others
        # form one assignment problem (the union of their clusters, independent blocks)
        shared = np.bincount(dj, minlength=M) > 1
        multi = (np.bincount(ti, weights=shared[dj], minlength=T) > 0)[ti]
        # isolated tracks: the cheapest gated detection (the assignment's answer with miss cost at the edge)
        chosen = np.zeros(len(ti), dtype=bool)
        single = np.flatnonzero(~multi)
        if len(single):
            o = single[np.lexsort((cost[single], ti[single]))]
            first = np.r_[True, ti[o][1:] != ti[o][:-1]]
            chosen[o[first]] = True
        if multi.any():
            pm = np.flatnonzero(multi)
            rows, r_idx = np.unique(ti[pm], return_inverse=True)
            cols, c_idx = np.unique(dj[pm], return_inverse=True)
            C = np.zeros((len(rows), len(cols)))
            G = np.zeros((len(rows), len(cols)), dtype=bool)
            C[r_idx, c_idx], G[r_idx, c_idx] = cost[pm], True
            miss = np.full(len(rows), -np.inf)
            np.maximum.at(miss, r_idx, self.gamma + logdet[pm])
            a = _assoc.gnn_assignment(C, G, miss)
            sel = a[r_idx] == c_idx
            chosen[pm[sel]] = True
        k = np.flatnonzero(chosen)
        i, j = ti[k], dj[k]
        u = _k.ekf_update(xp[k], Pp[k], z[j], self.sensor.h, self.sensor.jacobian, self.R, self.angles)
        x_new[i], P_new[i], t_new[i] = u.x, u.P, times[j]
        hit[i], logN[i], used[j] = True, loglik[k], True

    def _jpda(self, ti, dj, times, z, x_new, P_new, t_new, hit, logN, used):
        T, M = len(x_new), len(z)
        has = np.bincount(ti, minlength=T) > 0
        tau = np.where(has, np.bincount(ti, weights=times[dj], minlength=T) / np.maximum(np.bincount(ti, minlength=T), 1),
                       t_new)
        _, _, _, y, _, nis, loglik = self._fine(ti, dj, tau[ti], z)
        inside = nis <= self.gamma
        ti, dj, y, loglik = ti[inside], dj[inside], y[inside], loglik[inside]
        if not len(ti):
            return
        used[dj] = True
        hit[ti] = True
        best = np.full(T, -np.inf)
        np.maximum.at(best, ti, loglik)
        logN[hit] = best[hit]
        idx = np.flatnonzero(hit)
        xs, Ps = self._predict(idx, tau[idx])  # one prediction per track: its candidates' mean time
        t_new[idx] = tau[idx]
        H = self.sensor.jacobian(xs)
        zhat_b = self.sensor.h(xs)
        pos = np.full(T, -1)
        pos[idx] = np.arange(len(idx))
        shared = np.bincount(dj, minlength=M) > 1
        multi_track = np.bincount(ti, weights=shared[dj], minlength=T) > 0
        out_x, out_P = np.array(xs), np.array(Ps)
        # isolated tracks (no gated detection shared): one batched call, each its own run (T = 1),
        # its detections as linear pseudo-measurements H x + nu, so that z - H x is the EKF innovation
        single = idx[~multi_track[idx]]
        if len(single):
            ps = pos[single]
            sel = ~multi_track[ti]
            si, sj, sy = ti[sel], dj[sel], y[sel]
            o = np.lexsort((sj, si))
            si, sj, sy = si[o], sj[o], sy[o]
            cnt = np.bincount(pos[si], minlength=len(idx))[ps]
            rank = np.arange(len(si)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            row = np.repeat(np.arange(len(single)), cnt)
            Z = np.zeros((len(single), int(cnt.max()), self.m))
            mask = np.zeros(Z.shape[:2], dtype=bool)
            Z[row, rank] = _k.mv(H[pos[si]], xs[pos[si]]) + sy
            mask[row, rank] = True
            lam = self._lam(zhat_b[ps])
            if self.max_events >= 1 + Z.shape[1]:  # a lone target's events: missed or one of its detections
                u = _assoc.jpda_update(xs[ps][:, None], Ps[ps][:, None], Z, H[ps][:, None], self.R, P_D=self.P_D,
                                       P_G=self.P_G, clutter_density=lam, mask=mask, max_events=self.max_events)
                out_x[ps], out_P[ps] = u.x[:, 0], u.P[:, 0]
            else:  # a guard below a lone target's event count: the fall-back on each run over it
                for r, p in enumerate(ps):
                    Zr = Z[r, mask[r]]
                    if 1 + len(Zr) <= self.max_events:
                        u = _assoc.jpda_update(xs[p][None], Ps[p][None], Zr, H[p][None], self.R, P_D=self.P_D,
                                               P_G=self.P_G, clutter_density=lam[r], max_events=self.max_events)
                        xu, Pu = u.x, u.P
                    else:
                        xu, Pu = self._cheap_jpda(xs[p][None], Ps[p][None], Zr, H[p][None], lam[r])
                        self.fallbacks += 1
                    out_x[p], out_P[p] = xu[0], Pu[0]
        if not multi_track.any():
            x_new[idx], P_new[idx] = out_x, out_P
            return
        # tracks sharing detections: one jpda_update per gating cluster, the linearised measurement
        # offset carried by an augmented state [x, 1]: zhat = [H, h(x) - Hx] [x; 1] = h(x)
        Ha = np.concatenate([H, (zhat_b - _k.mv(H, xs))[..., None]], axis=-1)
        xa = np.concatenate([xs, np.ones((len(idx), 1))], axis=-1)
        Pa = np.zeros((len(idx), 5, 5))
        Pa[:, :4, :4] = Ps
        sel = multi_track[ti]
        n_comp, label = connected_components(
            coo_matrix((np.ones(int(sel.sum())), (ti[sel], T + dj[sel])), shape=(T + M, T + M)), directed=False)
        tracks_per = np.bincount(label[idx], minlength=n_comp)
        for comp in np.flatnonzero(tracks_per > 1):
            ct = idx[label[idx] == comp]
            cj = np.flatnonzero(label[T:] == comp)
            pc = pos[ct]
            Z = self._unwrap(z[cj], zhat_b[pc[0]])
            lam = float(np.mean(self._lam(Z)))
            try:
                u = _assoc.jpda_update(xa[pc], Pa[pc], Z, Ha[pc], self.R, P_D=self.P_D, P_G=self.P_G,
                                       clutter_density=lam, max_events=self.max_events)
                xu, Pu = u.x, u.P
            except ValueError as err:
                if "max_events" not in str(err):
                    raise
                xu, Pu = self._cheap_jpda(xa[pc], Pa[pc], Z, Ha[pc], lam)
                self.fallbacks += 1
            out_x[pc], out_P[pc] = xu[:, :4], Pu[:, :4, :4]
        x_new[idx], P_new[idx] = out_x, out_P

    def _unwrap(self, z, zhat):
        """Detections with their angle components moved within pi of ``zhat``, so that a plain
        difference is the wrapped residual."""
        return zhat + _k.residual(z, zhat, self.angles)

    def _cheap_jpda(self, xa, Pa, Z, Ha, lam):
        """Cheap JPDA (Fitzgerald 1985) marginals on one cluster, then the PDA-form update."""
        mask = np.ones(len(Z), dtype=bool)
        g, u = _assoc._gate(xa, Pa, Z[None], mask[None], Ha, self.R, self.P_G)
        logL0, logL, _, _ = _assoc._log_pda_terms(g, self.P_D, self.P_G, np.full(len(xa), lam))
        G = np.exp(logL - logL0[:, None])  # (T_c, M_c), 0 outside the gates
        denom = G.sum(1, keepdims=True) + G.sum(0, keepdims=True) - G + 1.0
        b = G / denom
        beta = np.concatenate([1.0 - b.sum(1, keepdims=True), b], axis=1)
        x, P, _ = _assoc._pda_combine(xa, Pa, u, g.nu, beta)
        return x, P

    def _manage(self, hit, logN, t_ref):
        self._age += 1
        self._hist = np.concatenate([self._hist[:, 1:], hit[:, None].astype(np.int8)], axis=1)
        keep = np.ones(len(hit), dtype=bool)
        kind = self.confirmation[0]
        if kind == "m_of_n":
            _, M, N = self.confirmation
            hits = self._hist[:, -N:] == 1
            ok = m_of_n_confirm(hits.T, M, N) >= 0
            tentative = ~self._conf
            self._conf |= tentative & ok
            keep &= ~(tentative & ~self._conf & (self._age >= N))
        else:
            lam = self._lam(self.sensor.h(self._x)) if self._lam is not None else None
            self._score = self._score + score_increment(hit, logN, P_D=self.P_D, P_G=self.P_G, clutter_density=lam)
            self._peak = np.maximum(self._peak, self._score)
            up, down = self._sprt
            tentative = ~self._conf
            self._conf |= tentative & (self._score >= up)
            keep &= ~(tentative & (self._score <= down))
            keep &= ~(self._conf & (self._score <= self._peak + down))
        if self.deletion[0] == "m_of_n" and kind == "m_of_n":
            _, M, N = self.deletion
            misses = self._hist[:, -N:] == 0
            keep &= ~(self._conf & (m_of_n_confirm(misses.T, M, N) >= 0))
        if self.max_std is not None:
            keep &= self._P[:, 0, 0] + self._P[:, 2, 2] <= self.max_std ** 2
        if not keep.all():
            self._keep(keep, t_ref)

    def _births(self, times, z):
        pc, Cc, tc = self._cand
        conv = self.sensor.to_cartesian(z)
        pn, Cn = np.asarray(conv[0]).reshape(-1, 2), np.asarray(conv[1]).reshape(-1, 2, 2)
        used = np.zeros(len(z), dtype=bool)
        if len(pc) and len(pn):
            radius = self.v_max * float(times.max() - tc.min()) + np.sqrt(
                self.gamma * (np.trace(Cc, axis1=1, axis2=2).max() + np.trace(Cn, axis1=1, axis2=2).max()))
            pairs = cKDTree(pc).query_ball_point(pn, r=radius)
            cnt = np.array([len(p) for p in pairs], dtype=int)
            jn = np.repeat(np.arange(len(pn)), cnt)
            ic = np.fromiter((i for p in pairs for i in p), dtype=int, count=int(cnt.sum()))
            if len(jn):
                dist = np.linalg.norm(pn[jn] - pc[ic], axis=1)
                dt = times[jn] - tc[ic]
                ok = (dt > 0) & (dist <= self.v_max * dt + np.sqrt(
                    self.gamma * (np.trace(Cc[ic], axis1=1, axis2=2) + np.trace(Cn[jn], axis1=1, axis2=2))))
                jn, ic, dist = jn[ok], ic[ok], dist[ok]
            if len(jn):
                rows, r_idx = np.unique(ic, return_inverse=True)
                cols, c_idx = np.unique(jn, return_inverse=True)
                C = np.zeros((len(rows), len(cols)))
                G = np.zeros(C.shape, dtype=bool)
                C[r_idx, c_idx], G[r_idx, c_idx] = dist, True
                a = _assoc.gnn_assignment(C, G, np.full(len(rows), C.max() + 1.0))
                take = a >= 0
                i_c, j_n = rows[take], cols[a[take]]
                xs, Ps, ts = [], [], []
                for i, j in zip(i_c, j_n):  # a loop over births only (few per scan)
                    x0, P0 = two_point_initiation(pc[i], pn[j], times[j] - tc[i], 0.5 * (Cc[i] + Cn[j]))
                    xs.append(x0)
                    Ps.append(P0)
                    ts.append(times[j])
                if xs:
                    self._add(np.array(xs), np.array(Ps), np.array(ts), confirmed=False)
                used[j_n] = True
        self._cand = (pn[~used], Cn[~used], times[~used])


# --------------------------------------------------------------------------------------------
# the public call
# --------------------------------------------------------------------------------------------
def track_scans(scans, *, method: str = "gnn", sensor, motion, P_D: float, clutter_density=None, P_G: float = 0.99,
                confirmation=(2, 3), deletion=(3, 3), max_std: float | None = None, v_max: float = 400.0,
                initiate: bool = True, initial_tracks=(), max_events: int = 10_000, **phd_options) -> Tracks:
    r"""Track many targets through a sequence of scans.

    Parameters
    ----------
    scans : sequence of scans with ``time``, ``times`` (m,) and ``z`` (m, d), e.g.
        :class:`kftrack.sensors.surveillance.Scan`.
    method : ``"gnn"``, ``"jpda"`` or ``"phd"``: the Gaussian-mixture PHD filter of
        :mod:`kftrack.phd` (:func:`kftrack.phd.phd_filter` with ``sensor``, ``motion``, ``P_D``,
        ``clutter_density`` and ``**phd_options``; the other arguments are not used). It keeps
        no identities: each extracted state is a one-row, confirmed :class:`Track` that ends at
        the next scan, ``P`` NaN, and the :class:`~kftrack.phd.PHDStep` list is ``Tracks.steps``.
    Other arguments: see :class:`MultiTargetTracker`.

    Returns
    -------
    Tracks
        The tracks (identity, times, states, covariances, status), :meth:`Tracks.snapshot`,
        :meth:`Tracks.to_csv`; ``fallbacks`` counts JPDA clusters over the guard.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.models import ConstantVelocity
    >>> from kftrack.sensors.radar import RangeBearing
    >>> from kftrack.multitarget import track_scans
    >>> from kftrack.sensors.surveillance import Scan
    >>> radar = RangeBearing(sigmas=(20.0, np.deg2rad(0.2)))
    >>> rng = np.random.default_rng(1)
    >>> truth = lambda t: np.array([20e3 + 200.0 * t, 200.0, 10e3, 0.0])       # [x, vx, y, vy]
    >>> scans = [Scan(4.0 * k, np.array([4.0 * k]), radar.simulate(truth(4.0 * k), rng)[None], np.zeros(1, int))
    ...          for k in range(8)]                   # one detection per scan, at the scan's start
    >>> tr = track_scans(scans, sensor=radar, motion=ConstantVelocity(ndim=2, q=1.0), P_D=1.0)
    >>> ids, x = tr.snapshot(28.0)
    >>> len(ids), bool(abs(x[0, 0] - truth(28.0)[0]) < 100.0)
    (1, True)
    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
    if method == "phd":
        try:
            from . import phd
        except ImportError:
            raise NotImplementedError("method='phd' needs kftrack.phd (the Gaussian-mixture PHD filter), "
                                      "which is not in this version of the package") from None
        return _phd_tracks(phd.phd_filter(scans, sensor, motion, P_D=P_D, clutter_density=clutter_density,
                                          **phd_options), motion)
    if phd_options:
        raise TypeError(f"track_scans got unexpected keyword arguments {sorted(phd_options)} (only method='phd' takes more)")
    if isinstance(scans, (str, bytes)) or not hasattr(scans, "__iter__"):
        raise TypeError(f"scans must be a sequence of scans (time, times, z), got {type(scans).__name__}")
    tracker = MultiTargetTracker(method=method, sensor=sensor, motion=motion, P_D=P_D, clutter_density=clutter_density,
                                 P_G=P_G, confirmation=confirmation, deletion=deletion, max_std=max_std, v_max=v_max,
                                 initiate=initiate, initial_tracks=initial_tracks, max_events=max_events)
    for k, scan in enumerate(scans):
        try:
            checked = tracker._check_scan(scan)
        except (ValueError, TypeError) as err:
            raise type(err)(f"scans[{k}]: {err}") from None
        tracker._run(*checked)
    return tracker.tracks()


def _phd_tracks(steps, motion) -> Tracks:
    """GM-PHD steps as unlabelled one-row tracks (so that snapshot, to_csv and plotting apply)."""
    tracks, ends, nid = [], {}, 0
    for k, st in enumerate(steps):
        end = steps[k + 1].time if k + 1 < len(steps) else np.inf
        for x in np.asarray(st.states).reshape(-1, 4):
            tracks.append(Track(nid, np.array([st.time]), x[None].copy(), np.full((1, 4, 4), np.nan), np.ones(1, bool)))
            ends[nid] = end
            nid += 1
    out = Tracks(tracks, ends, motion)
    out.steps = steps
    return out
