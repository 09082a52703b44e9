r"""A planar floor plan of walls and a simulated 2-D LIDAR (ray casting), seed 003's Algorithm 1 done right.

**Floor plan.** Walls are line segments ``(W, 2, 2)``: ``walls[w] = [[x0, y0], [x1, y1]]`` (m),
the top-down projection of a building (seed 003, §2.3.3).

**Ray casting.** A beam from the sensor at ``o`` in direction :math:`d = (\cos a, \sin a)` hits the
wall :math:`p + s e` (:math:`e = p_1 - p_0`, :math:`0 \le s \le 1`) at range

.. math::

    t = \frac{(p - o) \times e}{d \times e}, \qquad s = \frac{(p - o) \times d}{d \times e},
    \qquad u \times v = u_x v_y - u_y v_x,

when :math:`d \times e \neq 0`, :math:`t > 0` and :math:`0 \le s \le 1`; the reading is the smallest
such :math:`t` over the walls (all beams and walls at once, one array operation). Beams that hit
nothing within ``max_range`` return ``inf`` (no return), which :func:`scan_to_points` drops.

**Angular resolution.** Seed 003's Algorithm 1 takes the step :math:`\theta` in degrees and loops
``for i in 0 … 360/θ``: an inclusive bound that reads the 0°/360° beam twice. Here the scan
has exactly ``360/θ`` beams at :math:`a_i = i\theta` (:math:`i = 0 … 360/\theta - 1`), converted to
radians once, relative to the sensor heading.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validate import as_vector, check_finite, check_rng
from ..scanmatch import transform_points

__all__ = ["as_walls", "beam_angles", "ray_cast", "Lidar", "scan_to_points", "sample_walls"]


def as_walls(walls) -> np.ndarray:
    """Validate a floor plan: an array ``(W, 2, 2)`` of wall segments of positive length (m)."""
    w = check_finite(np.asarray(walls, dtype=float), "walls")
    if w.ndim != 3 or w.shape[1:] != (2, 2) or w.shape[0] < 1:
        raise ValueError(f"walls must have shape (W, 2, 2) (segments [[x0, y0], [x1, y1]]), got shape {w.shape}")
    if np.any(np.linalg.norm(w[:, 1] - w[:, 0], axis=-1) == 0):
        raise ValueError("walls must have positive length; a segment has equal end points")
    return w


def beam_angles(resolution_deg: float) -> np.ndarray:
    r"""Beam angles (rad) ``(360/θ,)`` of a full turn at angular resolution ``resolution_deg`` = θ (degrees).

    ``360/θ`` must be a whole number (1° gives 360 beams, 0.5° gives 720).
    """
    th = float(resolution_deg)
    if not (np.isfinite(th) and 0 < th <= 360):
        raise ValueError(f"resolution_deg must be an angle in (0, 360] degrees, got {resolution_deg!r}")
    n = 360.0 / th
    if abs(n - round(n)) > 1e-9 * n:
        raise ValueError(f"resolution_deg must divide 360 (a whole number of beams), got {resolution_deg!r}")
    return np.deg2rad(np.arange(round(n)) * th)


def _cross(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def ray_cast(walls, origin, angles, max_range: float = np.inf) -> np.ndarray:
    r"""Range (m) to the nearest wall along each beam; ``inf`` where nothing is hit within ``max_range``.

    Parameters
    ----------
    walls : (W, 2, 2) wall segments.
    origin : (..., 2) beam origins (sensor positions).
    angles : (B,) beam directions in the world frame (rad, counter-clockwise from +x).
    max_range : readings beyond this range are no-returns (``inf``).

    Returns
    -------
    (..., B) ranges.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.sensors.lidar import ray_cast
    >>> room = np.array([[[-2, -2], [2, -2]], [[2, -2], [2, 2]], [[2, 2], [-2, 2]], [[-2, 2], [-2, -2]]], float)
    >>> print(np.round(ray_cast(room, [0.0, 0.0], [0.0, np.pi / 4, np.pi / 2]), 6))   # a 4 m square room
    [2.       2.828427 2.      ]
    """
    w = as_walls(walls)
    o = as_vector(origin, "origin", 2)
    a = check_finite(np.atleast_1d(np.asarray(angles, dtype=float)), "angles")
    if a.ndim != 1:
        raise ValueError(f"angles must have shape (B,), got shape {a.shape}")
    if not max_range > 0:
        raise ValueError(f"max_range must be a positive distance (m), got {max_range!r}")
    d = np.stack([np.cos(a), np.sin(a)], -1)[:, None, :]          # (B, 1, 2)
    p, e = w[:, 0], w[:, 1] - w[:, 0]                                # (W, 2)
    po = p - o[..., None, None, :]                                    # (..., 1, W, 2)
    den = _cross(d, e)                                                # (B, W)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = _cross(po, e) / den
        s = _cross(po, d) / den
    hit = (den != 0) & (t > 0) & (s >= 0) & (s <= 1)
    r = np.min(np.where(hit, t, np.inf), axis=-1)
    return np.where(r <= max_range, r, np.inf)


@dataclass(frozen=True)
class Lidar:
    r"""A 2-D scanning LIDAR: ``360/resolution_deg`` beams per turn, Gaussian range noise.

    Attributes
    ----------
    resolution_deg : angular step θ between beams (degrees; seed 003's Algorithm 1 parameter).
    sigma_range : standard deviation of the range noise (m).
    max_range : readings beyond this are no-returns (m).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.sensors.lidar import Lidar
    >>> room = np.array([[[-2, -2], [2, -2]], [[2, -2], [2, 2]], [[2, 2], [-2, 2]], [[-2, 2], [-2, -2]]], float)
    >>> lidar = Lidar(resolution_deg=90.0)                      # four beams: ahead, left, behind, right
    >>> print(np.round(lidar.ranges(room, pose=[1.0, 0.0, 0.0]), 6))
    [1. 2. 3. 2.]
    >>> lidar.scan(room, [1.0, 0.0, 0.0], np.random.default_rng(0)).shape   # with range noise
    (4,)
    """

    resolution_deg: float = 1.0
    sigma_range: float = 0.02
    max_range: float = 10.0

    def __post_init__(self):
        beam_angles(self.resolution_deg)
        if not (np.isfinite(self.sigma_range) and self.sigma_range >= 0):
            raise ValueError(f"sigma_range must be a non-negative standard deviation (m), got {self.sigma_range!r}")
        if not self.max_range > 0:
            raise ValueError(f"max_range must be a positive distance (m), got {self.max_range!r}")

    @property
    def angles(self) -> np.ndarray:
        """Beam angles relative to the sensor heading (rad), ``(360/θ,)``."""
        return beam_angles(self.resolution_deg)

    def ranges(self, walls, pose) -> np.ndarray:
        """Noise-free ranges ``(..., B)`` from sensor poses ``(..., 3)`` ``(x, y, heading)``."""
        pose = as_vector(pose, "pose", 3)
        a = self.angles
        if pose.ndim == 1:
            return ray_cast(walls, pose[:2], a + pose[2], self.max_range)
        return np.stack([ray_cast(walls, q[:2], a + q[2], self.max_range) for q in pose.reshape(-1, 3)]).reshape(
            pose.shape[:-1] + a.shape)

    def scan(self, walls, pose, rng: np.random.Generator) -> np.ndarray:
        """Noisy ranges ``(..., B)``: true range plus :math:`N(0, \\sigma_r^2)`; no-returns stay ``inf``."""
        check_rng(rng)
        r = self.ranges(walls, pose)
        noisy = r + self.sigma_range * rng.standard_normal(r.shape)
        return np.where(np.isfinite(r), np.maximum(noisy, 0.0), np.inf)


def scan_to_points(ranges, angles, pose=None) -> np.ndarray:
    r"""Seed 003's Algorithm 1 output: the valid readings as points ``(K, 2)``, :math:`(d\cos a, d\sin a)`.

    No-returns (``inf``/``NaN``) are dropped. With ``pose`` ``(3,)`` the points are mapped from the
    sensor frame to the world frame (:func:`kftrack.scanmatch.transform_points`).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.sensors.lidar import scan_to_points
    >>> print(np.round(scan_to_points([1.0, np.inf, 2.0], [0.0, np.pi / 2, np.pi]), 6) + 0.0)   # no-return dropped
    [[ 1.  0.]
     [-2.  0.]]
    """
    r = np.asarray(ranges, dtype=float)
    a = np.asarray(angles, dtype=float)
    if r.ndim != 1 or a.shape != r.shape:
        raise ValueError(f"ranges and angles must both have shape (B,), got {r.shape} and {a.shape}")
    ok = np.isfinite(r)
    pts = np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], -1)
    return pts if pose is None else transform_points(pose, pts)


def sample_walls(walls, spacing: float) -> np.ndarray:
    """Points ``(K, 2)`` every ``spacing`` metres along each wall (end points included): the map as
    a point cloud for scan-to-map ICP."""
    w = as_walls(walls)
    if not (np.isfinite(spacing) and spacing > 0):
        raise ValueError(f"spacing must be a positive distance (m), got {spacing!r}")
    out = []
    for p0, p1 in w:
        n = max(int(np.ceil(np.linalg.norm(p1 - p0) / spacing)), 1)
        s = np.linspace(0.0, 1.0, n + 1)[:, None]
        out.append(p0 + s * (p1 - p0))
    return np.concatenate(out)
