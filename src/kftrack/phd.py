r"""The Gaussian-mixture probability hypothesis density (GM-PHD) filter (Vo & Ma 2006): a
random-finite-set filter that propagates the **intensity** :math:`D(x)` of the targets, whose
integral over a region is the expected number of targets in it, as a weighted Gaussian mixture
:math:`D(x) = \sum_j w_j N(x; m_j, P_j)`. It keeps no tracks and no identities.

One scan, with survival probability :math:`P_S`, detection probability :math:`P_D`, clutter
intensity :math:`\kappa(z)` (false alarms per unit measurement volume) and birth intensity
:math:`\gamma(x)`:

* prediction: :math:`D_{k|k-1}(x) = \sum_j P_S w_j N(x; F m_j, F P_j F^\top + Q) + \gamma(x)`;
* update, over the scan's measurements :math:`z_i`:

  .. math:: D_k(x) = (1 - P_D) D_{k|k-1}(x) + \sum_i \sum_j
     \frac{P_D w_j q_{ij}}{\kappa(z_i) + P_D \sum_l w_l q_{il}} N(x; m_{ij}, P_{ij}),

  :math:`q_{ij} = N(z_i; h(m_j), S_{ij})`, :math:`S_{ij} = H_j P_j H_j^\top + R`, and
  :math:`m_{ij}, P_{ij}` the extended Kalman update of component ``j`` by :math:`z_i`
  (:math:`H_j` the Jacobian of ``h`` at :math:`m_j`; the bearing residual wrapped to
  :math:`(-\pi, \pi]`; Joseph form);
* reduction (Vo & Ma 2006, table II): components with :math:`w < T` are pruned; from the
  heaviest down, the components within Mahalanobis distance :math:`U` of it,
  :math:`(m_i - m_j)^\top P_i^{-1}(m_i - m_j) \le U`, are merged into one of the same mass,
  mean and second moment; at most ``max_components`` heaviest are kept (no renormalisation);
* extraction: each component with :math:`w > 0.5` gives :math:`\operatorname{round}(w)` copies of
  its mean; the expected number of targets is :math:`\hat N = \sum_j w_j`.

**Birth.** ``birth="measurements"`` (default): the measurement-driven birth of Ristic, Clark,
Vo & Vo (2012): each measurement :math:`z_i` of a scan spawns a component for the next scan at
its converted position (linearised polar-to-Cartesian conversion, covariance :math:`JRJ^\top`),
velocity 0 with standard deviation ``birth_speed_sigma`` per axis, weighted
:math:`\nu_b (1 - \rho_i) / \sum_l (1 - \rho_l)`, where :math:`\rho_i` is the probability that
:math:`z_i` came from a target already in the mixture (its summed update weight) and
:math:`\nu_b` = ``birth_rate`` the expected number of new targets per scan. A radar's targets
appear anywhere along the coverage edge and at airports; a fixed birth mixture would have to
cover the whole surveillance area with broad components (diluting the update) or guess where
aircraft appear, while measurement-driven birth puts components where the data point. A fixed
mixture ``(weights (J,), means (J, n), covs (J, n, n))`` may be given instead (e.g. to align
with a peer library), or ``None`` for no birth.

**Per-detection times.** A rotating radar sees each target at its own time ``scan.times[i]``.
Each measurement is scored against the mixture predicted to its own time (the predictions
:math:`F(t_i - t)m_j` differ per measurement); each updated pair (component ``j``, measurement
``i``) is then predicted forward to the scan's **reference time** :math:`t_k = \max(\text{scan.time},
\max_i t_i)`, the missed-detection terms straight to :math:`t_k`. The PHD recursion assumes one
time per scan, so this is an approximation: the normalising sum :math:`\sum_l w_l q_{il}` treats
the intensity at each detection's time as the scan's; it is exact when all ``times`` coincide.

**Clutter.** ``clutter_density`` is the expected number of false alarms per scan per m² of
Cartesian coverage (uniform in the plane). In the measurement space of a range–bearing sensor
the intensity is :math:`\kappa(r, \theta) = \lambda\, r` (the area element is
:math:`r\,dr\,d\theta`); for a linear position sensor :math:`\kappa = \lambda`.

Arguments are duck-typed: ``sensor`` has ``h(x)``, ``jacobian(x)``, ``R`` and
``angle_components`` (e.g. :class:`kftrack.sensors.radar.RangeBearing`; measurement-driven birth
also needs ``to_cartesian`` and ``position_indices``); ``motion`` has ``F(dt)`` and ``Q(dt)``
(e.g. ``ConstantVelocity(ndim=2, q=...)``, state ``[x, vx, y, vy]``: a born component's velocity
components are those after each position index).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.stats import chi2

from ._validate import as_float_array, check_covariance, finite_scalar
from .kernels import wrap_angle

__all__ = ["PHDStep", "GMPHD", "phd_filter", "reduce_mixture", "extract_states"]

_LOG_2PI = np.log(2.0 * np.pi)


class PHDStep(NamedTuple):
    """The GM-PHD intensity after one scan.

    Attributes
    ----------
    time : the mixture's reference time (s), ``max(scan.time, max(scan.times))``.
    weights : (J,) component weights; ``means`` (J, n); ``covs`` (J, n, n).
    states : (k, n) extracted target states (unlabelled).
    cardinality : the expected number of targets, ``weights.sum()``.
    """

    time: float
    weights: np.ndarray
    means: np.ndarray
    covs: np.ndarray
    states: np.ndarray
    cardinality: float


# --------------------------------------------------------------------------------------------
# mixture reduction and extraction
# --------------------------------------------------------------------------------------------
def _reduce(w, m, P, prune, merge, cap):
    keep = (w >= prune) & (w > 0)
    w, m, P = w[keep], m[keep], P[keep]
    if len(w) == 0:
        return w, m, P
    Pinv = np.linalg.inv(P)
    order = list(np.argsort(-w, kind="stable"))
    alive = np.ones(len(w), dtype=bool)
    ow, om, oP = [], [], []
    for j in order:
        if not alive[j]:
            continue
        idx = np.flatnonzero(alive)
        d = m[idx] - m[j]
        d2 = np.einsum("ki,kij,kj->k", d, Pinv[idx], d)
        L = idx[d2 <= merge]
        alive[L] = False
        wl = w[L]
        wt = wl.sum()
        mt = wl @ m[L] / wt
        dm = m[L] - mt
        Pt = (np.einsum("k,kij->ij", wl, P[L]) + np.einsum("k,ki,kj->ij", wl, dm, dm)) / wt
        ow.append(wt)
        om.append(mt)
        oP.append(0.5 * (Pt + Pt.T))
    w, m, P = np.array(ow), np.array(om), np.array(oP)
    if len(w) > cap:
        top = np.argsort(-w, kind="stable")[:cap]
        w, m, P = w[top], m[top], P[top]
    return w, m, P


def _check_mixture(weights, means, covs, name="the mixture"):
    w = as_float_array(weights, "weights")
    m = as_float_array(means, "means")
    if w.ndim != 1 or m.ndim != 2 or m.shape[0] != w.shape[0]:
        raise ValueError(f"weights and means of {name} must have shapes (J,) and (J, n), got {w.shape} and {m.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError(f"weights of {name} must be finite and >= 0")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"means of {name} must be finite")
    P = check_covariance(covs, "covs", m.shape[1], positive_definite=True, origin=f"n = {m.shape[1]} from means")
    if P.shape != m.shape + (m.shape[1],):
        raise ValueError(f"covs of {name} must have shape {m.shape + (m.shape[1],)}, got shape {P.shape}")
    return w, m, P


def _check_reduction(prune_threshold, merge_threshold, max_components):
    prune = finite_scalar(prune_threshold, "prune_threshold")
    if not 0.0 <= prune < 0.5:
        raise ValueError(f"prune_threshold (smallest weight kept) must lie in [0, 0.5), got {prune_threshold!r}")
    merge = finite_scalar(merge_threshold, "merge_threshold")
    if merge < 0:
        raise ValueError(f"merge_threshold (squared Mahalanobis distance) must be >= 0, got {merge_threshold!r}")
    if isinstance(max_components, bool) or int(max_components) != max_components or max_components < 1:
        raise ValueError(f"max_components must be a positive integer, got {max_components!r}")
    return prune, merge, int(max_components)


def reduce_mixture(weights, means, covs, *, prune_threshold: float = 1e-5, merge_threshold: float = 4.0,
                   max_components: int = 500):
    r"""Prune, merge and cap a Gaussian mixture (Vo & Ma 2006, table II).

    Components of weight below ``prune_threshold`` (and of weight 0) are dropped; then, heaviest first, every
    remaining component ``i`` with :math:`(m_i - m_j)^\top P_i^{-1}(m_i - m_j) \le U`
    (``merge_threshold``) of the heaviest ``j`` is merged into
    :math:`w = \sum w_i`, :math:`m = \sum w_i m_i / w`,
    :math:`P = \sum w_i (P_i + (m_i - m)(m_i - m)^\top) / w` (same mass, mean and second
    moment); finally the ``max_components`` heaviest are kept. Weights are not renormalised.

    Parameters
    ----------
    weights : (J,) ``>= 0``; ``means`` (J, n); ``covs`` (J, n, n) positive definite.

    Returns
    -------
    ``(weights (J',), means (J', n), covs (J', n, n))``, heaviest first.
    """
    w, m, P = _check_mixture(weights, means, covs)
    return _reduce(w, m, P, *_check_reduction(prune_threshold, merge_threshold, max_components))


def extract_states(weights, means, threshold: float = 0.5) -> np.ndarray:
    r"""Target states of a PHD mixture (Vo & Ma 2006, table III): each component with
    :math:`w > ` ``threshold`` gives :math:`\operatorname{round}(w)` copies of its mean (at least
    one). ``weights`` (J,), ``means`` (J, n); returns (k, n)."""
    w, m = as_float_array(weights, "weights"), as_float_array(means, "means")
    if w.ndim != 1 or m.ndim != 2 or len(w) != len(m):
        raise ValueError(f"weights and means must have shapes (J,) and (J, n), got {w.shape} and {m.shape}")
    return _extract(w, m, finite_scalar(threshold, "threshold"))


def _extract(w, m, threshold):
    sel = w > threshold
    return np.repeat(m[sel], np.maximum(np.rint(w[sel]), 1).astype(int), axis=0)


# --------------------------------------------------------------------------------------------
# the filter
# --------------------------------------------------------------------------------------------
def _prob(value, name, what, lo_open=True):
    v = finite_scalar(value, name)
    if not (0.0 < v <= 1.0):
        raise ValueError(f"{name} ({what}) must lie in (0, 1], got {value!r}")
    return v


def _predict(m, P, F, Q):
    """Means (..., J, n) and covariances predicted with ``F``, ``Q`` (..., 1, n, n)."""
    m2 = (F @ m[..., None])[..., 0]
    P2 = F @ P @ np.swapaxes(F, -1, -2) + Q
    return m2, 0.5 * (P2 + np.swapaxes(P2, -1, -2))


class GMPHD:
    r"""Gaussian-mixture PHD filter (Vo & Ma 2006) for a sensor with per-detection times; see
    the module docstring for the equations, the birth model and the time approximation.

    Parameters
    ----------
    sensor : measurement model with ``h``, ``jacobian``, ``R``, ``angle_components`` (e.g.
        :class:`kftrack.sensors.radar.RangeBearing`).
    motion : motion model with ``F(dt)``, ``Q(dt)`` (e.g. ``ConstantVelocity(ndim=2, q=...)``).
    P_D : detection probability in (0, 1]; ``P_S`` survival probability per scan in (0, 1].
    clutter_density : false alarms per scan per m² of Cartesian coverage, ``>= 0``.
    birth : ``"measurements"`` (measurement-driven birth), a fixed mixture
        ``(weights (J,), means (J, n), covs (J, n, n))`` added at every scan, or ``None``.
    birth_rate : expected new targets per scan (measurement-driven birth), ``>= 0``.
    birth_speed_sigma : standard deviation of each velocity component of a born component (m/s).
    prune_threshold, merge_threshold, max_components : see :func:`reduce_mixture`.
    extract_threshold : see :func:`extract_states`.
    P_G : ``None`` (default: every measurement updates every component, the exact recursion) or
        a gate probability: a pair (measurement, component) outside the chi-square gate
        :math:`\nu^\top S^{-1}\nu \le \chi^2_d{}^{-1}(P_G)` is left out (its :math:`q_{ij}` taken
        as 0). It cuts the work of the update (a scan of 200 aircraft: most pairs are kilometres
        apart); with ``P_G = 1 - 10^{-6}`` a pair left out has :math:`q_{ij}` below
        :math:`10^{-6}` of its peak.
    initial : optional mixture ``(weights, means, covs)`` at time ``t0`` (default: empty).
    t0 : time of ``initial`` (s); default the first scan's ``time``.

    Examples
    --------
    >>> import numpy as np
    >>> from types import SimpleNamespace
    >>> from kftrack.models import ConstantVelocity
    >>> from kftrack.phd import GMPHD
    >>> from kftrack.sensors.radar import RangeBearing
    >>> radar = RangeBearing(sigmas=(20.0, np.deg2rad(0.2)))
    >>> f = GMPHD(radar, ConstantVelocity(ndim=2, q=1.0), P_D=1.0, clutter_density=0.0, P_S=1.0,
    ...           birth=None, initial=([1.0], [[10e3, 0.0, 5e3, 0.0]], [np.diag([1e4, 100.0, 1e4, 100.0])]))
    >>> scan = SimpleNamespace(time=0.0, times=np.array([0.0]), z=radar.h(np.array([10e3, 0, 5e3, 0]))[None])
    >>> step = f.step(scan)
    >>> round(step.cardinality, 12), step.states.shape
    (1.0, (1, 4))
    """

    def __init__(self, sensor, motion, *, P_D: float, clutter_density: float, P_S: float = 0.99,
                 birth="measurements", birth_rate: float = 0.1, birth_speed_sigma: float = 150.0,
                 prune_threshold: float = 1e-5, merge_threshold: float = 4.0, max_components: int = 500,
                 extract_threshold: float = 0.5, P_G: float | None = None, initial=None, t0: float | None = None):
        for attr in ("h", "jacobian", "R"):
            if not hasattr(sensor, attr):
                raise TypeError(f"sensor must have h, jacobian and R (e.g. RangeBearing), got {type(sensor).__name__} "
                                f"without {attr!r}")
        for attr in ("F", "Q"):
            if not hasattr(motion, attr):
                raise TypeError(f"motion must have F(dt) and Q(dt) (e.g. ConstantVelocity), got "
                                f"{type(motion).__name__} without {attr!r}")
        self.sensor, self.motion = sensor, motion
        self.R = check_covariance(sensor.R, "sensor.R", positive_definite=True)
        self.d = self.R.shape[0]
        self.angles = list(getattr(sensor, "angle_components", ()))
        if self.angles and not (self.d == 2 and self.angles == [1]):
            raise ValueError(f"sensor must be a linear sensor or a 2-D range-bearing one (angle_components (1,)), "
                             f"got angle_components {tuple(self.angles)} for a {self.d}-D measurement")
        self.n = np.shape(motion.F(0.0))[-1]
        self.P_D = _prob(P_D, "P_D", "detection probability")
        self.P_S = _prob(P_S, "P_S", "survival probability")
        lam = finite_scalar(clutter_density, "clutter_density")
        if lam < 0:
            raise ValueError(f"clutter_density (false alarms per scan per m^2) must be >= 0, got {clutter_density!r}")
        self.clutter_density = lam
        self.birth_rate = finite_scalar(birth_rate, "birth_rate")
        if self.birth_rate < 0:
            raise ValueError(f"birth_rate (expected new targets per scan) must be >= 0, got {birth_rate!r}")
        self.birth_speed_sigma = finite_scalar(birth_speed_sigma, "birth_speed_sigma")
        if not self.birth_speed_sigma > 0:
            raise ValueError(f"birth_speed_sigma (m/s) must be > 0, got {birth_speed_sigma!r}")
        if isinstance(birth, str):
            if birth != "measurements":
                raise ValueError(f"birth must be 'measurements', a mixture (weights, means, covs) or None, got {birth!r}")
            for attr in ("to_cartesian", "position_indices"):
                if not hasattr(sensor, attr):
                    raise TypeError(f"birth='measurements' needs a sensor with to_cartesian and position_indices, "
                                    f"got {type(sensor).__name__}")
            self._fixed_birth = None
        elif birth is None:
            self._fixed_birth = None
        else:
            if not (isinstance(birth, (tuple, list)) and len(birth) == 3):
                raise ValueError(f"birth must be 'measurements', a mixture (weights, means, covs) or None, "
                                 f"got {type(birth).__name__}")
            self._fixed_birth = self._mixture(birth, "birth")
        self.measurement_birth = birth == "measurements"
        self.reduction = _check_reduction(prune_threshold, merge_threshold, max_components)
        self.extract_threshold = finite_scalar(extract_threshold, "extract_threshold")
        if P_G is None:
            self.gamma = None
        else:
            g = finite_scalar(P_G, "P_G")
            if not 0.0 < g < 1.0:
                raise ValueError(f"P_G (gate probability) must lie in (0, 1) or be None (no gate), got {P_G!r}")
            self.gamma = float(chi2.ppf(g, self.d))
        if initial is None:
            self.w, self.m, self.P = np.zeros(0), np.zeros((0, self.n)), np.zeros((0, self.n, self.n))
        else:
            if not (isinstance(initial, (tuple, list)) and len(initial) == 3):
                raise ValueError(f"initial must be a mixture (weights, means, covs), got {type(initial).__name__}")
            self.w, self.m, self.P = self._mixture(initial, "initial")
        self.t = None if t0 is None else finite_scalar(t0, "t0")
        self._born = (np.zeros(0), np.zeros((0, self.n)), np.zeros((0, self.n, self.n)))
        self.states = np.zeros((0, self.n))

    def _mixture(self, mix, name):
        w, m, P = _check_mixture(*mix, name=name)
        if m.shape[1] != self.n:
            raise ValueError(f"means of {name} must have shape (J, {self.n}) (n = {self.n} from motion), got {m.shape}")
        return w, m, P

    def _check_scan(self, scan):
        try:
            time, times, z = scan.time, scan.times, scan.z
        except AttributeError:
            raise TypeError(f"scan must have time, times and z (a kftrack Scan), got {type(scan).__name__}") from None
        time = finite_scalar(time, "scan.time")
        times = np.atleast_1d(as_float_array(times, "scan.times"))
        z = as_float_array(z, "scan.z")
        if z.size == 0:
            z = z.reshape(0, self.d)
        if z.ndim != 2 or z.shape[1] != self.d or times.shape != (z.shape[0],):
            raise ValueError(f"scan.z and scan.times must have shapes (m, {self.d}) and (m,), got {z.shape} and {times.shape}")
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(times))):
            raise ValueError("scan.z and scan.times must be finite")
        t_prev = time if self.t is None else self.t
        if time < t_prev or (len(times) and times.min() < t_prev):
            raise ValueError(f"scans must come in time order: scan.time {time!r} (earliest detection "
                             f"{times.min() if len(times) else time!r}) is before the filter's time {t_prev!r}")
        return time, times, z

    def _clutter_log(self, z):
        if self.clutter_density == 0:
            return np.full(len(z), -np.inf)
        scale = z[:, 0] if self.angles else np.ones(len(z))  # area element r dr dtheta of range-bearing
        with np.errstate(divide="ignore"):
            return np.log(self.clutter_density) + np.log(np.maximum(scale, 0.0))

    def step(self, scan) -> PHDStep:
        """Predict the intensity to the scan, update it with the scan's detections, reduce it and
        extract the states; returns the :class:`PHDStep` (the filter keeps the mixture)."""
        time, times, z = self._check_scan(scan)
        if self.t is None:
            self.t = time
        t_ref = max(time, float(times.max())) if len(times) else time
        # the pool at self.t: survivors, last scan's measurement-driven births, a fixed birth mixture
        parts = [(self.P_S * self.w, self.m, self.P), self._born]
        if self._fixed_birth is not None:
            parts.append(self._fixed_birth)
        w = np.concatenate([p[0] for p in parts])
        m = np.concatenate([p[1] for p in parts])
        P = np.concatenate([p[2] for p in parts])
        F0, Q0 = self.motion.F(t_ref - self.t), self.motion.Q(t_ref - self.t)
        m0, P0 = _predict(m, P, F0, Q0)
        out_w, out_m, out_P = [(1.0 - self.P_D) * w], [m0], [P0]
        rho = np.zeros(len(z))
        if len(z) and len(w):
            dt = times - self.t
            Fi, Qi = self.motion.F(dt), self.motion.Q(dt)  # (M, n, n)
            mi = np.einsum("iab,jb->ija", Fi, m)  # (M, J, n): each component at each detection's time
            zhat = self.sensor.h(mi)
            Hj = self.sensor.jacobian(mi)  # (M, J, d, n)
            nu = z[:, None, :] - zhat
            if self.angles:
                nu[..., self.angles] = wrap_angle(nu[..., self.angles])
            if self.gamma is None:
                ii, jj = np.divmod(np.arange(len(z) * len(w)), len(w))
            else:  # the gate, with S = (H F) P (H F)' + H Q H' + R, cheaper than the full update
                A = Hj @ Fi[:, None]
                S = A @ P[None] @ np.swapaxes(A, -1, -2) + Hj @ Qi[:, None] @ np.swapaxes(Hj, -1, -2) + self.R
                d2 = np.einsum("...i,...i->...", nu, np.linalg.solve(S, nu[..., None])[..., 0])
                ii, jj = np.nonzero(d2 <= self.gamma)
            # the extended Kalman update of the (measurement i, component j) pairs, then on to t_ref
            Pi = Fi[ii] @ P[jj] @ np.swapaxes(Fi[ii], -1, -2) + Qi[ii]
            Pi = 0.5 * (Pi + np.swapaxes(Pi, -1, -2))
            Hp, nup = Hj[ii, jj], nu[ii, jj]
            PHt = Pi @ np.swapaxes(Hp, -1, -2)
            S = Hp @ PHt + self.R
            S = 0.5 * (S + np.swapaxes(S, -1, -2))
            Sinv_nu = np.linalg.solve(S, nup[..., None])[..., 0]
            _, logdet = np.linalg.slogdet(S)
            logq = np.full((len(z), len(w)), -np.inf)
            logq[ii, jj] = -0.5 * (np.einsum("...i,...i->...", nup, Sinv_nu) + logdet + self.d * _LOG_2PI)
            K = np.swapaxes(np.linalg.solve(S, np.swapaxes(PHt, -1, -2)), -1, -2)  # P H' S^-1
            mu = mi[ii, jj] + (K @ nup[..., None])[..., 0]
            IKH = np.eye(self.n) - K @ Hp
            Pu = IKH @ Pi @ np.swapaxes(IKH, -1, -2) + K @ self.R @ np.swapaxes(K, -1, -2)
            mu, Pu = _predict(mu, Pu, self.motion.F(t_ref - times)[ii], self.motion.Q(t_ref - times)[ii])
            with np.errstate(divide="ignore"):
                lognum = np.log(self.P_D) + np.log(w)[None, :] + logq  # (M, J)
            top = np.max(lognum, axis=1, keepdims=True)
            top = np.where(np.isfinite(top), top, 0.0)
            with np.errstate(divide="ignore"):
                logsum = np.log(np.sum(np.exp(lognum - top), axis=1)) + top[:, 0]
            logden = np.logaddexp(self._clutter_log(z), logsum)
            wij = np.where(np.isfinite(logden)[:, None], np.exp(lognum - np.where(np.isfinite(logden), logden, 0.0)[:, None]), 0.0)
            rho = wij.sum(1)
            out_w.append(wij[ii, jj])
            out_m.append(mu)
            out_P.append(Pu)
        w = np.concatenate(out_w)
        m = np.concatenate(out_m)
        P = np.concatenate(out_P)
        self.w, self.m, self.P = _reduce(w, m, P, *self.reduction)
        self._born = self._births(z, times, rho, t_ref)
        self.t = t_ref
        self.states = _extract(self.w, self.m, self.extract_threshold)
        return PHDStep(t_ref, self.w.copy(), self.m.copy(), self.P.copy(), self.states.copy(), float(self.w.sum()))

    def _births(self, z, times, rho, t_ref):
        """Measurement-driven birth components for the next scan, predicted to ``t_ref``."""
        empty = (np.zeros(0), np.zeros((0, self.n)), np.zeros((0, self.n, self.n)))
        if not self.measurement_birth or len(z) == 0 or self.birth_rate == 0:
            return empty
        free = np.clip(1.0 - rho, 0.0, 1.0)
        if free.sum() <= 0:
            return empty
        wb = self.birth_rate * free / free.sum()
        conv = self.sensor.to_cartesian(z, method="linearized")
        pos = list(self.sensor.position_indices)
        vel = [i + 1 for i in pos]
        mb = np.zeros((len(z), self.n))
        mb[:, pos] = conv.p
        Pb = np.zeros((len(z), self.n, self.n))
        Pb[:, np.array(pos)[:, None], np.array(pos)[None, :]] = conv.C
        Pb[:, vel, vel] = self.birth_speed_sigma**2
        mb, Pb = _predict(mb, Pb, self.motion.F(t_ref - times), self.motion.Q(t_ref - times))
        keep = wb >= self.reduction[0]
        return wb[keep], mb[keep], Pb[keep]

    def states_at(self, t: float) -> np.ndarray:
        """The last extracted states' means moved to time ``t`` (s) with ``F(t - time)`` (either
        sign: means only), ``(k, n)``."""
        t = finite_scalar(t, "t")
        if self.t is None:
            return self.states.copy()
        return (self.motion.F(t - self.t) @ self.states[..., None])[..., 0]


def phd_filter(scans, sensor, motion, **kwargs) -> list[PHDStep]:
    """Run a :class:`GMPHD` (built with ``sensor``, ``motion`` and the keywords ``kwargs``) over
    a sequence of scans (each with ``time``, ``times`` (m,), ``z`` (m, d)); one :class:`PHDStep`
    per scan: ``weights``, ``means``, ``covs``, extracted ``states`` and ``cardinality``."""
    f = GMPHD(sensor, motion, **kwargs)
    return [f.step(scan) for scan in scans]
