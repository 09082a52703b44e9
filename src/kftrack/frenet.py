r"""Curves in space: the Frenet–Serret frame, curvature and torsion, and a trajectory simulator.

A curve :math:`\mathbf r(s)` parametrized by arc length :math:`s` carries the orthonormal frame
of its tangent :math:`\mathbf t`, normal :math:`\mathbf n` and binormal :math:`\mathbf b`, which
turns as it moves (the Frenet–Serret equations, with the standard signs):

.. math::

    \mathbf t' = \kappa\,\mathbf n,\qquad \mathbf n' = -\kappa\,\mathbf t + \tau\,\mathbf b,
    \qquad \mathbf b' = -\tau\,\mathbf n ,

that is :math:`\mathbf e' = \mathbf d \times \mathbf e` for each frame vector, with the
Darboux vector :math:`\mathbf d = \tau\mathbf t + \kappa\mathbf b`. In time, with speed
:math:`v`: :math:`\kappa = |\mathbf v\times\mathbf a|/|\mathbf v|^3`,
:math:`\tau = (\mathbf v\times\mathbf a)\cdot\dot{\mathbf a}/|\mathbf v\times\mathbf a|^2`
(do Carmo 1976, §1-5; Stone Soup reference notes §2.7).

Contents
--------
* symbolic (SymPy): :func:`frenet_sym` (frame, :math:`\kappa`, :math:`\tau` of a parametric
  curve), :func:`helix_sym`;
* numeric: :func:`curvature_torsion` (from velocity, acceleration, jerk),
  :func:`curvature_torsion_from_samples`, :func:`frame_from_derivatives`, :func:`turn_rate`,
  :func:`turn_model_residual` (what the 3-D turn model :math:`\dot{\mathbf a} = -\omega^2\mathbf v`
  misses);
* the simulator of source study 000 (piecewise constant curvature and torsion, integrated in
  arc length), done two ways: :func:`simulate_euler` (the study's explicit Euler step with
  renormalisation, eqs. 36–46, for measuring its drift) and :func:`simulate` (exact: each step
  rotates the frame about the Darboux vector; segments may accelerate along the path).

Frames are arrays ``(..., 3, 3)`` whose **rows** are ``t, n, b``. Positions, velocities,
accelerations are ``(..., 3)``, metres and seconds. Curvature may be **signed** in the
simulator: a negative :math:`\kappa` turns the other way (towards :math:`-\mathbf n`), so a
zig-zag keeps one continuous frame; the geometric curvature is :math:`|\kappa|`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Sequence

import numpy as np
import sympy as sp

from ._validate import as_float_array, as_vector, check_finite, positive_scalar

__all__ = [
    "frenet_sym", "helix_sym", "curvature_torsion", "curvature_torsion_from_samples",
    "frame_from_derivatives", "turn_rate", "turn_model_residual", "frenet_generator",
    "CONVENTIONS", "initial_frame", "Segment", "FrenetTrack", "segments_from_radii",
    "simulate", "simulate_euler", "orthonormality_error", "circle_closure",
    "euler_endpoint_error",
]


# --------------------------------------------------------------------------------------------
# symbolic
# --------------------------------------------------------------------------------------------
def _cross(a: sp.Matrix, b: sp.Matrix) -> sp.Matrix:
    return a.cross(b)


def frenet_sym(r: sp.Matrix, t: sp.Symbol) -> dict[str, sp.Expr | sp.Matrix]:
    r"""Frenet–Serret quantities of a parametric curve :math:`\mathbf r(t)` (any parameter).

    Returns a dict with ``speed`` :math:`|\dot{\mathbf r}|`, the unit vectors ``t``, ``n``,
    ``b`` (:math:`\mathbf t = \dot{\mathbf r}/|\dot{\mathbf r}|`,
    :math:`\mathbf b = \dot{\mathbf r}\times\ddot{\mathbf r}/|\dot{\mathbf r}\times\ddot{\mathbf r}|`,
    :math:`\mathbf n = \mathbf b\times\mathbf t`), ``kappa``
    :math:`|\dot{\mathbf r}\times\ddot{\mathbf r}|/|\dot{\mathbf r}|^3` and ``tau``
    :math:`(\dot{\mathbf r}\times\ddot{\mathbf r})\cdot\dddot{\mathbf r}/|\dot{\mathbf r}\times\ddot{\mathbf r}|^2`,
    each simplified. ``r`` is a 3×1 SymPy matrix.
    """
    r = sp.Matrix(r)
    if r.shape != (3, 1):
        raise ValueError(f"r must be a 3x1 SymPy Matrix, got shape {r.shape}")
    v, a = r.diff(t), r.diff(t, 2)
    j = r.diff(t, 3)
    va = _cross(v, a)
    speed = sp.simplify(sp.sqrt(v.dot(v)))
    nva = sp.simplify(sp.sqrt(sp.simplify(va.dot(va))))
    tt = (v / speed).applyfunc(sp.simplify)
    bb = (va / nva).applyfunc(sp.simplify)
    nn = _cross(bb, tt).applyfunc(sp.simplify)
    return {
        "speed": speed, "t": tt, "n": nn, "b": bb,
        "kappa": sp.simplify(nva / speed**3),
        "tau": sp.simplify(va.dot(j) / nva**2),
    }


def helix_sym(radius: sp.Expr, pitch: sp.Expr, t: sp.Symbol) -> sp.Matrix:
    r"""The circular helix :math:`(R\cos t,\ R\sin t,\ c\,t)`; ``pitch`` is :math:`c` (rise per
    radian). Its curvature is :math:`R/(R^2+c^2)` and torsion :math:`c/(R^2+c^2)`."""
    return sp.Matrix([radius * sp.cos(t), radius * sp.sin(t), pitch * t])


# --------------------------------------------------------------------------------------------
# numeric curvature, torsion, frame
# --------------------------------------------------------------------------------------------
def curvature_torsion(v, a, jerk=None) -> tuple[np.ndarray, np.ndarray | None]:
    r"""Curvature and torsion from velocity, acceleration and (for the torsion) jerk.

    :math:`\kappa = |\mathbf v\times\mathbf a|/|\mathbf v|^3` (1/m) and
    :math:`\tau = (\mathbf v\times\mathbf a)\cdot\dot{\mathbf a}/|\mathbf v\times\mathbf a|^2`
    (1/m); ``v``, ``a``, ``jerk`` are ``(..., 3)``. The torsion is NaN where the motion is
    straight (:math:`\mathbf v\times\mathbf a = 0`); ``None`` when no ``jerk`` is given.
    A zero velocity (no direction, no curvature) is refused.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.frenet import curvature_torsion
    >>> # the helix (cos t, sin t, t) at t = 0: curvature and torsion 1 / (1 + 1) = 0.5 (1/m)
    >>> kappa, tau = curvature_torsion(v=[0.0, 1.0, 1.0], a=[-1.0, 0.0, 0.0], jerk=[0.0, -1.0, 0.0])
    >>> print(np.round([kappa, tau], 6))
    [0.5 0.5]
    """
    v = as_vector(v, "v", 3)
    a = as_vector(a, "a", 3)
    speed = np.linalg.norm(v, axis=-1)
    if np.any(speed == 0):
        raise ValueError("v must be non-zero everywhere: curvature and torsion are undefined at rest")
    va = np.cross(v, a)
    nva2 = np.sum(va * va, axis=-1)
    kappa = np.sqrt(nva2) / speed**3
    if jerk is None:
        return kappa, None
    jerk = as_vector(jerk, "jerk", 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = np.where(nva2 > 0, np.sum(va * jerk, axis=-1) / np.where(nva2 > 0, nva2, 1.0), np.nan)
    return kappa, tau


def curvature_torsion_from_samples(t, r) -> tuple[np.ndarray, np.ndarray]:
    r"""Curvature and torsion of a sampled path, ``r`` ``(T, ..., 3)`` at times ``t`` ``(T,)``.

    The derivatives are second-order finite differences (``numpy.gradient``, one-sided of
    order 2 at the ends), so the error is :math:`O(\Delta t^2)` for a smooth path; then
    :func:`curvature_torsion`. Returns ``(kappa, tau)``, each ``(T, ...)``.
    """
    t = check_finite(as_float_array(t, "t"), "t")
    r = as_vector(r, "r", 3)
    if t.ndim != 1 or r.shape[0] != t.shape[0] or t.shape[0] < 5:
        raise ValueError(f"t must be (T,) with T >= 5 and r (T, ..., 3); got t {t.shape}, r {r.shape}")
    if not np.all(np.diff(t) > 0):
        raise ValueError("t must be strictly increasing")
    v = np.gradient(r, t, axis=0, edge_order=2)
    a = np.gradient(v, t, axis=0, edge_order=2)
    j = np.gradient(a, t, axis=0, edge_order=2)
    return curvature_torsion(v, a, j)


def frame_from_derivatives(v, a) -> np.ndarray:
    r"""The Frenet frame ``(..., 3, 3)``, rows :math:`\mathbf t = \mathbf v/|\mathbf v|`,
    :math:`\mathbf n = \mathbf b\times\mathbf t`,
    :math:`\mathbf b = \mathbf v\times\mathbf a/|\mathbf v\times\mathbf a|`; undefined (NaN)
    on a straight line."""
    v = as_vector(v, "v", 3)
    a = as_vector(a, "a", 3)
    tt = v / np.linalg.norm(v, axis=-1, keepdims=True)
    va = np.cross(v, a)
    with np.errstate(divide="ignore", invalid="ignore"):
        bb = va / np.linalg.norm(va, axis=-1, keepdims=True)
    return np.stack([tt, np.cross(bb, tt), bb], axis=-2)


def turn_rate(v, a) -> np.ndarray:
    r"""Turn rate :math:`\omega = v\kappa = |\mathbf v\times\mathbf a|/|\mathbf v|^2` (rad/s)."""
    v = as_vector(v, "v", 3)
    a = as_vector(a, "a", 3)
    return np.linalg.norm(np.cross(v, a), axis=-1) / np.sum(v * v, axis=-1)


def turn_model_residual(v, a, jerk) -> np.ndarray:
    r"""What the 3-D turn model misses: :math:`\dot{\mathbf a} - (-\omega^2\mathbf v)`, with
    :math:`\omega` from :func:`turn_rate`.

    For constant speed, curvature and torsion this is :math:`v^3\kappa\tau\,\mathbf b`: zero if
    and only if the motion is planar (:math:`\tau = 0`). ``(..., 3)``.
    """
    jerk = as_vector(jerk, "jerk", 3)
    w = turn_rate(v, a)
    return jerk + (w * w)[..., None] * np.asarray(v, dtype=float)


# --------------------------------------------------------------------------------------------
# frame dynamics
# --------------------------------------------------------------------------------------------
#: Sign conventions for the frame's derivative in arc length, as rows ``t, n, b``.
#: ``"standard"``: do Carmo's (27)–(29) of study 000; ``"seed000-eq23"``: the study's text
#: eq. (23) :math:`\mathbf b' = +\tau\mathbf p` used with its eqs. (27)–(28), a mix of the two
#: sign conventions (not skew-symmetric: the frame does not stay orthonormal when
#: :math:`\tau \ne 0`); ``"seed000-eq26"``: eqs. (21), (23), (26) consistently, the opposite
#: torsion sign (the curve of :math:`+\tau` is the standard curve of :math:`-\tau`).
CONVENTIONS = ("standard", "seed000-eq23", "seed000-eq26")


def frenet_generator(kappa, tau, convention: str = "standard") -> np.ndarray:
    r"""The matrix :math:`G` with :math:`E' = G E` for the frame ``E`` (rows ``t, n, b``),
    ``(..., 3, 3)``. Standard: :math:`G = \begin{bmatrix}0&\kappa&0\\-\kappa&0&\tau\\0&-\tau&0\end{bmatrix}`,
    skew-symmetric, so :math:`e^{Gs}` is a rotation. See :data:`CONVENTIONS`."""
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    k, t = np.broadcast_arrays(np.asarray(kappa, dtype=float), np.asarray(tau, dtype=float))
    G = np.zeros(k.shape + (3, 3))
    G[..., 0, 1] = k
    G[..., 1, 0] = -k
    tb = -t if convention == "seed000-eq26" else t
    G[..., 1, 2] = tb
    G[..., 2, 1] = t if convention == "seed000-eq23" else -tb
    return G


def _s0(x):
    """sin(x)/x."""
    return np.sinc(x / np.pi)


def _s1(x):
    """(1 - cos x)/x**2, stable at 0."""
    return 0.5 * np.sinc(x / (2 * np.pi)) ** 2


def _s2(x):
    """(x - sin x)/x**3, stable at 0 (series below |x| = 0.5, error < 1e-17)."""
    x = np.asarray(x, dtype=float)
    small = np.abs(x) < 0.5
    xs = np.where(small, x, 0.0)
    x2 = xs * xs
    series = np.zeros_like(xs)
    for k in range(6, -1, -1):
        series = series * (-x2) + 1.0 / _fact(2 * k + 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        direct = (x - np.sin(x)) / x**3
    return np.where(small, series, direct)


def _fact(n: int) -> float:
    return float(np.prod(np.arange(1, n + 1, dtype=float)))


def _rotation_and_integral(kappa, tau, h) -> tuple[np.ndarray, np.ndarray]:
    r"""For constant :math:`\kappa, \tau` over an arc :math:`h`: the frame map
    :math:`M = e^{Gh}` and the first row of :math:`\int_0^h e^{G\sigma}d\sigma` (the
    displacement in frame coordinates). Rodrigues' formula with :math:`G = [\mathbf w]_\times`,
    :math:`|\mathbf w| = \sqrt{\kappa^2+\tau^2}`; stable as the angle goes to zero."""
    G = frenet_generator(kappa, tau)
    G2 = G @ G
    x = np.sqrt(np.asarray(kappa, float) ** 2 + np.asarray(tau, float) ** 2) * h
    h_ = np.asarray(h, dtype=float)[..., None, None]
    M = np.eye(3) + (h_ * _s0(x)[..., None, None]) * G + (h_**2 * _s1(x)[..., None, None]) * G2
    P = h_ * np.eye(3) + (h_**2 * _s1(x)[..., None, None]) * G + (h_**3 * _s2(x)[..., None, None]) * G2
    return M, P[..., 0, :]


def initial_frame(v0, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    r"""A starting frame ``(3, 3)``: :math:`\mathbf t_0 = \mathbf v_0/|\mathbf v_0|`, the
    binormal the part of ``up`` perpendicular to it, :math:`\mathbf n_0 = \mathbf b_0\times\mathbf t_0`.

    With ``up = +z`` and level flight, :math:`\mathbf n_0` points to the left, so a positive
    curvature turns counter-clockwise seen from above (the convention of the 2-D turn models).
    Study 000 does not say how it chose :math:`\mathbf p_0, \mathbf b_0` (§4.3.2); this is our choice.
    """
    v0 = as_vector(v0, "v0", 3)
    up = as_vector(up, "up", 3)
    if v0.ndim != 1 or up.ndim != 1:
        raise ValueError(f"v0 and up must have shape (3,), got {v0.shape} and {up.shape}")
    sp_ = np.linalg.norm(v0)
    if sp_ == 0:
        raise ValueError("v0 must be a non-zero velocity, got [0, 0, 0]")
    t0 = v0 / sp_
    b0 = up - (up @ t0) * t0
    nb = np.linalg.norm(b0)
    if nb < 1e-12 * max(1.0, np.linalg.norm(up)):
        raise ValueError(f"up must not be parallel to v0, got up={up.tolist()}, v0={v0.tolist()}")
    b0 = b0 / nb
    return np.stack([t0, np.cross(b0, t0), b0])


# --------------------------------------------------------------------------------------------
# the simulator
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Segment:
    r"""One piece of a trajectory: ``length`` (m of arc) at constant signed curvature
    ``kappa`` (1/m; 0 is straight, negative turns towards :math:`-\mathbf n`), torsion ``tau``
    (1/m) and tangential acceleration ``accel`` (m/s², the speed changes as
    :math:`v^2 = v_0^2 + 2 a s`)."""

    length: float
    kappa: float = 0.0
    tau: float = 0.0
    accel: float = 0.0

    def __post_init__(self):
        for name in ("length", "kappa", "tau", "accel"):
            val = getattr(self, name)
            arr = as_float_array(val, f"Segment.{name}")
            if isinstance(val, bool) or arr.ndim != 0 or not np.isfinite(arr):
                raise ValueError(f"Segment.{name} must be a finite scalar, got {val!r}")
            object.__setattr__(self, name, float(arr))
        if self.length <= 0:
            raise ValueError(f"Segment.length must be > 0 (m), got {self.length!r}")

    @property
    def turning(self) -> bool:
        """True for a curved segment (non-zero curvature)."""
        return self.kappa != 0.0


def segments_from_radii(radii, lengths) -> list[Segment]:
    r"""Study 000's segment description (§4.3.1): radius of curvature :math:`R = 1/\kappa` per
    segment, **R = 0 meaning a straight line**, and arc lengths. A negative radius turns
    right (the study has no turn direction)."""
    radii = check_finite(as_float_array(radii, "radii"), "radii")
    lengths = check_finite(as_float_array(lengths, "lengths"), "lengths")
    if radii.ndim != 1 or radii.shape != lengths.shape:
        raise ValueError(f"radii and lengths must be 1-D of equal length, got {radii.shape} and {lengths.shape}")
    return [Segment(float(L), 0.0 if R == 0 else 1.0 / float(R)) for R, L in zip(radii, lengths)]


class FrenetTrack(NamedTuple):
    """A simulated trajectory, time first.

    Attributes
    ----------
    t : (T,) times (s). s : (T,) arc length (m). r, v, a : (T, 3) position (m), velocity (m/s),
    acceleration (m/s²). frame : (T, 3, 3) rows t, n, b. kappa, tau : (T,) signed curvature and
    torsion of the segment at each sample (1/m). segment : (T,) index of that segment.
    """

    t: np.ndarray
    s: np.ndarray
    r: np.ndarray
    v: np.ndarray
    a: np.ndarray
    frame: np.ndarray
    kappa: np.ndarray
    tau: np.ndarray
    segment: np.ndarray

    @property
    def jerk(self) -> np.ndarray:
        r"""Exact jerk :math:`\dot{\mathbf a}` inside a segment, ``(T, 3)``: with
        :math:`\mathbf a = a_t\mathbf t + v^2\kappa\mathbf n`,
        :math:`\dot{\mathbf a} = -v^3\kappa^2\mathbf t + 3 v a_t\kappa\,\mathbf n + v^3\kappa\tau\,\mathbf b`."""
        speed = np.linalg.norm(self.v, axis=-1)
        acc_t = np.einsum("ti,ti->t", self.a, self.frame[:, 0])
        k, tau = self.kappa, self.tau
        c = np.stack([-speed**3 * k**2, 3 * speed * acc_t * k, speed**3 * k * tau], axis=-1)
        return np.einsum("tj,tji->ti", c, self.frame)

    @property
    def turning(self) -> np.ndarray:
        """(T,) bool, True where the segment is curved: the manoeuvre label."""
        return self.kappa != 0.0


def _check_segments(segments) -> list[Segment]:
    segs = list(segments)
    if not segs or not all(isinstance(s, Segment) for s in segs):
        raise TypeError(f"segments must be a non-empty sequence of Segment, got {segments!r}")
    return segs


def _schedule(segs: list[Segment], speed0: float, dt: float, n_max: int | None):
    """Sample times, arc lengths, speeds, tangential accelerations and segment indices."""
    L = np.array([s.length for s in segs])
    acc = np.array([s.accel for s in segs])
    S = np.concatenate([[0.0], np.cumsum(L)])
    v_start = np.empty(len(segs))
    dur = np.empty(len(segs))
    v = speed0
    for i, s in enumerate(segs):
        disc = v * v + 2 * s.accel * s.length
        if disc <= 0:
            raise ValueError(f"segment {i} decelerates to a stop: speed {v:.6g} m/s, accel {s.accel:.6g} m/s², "
                             f"length {s.length:.6g} m")
        v_start[i] = v
        v_end = np.sqrt(disc)
        dur[i] = 2 * s.length / (v + v_end)
        v = v_end
    tk = np.concatenate([[0.0], np.cumsum(dur)])
    short = int(np.argmin(dur))
    if dt > dur[short]:  # a segment shorter than dt can fall between two samples, unseen
        raise ValueError(f"dt must be at most the duration of every segment (each must be sampled), got dt = {dt:g} s "
                         f"but segment {short} lasts {dur[short]:.6g} s ({segs[short].length:g} m); total duration "
                         f"{tk[-1]:.6g} s; use a smaller dt")
    n = int(np.floor(tk[-1] / dt * (1 + 1e-12))) + 1
    if n_max is not None:
        n = min(n, n_max)
    t = np.arange(n) * dt
    idx = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(segs) - 1)
    u = t - tk[idx]
    speed = v_start[idx] + acc[idx] * u
    s = np.minimum(S[idx] + v_start[idx] * u + 0.5 * acc[idx] * u * u, S[idx + 1])
    return t, s, speed, acc[idx], idx, S


def _compose_steps(s, S, seg_k, seg_t, E0, r0):
    """Frames and positions at the arc lengths ``s`` by composing one rotation per step
    (steps split at the segment boundaries ``S``)."""
    inner = S[1:-1][S[1:-1] < s[-1]]
    knots = np.concatenate([s, inner])
    is_sample = np.concatenate([np.ones(len(s), bool), np.zeros(len(inner), bool)])
    order = np.argsort(knots, kind="stable")
    knots, is_sample = knots[order], is_sample[order]
    h = np.diff(knots)
    piece = np.clip(np.searchsorted(S, 0.5 * (knots[:-1] + knots[1:]), side="right") - 1, 0, len(seg_k) - 1)
    M, P = _rotation_and_integral(seg_k[piece], seg_t[piece], h)
    frames = np.empty((len(knots), 3, 3))
    pos = np.empty((len(knots), 3))
    E, r = E0.copy(), r0.astype(float).copy()
    frames[0], pos[0] = E, r
    for i in range(len(h)):
        r = r + P[i] @ E
        E = M[i] @ E
        frames[i + 1], pos[i + 1] = E, r
    return frames[is_sample], pos[is_sample]


def simulate(segments: Sequence[Segment], dt: float, r0=(0.0, 0.0, 0.0), v0=(1.0, 0.0, 0.0), *,
             up=(0.0, 0.0, 1.0), frame0=None, n_max: int | None = None,
             stepwise: bool = False) -> FrenetTrack:
    r"""Exact trajectory of piecewise constant curvature, torsion and tangential acceleration,
    sampled every ``dt`` seconds.

    Over a stretch of arc :math:`h` inside one segment the frame obeys :math:`E' = GE` with
    constant :math:`G` (:func:`frenet_generator`), so :math:`E(s+h) = e^{Gh}E(s)`: a rotation
    about the Darboux vector :math:`\mathbf d = \tau\mathbf t + \kappa\mathbf b` (fixed in
    space inside a segment) by the angle :math:`|\mathbf d|h`, computed with Rodrigues'
    formula; the position advances by :math:`\int_0^h \mathbf t\,d\sigma`, also in closed
    form. Nothing is approximated: the frame stays orthonormal to round-off and a full circle
    closes. The arc length at each sample is exact for a constant tangential acceleration.

    By default each sample is the segment-start frame rotated by the whole arc covered so far
    in that segment (one rotation, no rounding accumulates from step to step). With
    ``stepwise=True`` the rotations of the individual steps are composed instead (steps split
    at segment ends); rounding then accumulates slowly, about :math:`N\epsilon` after
    :math:`N` steps.

    Parameters
    ----------
    segments : sequence of :class:`Segment`.
    dt : sampling interval (s), ``> 0`` and at most the duration of the shortest segment
        (``ValueError`` otherwise: a segment shorter than ``dt`` could have no sample).
    r0, v0 : (3,) initial position (m) and velocity (m/s, non-zero).
    up : (3,) sets the initial binormal (see :func:`initial_frame`); ignored if ``frame0`` given.
    frame0 : optional (3, 3) initial frame, rows ``t, n, b`` (right-handed orthonormal, ``t``
        along ``v0``).
    n_max : optional cap on the number of samples (a positive integer).
    stepwise : compose the per-step rotations (see above).

    Returns
    -------
    FrenetTrack with samples at ``t = 0, dt, 2dt, ...`` up to the end of the last segment.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.frenet import Segment, simulate
    >>> circle = [Segment(length=2 * np.pi * 10.0, kappa=0.1)]     # one turn of radius 10 m
    >>> track = simulate(circle, dt=np.pi / 2, v0=(1.0, 0.0, 0.0))  # at 1 m/s: 40 steps
    >>> track.t.shape, track.r.shape, track.frame.shape
    ((41,), (41, 3), (41, 3, 3))
    >>> print(np.round(track.r[[10, 40]], 6) + 0.0)               # a quarter turn, then closed exactly
    [[10. 10.  0.]
     [ 0.  0.  0.]]
    """
    segs = _check_segments(segments)
    d = positive_scalar(dt, "dt", "s")
    if n_max is not None and (isinstance(n_max, bool) or not isinstance(n_max, (int, np.integer)) or n_max < 1):
        raise ValueError(f"n_max must be a positive integer or None, got {n_max!r}")
    r0 = as_vector(r0, "r0", 3)
    if r0.shape != (3,):
        raise ValueError(f"r0 must have shape (3,), got shape {r0.shape}")
    v0 = as_vector(v0, "v0", 3)
    speed0 = float(np.linalg.norm(v0))
    if frame0 is None:
        E0 = initial_frame(v0, up)
    else:
        E0 = as_vector(frame0, "frame0", 3)
        if E0.shape != (3, 3) or orthonormality_error(E0) > 1e-9 or np.linalg.det(E0) < 0:
            raise ValueError(f"frame0 must be a right-handed orthonormal (3, 3) frame (rows t, n, b), got {E0.tolist()}")
        if v0.shape != (3,) or speed0 == 0 or np.linalg.norm(E0[0] - v0 / speed0) > 1e-9:
            raise ValueError(f"frame0's tangent (first row) must point along v0, got {E0[0].tolist()} and v0={v0.tolist()}")
    t, s, speed, acc_t, idx, S = _schedule(segs, speed0, d, n_max)
    seg_k = np.array([g.kappa for g in segs])
    seg_t = np.array([g.tau for g in segs])
    if stepwise:
        frames, pos = _compose_steps(s, S, seg_k, seg_t, E0, r0)
    else:
        # frame and position at each segment start, then each sample from its segment start
        M, P = _rotation_and_integral(seg_k, seg_t, np.diff(S))
        E_start = np.empty((len(segs), 3, 3))
        r_start = np.empty((len(segs), 3))
        E, r = E0.copy(), r0.astype(float).copy()
        for j in range(len(segs)):
            E_start[j], r_start[j] = E, r
            r, E = r + P[j] @ E, M[j] @ E
        Ms, Ps = _rotation_and_integral(seg_k[idx], seg_t[idx], s - S[idx])
        frames = Ms @ E_start[idx]
        pos = r_start[idx] + np.einsum("ki,kij->kj", Ps, E_start[idx])
    kappa, tau = seg_k[idx], seg_t[idx]
    vel = speed[:, None] * frames[:, 0]
    accel = acc_t[:, None] * frames[:, 0] + (speed**2 * kappa)[:, None] * frames[:, 1]
    return FrenetTrack(t, s, pos, vel, accel, frames, kappa, tau, idx)


def simulate_euler(segments: Sequence[Segment], ds: float, r0=(0.0, 0.0, 0.0), v0=(1.0, 0.0, 0.0), *,
                   up=(0.0, 0.0, 1.0), convention: str = "standard", normalize: bool = True) -> FrenetTrack:
    r"""Study 000's simulator as printed (§4.3.3): explicit Euler in arc length, then each
    vector normalised on its own (no re-orthogonalisation), then the position from the
    **updated** tangent,

    .. math::

        \mathbf u_k = \frac{\mathbf u_{k-1} + \kappa\mathbf p_{k-1}ds}{|\cdot|},\;
        \mathbf p_k = \frac{\mathbf p_{k-1} + (-\kappa\mathbf u_{k-1} + \tau\mathbf b_{k-1})ds}{|\cdot|},\;
        \mathbf b_k = \frac{\mathbf b_{k-1} - \tau\mathbf p_{k-1}ds}{|\cdot|},\;
        \mathbf r_k = \mathbf r_{k-1} + \mathbf u_k\,ds,\; \mathbf v_k = |\mathbf v_0|\mathbf u_k .

    Each segment runs ``round(length / ds)`` equal steps of about ``ds`` (the study's ``L/ds``
    iterations, adjusted so each segment has its exact length); the speed is constant
    (``Segment.accel`` must be 0), so the samples are about ``dt = ds/|v0|`` apart.
    ``convention`` picks the torsion signs (:data:`CONVENTIONS`), ``normalize=False`` drops
    eqs. (42)–(44). Kept to measure its errors; use :func:`simulate` for data.
    """
    segs = _check_segments(segments)
    if any(g.accel != 0 for g in segs):
        raise ValueError("simulate_euler keeps the speed constant (as study 000): every Segment.accel must be 0")
    step = positive_scalar(ds, "ds", "m")
    r = as_vector(r0, "r0", 3).astype(float).copy()
    v0 = as_vector(v0, "v0", 3)
    E = initial_frame(v0, up)
    speed = float(np.linalg.norm(v0))
    counts = [max(1, int(round(g.length / step))) for g in segs]
    n = 1 + sum(counts)
    s = np.zeros(n)
    frames = np.empty((n, 3, 3))
    pos = np.empty((n, 3))
    seg_idx = np.empty(n, dtype=int)
    frames[0], pos[0], seg_idx[0] = E, r, 0
    k = 1
    for j, (g, c) in enumerate(zip(segs, counts)):
        h = g.length / c
        G = frenet_generator(g.kappa, g.tau, convention) * h
        for _ in range(c):
            E = E + G @ E
            if normalize:
                E = E / np.linalg.norm(E, axis=1, keepdims=True)
            r = r + E[0] * h
            frames[k], pos[k], seg_idx[k], s[k] = E, r, j, s[k - 1] + h
            k += 1
    kappa = np.array([g.kappa for g in segs])[seg_idx]
    tau = np.array([g.tau for g in segs])[seg_idx]
    vel = speed * frames[:, 0]
    accel = (speed**2 * kappa)[:, None] * frames[:, 1]
    return FrenetTrack(s / speed, s, pos, vel, accel, frames, kappa, tau, seg_idx)


def orthonormality_error(frame) -> np.ndarray:
    r""":math:`\max_{ij}|E E^\top - I|_{ij}` of frames ``(..., 3, 3)``, shape ``(...)``."""
    E = np.asarray(frame, dtype=float)
    return np.max(np.abs(E @ np.swapaxes(E, -1, -2) - np.eye(3)), axis=(-2, -1))


def circle_closure(radius: float, ds: float, method: str = "exact") -> float:
    r"""Distance (m) between the start and the end of one full circle of radius ``radius``
    (one segment of length :math:`2\pi R`) simulated with ``method`` ``"exact"``
    (:func:`simulate` at unit speed, ``dt = ds``) or ``"euler"`` (:func:`simulate_euler`).
    Zero for an exact integrator."""
    R = positive_scalar(radius, "radius", "m")
    ds = positive_scalar(ds, "ds", "m")
    seg = [Segment(2 * np.pi * R, 1.0 / R)]
    if method == "exact":
        # sample exactly at the end: choose dt dividing the circumference
        n = max(1, int(round(2 * np.pi * R / ds)))
        tr = simulate(seg, 2 * np.pi * R / n, n_max=n + 1)
    elif method == "euler":
        tr = simulate_euler(seg, 2 * np.pi * R / max(1, int(round(2 * np.pi * R / ds))))
    else:
        raise ValueError(f"method must be 'exact' or 'euler', got {method!r}")
    return float(np.linalg.norm(tr.r[-1] - tr.r[0]))


def euler_endpoint_error(segments: Sequence[Segment], ds: float) -> tuple[float, float]:
    r"""End-point error of study 000's Euler simulator and its first-order prediction.

    Returns ``(error, leading)``: ``error`` is :math:`|\mathbf r_{Euler}(L) - \mathbf r(L)|` (m),
    :func:`simulate_euler` against the exact :func:`simulate` at unit speed from the origin, and
    ``leading`` is :math:`\tfrac{ds}{2}\,|\mathbf t(L) - \mathbf t(0)|`. The Euler position steps
    along the tangent at the *end* of each step, so it samples the path half a step ahead:
    :math:`\sum_k \mathbf t(s_k)\,ds = \int_{ds/2}^{L+ds/2}\mathbf t\,d\sigma + O(ds^2)`, an error
    :math:`\tfrac{ds}{2}(\mathbf t(L) - \mathbf t(0)) + O(ds^2)`: first order in ``ds``, except on
    a closed curve, where it cancels (see :func:`circle_closure`).
    """
    segs = _check_segments(segments)
    step = positive_scalar(ds, "ds", "m")
    eu = simulate_euler(segs, step)
    n = len(eu.t) - 1
    total = float(sum(g.length for g in segs))
    ex = simulate(segs, total / n, n_max=n + 1)
    error = float(np.linalg.norm(eu.r[-1] - ex.r[-1]))
    leading = 0.5 * step * float(np.linalg.norm(ex.frame[-1, 0] - ex.frame[0, 0]))
    return error, leading
