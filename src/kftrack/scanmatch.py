r"""Planar rigid transforms and scan matching by ICP (point-to-point, Kabsch/SVD step).

A 2-D pose is ``(x, y, heading)`` (m, m, rad, heading counter-clockwise from +x); it maps
points from the body (sensor) frame to the world frame, :math:`p_w = R(\theta)\,p_b + t`.

**Kabsch step** (Arun, Huang & Blostein 1987; Besl & McKay 1992). Given paired points
:math:`p_i \to q_i`, the rotation and translation minimising :math:`\sum_i\lVert R p_i + t - q_i\rVert^2`
are, with centroids :math:`\bar p, \bar q` and :math:`W = \sum_i (p_i - \bar p)(q_i - \bar q)^\top = U S V^\top`,

.. math::

    R = V\,\operatorname{diag}(1, \det(V U^\top))\,U^\top, \qquad t = \bar q - R\bar p .

The middle factor guards against a reflection (:math:`\det R = -1`), which the bare
:math:`V U^\top` returns for nearly collinear or mirrored point sets.

**ICP** (Besl & McKay 1992) alternates nearest-neighbour pairing (a ``scipy.spatial.cKDTree``
over the target, built once) with the Kabsch step, composing the increments, until the
change of the mean squared pairing distance falls below ``tol`` or ``max_iterations`` is reached.
It converges to the nearest local minimum: the initial guess matters.

Points are ``(N, 2)`` arrays.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from ._validate import as_vector

__all__ = ["rotation", "transform_points", "compose", "inverse", "between", "kabsch", "ICPResult", "icp",
           "pose_covariance"]


def rotation(theta) -> np.ndarray:
    r"""Rotation matrices :math:`R(\theta)` ``(..., 2, 2)`` of angles ``theta`` ``(...)`` (rad)."""
    theta = np.asarray(theta, dtype=float)
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _wrap(a):
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


def transform_points(pose, points) -> np.ndarray:
    r"""Map body-frame ``points`` ``(..., N, 2)`` to the world with ``pose`` ``(..., 3)``: :math:`R p + t`.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.scanmatch import transform_points
    >>> pose = [1.0, 2.0, np.pi / 2]                  # (x, y, heading): at (1, 2), facing +y
    >>> print(np.round(transform_points(pose, [[1.0, 0.0]]), 6) + 0.0)   # 1 m ahead, in the world
    [[1. 3.]]
    """
    pose = as_vector(pose, "pose", 3)
    points = as_vector(points, "points", 2)
    return points @ np.swapaxes(rotation(pose[..., 2]), -1, -2) + pose[..., None, :2]


def compose(a, b) -> np.ndarray:
    r"""Pose composition :math:`a \oplus b` ``(..., 3)``: ``b`` expressed in the frame of ``a``,
    mapped to the world (heading wrapped to :math:`(-\pi, \pi]`).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.scanmatch import compose, inverse
    >>> a = np.array([1.0, 2.0, 0.5])
    >>> print(np.round(compose(a, inverse(a)), 9) + 0.0)
    [0. 0. 0.]
    """
    a = as_vector(a, "a", 3)
    b = as_vector(b, "b", 3)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * b[..., 0] - s * b[..., 1], a[..., 1] + s * b[..., 0] + c * b[..., 1],
                     _wrap(a[..., 2] + b[..., 2])], -1)


def inverse(a) -> np.ndarray:
    r"""Inverse pose :math:`\ominus a` with :math:`a \oplus (\ominus a) = 0`."""
    a = as_vector(a, "a", 3)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([-c * a[..., 0] - s * a[..., 1], s * a[..., 0] - c * a[..., 1], _wrap(-a[..., 2])], -1)


def between(a, b) -> np.ndarray:
    r"""Relative pose :math:`\ominus a \oplus b`: ``b`` seen from ``a`` (e.g. odometry between two poses)."""
    return compose(inverse(a), b)


def _points(value, name: str, min_points: int) -> np.ndarray:
    p = as_vector(value, name, 2)
    if p.ndim != 2 or p.shape[0] < min_points:
        raise ValueError(f"{name} must have shape (N, 2) with N >= {min_points}, got shape {p.shape}")
    return p


def _kabsch(p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pbar, qbar = p.mean(0), q.mean(0)
    W = (p - pbar).T @ (q - qbar)
    U, _, Vt = np.linalg.svd(W)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, d]) @ U.T
    return R, qbar - R @ pbar


def kabsch(source, target) -> tuple[np.ndarray, np.ndarray]:
    r"""Least-squares rigid transform ``(R, t)`` with ``R @ source[i] + t ≈ target[i]`` (paired points).

    Parameters
    ----------
    source, target : (N, 2) paired points, N >= 2.

    Returns
    -------
    R : (2, 2) rotation, :math:`\det R = +1` (reflection guarded); t : (2,) translation.
    """
    p = _points(source, "source", 2)
    q = _points(target, "target", 2)
    if q.shape != p.shape:
        raise ValueError(f"target must have the shape of source {p.shape}, got shape {q.shape}")
    return _kabsch(p, q)


class ICPResult(NamedTuple):
    """Result of :func:`icp`.

    Attributes
    ----------
    pose : (3,) ``(x, y, heading)`` of the source frame in the target frame
        (``transform_points(pose, source) ≈ target``).
    R, t : (2, 2) rotation and (2,) translation of that pose.
    rmse : root-mean-square distance of the final pairs (m).
    iterations : number of iterations run.
    converged : whether the stopping test was met before ``max_iterations``.
    pairs : number of pairs used in the last iteration.
    """

    pose: np.ndarray
    R: np.ndarray
    t: np.ndarray
    rmse: float
    iterations: int
    converged: bool
    pairs: int


def icp(source, target, initial=(0.0, 0.0, 0.0), *, max_iterations: int = 50, tol: float = 1e-10,
        max_distance: float | None = None, tree: cKDTree | None = None) -> ICPResult:
    r"""Point-to-point ICP (Besl & McKay 1992): align ``source`` to ``target``.

    Parameters
    ----------
    source : (N, 2) points in the source (e.g. sensor) frame.
    target : (M, 2) reference points (a previous scan or points sampled on the map).
    initial : (3,) initial pose guess ``(x, y, heading)`` of the source frame in the target frame.
    max_iterations : at most this many pair-and-align iterations.
    tol : stop when the mean squared pairing distance changes by less than ``tol`` (m²).
    max_distance : reject pairs farther apart than this (m) (outliers, parts of the scan the
        target does not contain); ``None`` keeps all pairs.
    tree : a prebuilt ``cKDTree(target)`` to reuse across calls.

    Returns
    -------
    ICPResult

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.scanmatch import icp, inverse, transform_points
    >>> target = np.random.default_rng(0).uniform(-5.0, 5.0, (200, 2))   # a reference scan
    >>> true = np.array([0.3, -0.2, 0.1])                              # pose of the source frame
    >>> source = transform_points(inverse(true), target)                # the same points, seen from it
    >>> res = icp(source, target)
    >>> print(np.round(res.pose, 6), res.converged)
    [ 0.3 -0.2  0.1] True
    """
    p = _points(source, "source", 3)
    q = _points(target, "target", 3)
    x0 = as_vector(initial, "initial", 3)
    if x0.ndim != 1:
        raise ValueError(f"initial must have shape (3,), got shape {x0.shape}")
    if int(max_iterations) != max_iterations or max_iterations < 1:
        raise ValueError(f"max_iterations must be a positive integer, got {max_iterations!r}")
    if max_distance is not None and not max_distance > 0:
        raise ValueError(f"max_distance must be a positive distance (m) or None, got {max_distance!r}")
    tree = cKDTree(q) if tree is None else tree
    R, t = rotation(x0[2]), x0[:2].copy()
    prev, converged, it, keep = np.inf, False, 0, np.ones(len(p), bool)
    for it in range(1, int(max_iterations) + 1):
        moved = p @ R.T + t
        dist, idx = tree.query(moved)
        keep = np.ones(len(p), bool) if max_distance is None else dist <= max_distance
        if keep.sum() < 3:
            raise ValueError(f"fewer than 3 pairs within max_distance={max_distance} m: the initial guess is too far")
        dR, dt = _kabsch(moved[keep], q[idx[keep]])
        R, t = dR @ R, dR @ t + dt
        err = float(np.mean(dist[keep] ** 2))
        if abs(prev - err) < tol:
            converged = True
            break
        prev = err
    dist, _ = tree.query(p @ R.T + t)
    keep = np.ones(len(p), bool) if max_distance is None else dist <= max_distance
    rmse = float(np.sqrt(np.mean(dist[keep] ** 2))) if keep.any() else float("nan")
    pose = np.array([t[0], t[1], np.arctan2(R[1, 0], R[0, 0])])
    return ICPResult(pose, R, t, rmse, it, converged, int(keep.sum()))


def pose_covariance(points, sigma: float, pose=(0.0, 0.0, 0.0)) -> np.ndarray:
    r"""Gauss–Newton covariance ``(3, 3)`` of a pose fitted to ``points`` with isotropic noise ``sigma``.

    For residuals :math:`r_i = R(\theta)p_i + t - q_i` with independent :math:`N(0, \sigma^2 I)`
    errors and *known* pairs, :math:`\operatorname{Cov}(x, y, \theta) \approx \sigma^2 (J^\top J)^{-1}`,
    :math:`J_i = \partial r_i/\partial(t_x, t_y, \theta) = [I_2,\; R'(\theta) p_i]`.

    Not the covariance of scan-to-map ICP, and not a bound on it either way: there the pairs
    are nearest map points, not the same physical points, a wall constrains only its normal
    direction, and LIDAR noise lies along the beam. Calibrate by Monte Carlo
    (:func:`kftrack.slam.scan_match_errors`).
    """
    p = _points(points, "points", 2)
    if not (np.isfinite(sigma) and sigma > 0):
        raise ValueError(f"sigma must be a positive standard deviation (m), got {sigma!r}")
    th = float(as_vector(pose, "pose", 3)[2])
    dRp = p @ np.array([[-np.sin(th), -np.cos(th)], [np.cos(th), -np.sin(th)]]).T
    J = np.zeros((2 * len(p), 3))
    J[0::2, 0] = J[1::2, 1] = 1.0
    J[0::2, 2], J[1::2, 2] = dRp[:, 0], dRp[:, 1]
    return sigma**2 * np.linalg.inv(J.T @ J)
