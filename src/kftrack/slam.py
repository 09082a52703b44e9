r"""Robot localization and EKF-SLAM in the plane (the simulation chapter seed 003 promised).

**Unicycle motion** (Thrun, Burgard & Fox 2005, simplified Euler form), pose ``[x, y, heading]``,
odometry input :math:`u = [v, \omega]` measured with white noise of standard deviations
:math:`(\sigma_v, \sigma_\omega)`:

.. math::

    f(x, u) = \begin{bmatrix} x + v T\cos\theta \\ y + v T\sin\theta \\ \theta + \omega T\end{bmatrix},
    \qquad Q = V \operatorname{diag}(\sigma_v^2, \sigma_\omega^2) V^\top,\; V = \partial f/\partial u .

**Range–bearing landmark observation** relative to the robot: the radar model of
:mod:`kftrack.sensors.radar` (``polar_measurement(2)``) applied to :math:`\Delta = m - p`, with the
bearing measured from the heading, :math:`h = [\lVert\Delta\rVert,\ \operatorname{atan2}(\Delta_y, \Delta_x) - \theta]`;
its inverse, for a first sighting, :math:`m = p + r[\cos(\varphi + \theta), \sin(\varphi + \theta)]`.
All Jacobians are derived with SymPy and generated once.

**EKF-SLAM** (Smith, Self & Cheeseman 1990; Durrant-Whyte & Bailey 2006): the state is
``[x, y, heading, l1x, l1y, l2x, l2y, ...]`` (heading wrapped to :math:`(-\pi, \pi]`), shape
``(..., 3 + 2N)``. Prediction touches the robot rows only (:math:`P_{rr} \to G P_{rr} G^\top + Q`,
:math:`P_{rm} \to G P_{rm}`); an update uses the sparse :math:`H = [H_r, 0, \dots, H_m, \dots, 0]`; a
new landmark :math:`m = g(x_r, z)` enters with

.. math::

    P_{mm} = G_r P_{rr} G_r^\top + G_z R G_z^\top, \qquad P_{m\cdot} = G_r P_{r\cdot},

the correlations with the robot *and with every landmark already mapped*. Data association is
nearest neighbour with a Mahalanobis gate :math:`\nu^\top S^{-1}\nu < \chi^2_2(p)`.

The functions broadcast over leading batch axes (Monte Carlo runs) as long as all runs share
the same landmark order, which holds with known associations on a common true path.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import sympy as sp
from scipy import stats
from scipy.spatial import cKDTree

from . import symbolic as sym
from ._validate import as_float_array, as_vector, check_covariance, check_finite
from .ekf import wrap_angle
from .kalman import Update
from .kernels import gain_update
from .scanmatch import icp
from .sensors.lidar import Lidar, scan_to_points
from .sensors.radar import polar_measurement, polar_to_cartesian_expr

__all__ = ["unicycle_motion", "landmark_observation", "landmark_inverse", "Unicycle", "observe",
           "observation_jacobians", "inverse_observation", "inverse_jacobians", "slam_predict", "slam_update",
           "add_landmark", "landmark_innovation", "associate", "SlamResult", "ekf_slam", "NEW", "REJECTED",
           "landmark_count", "landmark_block", "scan_match_errors", "Localization",
           "icp_localization", "pose_nees", "landmark_sd"]

# symbols of the pose, the input, the landmark and the measurement
_x, _y, _th = sp.symbols("x y theta", real=True)
_v, _w = sp.symbols("v omega", real=True)
_mx, _my = sp.symbols("m_x m_y", real=True)
_r = sp.Symbol("r", positive=True)
_phi = sp.Symbol("varphi", real=True)


def unicycle_motion() -> tuple[sp.Matrix, sp.Matrix, sp.Matrix]:
    """SymPy ``(f, pose, u)``: the Euler-discretized unicycle over the interval ``symbolic.T``."""
    pose, u = sp.Matrix([_x, _y, _th]), sp.Matrix([_v, _w])
    f = sp.Matrix([_x + _v * sym.T * sp.cos(_th), _y + _v * sym.T * sp.sin(_th), _th + _w * sym.T])
    return f, pose, u


def landmark_observation() -> tuple[sp.Matrix, sp.Matrix, sp.Matrix]:
    """SymPy ``(h, pose, m)``: range and bearing (from the heading) of landmark ``m`` seen from ``pose``,
    built from :func:`kftrack.sensors.radar.polar_measurement`."""
    h, d = polar_measurement(2)
    h = h.subs({d[0]: _mx - _x, d[1]: _my - _y}, simultaneous=True)
    h[1] = h[1] - _th
    return h, sp.Matrix([_x, _y, _th]), sp.Matrix([_mx, _my])


def landmark_inverse() -> tuple[sp.Matrix, sp.Matrix, sp.Matrix]:
    """SymPy ``(g, pose, z)``: the landmark position from a range–bearing measurement ``z = [r, varphi]``
    (inverse observation), built from :func:`kftrack.sensors.radar.polar_to_cartesian_expr`."""
    g, z = polar_to_cartesian_expr(2)
    g = g.subs({z[0]: _r, z[1]: _phi + _th}, simultaneous=True) + sp.Matrix([_x, _y])
    return g, sp.Matrix([_x, _y, _th]), sp.Matrix([_r, _phi])


@lru_cache(maxsize=None)
def _generated() -> dict:
    f, pose, u = unicycle_motion()
    h, _, m = landmark_observation()
    g, _, z = landmark_inverse()
    a_f = [_x, _y, _th, _v, _w, sym.T]
    a_h = [_x, _y, _th, _mx, _my]
    a_g = [_x, _y, _th, _r, _phi]
    return {"f": sym.GeneratedFunction(a_f, f), "G": sym.GeneratedFunction(a_f, f.jacobian(pose)),
            "V": sym.GeneratedFunction(a_f, f.jacobian(u)),
            "h": sym.GeneratedFunction(a_h, h), "Hr": sym.GeneratedFunction(a_h, h.jacobian(pose)),
            "Hm": sym.GeneratedFunction(a_h, h.jacobian(m)),
            "g": sym.GeneratedFunction(a_g, g), "Gr": sym.GeneratedFunction(a_g, g.jacobian(pose)),
            "Gz": sym.GeneratedFunction(a_g, g.jacobian(z))}


def _split(a):
    return [a[..., i] for i in range(a.shape[-1])]


@dataclass(frozen=True)
class Unicycle:
    r"""Unicycle odometry model, pose ``[x, y, heading]``, input ``u = [v, omega]`` (m/s, rad/s).

    Attributes
    ----------
    sigma_v : standard deviation of the measured speed (m/s).
    sigma_omega : standard deviation of the measured turn rate (rad/s).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.slam import Unicycle
    >>> robot = Unicycle(sigma_v=0.1, sigma_omega=0.01)
    >>> print(np.round(robot.f([0.0, 0.0, 0.0], u=[1.0, 0.0], dt=1.0), 6) + 0.0)   # 1 m/s straight ahead for 1 s
    [1. 0. 0.]
    >>> robot.Q([0.0, 0.0, 0.0], [1.0, 0.1], 1.0).shape
    (3, 3)
    """

    sigma_v: float
    sigma_omega: float

    def __post_init__(self):
        for name in ("sigma_v", "sigma_omega"):
            val = getattr(self, name)
            if not (np.isfinite(val) and val >= 0):
                raise ValueError(f"{name} must be a non-negative standard deviation, got {val!r}")

    def _args(self, pose, u, dt):
        pose = as_vector(pose, "pose", 3)
        u = as_vector(u, "u", 2)
        return _split(pose[..., :3]) + _split(u) + [np.asarray(dt, dtype=float)]

    def f(self, pose, u, dt) -> np.ndarray:
        """Next pose ``(..., 3)`` (heading wrapped)."""
        out = _generated()["f"](*self._args(pose, u, dt))[..., 0]
        out[..., 2] = wrap_angle(out[..., 2])
        return out

    def jacobian(self, pose, u, dt) -> np.ndarray:
        r""":math:`G = \partial f/\partial\,\mathrm{pose}`, ``(..., 3, 3)``."""
        return _generated()["G"](*self._args(pose, u, dt))

    def input_jacobian(self, pose, u, dt) -> np.ndarray:
        r""":math:`V = \partial f/\partial u`, ``(..., 3, 2)``."""
        return _generated()["V"](*self._args(pose, u, dt))

    def Q(self, pose, u, dt) -> np.ndarray:
        r"""Process noise :math:`V\operatorname{diag}(\sigma_v^2, \sigma_\omega^2)V^\top`, ``(..., 3, 3)``."""
        V = self.input_jacobian(pose, u, dt)
        return V @ np.diag([self.sigma_v**2, self.sigma_omega**2]) @ np.swapaxes(V, -1, -2)


def observe(pose, landmark) -> np.ndarray:
    """Noise-free range and bearing ``(..., 2)`` of ``landmark`` ``(..., 2)`` from ``pose`` ``(..., 3)``;
    bearing from the heading, wrapped to (-pi, pi].

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.slam import inverse_observation, observe
    >>> pose = [0.0, 0.0, np.pi / 2]                  # at the origin, facing +y
    >>> z = observe(pose, [0.0, 5.0])                  # range, bearing from the heading
    >>> print(np.round(z, 6) + 0.0)
    [5. 0.]
    >>> print(np.round(inverse_observation(pose, z), 6) + 0.0)
    [0. 5.]
    """
    pose = as_vector(pose, "pose", 3)
    landmark = as_vector(landmark, "landmark", 2)
    z = _generated()["h"](*_split(pose), *_split(landmark))[..., 0]
    z[..., 1] = wrap_angle(z[..., 1])
    return z


def observation_jacobians(pose, landmark) -> tuple[np.ndarray, np.ndarray]:
    """``(H_r, H_m)``: Jacobians of :func:`observe` with respect to the pose ``(..., 2, 3)`` and the
    landmark ``(..., 2, 2)``."""
    args = _split(as_vector(pose, "pose", 3)) + _split(as_vector(landmark, "landmark", 2))
    return _generated()["Hr"](*args), _generated()["Hm"](*args)


def inverse_observation(pose, z) -> np.ndarray:
    """Landmark position ``(..., 2)`` from a measurement ``z = [r, bearing]`` ``(..., 2)`` taken at ``pose``."""
    return _generated()["g"](*_split(as_vector(pose, "pose", 3)), *_split(as_vector(z, "z", 2)))[..., 0]


def inverse_jacobians(pose, z) -> tuple[np.ndarray, np.ndarray]:
    """``(G_r, G_z)``: Jacobians of :func:`inverse_observation` with respect to the pose ``(..., 2, 3)``
    and the measurement ``(..., 2, 2)``."""
    args = _split(as_vector(pose, "pose", 3)) + _split(as_vector(z, "z", 2))
    return _generated()["Gr"](*args), _generated()["Gz"](*args)


# --------------------------------------------------------------------------------------------
# EKF-SLAM on the augmented state [x, y, heading, l1x, l1y, ...]
# --------------------------------------------------------------------------------------------
NEW = -1
"""Returned by :func:`associate` for a measurement outside every gate: a new landmark."""
REJECTED = -2
"""Returned by :func:`associate` for a measurement inside no gate but too close to a landmark to be new."""


def landmark_count(x) -> int:
    """Number of landmarks ``N`` in a SLAM state of length ``3 + 2N``."""
    n = np.shape(x)[-1]
    if n < 3 or (n - 3) % 2:
        raise ValueError(f"x must have length 3 + 2N ([x, y, heading, l1x, l1y, ...]), got length {n}")
    return (n - 3) // 2


def landmark_block(j: int) -> slice:
    """Slice of landmark ``j`` (0-based) in the SLAM state."""
    if not isinstance(j, (int, np.integer)) or j < 0:
        raise ValueError(f"j must be a landmark index >= 0 (0-based), got {j!r}")
    return slice(3 + 2 * j, 5 + 2 * j)


def _check_motion(dt, model) -> float:
    """Boundary check of a time step (s) and the motion model."""
    if not isinstance(model, Unicycle):
        raise TypeError(f"model must be a kftrack.slam.Unicycle, got {type(model).__name__}")
    try:
        dt = float(dt)
    except (TypeError, ValueError):
        raise TypeError(f"dt must be a time step in seconds (a number), got {type(dt).__name__}") from None
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive, finite time step (s), got {dt!r}")
    return dt


def _check(x, P):
    x = as_vector(x, "x")
    landmark_count(x)
    P = check_covariance(P, "P", x.shape[-1])
    return x, P


def _predict(x, P, u, dt, model: Unicycle):
    r = x[..., :3]
    G = model.jacobian(r, u, dt)
    x = x.copy()
    x[..., :3] = model.f(r, u, dt)
    P = P.copy()
    P[..., :3, :] = G @ P[..., :3, :]
    P[..., :, :3] = P[..., :, :3] @ np.swapaxes(G, -1, -2)
    P[..., :3, :3] += model.Q(r, u, dt)
    return x, P


def slam_predict(x, P, u, dt: float, model: Unicycle) -> tuple[np.ndarray, np.ndarray]:
    r"""EKF-SLAM time update with odometry ``u = [v, omega]`` ``(..., 2)``: the landmarks stay put.

    :math:`P_{rr} \leftarrow G P_{rr} G^\top + Q`, :math:`P_{rm} \leftarrow G P_{rm}` (cost :math:`O(N)`).
    """
    x, P = _check(x, P)
    as_vector(u, "u", 2)
    dt = _check_motion(dt, model)
    return _predict(x, P, u, dt, model)


def _innovation(x, z, j):
    n = x.shape[-1]
    r, m = x[..., :3], x[..., landmark_block(j)]
    zhat = observe(r, m)
    Hr, Hm = observation_jacobians(r, m)
    H = np.zeros(Hr.shape[:-1] + (n,))
    H[..., :3], H[..., landmark_block(j)] = Hr, Hm
    y = z - zhat
    y[..., 1] = wrap_angle(y[..., 1])
    return y, H


def _update(x, P, z, j, R) -> Update:
    y, H = _innovation(x, z, j)
    u = gain_update(x, P, y, H, R)
    u.x[..., 2] = wrap_angle(u.x[..., 2])
    return u


def _check_landmark(x, j) -> int:
    N = landmark_count(x)
    if int(j) != j or not 0 <= j < N:
        raise ValueError(f"j must be a landmark index in [0, {N}), got {j!r}")
    return int(j)


def slam_update(x, P, z, j: int, R) -> Update:
    """EKF update with the range–bearing measurement ``z`` ``(..., 2)`` of mapped landmark ``j``
    (Joseph form; bearing innovation and heading wrapped). Returns :class:`kftrack.kalman.Update`."""
    x, P = _check(x, P)
    j = _check_landmark(x, j)
    z = as_vector(z, "z", 2)
    R = check_covariance(R, "R", 2, positive_definite=True)
    return _update(x, P, z, j, R)


def _add(x, P, z, R):
    r = x[..., :3]
    m = inverse_observation(r, z)
    Gr, Gz = inverse_jacobians(r, z)
    n = x.shape[-1]
    xa = np.concatenate([x, m], -1)
    Pa = np.zeros(P.shape[:-2] + (n + 2, n + 2))
    Pa[..., :n, :n] = P
    cross = Gr @ P[..., :3, :]                                    # (..., 2, n)
    Pa[..., n:, :n] = cross
    Pa[..., :n, n:] = np.swapaxes(cross, -1, -2)
    Pa[..., n:, n:] = Gr @ P[..., :3, :3] @ np.swapaxes(Gr, -1, -2) + Gz @ R @ np.swapaxes(Gz, -1, -2)
    return xa, Pa


def add_landmark(x, P, z, R) -> tuple[np.ndarray, np.ndarray]:
    r"""Append a landmark first seen as ``z = [r, bearing]``: state ``(..., n + 2)``, covariance with
    :math:`P_{mm} = G_r P_{rr} G_r^\top + G_z R G_z^\top` and cross-covariances :math:`G_r P_{r\cdot}`."""
    x, P = _check(x, P)
    z = as_vector(z, "z", 2)
    R = check_covariance(R, "R", 2)
    return _add(x, P, z, R)


def landmark_innovation(x, P, z, R) -> tuple[np.ndarray, np.ndarray]:
    """Innovations ``(N, 2)`` of ``z`` against every mapped landmark and their covariances ``(N, 2, 2)``
    (one unbatched state ``x`` ``(n,)``)."""
    x, P = _check(x, P)
    z = as_vector(z, "z", 2)
    R = check_covariance(R, "R", 2)
    if x.ndim != 1:
        raise ValueError(f"x must have shape (n,) for data association, got shape {x.shape}")
    return _innovations(x, P, z, R)


def _innovations(x, P, z, R):
    N = landmark_count(x)
    if N == 0:
        return np.zeros((0, 2)), np.zeros((0, 2, 2))
    m = x[3:].reshape(N, 2)
    r = np.broadcast_to(x[:3], (N, 3))
    y = z - observe(r, m)
    y[:, 1] = wrap_angle(y[:, 1])
    Hr, Hm = observation_jacobians(r, m)
    idx = np.arange(N)
    Prr = P[:3, :3]
    Prm = np.stack([P[:3, landmark_block(j)] for j in idx])           # (N, 3, 2)
    Pmm = np.stack([P[landmark_block(j), landmark_block(j)] for j in idx])
    HrT, HmT = np.swapaxes(Hr, -1, -2), np.swapaxes(Hm, -1, -2)
    S = Hr @ Prr @ HrT + Hr @ Prm @ HmT + Hm @ np.swapaxes(Prm, -1, -2) @ HrT + Hm @ Pmm @ HmT + R
    return y, 0.5 * (S + np.swapaxes(S, -1, -2))


def associate(x, P, zs, R, gate: float = 0.99, new: float | None = 0.9999) -> np.ndarray:
    r"""Nearest-neighbour data association with a Mahalanobis gate.

    For each measurement ``zs[i]`` the landmark with the smallest :math:`d^2 = \nu^\top S^{-1}\nu`
    is chosen if :math:`d^2 < \chi^2_2(\text{gate})` (5.991 at 0.95, 9.210 at 0.99). Outside every
    gate the measurement is a new landmark if :math:`d^2 > \chi^2_2(\text{new})` for all landmarks,
    otherwise it is ambiguous and rejected. ``new=None`` makes every ungated measurement a new
    landmark. Each landmark takes at most one measurement per scan (the closest, in order).

    Parameters
    ----------
    x, P : (n,), (n, n) one SLAM state (no batch axes).
    zs : (M, 2) range–bearing measurements of one scan.
    R : (2, 2) measurement noise.

    Returns
    -------
    (M,) int: landmark index, :data:`NEW` or :data:`REJECTED`.
    """
    x, P = _check(x, P)
    if x.ndim != 1:
        raise ValueError(f"x must have shape (n,) for data association, got shape {x.shape}")
    zs = as_vector(zs, "zs", 2)
    if zs.ndim != 2:
        raise ValueError(f"zs must have shape (M, 2), got shape {zs.shape}")
    R = check_covariance(R, "R", 2, positive_definite=True)
    if not 0 < gate < 1:
        raise ValueError(f"gate must be a probability in (0, 1), got {gate!r}")
    if new is not None and not gate <= new < 1:
        raise ValueError(f"new must be a probability in [gate, 1) or None, got {new!r}")
    g2 = stats.chi2.ppf(gate, 2)
    n2 = g2 if new is None else stats.chi2.ppf(new, 2)
    out = np.full(len(zs), NEW, dtype=int)
    if landmark_count(x) == 0:
        return out
    d2 = np.stack([_mahal(*_innovations(x, P, z, R)) for z in zs])  # (M, N)
    taken: set[int] = set()
    for i in np.argsort(d2.min(axis=1), kind="stable"):
        row = d2[i].copy()
        row[list(taken)] = np.inf
        j = int(np.argmin(row))
        if row[j] < g2:
            out[i] = j
            taken.add(j)
        elif d2[i].min() <= n2:
            out[i] = REJECTED
    return out


def _mahal(y, S):
    return np.einsum("...i,...i->...", y, np.linalg.solve(S, y[..., None])[..., 0])


class SlamResult(NamedTuple):
    """An EKF-SLAM run, time first.

    Attributes
    ----------
    pose : (T, ..., 3) robot pose estimates after each step's updates.
    pose_P : (T, ..., 3, 3) their covariances.
    x : list of T states ``(..., 3 + 2N_k)`` (the map grows).
    P : list of T covariances.
    ids : list of the true landmark ids in state order (known associations) or the
        association decisions per step (``associate``).
    nis : list of T arrays of the NIS of each update at that step.
    """

    pose: np.ndarray
    pose_P: np.ndarray
    x: list
    P: list
    ids: list
    nis: list


def _check_observations(observations, known: bool) -> None:
    """Boundary check of :func:`ekf_slam`'s observations: pairs ``(ids (M,), z (M, ..., 2))``, finite."""
    for k, item in enumerate(observations):
        name = f"observations[{k}]"
        if not isinstance(item, (tuple, list)) or len(item) != 2:
            raise TypeError(f"{name} must be a pair (ids, z), got {type(item).__name__}")
        ids, z = np.asarray(item[0]), check_finite(as_float_array(item[1], f"{name} z"), f"{name} z")
        if z.size == 0 and (ids.size == 0 or not known):
            continue
        if z.shape[-1] != 2 or (known and (ids.ndim != 1 or z.ndim < 2 or z.shape[0] != ids.size)):
            raise ValueError(f"{name} must be (ids (M,), z (M, ..., 2)) (range, bearing per landmark), "
                             f"got ids shape {ids.shape} and z shape {z.shape}")


