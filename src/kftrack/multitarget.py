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
  isolated target: it is then the PDAF), counted in ``Tracks.fallbacks``;
* **initiation**: a detection left unassociated stays a candidate for ``candidate_scans`` scans; a
  later unassociated detection closer to it than
  :math:`v_{max}\,\Delta t + \sqrt{\gamma\,\mathrm{tr}(C_1 + C_2)}` (:math:`\Delta t` the pair's
  own interval) starts a tentative track by two-point differencing
  (:func:`kftrack.trackmanagement.two_point_initiation`) of their Cartesian conversions
  (``sensor.to_cartesian``), one to one by :func:`~kftrack.association.gnn_assignment` on the
  distance (default 2 scans: a 2-of-3 start, the second detection may follow one missed scan);
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

**IMM modes per track** (``motion`` a :class:`kftrack.imm.IMM`, e.g. constant velocity and
coordinated turn): see :class:`MultiTargetTracker`.

Python loops run over the multi-target JPDA clusters (and an IMM's modes) only; the cost per
scan grows with the number of tracks and detections through vectorised array operations. The
arguments are checked once, at construction (and each scan's arrays as it arrives); the per-scan
work then calls the unchecked kernels (:mod:`kftrack.kernels`, the generated functions of a
``RangeBearing`` sensor and a ``ConstantVelocity`` model, the private PDAF pieces of
:mod:`kftrack.association`), which give the same bits as the checked public calls.
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
from . import models as _models
from ._validate import as_float_array
from .engines import PerDt
from .sensors import radar as _radar
from .trackmanagement import m_of_n_confirm, score_increment, sprt_thresholds

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
    """One track's history, one row per scan it lived through (an initial track's first row is its
    start): ``id``, ``times`` (k,), ``x`` (k, 4), ``P`` (k, 4, 4) and ``confirmed`` (k,) bool (its
    status after that scan)."""

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
    mu : with an IMM ``motion``, dict id -> (k, r) mode probabilities of the track after each of
        its rows (None otherwise; not written by :meth:`to_csv`).
    """

    def __init__(self, tracks, ends, motion=None, fallbacks: int = 0, seconds=()):
        self.tracks = list(tracks)
        self.ends = dict(ends)
        self.motion = motion
        self.fallbacks = int(fallbacks)
        self.seconds = np.asarray(seconds, dtype=float)
        self.steps = None
        self.mu = None
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


def _check_imm(est, turn_rate_std):
    """An :class:`kftrack.imm.IMM` as the motion: common state ``[x, vx, y, vy(, extra...)]``."""
    for attr in ("modes", "components", "N", "mu0", "_mix", "_combine", "_mixing_weights"):
        if not hasattr(est, attr):
            raise TypeError(f"motion must be a motion model with F(dt), Q(dt) or a kftrack.imm.IMM, got "
                            f"{type(est).__name__} without {attr!r}")
    if est.N < 4:
        raise ValueError(f"motion (an IMM) must have the common state [x, vx, y, vy, ...] (N >= 4), got N = {est.N}")
    for j, mode in enumerate(est.modes):
        if not callable(getattr(mode, "predict", None)):
            raise TypeError(f"motion.modes[{j}] must have predict(x, P, dt), got {type(mode).__name__}")
    std = _positive(turn_rate_std, "turn_rate_std", "prior standard deviation of the extra IMM state components")
    Pi = est.transition(1.0)
    # a fixed (r, r) matrix is shared by every track; a callable Pi(dt) is evaluated per track
    return std, (None if isinstance(getattr(est, "_transition", None), PerDt) else Pi)


def _imm_growth(est, cv):
    """``dt -> (F, Q)`` for the coarse test's covariance growth with an IMM: the constant-velocity
    ``F`` and the sum of the modes' ``Q(dt)`` on ``[x, vx, y, vy]`` (at least any one mode's)."""
    def FQ(dt):
        F, Q = cv(dt)
        for mode, comps in zip(est.modes, est.components):
            model = getattr(mode, "model", None)
            if tuple(comps[:4]) == (0, 1, 2, 3) and not getattr(mode, "state_dependent_Q", False) \
                    and callable(getattr(model, "Q", None)):
                Q = Q + np.asarray(model.Q(dt))[..., :4, :4]
        return F, Q
    return FQ


def _mode_predict(mode, x, P, dt):
    """Mode-matched prediction over per-track intervals ``dt`` (k,): a linear
    :class:`~kftrack.imm.KalmanMode` through its model's ``F(dt)``, ``Q(dt)`` (its own ``predict``
    caches one scalar ``dt``), any other mode through ``mode.predict``."""
    model = getattr(mode, "model", None)
    if type(mode).__name__ == "KalmanMode":
        return _k.kf_predict(x, P, model.F(dt), model.Q(dt))
    return mode.predict(x, P, dt)


def _check_motion(motion):
    if not (callable(getattr(motion, "F", None)) and callable(getattr(motion, "Q", None))):
        raise TypeError(f"motion must be a motion model with F(dt) and Q(dt), e.g. "
                        f"kftrack.models.ConstantVelocity(ndim=2, q=...), got {type(motion).__name__}")
    F = np.asarray(motion.F(1.0))
    if F.shape != (4, 4):
        raise ValueError(f"motion must have the state [x, vx, y, vy] (F(dt) of shape (4, 4)), got shape {F.shape}")


# --------------------------------------------------------------------------------------------
# the per-scan kernels, chosen once at construction (no checks inside: the arguments were checked)
# --------------------------------------------------------------------------------------------
def _sensor_kernels(sensor):
    """``(h, jacobian)`` of the sensor without per-call checks: for a
    :class:`~kftrack.sensors.radar.RangeBearing` its generated functions called directly (the
    same operations as ``sensor.h`` / ``sensor.jacobian``, so the same bits); for any other
    sensor its own methods."""
    if type(sensor) is not _radar.RangeBearing:
        return sensor.h, sensor.jacobian
    gen = _radar._generated(2)
    h_fn, H_fn = gen["h"]._exact, gen["H"]._exact
    idx, site = list(sensor.position_indices), np.asarray(sensor.sensor)

    def h(x):
        d = x[..., idx] - site
        return np.stack(h_fn(d[..., 0], d[..., 1]), axis=-1)

    def jacobian(x):
        d = x[..., idx] - site
        H = np.zeros(x.shape[:-1] + (2, x.shape[-1]))
        H[..., idx] = np.stack(H_fn(d[..., 0], d[..., 1]), axis=-1).reshape(x.shape[:-1] + (2, 2))
        return H

    return h, jacobian


def _motion_kernel(motion):
    """``dt (k,) -> (F (k, 4, 4), Q (k, 4, 4))`` without per-call checks: for
    :class:`~kftrack.models.ConstantVelocity` ``(ndim=2)`` its generated per-axis entries
    assembled directly (the same operations as ``motion.F`` / ``motion.Q``, so the same bits);
    for any other model ``motion.F(dt)``, ``motion.Q(dt)``."""
    if type(motion) is not _models.ConstantVelocity or motion.ndim != 2:
        return lambda dt: (motion.F(dt), motion.Q(dt))
    continuous = motion.noise == "continuous"
    q_fn = _models._kinematic(1)["Qc" if continuous else "Qd"]._exact
    scale = motion.q if continuous else motion.sigma2

    def FQ(dt):
        dt = np.asarray(dt, dtype=float)
        F = np.zeros(dt.shape + (4, 4))
        Q = np.zeros(dt.shape + (4, 4))
        e = q_fn(dt)  # per axis [Q00, Q01, Q10, Q11] / q
        for a in range(2):
            o = 2 * a
            F[..., o, o] = F[..., o + 1, o + 1] = 1.0
            F[..., o, o + 1] = dt
            for k, (i, j) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
                Q[..., o + i, o + j] = scale[a] * e[k]
        return F, Q

    return FQ


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
    candidate_scans : how many scans an unassociated detection stays an initiation candidate
        (a positive integer): the two detections of a two-point start may be up to this many
        scans apart. Default 2: the 2-of-3 history logic counted from a first detection (M-of-N
        logic, Blackman & Popoli 1999; 2-of-3 is the default of MATLAB's ``trackHistoryLogic``,
        which cites them) takes the second hit in either of the next 2 scans, so one missed
        scan between the two does not restart the start; 1: consecutive scans only.
    initiate : start tracks from unassociated detections (False: only ``initial_tracks``).
    initial_tracks : list of ``(t, x (4,), P (4, 4))`` known starts, confirmed from the start (and
        recorded as their tracks' first rows, at ``t``).
    max_events : JPDA guard, the largest number of joint events of one cluster enumerated exactly.
    turn_rate_std : with an IMM ``motion``, the prior standard deviation of the common state's
        components beyond ``[x, vx, y, vy]`` (the turn rate ``omega``, rad/s) of a new track
        (mean 0); default 0.05 rad/s (about a standard-rate turn, 3 deg/s).

    **IMM modes per track.** ``motion`` may be a :class:`kftrack.imm.IMM` (the estimator
    :func:`kftrack.imm.imm_filter` takes: its modes, e.g. :class:`~kftrack.imm.EKFMode` of
    :class:`~kftrack.models.ConstantVelocity` and of :class:`~kftrack.models.CoordinatedTurn`,
    the Markov matrix ``Pi`` and ``mu0``, ``components`` for modes of different dimension; the
    common state begins ``[x, vx, y, vy]``). Each track then carries its modes' estimates and
    mode probabilities :math:`\mu`; a prediction is the IMM's mixing and mode-matched prediction
    (``Pi(dt)`` of each track's own interval); the measurement model is the tracker's ``sensor``
    (the modes' own ``h``, ``R`` are not used). The reported ``x``, ``P`` are the combined
    (moment-matched) estimate's first four components. Gating and the coarse test use the
    combined prediction. **GNN**: the cost of a pair is
    :math:`-2\log\sum_j \bar c_j N(\nu_j; 0, S_j) - m\log 2\pi` (the IMM's mixed likelihood;
    :math:`d^2 + \log|S|` for one mode), then each mode's EKF update and :math:`\mu_j \propto \bar c_j N(\nu_j; 0, S_j)`, as :meth:`kftrack.imm.IMM.update`.
    **JPDA**: an isolated track takes the IMM-PDAF update (the equations of
    :func:`kftrack.association.imm_pdaf_update`, each mode linearised at its own prediction:
    a PDAF per mode, :math:`\mu_j \propto \bar c_j\Lambda_j`); in a multi-target cluster the
    marginals :math:`\beta_{tj}` are computed once on the tracks' combined predictions (exact
    JPDA, or cheap JPDA over the guard) and each mode is updated in PDA form with those
    :math:`\beta` and its own innovations, its likelihood :math:`\Lambda_j` that of its own
    PDAF on the cluster's detections (an approximation: the exact IMM-JPDA enumerates joint
    events per mode combination). Mode probabilities: :meth:`Tracks.mu` per track, and
    :attr:`mode_probabilities` while streaming. :meth:`Tracks.snapshot` extrapolates the
    combined state in a straight line (constant velocity).
    """

    def __init__(self, *, method: str = "gnn", sensor, motion, P_D: float, clutter_density=None,
                 P_G: float = 0.99, confirmation=(2, 3), deletion=(3, 3), max_std: float | None = None,
                 v_max: float = 400.0, initiate: bool = True, initial_tracks=(), max_events: int = 10_000,
                 turn_rate_std: float = 0.05, candidate_scans: int = 2):
        if method not in ("gnn", "jpda"):
            raise ValueError(f"method must be 'gnn' or 'jpda' for MultiTargetTracker ('phd' via track_scans), got {method!r}")
        self.R, self.angles = _check_sensor(sensor)
        self._imm = None
        if hasattr(motion, "modes"):
            self._imm = motion
            self._omega_std, self._Pi = _check_imm(motion, turn_rate_std)
            r = len(motion.modes)
            self._mx = [np.zeros((0, len(c))) for c in motion.components]
            self._mP = [np.zeros((0, len(c), len(c))) for c in motion.components]
            self._logmu = np.zeros((0, r))
            self._mu_records: list[np.ndarray] = []
            self._snapshot_motion = _models.ConstantVelocity(ndim=2, q=0.0)
            self._FQ = _imm_growth(motion, _motion_kernel(self._snapshot_motion))
        else:
            _check_motion(motion)
            self._FQ = _motion_kernel(motion)
            self._snapshot_motion = motion
        self.method, self.sensor, self.motion = method, sensor, motion
        self._h, self._H = _sensor_kernels(sensor)
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
        if isinstance(candidate_scans, bool) or not isinstance(candidate_scans, (int, np.integer)) or candidate_scans < 1:
            raise ValueError(f"candidate_scans (scans an unassociated detection stays an initiation candidate) must be "
                             f"a positive integer, got {candidate_scans!r}")
        self.candidate_scans = int(candidate_scans)
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
        # initiation candidates: unassociated detections' positions, covariances, times, age in scans
        self._cand = (np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0), np.zeros(0, dtype=int))
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
            N = self._imm.N if self._imm is not None else 4
            if not (x0.shape == (4,) and P0.shape == (4, 4) or x0.shape == (N,) and P0.shape == (N, N)):
                raise ValueError(f"initial_tracks[{k}] must be (t, x (4,), P (4, 4))"
                                 + (f" or (t, x ({N},), P ({N}, {N}))" if N > 4 else "")
                                 + f", got x of shape {x0.shape} and P of shape {P0.shape}")
            self._add(x0[None], P0[None], np.array([float(t0)]), confirmed=True)
            self._last_time = max(self._last_time, float(t0))
        if len(self._t):  # the initial tracks' first rows: their starts (so that snapshot(t0) reports them)
            self._record()

    # ---------------------------------------------------------------------------------------
    def _add(self, x, P, t, confirmed):
        k = len(t)
        if self._imm is not None:  # every mode starts from (x, P), the extra components (omega) from the prior
            est, N = self._imm, self._imm.N
            xN, PN = np.zeros((k, N)), np.zeros((k, N, N))
            xN[:, :x.shape[1]], PN[:, :x.shape[1], :x.shape[1]] = x, P
            extra = np.arange(x.shape[1], N)
            PN[:, extra, extra] = self._omega_std ** 2
            for j, c in enumerate(est.components):
                c = np.array(c)
                self._mx[j] = np.concatenate([self._mx[j], xN[:, c]])
                self._mP[j] = np.concatenate([self._mP[j], PN[:, c[:, None], c]])
            with np.errstate(divide="ignore"):
                logmu = np.broadcast_to(np.log(est.mu0), (k, est.r))
            self._logmu = np.concatenate([self._logmu, logmu])
            _, xc, Pc = est._combine(logmu, [xN[:, np.array(c)] for c in est.components],
                                     [PN[:, np.array(c)[:, None], np.array(c)] for c in est.components])
            x, P = xc[:, :4], Pc[:, :4, :4]
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
        if self._imm is not None:
            self._mx, self._mP = [a[keep] for a in self._mx], [b[keep] for b in self._mP]
            self._logmu = self._logmu[keep]

    def _predict(self, idx, t, modes=False):
        """Tracks ``idx`` (k,) predicted to times ``t`` (k,) from their last states: ``(x, P)``,
        with ``modes=True`` also the IMM's ``(xs, Ps, log_cbar)`` (None without an IMM)."""
        if self._imm is None:
            F, Q = self._FQ(t - self._t[idx])
            out = _k.kf_predict(self._x[idx], self._P[idx], F, Q)
            return out + (None,) if modes else out
        est, dt = self._imm, t - self._t[idx]
        Pi = self._Pi if self._Pi is not None else np.stack(
            [est.transition(float(d)) for d in dt] or [np.eye(est.r)])[:len(dt)]
        w, log_cbar = est._mixing_weights(self._logmu[idx], Pi)
        x0, P0 = est._mix(w, [a[idx] for a in self._mx], [b[idx] for b in self._mP])
        pred = [_mode_predict(m, a, b, dt) for m, a, b in zip(est.modes, x0, P0)]
        xs, Ps = [p[0] for p in pred], [p[1] for p in pred]
        _, x, P = est._combine(log_cbar, xs, Ps)
        out = (x[..., :4], P[..., :4, :4])
        return out + ((xs, Ps, log_cbar),) if modes else out

    def _imm_update(self, xs, Ps, log_cbar, loglik):
        r"""Mode probabilities :math:`\mu_j \propto \bar c_j \Lambda_j` and the combination, as
        :meth:`kftrack.imm.IMM.update`: returns ``(x (k, 4), P (k, 4, 4), log_mu (k, r))``."""
        joint = log_cbar + loglik
        log_mu = joint - _k.logsumexp(joint, axis=-1, keepdims=True)
        _, x, P = self._imm._combine(log_mu, xs, Ps)
        return x[..., :4], P[..., :4, :4], log_mu

    @property
    def mode_probabilities(self) -> tuple[np.ndarray, np.ndarray]:
        """With an IMM ``motion``: ``(ids (T,), mu (T, r))`` of the tracks alive now."""
        if self._imm is None:
            raise ValueError("mode_probabilities needs an IMM motion (kftrack.imm.IMM), got a single model")
        return self._id.copy(), np.exp(self._logmu)

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
        self._run(*self._check_scan(scan))
        return [TrackState(int(i), float(t), x, P, bool(c))
                for i, t, x, P, c in zip(self._id, self._t, self._x, self._P, self._conf)]

    def _run(self, t_scan, times, z) -> None:
        start = _time.perf_counter()
        self._step(t_scan, times, z)
        self._seconds.append(_time.perf_counter() - start)

    def tracks(self) -> Tracks:
        """All tracks so far, as :class:`Tracks`."""
        ends = dict(self._ends)
        for i in self._id:
            ends[int(i)] = np.inf
        if not self._records:
            return Tracks([], ends, self._snapshot_motion, self.fallbacks, self._seconds)
        ids, ts, xs, Ps, cs = (np.concatenate(a) for a in zip(*self._records))
        order = np.argsort(ids, kind="stable")
        ids, ts, xs, Ps, cs = ids[order], ts[order], xs[order], Ps[order], cs[order]
        cut = np.flatnonzero(np.diff(ids)) + 1
        tracks = [Track(int(i[0]), t, x, P, c) for i, t, x, P, c in
                  zip(*(np.split(a, cut) for a in (ids, ts, xs, Ps, cs)))]
        out = Tracks(tracks, ends, self._snapshot_motion, self.fallbacks, self._seconds)
        if self._imm is not None:
            mus = np.split(np.concatenate(self._mu_records)[order], cut)
            out.mu = {tr.id: mu for tr, mu in zip(tracks, mus)}
        return out

    def _step(self, t_scan, times, z):
        M, T = len(z), len(self._t)
        t_ref = float(times.mean()) if M else t_scan
        hit = np.zeros(T, dtype=bool)
        logN = np.zeros(T)
        used = np.zeros(M, dtype=bool)  # detections associated (GNN) or gated (JPDA)
        x_new, P_new, t_new, m_new = None, None, np.full(T, t_ref), None
        if T:
            x_new, P_new, m_new = self._predict(np.arange(T), np.full(T, t_ref), modes=True)
            if m_new is not None:  # IMM: (xs, Ps, log_mu) of every track, predicted; updated rows replaced
                m_new = (list(m_new[0]), list(m_new[1]), m_new[2])
        if T and M:
            ti, dj = self._candidates(x_new, P_new, times, z, t_ref)
            if self.method == "gnn":
                self._gnn(ti, dj, times, z, x_new, P_new, t_new, hit, logN, used, m_new)
            else:
                self._jpda(ti, dj, times, z, x_new, P_new, t_new, hit, logN, used, m_new)
        if T:
            self._x, self._P, self._t = x_new, P_new, t_new
            if m_new is not None:
                self._mx, self._mP, self._logmu = m_new
            self._manage(hit, logN, t_ref)
        self._last_time = max(t_scan, times.max(initial=-np.inf), self._last_time)
        if self.initiate:
            self._births(times[~used], z[~used])
        if len(self._t):
            self._record()

    def _record(self):
        self._records.append((self._id.copy(), self._t.copy(), self._x.copy(), self._P.copy(), self._conf.copy()))
        if self._imm is not None:
            self._mu_records.append(np.exp(self._logmu))

    def _candidates(self, xr, Pr, times, z, t_ref):
        """Coarse test: pairs (track, detection) within per-component windows, vectorised."""
        T = len(xr)
        delta = float(np.max(np.abs(times - t_ref)))
        F, Q = self._FQ(delta)
        _, P_far = _k.kf_predict(xr, Pr, F, Q)  # covariance grown over the largest time offset
        zr, H = self._h(xr), self._H(xr)
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
        r"""Per pair: prediction to ``tau`` (k,), the EKF innovation, gain, NIS and log-likelihood,
        ``log|S|`` and the IMM's modes (None without one). With an IMM the NIS is that of the
        combined prediction, the log-likelihood the mixture's :math:`\log\sum_j \bar c_j
        N(\nu_j; 0, S_j)` and ``logdet`` the value that makes ``nis + logdet`` its
        :math:`-2\log L - m\log 2\pi`."""
        xp, Pp, modes = self._predict(ti, tau, modes=True)
        H = self._H(xp)
        y = _k.residual(z[dj], self._h(xp), self.angles)
        g = _k.kf_gain(Pp, H, self.R)
        nis, loglik = _k.kf_score(y, g)
        if modes is None:
            return xp, Pp, H, y, g, nis, loglik, g.logdet, None
        ll = np.stack([_k.kf_score(_k.residual(z[dj], self._h(a), self.angles), _k.kf_gain(b, self._H(a), self.R))[1]
                       for a, b in zip(modes[0], modes[1])], axis=-1)
        loglik = _k.logsumexp(modes[2] + ll, axis=-1)
        return xp, Pp, H, y, g, nis, loglik, -2.0 * loglik - self.m * _assoc._LOG_2PI - nis, modes

    def _gnn(self, ti, dj, times, z, x_new, P_new, t_new, hit, logN, used, m_new=None):
        xp, Pp, _, y, g, nis, loglik, logdet, modes = self._fine(ti, dj, times[dj], z)
        inside = nis <= self.gamma
        ti, dj, xp, Pp, nis, loglik, logdet = (a[inside] for a in (ti, dj, xp, Pp, nis, loglik, logdet))
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
        if modes is None:  # the EKF update x + K y at the pair's prediction, its gain and P+ already in g
            kk = np.flatnonzero(inside)[k]  # (kernels.ekf_update would compute the same numbers again)
            x_new[i], P_new[i] = xp[k] + _k.mv(g.K[kk], y[kk]), g.P[kk]
        else:  # each mode's EKF update, then the mode probabilities and the combination
            kk = np.flatnonzero(inside)[k]
            ups = [_k.ekf_update(a[kk], b[kk], z[j], self._h, self._H, self.R, self.angles)
                   for a, b in zip(modes[0], modes[1])]
            xs, Ps = [u.x for u in ups], [u.P for u in ups]
            x_new[i], P_new[i], log_mu = self._imm_update(xs, Ps, modes[2][kk], np.stack([u.loglik for u in ups], -1))
            self._set_modes(m_new, i, xs, Ps, log_mu)
        t_new[i] = times[j]
        hit[i], logN[i], used[j] = True, loglik[k], True

    @staticmethod
    def _set_modes(m_new, i, xs, Ps, log_mu):
        for a, v in zip(m_new[0], xs):
            a[i] = v
        for b, v in zip(m_new[1], Ps):
            b[i] = v
        m_new[2][i] = log_mu

    def _jpda(self, ti, dj, times, z, x_new, P_new, t_new, hit, logN, used, m_new=None):
        T, M = len(x_new), len(z)
        has = np.bincount(ti, minlength=T) > 0
        tau = np.where(has, np.bincount(ti, weights=times[dj], minlength=T) / np.maximum(np.bincount(ti, minlength=T), 1),
                       t_new)
        _, _, _, y, _, nis, loglik, _, _ = self._fine(ti, dj, tau[ti], z)
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
        xs, Ps, modes = self._predict(idx, tau[idx], modes=True)  # one prediction per track: its candidates' mean time
        t_new[idx] = tau[idx]
        H = self._H(xs)
        zhat_b = self._h(xs)
        pos = np.full(T, -1)
        pos[idx] = np.arange(len(idx))
        shared = np.bincount(dj, minlength=M) > 1
        multi_track = np.bincount(ti, weights=shared[dj], minlength=T) > 0
        out_x, out_P = np.array(xs), np.array(Ps)
        # isolated tracks (no gated detection shared): one batched call, each its own run (T = 1),
        # its detections as linear pseudo-measurements H x + nu, so that z - H x is the EKF innovation
        single = idx[~multi_track[idx]]
        if len(single) and modes is not None:  # IMM-PDAF: a PDAF per mode, each linearised at its own prediction
            ps = pos[single]
            sel = ~multi_track[ti]
            si, sj = ti[sel], dj[sel]
            o = np.lexsort((sj, si))
            si, sj = si[o], sj[o]
            cnt = np.bincount(pos[si], minlength=len(idx))[ps]
            rank = np.arange(len(si)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            row = np.repeat(np.arange(len(single)), cnt)
            mask = np.zeros((len(single), int(cnt.max())), dtype=bool)
            mask[row, rank] = True
            lam = self._lam(zhat_b[ps])
            xm, Pm, ll = [], [], []
            for a, b in zip(modes[0], modes[1]):
                a, b = a[ps], b[ps]
                Hj = self._H(a)
                Z = np.zeros(mask.shape + (self.m,))
                Z[row, rank] = _k.mv(Hj[row], a[row]) + _k.residual(z[sj], self._h(a)[row], self.angles)
                xu, Pu, lu = self._pdaf(a[:, None], b[:, None], Z[:, None], mask[:, None], Hj[:, None], lam[:, None])
                xm.append(xu[:, 0])
                Pm.append(Pu[:, 0])
                ll.append(lu[:, 0])
            out_x[ps], out_P[ps], log_mu = self._imm_update(xm, Pm, modes[2][ps], np.stack(ll, -1))
            self._set_modes(m_new, single, xm, Pm, log_mu)
        elif len(single):
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
                xu, Pu, _ = self._pdaf(xs[ps][:, None], Ps[ps][:, None], Z[:, None], mask[:, None], H[ps][:, None],
                                       lam[:, None])
                out_x[ps], out_P[ps] = xu[:, 0], Pu[:, 0]
            else:  # a guard below a lone target's event count: the fall-back on each run over it
                for r, p in enumerate(ps):
                    Zr = Z[r, mask[r]]
                    if 1 + len(Zr) <= self.max_events:
                        u = _assoc.jpda_update(xs[p][None], Ps[p][None], Zr, H[p][None], self.R, P_D=self.P_D,
                                               P_G=self.P_G, clutter_density=lam[r], max_events=self.max_events)
                        xu, Pu = u.x, u.P
                    else:
                        xu, Pu, _ = self._cheap_jpda(xs[p][None], Ps[p][None], Zr, H[p][None], lam[r])
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
            if not 0.0 < lam < np.inf:  # (a callable clutter_density) the one check of jpda_update left to make
                raise ValueError(f"clutter_density must be finite and > 0 for JPDA, got {lam!r} (mean over a cluster)")
            try:  # jpda_update's kernel: the arguments are the tracker's, checked at construction and per scan
                u = _assoc._jpda_update(xa[pc], Pa[pc], Z, np.ones(len(Z), dtype=bool), Ha[pc], self.R, self.P_D,
                                        self.P_G, lam, self.max_events)
                xu, Pu, beta = u.x, u.P, u.beta
            except ValueError as err:
                if "max_events" not in str(err):
                    raise
                xu, Pu, beta = self._cheap_jpda(xa[pc], Pa[pc], Z, Ha[pc], lam)
                self.fallbacks += 1
            if modes is None:
                out_x[pc], out_P[pc] = xu[:, :4], Pu[:, :4, :4]
                continue
            # IMM (approximation): the cluster's marginals beta from the combined predictions; each
            # mode updated in PDA form with them, its likelihood that of its own PDAF on the cluster
            xm, Pm, ll = [], [], []
            for a, b in zip(modes[0], modes[1]):
                a, b = a[pc], b[pc]
                Hj = self._H(a)
                n = a.shape[-1]
                Haj = np.concatenate([Hj, (self._h(a) - _k.mv(Hj, a))[..., None]], axis=-1)
                xaj = np.concatenate([a, np.ones((len(a), 1))], axis=-1)
                Paj = np.zeros((len(a), n + 1, n + 1))
                Paj[:, :n, :n] = b
                xu, Pu, lu = self._pdaf(xaj, Paj, Z, np.ones(len(Z), dtype=bool), Haj, np.full(len(a), lam), beta)
                xm.append(xu[:, :n])
                Pm.append(Pu[:, :n, :n])
                ll.append(lu)
            out_x[pc], out_P[pc], log_mu = self._imm_update(xm, Pm, modes[2][pc], np.stack(ll, -1))
            self._set_modes(m_new, ct, xm, Pm, log_mu)
        x_new[idx], P_new[idx] = out_x, out_P

    def _pdaf(self, x, P, Z, mask, H, lam, beta=None):
        r"""PDAF update of a batch of lone targets (each its own gating cluster, so its JPDA
        marginals are its own normalised weights): :func:`kftrack.association.jpda_update` on
        ``T = 1`` runs without its argument checks, the same operations and bits. ``x`` (..., n),
        ``P``, padded ``Z`` (..., M, m) with ``mask`` (..., M), ``H`` (..., m, n), ``lam`` (...).
        Returns ``(x, P, loglik)``, ``loglik`` the log of the PDAF's likelihood ratio against all
        clutter, :math:`\log(1 - P_D P_G + \sum_i L_i)` (an IMM mode's likelihood in IMM-PDAF).
        ``beta`` (..., M + 1): marginals to combine with instead of the PDAF's own (a cluster's
        JPDA marginals)."""
        g, u = _assoc._gate(x, P, Z, mask, H, self.R, self.P_G)
        logL0, logL, _, _ = _assoc._log_pda_terms(g, self.P_D, self.P_G, lam)
        table = np.concatenate([logL0[..., None], logL], axis=-1)
        total = _assoc._logsumexp(table)
        if beta is None:
            beta = np.exp(table - total[..., None])
        x_post, P_post, _ = _assoc._pda_combine(x, P, u, g.nu, beta)
        return x_post, P_post, total

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
        return x, P, beta

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
            lam = self._lam(self._h(self._x)) if self._lam is not None else None
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
        """Two-point starts from the unassociated detections ``z`` (k, m) at ``times`` (k,) and the
        candidates of the last ``candidate_scans`` scans; the rest become candidates."""
        pc, Cc, tc, age = self._cand
        conv = self.sensor.to_cartesian(z)
        pn, Cn = np.asarray(conv[0]).reshape(-1, 2), np.asarray(conv[1]).reshape(-1, 2, 2)
        used, taken = np.zeros(len(z), dtype=bool), np.zeros(len(pc), dtype=bool)
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
                if len(i_c):
                    x0, P0 = _two_point(pc[i_c], pn[j_n], times[j_n] - tc[i_c], 0.5 * (Cc[i_c] + Cn[j_n]))
                    self._add(x0, P0, times[j_n], confirmed=False)
                used[j_n], taken[i_c] = True, True
        keep, new = ~taken & (age + 1 < self.candidate_scans), ~used  # older candidates still in memory; new ones
        self._cand = (np.concatenate([pc[keep], pn[new]]), np.concatenate([Cc[keep], Cn[new]]),
                      np.concatenate([tc[keep], times[new]]), np.append(age[keep] + 1, np.zeros(int(new.sum()), int)))


def _two_point(p1, p2, dt, C):
    r"""Two-point initiation of ``B`` tracks at once, :func:`kftrack.trackmanagement.two_point_initiation`
    vectorised over per-birth intervals and covariances (the same operations per birth, the same
    bits): positions ``p1``, ``p2`` ``(B, 2)`` at times ``-dt`` and 0, ``dt`` ``(B,)``, position
    covariance ``C`` ``(B, 2, 2)``. With :math:`A = [[1, -\Delta t], [1, 0]]`,
    :math:`G = (A^\top A)^{-1}`: ``x`` ``(B, 4)`` the least-squares ``[x, vx, y, vy]`` at the second
    point and ``P = sym(C \otimes G)`` ``(B, 4, 4)``."""
    B = len(dt)
    A = np.stack([np.ones((B, 2)), dt[:, None] * np.arange(-1, 1)], axis=-1)  # (B, k, 2)
    G = np.linalg.inv(np.swapaxes(A, -1, -2) @ A)
    coef = np.einsum("...ab,...kb,...kd->...ad", G, A, np.stack([p1, p2], axis=1))  # (B, 2, d): [pos, vel]
    x = np.swapaxes(coef, -1, -2).reshape(B, 4)
    P = (C[:, :, None, :, None] * G[:, None, :, None, :]).reshape(B, 4, 4)  # kron(C, G)
    return x, 0.5 * (P + np.swapaxes(P, -1, -2))


# --------------------------------------------------------------------------------------------
# the public call
# --------------------------------------------------------------------------------------------
def track_scans(scans, *, method: str = "gnn", sensor, motion, P_D: float, clutter_density=None, P_G: float = 0.99,
                confirmation=(2, 3), deletion=(3, 3), max_std: float | None = None, v_max: float = 400.0,
                initiate: bool = True, initial_tracks=(), max_events: int = 10_000, turn_rate_std: float = 0.05,
                candidate_scans: int = 2, **phd_options) -> Tracks:
    r"""Track many targets through a sequence of scans.

    Parameters
    ----------
    scans : sequence of scans with ``time``, ``times`` (m,) and ``z`` (m, d), e.g.
        :class:`kftrack.sensors.surveillance.Scan`.
    method : ``"gnn"``, ``"jpda"`` or ``"phd"``: the Gaussian-mixture PHD filter of
        :mod:`kftrack.phd` (:func:`kftrack.phd.phd_filter` with ``sensor``, ``motion``, ``P_D``,
        ``clutter_density`` and ``**phd_options``; the other arguments are not used). It keeps
        no identities: each extracted state is a one-row, confirmed :class:`Track` that ends at
        the next scan, ``P`` NaN, and the :class:`~kftrack.phd.PHDStep` list is ``Tracks.steps``
        (each step's time in ``Tracks.seconds``, as for the other methods).
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
        f = phd.GMPHD(sensor, motion, P_D=P_D, clutter_density=clutter_density, **phd_options)
        steps, seconds = [], []
        for scan in scans:  # phd.phd_filter, each step timed
            start = _time.perf_counter()
            steps.append(f.step(scan))
            seconds.append(_time.perf_counter() - start)
        return _phd_tracks(steps, motion, seconds)
    if phd_options:
        raise TypeError(f"track_scans got unexpected keyword arguments {sorted(phd_options)} (only method='phd' takes more)")
    if isinstance(scans, (str, bytes)) or not hasattr(scans, "__iter__"):
        raise TypeError(f"scans must be a sequence of scans (time, times, z), got {type(scans).__name__}")
    tracker = MultiTargetTracker(method=method, sensor=sensor, motion=motion, P_D=P_D, clutter_density=clutter_density,
                                 P_G=P_G, confirmation=confirmation, deletion=deletion, max_std=max_std, v_max=v_max,
                                 initiate=initiate, initial_tracks=initial_tracks, max_events=max_events,
                                 turn_rate_std=turn_rate_std, candidate_scans=candidate_scans)
    for k, scan in enumerate(scans):
        try:
            checked = tracker._check_scan(scan)
        except (ValueError, TypeError) as err:
            raise type(err)(f"scans[{k}]: {err}") from None
        tracker._run(*checked)
    return tracker.tracks()


def _phd_tracks(steps, motion, seconds) -> Tracks:
    """GM-PHD steps as unlabelled one-row tracks (so that snapshot, to_csv and plotting apply)."""
    tracks, ends, nid = [], {}, 0
    for k, st in enumerate(steps):
        end = steps[k + 1].time if k + 1 < len(steps) else np.inf
        for x in np.asarray(st.states).reshape(-1, 4):
            tracks.append(Track(nid, np.array([st.time]), x[None].copy(), np.full((1, 4, 4), np.nan), np.ones(1, bool)))
            ends[nid] = end
            nid += 1
    out = Tracks(tracks, ends, motion, seconds=seconds)
    out.steps = steps
    return out
