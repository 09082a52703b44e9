r"""Drone attitude (pitch, roll) and height from an IMU and an altimeter (chapter 14, seed 004).

The models of Marques, Trindade & Afonso (2018) for the Parrot AR.Drone, corrected:

* **Inclinometer**: pitch and roll from the accelerometer when it senses gravity only
  (:func:`tilt_from_accel`), the vertical acceleration in the level frame
  (:func:`vertical_acceleration`) and the tilt-corrected altimeter
  (:func:`altimeter_tilt_correction`). The body frame is x forward, y right, z down; at rest
  the accelerometer reads :math:`[g\sin\theta, -g\cos\theta\sin\phi, -g\cos\theta\cos\phi]`.
* **Dynamic models** (:func:`dynamic_model`) from the identified closed-loop plant transfer
  functions :data:`PITCH_PLANT` (also used for roll) and :data:`HEIGHT_PLANT`, with the fast
  sensor (gyro, accelerometer) as a second output and optionally its bias as a state.
* **Kinematic models** (:func:`kinematic_model`): the fast sensor is the input, integrated
  once (angles) or twice (height); the slow sensor corrects it; optional bias state. These
  are complementary filters.
* **Integrated roll/pitch and gyro-bias filter** (Batista, Silvestre & Oliveira 2011):
  the linear time-varying model :func:`integrated_A` and its discrete Kalman filter
  :func:`integrated_filter`.
* Seeded simulation of the sensors (:func:`simulate_imu`, :func:`simulate_height_sensors`)
  for truths given as functions of time: the study's logs are not published.

State orders: angle models ``[angle(, gyro_bias)]``; height models ``[h, hdot(, accel_bias)]``
(the study writes ``[hdot, h, b]``; this module follows the book's position-first order);
dynamic models ``[x1, x2(, bias)]`` in controllable canonical form (no physical meaning).
Units: SI and radians.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.linalg
import scipy.signal
from scipy.spatial.transform import Rotation

from ._validate import as_float_array, as_vector, check_covariance, check_rng
from .kernels import kf_predict, kf_update
from .steady import (SteadyState, continuous_gain, discrete_gain, estimator_tf, observability_gramian,
                     sampled_model)

__all__ = [
    "GRAVITY", "PITCH_PLANT", "HEIGHT_PLANT", "StateSpace", "filter_tfs", "SampledFilter", "sampled_filter", "density_from_variance", "plant_response", "tilt_from_accel",
    "accel_from_tilt", "vertical_acceleration", "altimeter_tilt_correction", "dynamic_model",
    "kinematic_model", "skew", "integrated_A", "integrated_gramian", "body_rates",
    "simulate_imu", "simulate_height_sensors", "integrated_filter", "INTEGRATED_XI",
    "INTEGRATED_THETA",
]

#: Gravity (m/s²) used by the study's conversions and by the simulations.
GRAVITY = 9.81

#: Identified closed-loop pitch plant theta_ref -> theta, (num, den) in s (the study assumes the
#: same for roll).
PITCH_PLANT = (np.array([2.8065, 7.0915]), np.array([1.0, 5.21, 16.9695]))
#: Identified closed-loop height plant h_ref -> h, (num, den) in s.
HEIGHT_PLANT = (np.array([2.169]), np.array([1.0, 2.633, 2.206]))

#: Process-noise spectral densities of the integrated filter as the study sets them (§6):
#: diag(2, 2.5, 1.5, 2/5, 2.5/5, 1.5/5) (π/180)².
INTEGRATED_XI = np.diag([2.0, 2.5, 1.5, 0.4, 0.5, 0.3]) * (np.pi / 180) ** 2
#: Accelerometer noise densities of the integrated filter, diag(20, 20, 40)/100² (m/s²)².
INTEGRATED_THETA = np.diag([20.0, 20.0, 40.0]) / 100**2


class StateSpace(NamedTuple):
    r"""A continuous linear model :math:`\dot x = A x + B u`, :math:`y = C x + D u`."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray


