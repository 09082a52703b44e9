r"""Radar measurement models: 2-D range–bearing and 3-D range–azimuth–elevation.

Geometry (right-handed, angles in radians, measured counter-clockwise from the +x axis;
East–North–Up when x is East):

.. math::

    r = \lVert p - s \rVert, \qquad
    \theta = \operatorname{atan2}(\Delta y, \Delta x), \qquad
    \varphi = \operatorname{atan2}\!\left(\Delta z, \sqrt{\Delta x^2 + \Delta y^2}\right),

with ``p`` the target position taken from the state at ``position_indices`` and ``s`` the
sensor position. Compass azimuths (clockwise from North) are converted at the edges with
:func:`compass_to_math` / :func:`math_to_compass`.

The measurement functions, their Jacobians and the polar-to-Cartesian conversion with its
Jacobian are derived with SymPy here (:func:`polar_measurement`, :func:`polar_to_cartesian_expr`)
and generated once per process with ``lambdify(cse=True)``. The Jacobians are singular at
the sensor (``r = 0``) and, in 3-D, straight overhead (``\rho = 0``).

Converted measurements (:meth:`Radar.to_cartesian`):

* ``"linearized"``: :math:`p = s + g(z)`, :math:`C = J R J^\top` with :math:`J = \partial g / \partial z`
  at the measurement; biased at long range with large angle noise.
* ``"debiased"``: the unbiased conversion of Longbin, Xiaoquan, Yiyu, Kang & Bar-Shalom (1998):
  each cosine/sine factor of the measured angles is divided by :math:`\lambda = e^{-\sigma_\theta^2/2}`,
  and the covariance is the measurement-conditioned :math:`E[(p_u - p)(p_u - p)^\top \mid z]`, built
  from :math:`E[\cos(\theta_m - \tilde\theta)] = \lambda\cos\theta_m`,
  :math:`E[\cos^2(\theta_m - \tilde\theta)] = \tfrac12(1 + \lambda^4 \cos 2\theta_m)`, etc.

Seed 001's velocity estimate from the last three converted positions is
:func:`three_point_velocity` (the 3-point least-squares quadratic fit, which interpolates
exactly, so it is the Lagrange derivative :math:`(3p_k - 4p_{k-1} + p_{k-2})/(2T)` for uniform
sampling, with noise gain :math:`\sqrt{26}/(2T)`).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import sympy as sp

from .. import symbolic as sym
from .._validate import as_float_array, as_vector, check_covariance, check_rng
from ..ekf import wrap_angle

__all__ = ["polar_measurement", "polar_to_cartesian_expr", "Radar", "RangeBearing", "RangeAzimuthElevation",
           "Converted", "three_point_velocity", "three_point_weights", "three_point_velocity_gain", "three_point_state",
           "compass_to_math", "math_to_compass"]

_dx, _dy, _dz = sp.symbols("Delta_x Delta_y Delta_z", real=True)
_r = sp.Symbol("r", positive=True)
_th, _ph = sp.symbols("theta varphi", real=True)


def polar_measurement(ndim: int) -> tuple[sp.Matrix, sp.Matrix]:
    r"""SymPy ``(h, d)``: the polar measurement ``h`` of the relative position ``d``.

    ``ndim=2``: :math:`h = [r, \theta]`, ``d = [Δx, Δy]``; ``ndim=3``: :math:`h = [r, \theta, \varphi]`,
    ``d = [Δx, Δy, Δz]``.
    """
    if ndim == 2:
        d = sp.Matrix([_dx, _dy])
        return sp.Matrix([sp.sqrt(_dx**2 + _dy**2), sp.atan2(_dy, _dx)]), d
    if ndim == 3:
        d = sp.Matrix([_dx, _dy, _dz])
        rho = sp.sqrt(_dx**2 + _dy**2)
        return sp.Matrix([sp.sqrt(_dx**2 + _dy**2 + _dz**2), sp.atan2(_dy, _dx), sp.atan2(_dz, rho)]), d
    raise ValueError(f"ndim must be 2 or 3, got {ndim!r}")


def polar_to_cartesian_expr(ndim: int) -> tuple[sp.Matrix, sp.Matrix]:
    r"""SymPy ``(g, z)``: the relative Cartesian position ``g`` of the polar measurement ``z``.

    2-D: :math:`g = r[\cos\theta, \sin\theta]`; 3-D: :math:`g = r[\cos\varphi\cos\theta, \cos\varphi\sin\theta, \sin\varphi]`.
    """
    if ndim == 2:
        return sp.Matrix([_r * sp.cos(_th), _r * sp.sin(_th)]), sp.Matrix([_r, _th])
    if ndim == 3:
        return (sp.Matrix([_r * sp.cos(_ph) * sp.cos(_th), _r * sp.cos(_ph) * sp.sin(_th), _r * sp.sin(_ph)]),
                sp.Matrix([_r, _th, _ph]))
    raise ValueError(f"ndim must be 2 or 3, got {ndim!r}")


@lru_cache(maxsize=None)
def _generated(ndim: int) -> dict:
    """Numeric functions generated once per process from the SymPy expressions."""
    h, d = polar_measurement(ndim)
    g, z = polar_to_cartesian_expr(ndim)
    return {
        "h": sym.GeneratedFunction(list(d), h),
        "H": sym.GeneratedFunction(list(d), h.jacobian(d)),
        "g": sym.GeneratedFunction(list(z), g),
        "J": sym.GeneratedFunction(list(z), g.jacobian(z)),
    }


class Converted(NamedTuple):
    """A polar measurement converted to Cartesian position: ``p`` ``(..., d)``, covariance ``C`` ``(..., d, d)``."""

    p: np.ndarray
    C: np.ndarray


# The trig factor of each Cartesian component per angle: "c" cos, "s" sin, "1" none.
_FACTORS = {2: (("c",), ("s",)), 3: (("c", "c"), ("s", "c"), ("1", "s"))}


def _trig_moments(theta: np.ndarray, lam: np.ndarray):
    """First and second moments of cos/sin of ``theta_m - noise`` given the measured ``theta_m``."""
    c, s = np.cos(theta), np.sin(theta)
    l4 = lam**4
    c2, s2 = np.cos(2 * theta), np.sin(2 * theta)
    value = {"c": c, "s": s, "1": np.ones_like(theta)}
    first = {"c": lam * c, "s": lam * s, "1": np.ones_like(theta)}
    second = {("c", "c"): 0.5 * (1 + l4 * c2), ("s", "s"): 0.5 * (1 - l4 * c2), ("c", "s"): 0.5 * l4 * s2}
    for (a, b), v in list(second.items()):
        second[(b, a)] = v
    for a in "cs1":
        second[("1", a)] = second[(a, "1")] = first[a]
    second[("1", "1")] = np.ones_like(theta)
    debias = {"c": 1 / lam, "s": 1 / lam, "1": np.ones_like(theta)}
    return value, first, second, debias


def _polar_moments(z: np.ndarray, sigmas: np.ndarray):
    """Debiased point ``p_u``, ``E[p]`` and ``E[p p^T]`` of ``p = g(z - noise)`` given ``z``."""
    ndim = z.shape[-1]
    r, angles = z[..., 0], [z[..., 1 + i] for i in range(ndim - 1)]
    lams = np.exp(-0.5 * sigmas[1:] ** 2)
    mom = [_trig_moments(a, lam) for a, lam in zip(angles, lams)]
    fac = _FACTORS[ndim]
    pu = np.stack([r * np.prod([mom[k][0][f[k]] * mom[k][3][f[k]] for k in range(len(f))], axis=0)
                   for f in fac], axis=-1)
    Ep = np.stack([r * np.prod([mom[k][1][f[k]] for k in range(len(f))], axis=0) for f in fac], axis=-1)
    r2 = r**2 + sigmas[0] ** 2
    Epp = np.empty(z.shape[:-1] + (ndim, ndim))
    for i, fi in enumerate(fac):
        for j, fj in enumerate(fac):
            Epp[..., i, j] = r2 * np.prod([mom[k][2][(fi[k], fj[k])] for k in range(len(fi))], axis=0)
    return pu, Ep, Epp


def _outer(a, b):
    return a[..., :, None] * b[..., None, :]


def _sym(C):
    return 0.5 * (C + np.swapaxes(C, -1, -2))


@dataclass(frozen=True)
class Radar:
    r"""A polar radar at ``sensor`` measuring the position components ``position_indices`` of the state.

    Use :class:`RangeBearing` (2-D) or :class:`RangeAzimuthElevation` (3-D).

    Attributes
    ----------
    sigmas : standard deviations ``(sigma_range (m), sigma_angle (rad)[, sigma_elevation (rad)])``.
    position_indices : state components of the position, ``(0, 2)`` or ``(0, 2, 4)`` for the
        interleaved state ``[x, vx, y, vy(, z, vz)]``.
    sensor : sensor position (m).
    """

    sigmas: tuple[float, ...]
    position_indices: tuple[int, ...]
    sensor: tuple[float, ...]

    def __post_init__(self):
        d = self.ndim
        sig = tuple(float(s) for s in np.atleast_1d(as_float_array(self.sigmas, "sigmas")))
        if len(sig) != d or not all(np.isfinite(s) and s > 0 for s in sig):
            raise ValueError(f"sigmas must be {d} positive standard deviations (range, angles), got {self.sigmas!r}")
        big = [i for i in range(1, d) if sig[i] > np.pi]
        if big:  # an angle noise above pi rad is no angle noise: degrees passed for radians
            raise ValueError(f"sigmas[{big[0]}] is an angle standard deviation in radians and must be at most pi, got "
                             f"{sig[big[0]]!r} rad in sigmas={self.sigmas!r}; convert degrees with np.deg2rad, "
                             f"e.g. sigmas=({sig[0]!r}, np.deg2rad({sig[big[0]]!r}))")
        idx = tuple(int(i) for i in self.position_indices)
        if len(idx) != d or min(idx) < 0 or len(set(idx)) != d:
            raise ValueError(f"position_indices must be {d} distinct non-negative indices, got {self.position_indices!r}")
        sensor = as_vector(self.sensor, "sensor", d)
        if sensor.ndim != 1:
            raise ValueError(f"sensor must have shape ({d},), got shape {sensor.shape}")
        object.__setattr__(self, "sigmas", sig)
        object.__setattr__(self, "position_indices", idx)
        object.__setattr__(self, "sensor", tuple(float(s) for s in sensor))

    ndim = 0  # set by the subclasses

    @property
    def angle_components(self) -> tuple[int, ...]:
        """Indices of the measurement that are angles (wrap their residuals)."""
        return tuple(range(1, self.ndim))

    @property
    def R(self) -> np.ndarray:
        """Measurement-noise covariance ``diag(sigmas**2)``, ``(d, d)``."""
        return np.diag(np.square(self.sigmas))

    def _relative(self, x) -> np.ndarray:
        x = as_vector(x, "x")
        if x.shape[-1] <= max(self.position_indices):
            raise ValueError(f"x must have shape (..., n) with n > {max(self.position_indices)}, got shape {x.shape}")
        return x[..., list(self.position_indices)] - np.asarray(self.sensor)

    def h(self, x) -> np.ndarray:
        """Noise-free measurement ``(..., d)`` of the states ``x`` ``(..., n)``; angles in (-pi, pi]."""
        d = self._relative(x)
        return _generated(self.ndim)["h"](*np.moveaxis(d, -1, 0))[..., 0]

    def jacobian(self, x) -> np.ndarray:
        """Jacobian ``dh/dx`` ``(..., d, n)`` (zero in the non-position columns)."""
        x = as_vector(x, "x")
        d = self._relative(x)
        Hp = _generated(self.ndim)["H"](*np.moveaxis(d, -1, 0))
        H = np.zeros(Hp.shape[:-1] + (x.shape[-1],))
        H[..., list(self.position_indices)] = Hp
        return H

    def simulate(self, x, rng: np.random.Generator) -> np.ndarray:
        """Noisy measurements of the states ``x`` ``(..., n)``: ``h(x)`` plus Gaussian noise, angles wrapped."""
        check_rng(rng)
        z = self.h(x)
        z = z + rng.standard_normal(z.shape) * np.asarray(self.sigmas)
        z[..., 1:] = wrap_angle(z[..., 1:])
        return z

    def to_cartesian(self, z, method: str = "debiased") -> Converted:
        """Convert measurements ``z`` ``(..., d)`` to Cartesian positions with covariances.

        ``method="linearized"``: ``p = s + g(z)``, ``C = J R J^T``. ``method="debiased"``:
        the unbiased conversion and measurement-conditioned covariance of Longbin et al. (1998).
        """
        z = as_vector(z, "z", self.ndim)
        if method == "linearized":
            zz = np.moveaxis(z, -1, 0)
            g = _generated(self.ndim)["g"](*zz)[..., 0]
            J = _generated(self.ndim)["J"](*zz)
            return Converted(g + np.asarray(self.sensor), _sym(J @ self.R @ np.swapaxes(J, -1, -2)))
        if method == "debiased":
            pu, Ep, Epp = _polar_moments(z, np.asarray(self.sigmas))
            C = _outer(pu, pu) - _outer(pu, Ep) - _outer(Ep, pu) + Epp  # E[(pu - p)(pu - p)^T | z]
            return Converted(pu + np.asarray(self.sensor), _sym(C))
        raise ValueError(f"method must be 'linearized' or 'debiased', got {method!r}")

    def exact_moments(self, z) -> Converted:
        r"""Exact mean and covariance of the Cartesian position :math:`s + g(\tilde z)` when
        :math:`\tilde z \sim N(z, R)` (``z`` ``(..., d)``): the reference against which the
        linearized and unscented approximations are judged (closed form, no sampling).
        """
        z = as_vector(z, "z", self.ndim)
        _, Ep, Epp = _polar_moments(z, np.asarray(self.sigmas))
        return Converted(Ep + np.asarray(self.sensor), _sym(Epp - _outer(Ep, Ep)))


@dataclass(frozen=True)
class RangeBearing(Radar):
    r"""2-D radar, :math:`z = [r, \theta]` with :math:`\theta = \operatorname{atan2}(\Delta y, \Delta x)`.

    ``sigmas = (sigma_range, sigma_bearing)`` in m and rad; default position indices ``(0, 2)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.sensors.radar import RangeBearing
    >>> radar = RangeBearing(sigmas=(10.0, np.deg2rad(1.0)))   # m and rad, at the origin
    >>> x = np.array([3000.0, 0.0, 4000.0, 0.0])                # state [x, vx, y, vy]
    >>> print(np.round(radar.h(x), 6).tolist())                 # range (m), bearing from +x (rad)
    [5000.0, 0.927295]
    >>> radar.jacobian(x).shape
    (2, 4)
    >>> print(np.round(radar.to_cartesian(radar.h(x)).p, 1))    # debiased conversion to x, y (m)
    [3000.5 4000.6]
    """

    position_indices: tuple[int, ...] = (0, 2)
    sensor: tuple[float, ...] = (0.0, 0.0)
    ndim = 2


@dataclass(frozen=True)
class RangeAzimuthElevation(Radar):
    r"""3-D radar, :math:`z = [r, \theta, \varphi]`: range, azimuth from +x (counter-clockwise),
    elevation above the x–y plane.

    ``sigmas = (sigma_range, sigma_azimuth, sigma_elevation)`` in m and rad; default position
    indices ``(0, 2, 4)`` for ``[x, vx, y, vy, z, vz, ...]``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.sensors.radar import RangeAzimuthElevation
    >>> radar = RangeAzimuthElevation(sigmas=(10.0, 0.01, 0.01))
    >>> print(np.round(radar.h(np.array([3.0, 0.0, 4.0, 0.0, 0.0, 0.0])), 6) + 0.0)   # r, azimuth, elevation
    [5.       0.927295 0.      ]
    """

    position_indices: tuple[int, ...] = (0, 2, 4)
    sensor: tuple[float, ...] = (0.0, 0.0, 0.0)
    ndim = 3


def compass_to_math(azimuth) -> np.ndarray:
    r"""Compass azimuth (clockwise from North = +y) to the math angle from +x (counter-clockwise),
    :math:`\theta = \pi/2 - a`, wrapped to :math:`(-\pi, \pi]`."""
    return wrap_angle(0.5 * np.pi - as_float_array(azimuth, "azimuth"))


def math_to_compass(theta) -> np.ndarray:
    r"""Math angle from +x to compass azimuth from North in :math:`[0, 2\pi)`."""
    return np.mod(0.5 * np.pi - as_float_array(theta, "theta"), 2.0 * np.pi)


# --------------------------------------------------------------------------------------------
# seed 001: velocity from the last three positions
# --------------------------------------------------------------------------------------------
def three_point_weights(times) -> np.ndarray:
    r"""Weights ``w`` with :math:`\hat v(t_2) = w_0 p_0 + w_1 p_1 + w_2 p_2`: the derivative at the
    newest time of the quadratic through three points (the 3-point least-squares fit).

    .. math::

        w_0 = \frac{t_2 - t_1}{(t_0 - t_1)(t_0 - t_2)},\;
        w_1 = \frac{t_2 - t_0}{(t_1 - t_0)(t_1 - t_2)},\;
        w_2 = \frac{2t_2 - t_0 - t_1}{(t_2 - t_0)(t_2 - t_1)}

    ``times`` ``(3, ...)``, strictly increasing; returns ``(3, ...)``. Uniform spacing ``T`` gives
    ``[1, -4, 3] / (2T)``.
    """
    t = as_float_array(times, "times")
    if t.ndim < 1 or t.shape[0] != 3:
        raise ValueError(f"times must have shape (3, ...) (oldest first), got shape {t.shape}")
    t0, t1, t2 = t
    if not (np.all(t1 > t0) and np.all(t2 > t1)):
        raise ValueError("times must be strictly increasing (oldest first)")
    return np.stack([(t2 - t1) / ((t0 - t1) * (t0 - t2)),
                     (t2 - t0) / ((t1 - t0) * (t1 - t2)),
                     (2 * t2 - t0 - t1) / ((t2 - t0) * (t2 - t1))])


def three_point_velocity(positions, dt=None, times=None, covariances=None):
    r"""Seed 001's velocity from the last three positions (3-point least squares = Lagrange derivative).

    Parameters
    ----------
    positions : (3, ..., d) positions, oldest first, newest last (time first).
    dt : uniform sampling interval (s); or give ``times`` (3, ...) instead.
    covariances : optional (3, ..., d, d) covariances of independent position errors.

    Returns
    -------
    v : (..., d) velocity at the newest time; with ``covariances`` also its covariance
        :math:`\sum_i w_i^2 C_i` ``(..., d, d)``. For equal ``C`` and uniform ``dt`` the
        standard deviation gain is :math:`\sqrt{26}/(2T)` (:func:`three_point_velocity_gain`).
    """
    p = as_float_array(positions, "positions")
    if p.ndim < 2 or p.shape[0] != 3:
        raise ValueError(f"positions must have shape (3, ..., d) (oldest first), got shape {p.shape}")
    if (dt is None) == (times is None):
        raise ValueError(f"give exactly one of dt and times, got dt={dt!r}, times={times!r}")
    if dt is not None:
        dt = float(dt)
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
        times = np.array([0.0, dt, 2 * dt])
    w = three_point_weights(times)
    w = w.reshape(w.shape + (1,) * (p.ndim - w.ndim))
    v = np.sum(w * p, axis=0)
    if covariances is None:
        return v
    d = p.shape[-1]
    C = check_covariance(covariances, "covariances", d)
    if C.shape[0] != 3:
        raise ValueError(f"covariances must have shape (3, ..., {d}, {d}), got shape {C.shape}")
    return v, np.sum(np.square(w)[..., None] * C, axis=0)


def three_point_velocity_gain(dt) -> float:
    r"""Velocity noise std per unit position noise std for uniform sampling: :math:`\sqrt{26}/(2T)`."""
    dt = float(dt)
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
    return float(np.sqrt(26.0) / (2.0 * dt))


def three_point_state(positions, covariances, dt=None, times=None) -> tuple[np.ndarray, np.ndarray]:
    r"""Initial state and covariance from the last three position fixes (seed 001's track start).

    Position: the newest fix :math:`p_2`; velocity: :func:`three_point_velocity`. With
    independent fix errors of covariances :math:`C_i`, the joint covariance is
    :math:`\operatorname{Cov}(p_2) = C_2`, :math:`\operatorname{Cov}(p_2, v) = w_2 C_2`,
    :math:`\operatorname{Cov}(v) = \sum_i w_i^2 C_i`.

    Parameters
    ----------
    positions : (3, ..., d) fixes, oldest first (e.g. converted radar measurements).
    covariances : (3, ..., d, d) their error covariances.
    dt, times : uniform interval or the three times, as in :func:`three_point_velocity`.

    Returns
    -------
    x : (..., 2d) interleaved state ``[x, vx, y, vy(, z, vz)]`` at the newest time.
    P : (..., 2d, 2d) its covariance.
    """
    v, Cv = three_point_velocity(positions, dt=dt, times=times, covariances=covariances)
    p = as_float_array(positions, "positions")[-1]
    C = check_covariance(covariances, "covariances", p.shape[-1])
    if dt is not None:
        times = np.array([0.0, float(dt), 2.0 * float(dt)])
    w2 = three_point_weights(times)[-1]
    w2 = np.reshape(w2, np.shape(w2) + (1, 1))
    d = p.shape[-1]
    x = np.empty(v.shape[:-1] + (2 * d,))
    x[..., 0::2], x[..., 1::2] = p, v
    P = np.empty(Cv.shape[:-2] + (2 * d, 2 * d))
    P[..., 0::2, 0::2] = C[-1]
    P[..., 0::2, 1::2] = w2 * C[-1]
    P[..., 1::2, 0::2] = w2 * C[-1]
    P[..., 1::2, 1::2] = Cv
    return x, P