def ekf_slam(x0, P0, odometry, dt: float, observations, R, model: Unicycle, *, known: bool = True,
             gate: float = 0.99, new: float | None = 0.9999) -> SlamResult:
    r"""Run EKF-SLAM: at each step, update with that step's landmark observations, then predict.

    Parameters
    ----------
    x0, P0 : (..., 3), (..., 3, 3) prior of the robot pose at step 0 (the map starts empty).
    odometry : (T, ..., 2) measured ``[v, omega]`` applied after step ``k`` (the last row is unused).
    dt : time step (s).
    observations : sequence of T pairs ``(ids, z)``: ``ids`` ``(M_k,)`` true landmark ids,
        ``z`` ``(M_k, ..., 2)`` range–bearing measurements.
    R : (2, 2) measurement noise.
    model : the :class:`Unicycle` odometry model.
    known : use the true ids (known associations; batch axes allowed). ``False``: nearest
        neighbour with the Mahalanobis gate (:func:`associate`; no batch axes).

    Returns
    -------
    SlamResult

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.scenarios import ring_landmarks, slam_loop
    >>> from kftrack.slam import Unicycle, ekf_slam, landmark_count
    >>> rng = np.random.default_rng(0)
    >>> world = slam_loop(rng, ring_landmarks(rng, count=12), loops=1.0)   # one loop, dt = 0.25 s
    >>> model = Unicycle(sigma_v=0.05, sigma_omega=np.deg2rad(3.0))
    >>> R = np.diag([0.1 ** 2, np.deg2rad(2.0) ** 2])                    # range (m), bearing (rad)
    >>> res = ekf_slam(world.truth[0], np.zeros((3, 3)), world.odometry, 0.25, world.observations, R, model)
    >>> res.pose.shape, landmark_count(res.x[-1]), res.x[-1].shape        # pose per step; the map grew to 12
    ((152, 3), 12, (27,))
    """
    dt = _check_motion(dt, model)
    x = as_vector(x0, "x0", 3)
    P = check_covariance(P0, "P0", 3)
    try:
        batch = np.broadcast_shapes(x.shape[:-1], P.shape[:-2])
    except ValueError:
        raise ValueError(f"x0 {x.shape} and P0 {P.shape} batch axes do not broadcast") from None
    x, P = np.broadcast_to(x, batch + (3,)).copy(), np.broadcast_to(P, batch + (3, 3)).copy()
    R = check_covariance(R, "R", 2, positive_definite=True)
    u = as_vector(odometry, "odometry", 2)
    T = u.shape[0]
    if len(observations) != T:
        raise ValueError(f"observations must hold one (ids, z) pair per step, {T} steps; got {len(observations)}")
    _check_observations(observations, known)
    if not known and x.ndim != 1:
        raise ValueError(f"x0 must have shape (3,) when known=False (association runs one state), got {x.shape}")
    slot: dict[int, int] = {}
    order: list[int] = []
    decisions: list[np.ndarray] = []
    poses, poses_P, xs, Ps, nis_all = [], [], [], [], []
    for k in range(T):
        ids, zk = observations[k]
        zk = np.asarray(zk, dtype=float)
        nis_k = []
        if known:
            for i, lid in enumerate(np.asarray(ids, dtype=int)):
                if lid in slot:
                    upd = _update(x, P, zk[i], slot[lid], R)
                    x, P = upd.x, upd.P
                    nis_k.append(upd.nis)
                else:
                    slot[int(lid)] = landmark_count(x)
                    order.append(int(lid))
                    x, P = _add(x, P, zk[i], R)
        else:
            dec = associate(x, P, zk.reshape(-1, 2), R, gate, new) if len(zk) else np.zeros(0, int)
            decisions.append(dec)
            for i in np.flatnonzero(dec >= 0):
                upd = _update(x, P, zk[i], int(dec[i]), R)
                x, P = upd.x, upd.P
                nis_k.append(upd.nis)
            for i in np.flatnonzero(dec == NEW):
                x, P = _add(x, P, zk[i], R)
        poses.append(x[..., :3].copy())
        poses_P.append(P[..., :3, :3].copy())
        xs.append(x)
        Ps.append(P)
        nis_all.append(np.array(nis_k))
        if k < T - 1:
            x, P = _predict(x, P, u[k], dt, model)
    return SlamResult(np.stack(poses), np.stack(poses_P), xs, Ps, order if known else decisions, nis_all)