# --------------------------------------------------------------------------------------------
# inclinometer and pre-processing
# --------------------------------------------------------------------------------------------
def tilt_from_accel(a, wide: bool = False) -> tuple[np.ndarray, np.ndarray]:
    r"""Pitch and roll (rad) from the specific force sensed by an accelerometer at rest.

    The study's formulas (its §2.4), valid for angles in (-90°, 90°):

    .. math:: \theta = \arctan\frac{a_x}{\sqrt{a_y^2 + a_z^2}}, \qquad \phi = \arctan\frac{a_y}{a_z}.

    With ``wide=True`` roll uses ``arctan2(-a_y, -a_z)``, valid over (-180°, 180°].
    Independent of the unit of ``a`` (ratios). ``a`` has shape ``(..., 3)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.attitude import accel_from_tilt, tilt_from_accel
    >>> a = accel_from_tilt(pitch=0.1, roll=-0.2)     # specific force at rest (m/s²)
    >>> print(np.round(tilt_from_accel(a), 6))        # pitch and roll back (rad)
    [ 0.1 -0.2]
    """
    a = as_vector(a, "a", 3)
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    pitch = np.arctan2(ax, np.hypot(ay, az))
    roll = np.arctan2(-ay, -az) if wide else np.arctan(ay / az)
    return pitch, roll


def accel_from_tilt(pitch, roll, g: float = GRAVITY) -> np.ndarray:
    r"""Specific force sensed at rest, :math:`R^\top [0, 0, -g]^\top`, shape ``(..., 3)``."""
    th, ph = np.broadcast_arrays(as_float_array(pitch, "pitch"), as_float_array(roll, "roll"))
    return np.stack([g * np.sin(th), -g * np.cos(th) * np.sin(ph), -g * np.cos(th) * np.cos(ph)], axis=-1)


def vertical_acceleration(a, pitch, roll, g: float = GRAVITY) -> np.ndarray:
    r"""Upward acceleration :math:`\ddot h` from the body accelerometer ``a`` ``(..., 3)`` (m/s²).

    .. math:: \ddot h_m = -(-\sin\theta\,a_x + \sin\phi\cos\theta\,a_y + \cos\phi\cos\theta\,a_z + g)

    (the study's §3.1.3: the specific force rotated to the level frame, gravity removed).
    """
    a = as_vector(a, "a", 3)
    th, ph = as_float_array(pitch, "pitch"), as_float_array(roll, "roll")
    down = -np.sin(th) * a[..., 0] + np.sin(ph) * np.cos(th) * a[..., 1] + np.cos(ph) * np.cos(th) * a[..., 2]
    return -(down + g)


def altimeter_tilt_correction(h, pitch, roll) -> np.ndarray:
    r"""Height from a body-fixed downward range sensor: :math:`h = h_s \cos\phi\cos\theta`."""
    return as_float_array(h, "h") * np.cos(as_float_array(pitch, "pitch")) * np.cos(as_float_array(roll, "roll"))


