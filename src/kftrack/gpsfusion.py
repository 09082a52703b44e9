r"""Fusing GPS receivers: the speed-heading model of Stahlschmidt (2018), stacked and weighted
fusion, and the lane-distance metric (chapter 13).

State (the thesis's order, kept because the model is not a Cartesian one):
``[x, y, v, h]`` = East (m), North (m), speed (m/s), heading ``h`` (rad, counter-clockwise from +x,
the book's convention; see :func:`kftrack.sensors.gps.course_to_heading`).

Model (thesis eqs. 27-30 with the unknown acceleration ``a`` and turn rate ``w`` as noise):

.. math::

    x_{k+1} = x_k + \Delta T v_k \cos h_k, \quad y_{k+1} = y_k + \Delta T v_k \sin h_k, \quad
    v_{k+1} = v_k, \quad h_{k+1} = h_k.

The thesis propagates the covariance with the state-dependent matrix
:math:`A_k` (:func:`thesis_transition`), which is *not* the Jacobian of this map: the Jacobian
(:func:`speed_heading_jacobian`) has the extra column
:math:`\partial x_{k+1}/\partial h = -\Delta T v \sin h`, :math:`\partial y_{k+1}/\partial h = \Delta T v\cos h`.
:func:`speed_heading_filter` runs either, over any number of stacked receivers
(:math:`H = [I; I; \dots]`), with leading batch axes (Monte Carlo runs) and wrapped angle innovations.

Layer: numerics/models (no I/O). The synthetic athletics-track world is :mod:`kftrack.gpstrack`.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from scipy.linalg import block_diag

from ._validate import as_float_array, as_vector, check_covariance
from .ekf import wrap_angle as _wrap
from .kalman import kalman_filter, rts_smoother
from .kernels import kf_predict, kf_update

__all__ = [
    "thesis_transition", "speed_heading_jacobian", "thesis_process_noise", "thesis_quadrant_terms",
    "SpeedHeadingResult", "speed_heading_filter", "fusion_weights", "lane_distances", "lane_rmse",
    "BiasModel", "gauss_markov_bias_model", "velocity_measurements", "bias_state_positions",
]


def thesis_transition(h, dt: float = 1.0) -> np.ndarray:
    r"""The thesis's state-dependent matrix :math:`A_k` (Sec. 2.2.2), heading ``h`` ``(...)`` in rad.

    .. math::
        A_k = \begin{bmatrix}1&0&\Delta T\cos h_k&0\\0&1&\Delta T\sin h_k&0\\0&0&1&0\\0&0&0&1\end{bmatrix}

    Returns ``(..., 4, 4)``. ``A_k x_k`` is the exact mean prediction of the model.
    """
    h = as_float_array(h, "h")
    A = np.broadcast_to(np.eye(4), h.shape + (4, 4)).copy()
    A[..., 0, 2] = dt * np.cos(h)
    A[..., 1, 2] = dt * np.sin(h)
    return A


def speed_heading_jacobian(x, dt: float = 1.0) -> np.ndarray:
    """Jacobian of the speed-heading model at ``x = [x, y, v, h]`` ``(..., 4)``: :func:`thesis_transition`
    plus the heading column ``[-dt v sin h, dt v cos h, 0, 1]``. Returns ``(..., 4, 4)``."""
    x = as_vector(x, "x", 4)
    F = thesis_transition(x[..., 3], dt)
    F[..., 0, 3] = -dt * x[..., 2] * np.sin(x[..., 3])
    F[..., 1, 3] = dt * x[..., 2] * np.cos(x[..., 3])
    return F


def thesis_process_noise(h, dt: float, sigma2_a: float, sigma2_w: float) -> np.ndarray:
    r"""The thesis's :math:`Q_k` (Sec. 2.2.2): :math:`\sigma_a^2 G_a G_a^\top + \sigma_w^2 G_w G_w^\top`
    with :math:`G_a = [\tfrac12\Delta T^2\cos h, \tfrac12\Delta T^2\sin h, \Delta T, 0]^\top`,
    :math:`G_w = [0,0,0,\Delta T]^\top`; ``sigma2_a`` (m²/s⁴) and ``sigma2_w`` (rad²/s²) are the
    discrete variances of the acceleration and turn rate. Returns ``(..., 4, 4)``, rank 2."""
    h = as_float_array(h, "h")
    if sigma2_a < 0 or sigma2_w < 0:
        raise ValueError(f"sigma2_a and sigma2_w must be >= 0, got {sigma2_a!r} and {sigma2_w!r}")
    Ga = np.stack([0.5 * dt**2 * np.cos(h), 0.5 * dt**2 * np.sin(h), np.full(h.shape, dt), np.zeros(h.shape)], -1)
    Q = sigma2_a * Ga[..., :, None] * Ga[..., None, :]
    Q[..., 3, 3] += sigma2_w * dt**2
    return Q


def thesis_quadrant_terms(course_deg) -> tuple[np.ndarray, np.ndarray]:
    """The thesis's per-quadrant ``(a13, a23)`` for a course ``course_deg`` (degrees clockwise from
    North), transcribed literally (Sec. 3.3, with quadrant i = [90(i-1), 90 i) and theta_i = course,
    Delta T = 1). Kept to show the error: the correct terms are ``(sin course, cos course)``;
    quadrants 2 and 4 give ``(-sin, -cos)`` and ``(sin, -cos)``."""
    c = np.mod(as_float_array(course_deg, "course_deg"), 360.0)
    r = np.deg2rad
    q = np.floor(c / 90.0).astype(int)
    a13 = np.choose(q, [np.cos(r(90 - c)), np.cos(r(-90 - c)), -np.sin(r(-(180 - c))), -np.cos(r(-(270 - c)))])
    a23 = np.choose(q, [np.sin(r(90 - c)), np.sin(r(-90 - c)), -np.cos(r(-(180 - c))), -np.sin(r(-(270 - c)))])
    return a13, a23


class SpeedHeadingResult(NamedTuple):
    """Filtered estimates ``x`` ``(T, ..., 4)`` and covariances ``P`` ``(T, ..., 4, 4)`` (after each
    update), and the gain ``K`` ``(..., 4, m)`` of the last step."""

    x: np.ndarray
    P: np.ndarray
    K: np.ndarray


def speed_heading_filter(zs, x0, P0, Q, R, dt: float = 1.0, *, jacobian: bool = False) -> SpeedHeadingResult:
    r"""Kalman filter of the speed-heading model over ``r`` stacked receivers.

    Each receiver measures the whole state ``[x, y, v, h]`` (thesis: :math:`H = I_4`; fused,
    :math:`H = [I_4; I_4]`, eq. 33). Update then predict at each step, as
    :func:`kftrack.kalman.kalman_filter`, with :func:`kftrack.kalman.update`'s Joseph form.
    Heading innovations are wrapped to (-pi, pi]: before each update the measured headings are
    moved by multiples of 2 pi to within pi of the predicted heading.

    Parameters
    ----------
    zs : (T, ..., 4 r) stacked measurements ``[x1, y1, v1, h1, x2, y2, v2, h2, ...]``.
    x0 : (..., 4) prior for step 0; P0 : (..., 4, 4).
    Q : (4, 4) or (..., 4, 4) process-noise covariance per step (the thesis: ``I``).
    R : (4 r, 4 r) measurement covariance (thesis fused: ``0.05 I_8``; may couple receivers).
    dt : sampling interval (s).
    jacobian : False propagates P with the thesis's :math:`A_k` (not a Jacobian, the thesis's
        "EKF"); True with the true Jacobian (:func:`speed_heading_jacobian`), an EKF.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.gpsfusion import speed_heading_filter
    >>> t = np.arange(30.0)
    >>> truth = np.stack([2.0 * t, np.zeros(30), np.full(30, 2.0), np.zeros(30)], axis=-1)   # [x, y, v, h]: east at 2 m/s
    >>> sd = np.array([1.0, 1.0, 0.1, 0.05, 2.0, 2.0, 0.2, 0.1])    # two receivers, the second twice as noisy
    >>> zs = np.tile(truth, 2) + np.random.default_rng(0).normal(size=(30, 8)) * sd   # stacked [x1, y1, v1, h1, x2, ...]
    >>> res = speed_heading_filter(zs, truth[0], np.eye(4), 0.01 * np.eye(4), np.diag(sd ** 2))
    >>> res.x.shape, res.P.shape
    ((30, 4), (30, 4, 4))
    """
    zs = as_vector(zs, "zs")
    if zs.ndim < 2 or zs.shape[-1] % 4:
        raise ValueError(f"zs must have shape (T, ..., 4 r) with r stacked receivers, got shape {zs.shape}")
    r = zs.shape[-1] // 4
    x = as_vector(x0, "x0", 4).copy()
    P = check_covariance(P0, "P0", 4).copy()
    Q = check_covariance(Q, "Q", 4)
    R = check_covariance(R, "R", 4 * r, positive_definite=True)
    H = np.tile(np.eye(4), (r, 1))
    angle = np.arange(3, 4 * r, 4)
    T = zs.shape[0]
    batch = np.broadcast_shapes(zs.shape[1:-1], x.shape[:-1], P.shape[:-2])
    x = np.broadcast_to(x, batch + (4,)).copy()
    P = np.broadcast_to(P, batch + (4, 4)).copy()
    out_x, out_P = np.empty((T,) + batch + (4,)), np.empty((T,) + batch + (4, 4))
    K = None
    for k in range(T):
        z = np.broadcast_to(zs[k], batch + (4 * r,)).copy()
        z[..., angle] = x[..., 3:4] + _wrap(z[..., angle] - x[..., 3:4])
        upd = kf_update(x, P, z, H, R)
        x, P, K = upd.x, upd.P, upd.K
        x[..., 3] = _wrap(x[..., 3])
        out_x[k], out_P[k] = x, P
        A = thesis_transition(x[..., 3], dt)
        F = speed_heading_jacobian(x, dt) if jacobian else A
        x_next = (A @ x[..., None])[..., 0]
        _, P = kf_predict(x, P, F, Q)
        x = x_next
    return SpeedHeadingResult(out_x, out_P, K)


def fusion_weights(C) -> np.ndarray:
    r"""Minimum-variance weights for averaging ``r`` unbiased measurements of one quantity whose
    errors have covariance ``C`` ``(r, r)``: :math:`w = C^{-1}\mathbf 1 / (\mathbf 1^\top C^{-1}\mathbf 1)`,
    variance :math:`1/(\mathbf 1^\top C^{-1}\mathbf 1)`. Returns ``w`` ``(r,)`` (sums to one).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.gpsfusion import fusion_weights
    >>> print(np.round(fusion_weights(np.diag([1.0, 4.0])), 6))   # inverse-variance weights
    [0.8 0.2]
    >>> print(np.round(fusion_weights([[1.0, 0.5], [0.5, 4.0]]), 6))   # correlated errors
    [0.875 0.125]
    """
    C = check_covariance(C, "C", positive_definite=True)
    if C.ndim != 2:
        raise ValueError(f"C must have shape (r, r), got shape {C.shape}")
    u = np.linalg.solve(C, np.ones(C.shape[0]))
    return u / u.sum()


def _segment_distance(p, a, b):
    """Distance from points p (..., N, 1, 2) to segments a-b (..., 1, M, 2)."""
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, -1) / np.maximum(np.sum(ab * ab, -1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def _nearest_distances(inner, outer, max_elements: int = 2**19):
    """min over j of |outer_i - inner_j|, (..., No). The nearest index comes from
    |o|^2 + |i|^2 - 2 o.i (one matrix product, about the inner centroid), in chunks of the batch
    to bound memory; the returned distance is then computed directly from the chosen pair."""
    batch = np.broadcast_shapes(inner.shape[:-2], outer.shape[:-2])
    Ni, No = inner.shape[-2], outer.shape[-2]
    inner = np.broadcast_to(inner, batch + (Ni, 2)).reshape(-1, Ni, 2)
    outer = np.broadcast_to(outer, batch + (No, 2)).reshape(-1, No, 2)
    out = np.empty(outer.shape[:2])
    step = max(1, max_elements // max(Ni * No, 1))
    for s in range(0, len(outer), step):
        i, o = inner[s:s + step], outer[s:s + step]
        c = i.mean(-2, keepdims=True)
        ic, oc = i - c, o - c
        d2 = np.sum(ic * ic, -1)[:, None, :] - 2.0 * oc @ np.swapaxes(ic, -1, -2)  # + |o|^2, same per row
        j = np.argmin(d2, -1)
        nearest = np.take_along_axis(i, j[..., None], axis=-2)
        out[s:s + step] = np.linalg.norm(o - nearest, axis=-1)
    return out.reshape(batch + (No,))


def lane_distances(inner, outer, pairing: str = "nearest") -> np.ndarray:
    """Distance from each point of the ``outer`` lap to the ``inner`` lap (the thesis's metric, Sec. 3.4).

    Parameters
    ----------
    inner : (..., Ni, 2) East-North points of the inner-lane lap.
    outer : (..., No, 2) points of the outer-lane lap (same batch axes).
    pairing : ``"index"`` pairs the i-th points of the two laps (first ``min(Ni, No)``), which slants
        the pairs because the outer lap is longer; ``"nearest"`` takes the nearest inner point (the
        thesis); ``"polyline"`` the distance to the closed inner polyline (no discretization bias).

    Returns
    -------
    (..., No) distances (``(..., min(Ni, No))`` for ``"index"``).
    """
    inner = as_vector(inner, "inner", 2)
    outer = as_vector(outer, "outer", 2)
    if inner.ndim < 2 or outer.ndim < 2:
        raise ValueError(f"inner and outer must have shape (..., N, 2), got {inner.shape} and {outer.shape}")
    if pairing == "index":
        n = min(inner.shape[-2], outer.shape[-2])
        return np.linalg.norm(outer[..., :n, :] - inner[..., :n, :], axis=-1)
    if pairing == "nearest":
        return _nearest_distances(inner, outer)
    if pairing == "polyline":
        a = inner[..., None, :, :]
        b = np.roll(inner, -1, axis=-2)[..., None, :, :]
        return _segment_distance(outer[..., :, None, :], a, b).min(-1)
    raise ValueError(f"pairing must be 'index', 'nearest' or 'polyline', got {pairing!r}")


def lane_rmse(inner, outer, separation: float = 7.32, pairing: str = "nearest") -> np.ndarray:
    r"""Per-lap-pair RMSE of the lane distance about the true separation:
    :math:`\sqrt{\operatorname{mean}_i (d_i - d_\mathrm{true})^2}` over the outer points. Returns ``(...)``."""
    if not separation > 0:
        raise ValueError(f"separation must be a positive distance in metres, got {separation!r}")
    d = lane_distances(inner, outer, pairing)
    return np.sqrt(np.mean((d - separation) ** 2, axis=-1))


class BiasModel(NamedTuple):
    """Linear model with Gauss–Markov receiver biases (see :func:`gauss_markov_bias_model`).

    ``F``, ``Q`` ``(2(2+r), 2(2+r))``; ``H`` ``(4r, 2(2+r))``; ``R`` ``(4r, 4r)``; ``P0`` the prior
    covariance (position 25 m², velocity 1 m²/s², biases at their stationary covariance).
    """

    F: np.ndarray
    Q: np.ndarray
    H: np.ndarray
    R: np.ndarray
    P0: np.ndarray


def gauss_markov_bias_model(dt: float, q: float, sigma_gm, tau, rho: float, sigma_white, sigma_vel) -> BiasModel:
    r"""Constant-velocity walker seen by ``r`` receivers whose position errors are Gauss–Markov
    biases plus white noise, and which also measure velocity (Doppler).

    State, interleaved by axis: ``[x, vx, b1x, ..., brx, y, vy, b1y, ..., bry]``. Per axis:
    :math:`p_{k+1} = p_k + \Delta T v_k`, :math:`v` a white-acceleration random walk with spectral
    density ``q`` (m²/s³), :math:`b_{i,k+1} = \phi_i b_{i,k} + w_{i,k}`, :math:`\phi_i = e^{-\Delta T/\tau_i}`,
    driving noises of variance :math:`d_i^2 = \sigma_i^2(1-\phi_i^2)` and correlation ``rho``, as in
    :func:`kftrack.gpstrack.gauss_markov_errors`; the stationary bias covariance is then
    :math:`\sigma_i^2` on the diagonal and :math:`\rho d_i d_j / (1 - \phi_i\phi_j)` off it
    (:math:`\rho\sigma_i\sigma_j` when the ``tau`` are equal). Measurements, receiver by receiver:
    ``[x + bix, y + biy, vx, vy]`` with white noise ``sigma_white[i]``, ``sigma_vel[i]``
    (see :func:`velocity_measurements`).

    Parameters
    ----------
    sigma_gm, tau, sigma_white, sigma_vel : (r,) per receiver (m, s, m, m/s).
    """
    sig = np.atleast_1d(as_float_array(sigma_gm, "sigma_gm"))
    r = sig.size

    def per_receiver(value, name):
        arr = as_float_array(value, name)
        if arr.ndim > 1 or arr.size not in (1, r):
            raise ValueError(f"{name} must be a scalar or have shape ({r},), one per receiver of sigma_gm, "
                             f"got shape {arr.shape}")
        return np.broadcast_to(arr.reshape(-1), (r,))

    tau, white, svel = (per_receiver(v, name) for v, name in
                        ((tau, "tau"), (sigma_white, "sigma_white"), (sigma_vel, "sigma_vel")))
    if not (dt > 0 and q >= 0 and np.all(tau > 0) and np.all(sig > 0) and np.all(white > 0) and np.all(svel > 0)):
        raise ValueError("dt, tau, sigma_gm, sigma_white and sigma_vel must be positive and q >= 0; "
                         f"got dt={dt!r}, q={q!r}, tau={tau}, sigma_gm={sig}, sigma_white={white}, sigma_vel={svel}")
    if not -1.0 / max(r - 1, 1) <= rho <= 1.0:
        raise ValueError(f"rho must be in [-1/(r-1), 1] for r={r} receivers, got {rho!r}")
    phi = np.exp(-dt / tau)
    C = np.full((r, r), rho) + (1 - rho) * np.eye(r)
    n = 2 + r
    F1 = np.eye(n)
    F1[0, 1] = dt
    F1[2:, 2:] = np.diag(phi)
    Q1 = np.zeros((n, n))
    Q1[:2, :2] = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    d = sig * np.sqrt(1 - phi**2)
    Q1[2:, 2:] = C * np.outer(d, d)
    P1 = np.zeros((n, n))
    P1[:2, :2] = np.diag([25.0, 1.0])
    P1[2:, 2:] = C * np.outer(d, d) / (1 - np.outer(phi, phi))
    H = np.zeros((4 * r, 2 * n))
    R = np.zeros((4 * r, 4 * r))
    for i in range(r):
        for a in range(2):
            H[4 * i + a, a * n] = H[4 * i + a, a * n + 2 + i] = 1.0
            H[4 * i + 2 + a, a * n + 1] = 1.0
            R[4 * i + a, 4 * i + a] = white[i] ** 2
            R[4 * i + 2 + a, 4 * i + 2 + a] = svel[i] ** 2
    return BiasModel(block_diag(F1, F1), block_diag(Q1, Q1), H, R, block_diag(P1, P1))


def velocity_measurements(z) -> np.ndarray:
    """Receiver outputs ``[x, y, v, h]`` ``(..., r, 4)`` to ``[x, y, vx, vy]`` stacked over receivers
    ``(..., 4 r)``, the measurement order of :func:`gauss_markov_bias_model`."""
    z = as_vector(z, "z", 4)
    if z.ndim < 2:
        raise ValueError(f"z must have shape (..., r, 4), got shape {z.shape}")
    out = np.stack([z[..., 0], z[..., 1], z[..., 2] * np.cos(z[..., 3]), z[..., 2] * np.sin(z[..., 3])], -1)
    return out.reshape(out.shape[:-2] + (-1,))


def bias_state_positions(z, model: BiasModel, *, smooth: bool = False) -> np.ndarray:
    """Filter (or smooth) receiver outputs with a :func:`gauss_markov_bias_model` and return positions.

    Parameters
    ----------
    z : (T, ..., r, 4) receiver outputs ``[x, y, v, h]``, time first (``h``: heading in rad).
    model : the :class:`BiasModel` for the same ``r`` receivers.
    smooth : False: the causal :func:`kftrack.kalman.kalman_filter`; True: followed by the RTS
        smoother (:func:`kftrack.kalman.rts_smoother`), which uses the whole lap.

    Returns
    -------
    (T, ..., 2) estimated East-North positions. The prior mean is the receivers' average first
    position and velocity with zero biases; its covariance is ``model.P0``.
    """
    zs = velocity_measurements(z)
    r = zs.shape[-1] // 4
    if model.H.shape[0] != 4 * r:
        raise ValueError(f"model is for {model.H.shape[0] // 4} receivers but z has {r}")
    n = 2 + r
    first = zs[0].reshape(zs.shape[1:-1] + (r, 4)).mean(-2)
    x0 = np.zeros(zs.shape[1:-1] + (2 * n,))
    x0[..., [0, 1, n, n + 1]] = first[..., [0, 2, 1, 3]]
    res = kalman_filter(zs, x0, model.P0, model.F, model.Q, model.H, model.R)
    x = rts_smoother(res, model.F).x if smooth else res.x
    return x[..., [0, n]]