# --------------------------------------------------------------------------------------------
# seed 003's Algorithm 2 done right: LIDAR scan -> ICP against the map -> pose -> Kalman filter
# --------------------------------------------------------------------------------------------
def _icp_pose(scan, angles, map_points, tree, guess, max_distance):
    pts = scan_to_points(scan, angles)
    return icp(pts, map_points, guess, max_distance=max_distance, tree=tree)


def scan_match_errors(walls, sensor: Lidar, poses, map_points, rng: np.random.Generator, offset_sigmas,
                      max_distance: float = 0.5) -> np.ndarray:
    r"""Errors ``(K, 3)`` (x, y, heading; heading wrapped) of scan-to-map ICP at the true ``poses``
    ``(K, 3)``, each started from the truth displaced by :math:`N(0, \operatorname{diag}(\text{offset\_sigmas})^2)`
    (the prediction error of a filter): the Monte Carlo calibration of the ICP pose covariance."""
    poses = as_vector(poses, "poses", 3).reshape(-1, 3)
    off = as_vector(offset_sigmas, "offset_sigmas", 3)
    tree = cKDTree(map_points)
    out = np.empty_like(poses)
    for k, p in enumerate(poses):
        scan = sensor.scan(walls, p, rng)
        guess = p + off * rng.standard_normal(3)
        out[k] = _icp_pose(scan, sensor.angles, map_points, tree, guess, max_distance).pose - p
    out[:, 2] = wrap_angle(out[:, 2])
    return out