# --------------------------------------------------------------------------------------------
# linear models of the study
# --------------------------------------------------------------------------------------------
def _plant_ss(num, den, derivatives: int, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``A, B, C`` of ``num/den`` (``tf2ss``), checking that its first ``derivatives`` output
    derivatives need no derivative of the input: relative degree ``>= derivatives``."""
    num = np.trim_zeros(np.atleast_1d(as_float_array(num, "num")), "f")
    den = np.trim_zeros(np.atleast_1d(as_float_array(den, "den")), "f")
    if num.size == 0 or den.size < 2:
        raise ValueError(f"num/den must be a nonzero plant of order >= 1, got num={num}, den={den}")
    rel = den.size - num.size
    if rel < 1:
        raise ValueError("num/den must be strictly proper (deg num < deg den)")
    if derivatives > rel:
        raise ValueError(f"{name}={derivatives} exceeds the relative degree {rel} of num/den: that "
                         f"derivative of the output depends on derivatives of the input")
    A, B, C, _ = scipy.signal.tf2ss(num, den)
    return A, B, C


def dynamic_model(num, den, derivative: int, bias: bool = False) -> StateSpace:
    r"""Dynamic model: the plant ``num/den`` (reference in, angle or height out) in controllable
    canonical form, with the ``derivative``-th derivative of the output as a second output.

    ``scipy.signal.tf2ss`` gives the same form as MATLAB's ``tf2ss``. With :math:`y = Cx` and
    a strictly proper plant of relative degree ``>= derivative``,

    .. math:: C' = \begin{bmatrix} C \\ C A^k \end{bmatrix}, \quad
              D' = \begin{bmatrix} 0 \\ C A^{k-1} B \end{bmatrix}

    (``k = 1`` for the gyro, ``2`` for the vertical accelerometer). With ``bias=True`` a
    constant state ``b`` is appended and the fast sensor reads the derivative plus ``b``.
    """
    if not isinstance(derivative, (int, np.integer)) or derivative < 1:
        raise ValueError(f"derivative must be a positive integer, got {derivative!r}")
    A, B, C = _plant_ss(num, den, derivative, "derivative")
    Ak = np.linalg.matrix_power(A, derivative)
    C2 = np.vstack([C, C @ Ak])
    D2 = np.vstack([np.zeros((1, 1)), C @ np.linalg.matrix_power(A, derivative - 1) @ B])
    if not bias:
        return StateSpace(A, B, C2, D2)
    n = A.shape[0]
    Ab = np.zeros((n + 1, n + 1))
    Ab[:n, :n] = A
    Bb = np.vstack([B, [[0.0]]])
    Cb = np.hstack([C2, [[0.0], [1.0]]])
    return StateSpace(Ab, Bb, Cb, D2)


def kinematic_model(order: int, bias: bool = False) -> StateSpace:
    r"""Kinematic model: a chain of ``order`` integrators driven by the fast sensor.

    ``order = 1``: angle, :math:`\dot\theta = \omega_m (- b)`, state ``[theta(, b)]``.
    ``order = 2``: height, :math:`\ddot h = \ddot h_m (- b)`, state ``[h, hdot(, b)]``.
    The slow sensor measures the first state (``C = e_0``); ``D = 0``.
    """
    if order not in (1, 2):
        raise ValueError(f"order must be 1 (angle) or 2 (height), got {order!r}")
    n = order + int(bias)
    A = np.zeros((n, n))
    for i in range(order - 1):
        A[i, i + 1] = 1.0
    if bias:
        A[order - 1, order] = -1.0
    B = np.zeros((n, 1))
    B[order - 1, 0] = 1.0
    C = np.zeros((1, n))
    C[0, 0] = 1.0
    return StateSpace(A, B, C, np.zeros((1, 1)))


def filter_tfs(model: StateSpace, Q, R) -> tuple[SteadyState, list[tuple[np.ndarray, np.ndarray]]]:
    r"""Steady-state continuous filter of ``model`` (``G = I``) and its transfer functions
    from each sensor and input to the estimated output ``C[0] x`` (angle or height).

    Returns ``(SteadyState(L, P), tfs)`` with ``tfs`` ordered as the inputs
    ``[slow sensor, fast sensor, reference]`` for a dynamic model and ``[slow sensor, fast
    sensor]`` for a kinematic one (where the fast sensor is the model input). This is what
    the study computed with MATLAB's ``kalman()`` and ``tf``.
    """
    ss = continuous_gain(model.A, model.C, Q, R)
    return ss, estimator_tf(model.A, model.B, model.C, model.D, ss.L, outputs=model.C[:1])[0]


class SampledFilter(NamedTuple):
    """A steady-state filter sampled at ``dt``: the arguments ``F, B, H, D, K`` of
    :func:`kftrack.steady.run_steady_filter`."""

    F: np.ndarray
    B: np.ndarray
    H: np.ndarray
    D: np.ndarray
    K: np.ndarray


def sampled_filter(model: StateSpace, q, r, dt: float) -> SampledFilter:
    r"""Discrete equivalent at the sample time ``dt`` of the continuous steady-state filter
    of ``model`` with spectral **densities** ``q`` (process, ``G = I``) and ``r``
    (measurement): :math:`F = e^{A dt}`, the zero-order-hold input matrix, Van Loan's
    :math:`Q_d \approx q\,dt` and :math:`R_d = r/dt` (:func:`kftrack.steady.sampled_model`,
    :func:`kftrack.steady.discrete_gain`). ``K / dt`` tends to the continuous ``L`` as
    ``dt -> 0``.

    ``q`` and ``r`` are densities, not per-sample variances: a sensor whose samples at ``dt``
    have variance ``sigma2`` is white noise of density ``sigma2 * dt``
    (:func:`density_from_variance`). Passing ``sigma2`` itself, as the study's continuous
    design does with its measured variances, assumes ``1/dt`` times the actual noise.
    Scaling ``q`` and ``r`` by the same factor leaves ``K`` unchanged.

    Parameters
    ----------
    model : the continuous model (``A, B, C, D``), state dimension ``n``, ``m`` outputs.
    q : (n, n) process-noise density. r : (m, m) measurement-noise density. dt : s, > 0.
    """
    if not dt > 0:
        raise ValueError(f"dt must be > 0, got {dt!r}")
    F, Bd, Qd = sampled_model(model.A, model.B, q, dt)
    r = check_covariance(r, "r", model.C.shape[0], positive_definite=True)
    K = discrete_gain(F, model.C, Qd, r / dt).K
    return SampledFilter(F, Bd, model.C, model.D, K)


def density_from_variance(sigma2, dt: float) -> np.ndarray:
    r"""Spectral density of white noise whose samples at interval ``dt`` have variance
    ``sigma2``: :math:`q = \sigma^2\,\Delta t` (the inverse of :math:`R_d = r/\Delta t`).

    ``sigma2`` is a scalar or an array of per-sample variances (any shape); ``dt`` in s.
    Use it to hand measured per-sample variances (as simulated by :func:`simulate_imu` and
    :func:`simulate_height_sensors`) to :func:`sampled_filter` or :func:`integrated_filter`,
    whose arguments are densities.
    """
    sigma2 = np.asarray(sigma2, dtype=float)
    if np.any(~np.isfinite(sigma2)):
        raise ValueError(f"sigma2 must be finite, got {sigma2!r}")
    if not (isinstance(dt, (int, float, np.floating, np.integer)) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
    return sigma2 * dt


def plant_response(num, den, t, ref, derivatives: int = 1, delay: float = 0.0) -> np.ndarray:
    r"""Response of the plant ``num/den`` to the reference ``ref`` ``(T,)`` sampled at the
    times ``t`` ``(T,)`` (held between samples), optionally delayed by ``delay`` s (the
    Wi-Fi link of the AR.Drone). Returns ``(T, derivatives + 1)``: the output and its first
    ``derivatives`` time derivatives, exact for a strictly proper plant of relative degree
    ``>= derivatives``. Starts at rest."""
    t = as_float_array(t, "t")
    ref = as_float_array(ref, "ref")
    if t.ndim != 1 or ref.shape != t.shape:
        raise ValueError(f"t and ref must both have shape (T,), got {t.shape} and {ref.shape}")
    if delay < 0:
        raise ValueError(f"delay must be >= 0, got {delay}")
    if not isinstance(derivatives, (int, np.integer)) or derivatives < 0:
        raise ValueError(f"derivatives must be a non-negative integer, got {derivatives!r}")
    dt = t[1] - t[0] if t.size > 1 else 0.0
    if not dt > 0 or not np.allclose(np.diff(t), dt, rtol=1e-9, atol=0):
        raise ValueError("t must be uniformly spaced and increasing, with at least 2 samples")
    A, B, C = _plant_ss(num, den, max(derivatives, 1), "derivatives")
    rows = [C]
    Dcol = [np.zeros((1, 1))]
    for k in range(1, derivatives + 1):
        rows.append(rows[-1] @ A)
        Dcol.append(C @ np.linalg.matrix_power(A, k - 1) @ B)
    u = np.interp(t - delay, t, ref, left=ref[0]) if delay else ref
    # ZOH at the sample rate: exact for a held reference
    F, Bd, _ = sampled_model(A, B, np.zeros((A.shape[0], A.shape[0])), dt)
    x = np.zeros(A.shape[0])
    out = np.empty((t.size, derivatives + 1))
    Co, Do = np.vstack(rows), np.vstack(Dcol)
    for k in range(t.size):
        out[k] = Co @ x + Do[:, 0] * u[k]
        x = F @ x + Bd[:, 0] * u[k]
    return out


# --------------------------------------------------------------------------------------------
# the integrated roll/pitch + gyro-bias filter (LTV)
# --------------------------------------------------------------------------------------------
def skew(v) -> np.ndarray:
    r"""Cross-product matrix :math:`S(v)` with :math:`S(v) w = v \times w`, ``(..., 3, 3)``."""
    v = as_vector(v, "v", 3)
    z = np.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def integrated_A(y_a, omega_m) -> np.ndarray:
    r"""System matrix of the integrated filter, state ``[g_b (3), b_omega (3)]``:

    .. math:: A = \begin{bmatrix} -S(\omega_m) & -S(y_a) \\ 0 & 0 \end{bmatrix},

    from :math:`\dot y = -S(\omega) y` with :math:`\omega = \omega_m - b` (the measured
    specific force ``y_a`` replaces ``y`` inside ``A``). Shapes ``(..., 3)`` -> ``(..., 6, 6)``.
    """
    Sy, Sw = skew(y_a), skew(omega_m)
    shape = np.broadcast_shapes(Sy.shape, Sw.shape)[:-2]
    A = np.zeros(shape + (6, 6))
    A[..., :3, :3] = -Sw
    A[..., :3, 3:] = -Sy
    return A


def integrated_gramian(omega, y0, duration: float) -> np.ndarray:
    r"""Observability Gramian of the integrated model over ``[0, duration]`` when the body
    turns at the constant rate ``omega`` (rad/s) and the sensed vector starts at ``y0``:
    :math:`y(t) = e^{-S(\omega)t} y_0`, ``C = [I_3, 0]``. Returns ``(6, 6)``."""
    w = as_vector(omega, "omega", 3)
    y0 = as_vector(y0, "y0", 3)
    C = np.hstack([np.eye(3), np.zeros((3, 3))])
    return observability_gramian(lambda t: integrated_A(Rotation.from_rotvec(-w * t).as_matrix() @ y0, w),
                                 C, 0.0, duration)


class IntegratedResult(NamedTuple):
    """Output of :func:`integrated_filter`: states ``x`` ``(T, 6)``, covariances ``P``
    ``(T, 6, 6)``, and the pitch and roll ``(T,)`` from the estimated gravity vector."""

    x: np.ndarray
    P: np.ndarray
    pitch: np.ndarray
    roll: np.ndarray


def integrated_filter(dt: float, y_a, omega_m, Xi=INTEGRATED_XI, Theta=INTEGRATED_THETA,
                      x0=None, P0=None) -> IntegratedResult:
    r"""Discrete time-varying Kalman filter of the integrated roll/pitch + gyro-bias model.

    The continuous filter of the study (with the missing transpose restored),
    :math:`\dot P = AP + PA^\top + \Xi - PC^\top\Theta^{-1}CP`, :math:`K = PC^\top\Theta^{-1}`,
    :math:`\dot{\hat x} = A\hat x + K(y_a - C\hat x)`, sampled at ``dt``: at each step
    :math:`F_k = e^{A(y_{a,k-1}, \omega_{m,k-1})dt}`, :math:`Q = \Xi\,dt`, :math:`R = \Theta/dt`.

    Parameters
    ----------
    dt : sample time (s). y_a : (T, 3) accelerometer (m/s²). omega_m : (T, 3) gyro (rad/s).
    Xi : (6, 6) spectral density of the process noise. Theta : (3, 3) of the accelerometer noise.
    x0 : (6,) initial state, default ``[y_a[0], 0, 0, 0]``. P0 : (6, 6), default
    ``diag(Theta/dt, (1 deg/s)^2 I)``.
    """
    y_a = as_vector(y_a, "y_a", 3)
    omega_m = as_vector(omega_m, "omega_m", 3)
    if y_a.ndim != 2 or omega_m.shape != y_a.shape:
        raise ValueError(f"y_a and omega_m must both have shape (T, 3), got {y_a.shape} and {omega_m.shape}")
    if not dt > 0:
        raise ValueError(f"dt must be > 0, got {dt}")
    Xi = check_covariance(Xi, "Xi", 6)
    Theta = check_covariance(Theta, "Theta", 3, positive_definite=True)
    x = np.concatenate([y_a[0], np.zeros(3)]) if x0 is None else as_vector(x0, "x0", 6)
    if P0 is None:
        P0 = scipy.linalg.block_diag(Theta / dt, np.eye(3) * np.deg2rad(1.0) ** 2)
    P = check_covariance(P0, "P0", 6)
    H = np.hstack([np.eye(3), np.zeros((3, 3))])
    Q, R = Xi * dt, Theta / dt
    T = y_a.shape[0]
    xs, Ps = np.empty((T, 6)), np.empty((T, 6, 6))
    # A depends only on the measured inputs: all transitions in one batched expm
    Fs = scipy.linalg.expm(integrated_A(y_a[:-1], omega_m[:-1]) * dt)
    for k in range(T):
        if k:
            x, P = kf_predict(x, P, Fs[k - 1], Q)
        u = kf_update(x, P, y_a[k], H, R)
        x, P = u.x, u.P
        xs[k], Ps[k] = x, P
    pitch, roll = tilt_from_accel(xs[:, :3], wide=True)
    return IntegratedResult(xs, Ps, pitch, roll)


# --------------------------------------------------------------------------------------------
# simulation of the sensors (the study's logs are not published)
# --------------------------------------------------------------------------------------------
def _variance(value, name: str) -> np.ndarray:
    v = as_float_array(value, name)
    if np.any(~np.isfinite(v)) or np.any(v < 0):
        raise ValueError(f"{name} must be a finite per-sample variance >= 0, got {v}")
    return v


def body_rates(roll, pitch, roll_rate, pitch_rate, yaw_rate) -> np.ndarray:
    r"""Body angular rates ``[p, q, r]`` (rad/s) from ZYX Euler angles and their rates:
    :math:`p = \dot\phi - \dot\psi\sin\theta`, :math:`q = \dot\theta\cos\phi + \dot\psi\cos\theta\sin\phi`,
    :math:`r = -\dot\theta\sin\phi + \dot\psi\cos\theta\cos\phi`. Shape ``(..., 3)``."""
    ph, th = as_float_array(roll, "roll"), as_float_array(pitch, "pitch")
    dph, dth, dps = (as_float_array(v, n) for v, n in ((roll_rate, "roll_rate"), (pitch_rate, "pitch_rate"),
                                                       (yaw_rate, "yaw_rate")))
    p = dph - dps * np.sin(th)
    q = dth * np.cos(ph) + dps * np.cos(th) * np.sin(ph)
    r = -dth * np.sin(ph) + dps * np.cos(th) * np.cos(ph)
    return np.stack(np.broadcast_arrays(p, q, r), axis=-1)


class ImuLog(NamedTuple):
    """Simulated IMU samples, time first: ``accel`` ``(T, 3)`` m/s², ``gyro`` ``(T, 3)`` rad/s."""

    accel: np.ndarray
    gyro: np.ndarray


def simulate_imu(rng: np.random.Generator, rates, pitch, roll, *, gyro_bias=0.0, gyro_var=0.0,
                 accel_var=0.0, accel_extra=None, g: float = GRAVITY) -> ImuLog:
    r"""Sample a gyro and an accelerometer for a given attitude history.

    ``rates`` ``(T, 3)`` true body rates, ``pitch``, ``roll`` ``(T,)`` true angles. The gyro
    reads ``rates + gyro_bias + n`` and the accelerometer the gravity-only specific force
    (:func:`accel_from_tilt`) plus ``accel_extra`` ``(T, 3)`` (non-gravitational specific force,
    default 0) plus noise. ``gyro_var`` ((rad/s)²) and ``accel_var`` ((m/s²)²) are the
    **per-sample variances** (scalar or per axis), as measured at rest in chapter 1; white
    Gaussian noise from ``rng``.
    """
    check_rng(rng)
    rates = as_vector(rates, "rates", 3)
    accel = accel_from_tilt(pitch, roll, g)
    if accel.shape != rates.shape:
        raise ValueError(f"pitch and roll must have shape {rates.shape[:-1]}, got {accel.shape[:-1]}")
    if accel_extra is not None:
        accel = accel + as_vector(accel_extra, "accel_extra", 3)
    gs = np.sqrt(np.broadcast_to(_variance(gyro_var, "gyro_var"), (3,)))
    as_ = np.sqrt(np.broadcast_to(_variance(accel_var, "accel_var"), (3,)))
    gyro = rates + gyro_bias + gs * rng.standard_normal(rates.shape)
    return ImuLog(accel + as_ * rng.standard_normal(accel.shape), gyro)


def simulate_height_sensors(rng: np.random.Generator, h, hddot, *, accel_bias=0.0, accel_var=0.0,
                            alt_var=0.0, dead_zone: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    r"""Altimeter and vertical-accelerometer samples for a true height history.

    Returns ``(h_m, hddot_m)`` ``(T,)`` each: ``h_m = h + n`` but exactly 0 where the true
    height is below ``dead_zone`` (the AR.Drone's ultrasound reads nothing below ~25 cm, and
    the study feeds the 0 to its filter), ``hddot_m = hddot + accel_bias + n``. Variances are
    per sample (m², (m/s²)²).
    """
    check_rng(rng)
    h = as_float_array(h, "h")
    hddot = as_float_array(hddot, "hddot")
    if h.shape != hddot.shape or h.ndim != 1:
        raise ValueError(f"h and hddot must both have shape (T,), got {h.shape} and {hddot.shape}")
    h_m = h + np.sqrt(_variance(alt_var, "alt_var")) * rng.standard_normal(h.shape)
    h_m = np.where(h < dead_zone, 0.0, h_m)
    a_m = hddot + accel_bias + np.sqrt(_variance(accel_var, "accel_var")) * rng.standard_normal(h.shape)
    return h_m, a_m