class Localization(NamedTuple):
    """Result of :func:`icp_localization`, time first: estimates ``x`` ``(T, 3)``, covariances ``P``
    ``(T, 3, 3)``, ICP pose measurements ``z`` ``(T, 3)``, their NIS ``(T,)`` and ICP residual
    RMS ``icp_rmse`` ``(T,)`` (m)."""

    x: np.ndarray
    P: np.ndarray
    z: np.ndarray
    nis: np.ndarray
    icp_rmse: np.ndarray


def icp_localization(scans, angles, map_points, odometry, dt: float, x0, P0, model: Unicycle, R_icp,
                     *, max_distance: float = 0.5) -> Localization:
    r"""Seed 003's Algorithm 2 done right: each scan is matched to the map by ICP, started from the
    filter's prediction; the ICP pose ``z = (x, y, heading)`` is the measurement (``H = I``,
    covariance ``R_icp``, heading innovation wrapped) of an EKF with the unicycle odometry model.

    Parameters
    ----------
    scans : (T, B) LIDAR ranges (``inf`` = no return); ``angles`` (B,) beam angles in the sensor frame.
    map_points : (M, 2) the map as points (:func:`kftrack.sensors.lidar.sample_walls`).
    odometry : (T, 2) measured ``[v, omega]`` applied after each scan.
    dt : time step (s); ``x0``, ``P0``: prior of the pose at step 0.
    model : :class:`Unicycle`; ``R_icp`` (3, 3): the stated covariance of the ICP pose.
    max_distance : ICP pair rejection distance (m).
    """
    dt = _check_motion(dt, model)
    scans = np.asarray(scans, dtype=float)
    u = as_vector(odometry, "odometry", 2)
    if scans.ndim != 2 or u.shape != (scans.shape[0], 2):
        raise ValueError(f"scans (T, B) and odometry (T, 2) must share T, got {scans.shape} and {u.shape}")
    x = as_vector(x0, "x0", 3).copy()
    P = check_covariance(P0, "P0", 3)
    R = check_covariance(R_icp, "R_icp", 3, positive_definite=True)
    tree = cKDTree(as_vector(map_points, "map_points", 2))
    H = np.eye(3)
    out = {k: [] for k in Localization._fields}
    for k in range(len(scans)):
        m = _icp_pose(scans[k], angles, map_points, tree, x, max_distance)
        y = m.pose - x
        y[2] = wrap_angle(y[2])
        upd = gain_update(x, P, y, H, R)
        x, P = upd.x, upd.P
        x[2] = wrap_angle(x[2])
        for name, val in zip(Localization._fields, (x, P, m.pose, upd.nis, m.rmse)):
            out[name].append(val)
        if k < len(scans) - 1:
            x, P = _predict(x, P, u[k], dt, model)
    return Localization(*(np.array(out[f]) for f in Localization._fields))


def pose_nees(result: SlamResult, truth) -> np.ndarray:
    """NEES ``(T, ...)`` of the robot pose of an EKF-SLAM run against the true poses ``truth``
    ``(T, 3)`` (or ``(T, ..., 3)``), heading error wrapped; chi-square with 3 degrees of freedom
    for a consistent filter."""
    truth = as_vector(truth, "truth", 3)
    if truth.shape[0] != result.pose.shape[0]:
        raise ValueError(f"truth must have shape ({result.pose.shape[0]}, ..., 3), one pose per step of the run, "
                         f"got shape {truth.shape}")
    e = result.pose - (truth if truth.ndim == result.pose.ndim else truth.reshape(
        truth.shape[:1] + (1,) * (result.pose.ndim - truth.ndim) + (3,)))
    e[..., 2] = wrap_angle(e[..., 2])
    return np.einsum("...i,...i->...", e, np.linalg.solve(result.pose_P, e[..., None])[..., 0])


def landmark_sd(result: SlamResult, count: int) -> np.ndarray:
    r"""Uncertainty :math:`\sqrt{\operatorname{tr} P_{mm}}` (m) of each landmark over time, ``(T, count)``,
    indexed by true landmark id (known-association runs, one run); NaN before it is mapped."""
    if not result.ids or not isinstance(result.ids[0], (int, np.integer)):
        raise ValueError("result must come from ekf_slam(..., known=True) (ids in state order)")
    if int(count) != count or count < max(result.ids) + 1:
        raise ValueError(f"count must be an integer above the largest landmark id {max(result.ids)}, got {count!r}")
    out = np.full((len(result.P), int(count)), np.nan)
    for k, P in enumerate(result.P):
        for slot in range(landmark_count(result.x[k])):
            b = landmark_block(slot)
            out[k, result.ids[slot]] = np.sqrt(np.trace(P[..., b, b], axis1=-2, axis2=-1))
    return out
