r"""Seeded simulation of what a real sensor reports each scan: the target's measurement with
probability :math:`P_D` (missed otherwise) and Poisson false alarms uniform in a region.

Clutter: the number of false alarms in a region of volume :math:`V` is Poisson with mean
:math:`\lambda V` (:math:`\lambda` the spatial density, per unit measurement volume), their
positions independent and uniform (Bar-Shalom, Willett & Tian 2011, §6.2). The scans come out
**padded** for :mod:`kftrack.association`: ``Z`` ``(..., M_max, m)`` and a ``mask``.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._validate import as_float_array, as_vector, check_rng

__all__ = ["Scans", "simulate_scans"]


class Scans(NamedTuple):
    """Padded scans (leading axes those of the true measurements without the target axis).

    Attributes
    ----------
    Z : (..., M_max, m) measurements, in random order (zero at padding).
    mask : (..., M_max) bool, true for a real measurement.
    origin : (..., M_max) int: the target index (0 for a single target) or -1 for clutter and
        padding.
    amplitude : (..., M_max) detector power, Swerling I: exponential of mean ``1 + snr`` for a
        target, ``1`` for clutter (0 at padding); for strongest-neighbour association.
    detected : (..., K) bool, which targets were detected (K = 1 for a single target).
    """

    Z: np.ndarray
    mask: np.ndarray
    origin: np.ndarray
    amplitude: np.ndarray
    detected: np.ndarray


def simulate_scans(z_true, *, P_D: float, clutter_density: float, region, rng: np.random.Generator,
                   several_targets: bool = False, snr: float = 10.0, center=None) -> Scans:
    r"""Scans with missed detections and Poisson clutter.

    Parameters
    ----------
    z_true : (..., m) noisy target measurements (one target), or (..., K, m) with
        ``several_targets=True``.
    P_D : detection probability in (0, 1].
    clutter_density : :math:`\lambda >= 0`, false alarms per unit measurement volume.
    region : ``(lo, hi)``, each (m,): the box in which clutter falls, volume
        :math:`V = \prod(hi - lo)`; with ``center`` (..., m) given, the box is shifted by it
        (a window that moves with the target: the clutter the tracker can meet, at a fraction
        of the cost of a whole surveillance region).
    rng : the random generator.
    snr : mean signal-to-noise ratio of a target detection (for ``amplitude``).

    Returns
    -------
    Scans

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.clutter import simulate_scans
    >>> z_true = np.zeros((100, 2))                   # 100 scans of a target at the origin
    >>> scans = simulate_scans(z_true, P_D=0.9, clutter_density=0.01, region=([-10.0, -10.0], [10.0, 10.0]),
    ...                        rng=np.random.default_rng(0))   # lambda V = 0.01 * 400 = 4 false alarms a scan
    >>> scans.Z.shape[0], scans.Z.shape[-1], scans.mask.shape == scans.Z.shape[:2], scans.detected.shape
    (100, 2, True, (100, 1))
    >>> int(scans.detected.sum()), int((scans.mask & (scans.origin == 0)).sum())   # scans holding the target
    (96, 96)
    """
    rng = check_rng(rng)
    z_true = as_vector(z_true, "z_true")
    if not several_targets:
        z_true = z_true[..., None, :]
    elif z_true.ndim < 2:
        raise ValueError(f"z_true must have shape (..., K, m) with several_targets=True, got shape {z_true.shape}")
    P_D_ = float(as_float_array(P_D, "P_D"))
    if not 0.0 < P_D_ <= 1.0:
        raise ValueError(f"P_D (detection probability) must lie in (0, 1], got {P_D!r}")
    lam = float(as_float_array(clutter_density, "clutter_density"))
    if not (np.isfinite(lam) and lam >= 0):
        raise ValueError(f"clutter_density must be finite and >= 0 (false alarms per unit volume), got {clutter_density!r}")
    m = z_true.shape[-1]
    lo, hi = (as_float_array(b, "region").reshape(-1) for b in region)
    if lo.shape != (m,) or hi.shape != (m,) or np.any(hi <= lo):
        raise ValueError(f"region must be (lo, hi) with lo < hi, each of width m = {m} (from z_true), "
                         f"got {region!r}")
    batch, K = z_true.shape[:-2], z_true.shape[-2]
    V = float(np.prod(hi - lo))
    n_fa = rng.poisson(lam * V, size=batch)
    n_max = int(n_fa.max()) if n_fa.size else 0
    detected = rng.random(batch + (K,)) < P_D_
    M = K + n_max
    fa = lo + (hi - lo) * rng.random(batch + (n_max, m))
    if center is not None:
        fa = fa + as_vector(center, "center", m)[..., None, :]
    Z = np.concatenate([z_true, fa], axis=-2)
    mask = np.concatenate([detected, np.arange(n_max) < n_fa[..., None]], axis=-1)
    origin = np.concatenate([np.broadcast_to(np.arange(K), batch + (K,)), np.full(batch + (n_max,), -1)], axis=-1)
    amp = np.concatenate([rng.exponential(1.0 + snr, batch + (K,)), rng.exponential(1.0, batch + (n_max,))], axis=-1)
    # random order of the real measurements, padding last
    key = np.where(mask, rng.random(batch + (M,)), 2.0)
    order = np.argsort(key, axis=-1)
    Z = np.take_along_axis(Z, order[..., None], axis=-2)
    mask = np.take_along_axis(mask, order, axis=-1)
    origin = np.where(mask, np.take_along_axis(origin, order, axis=-1), -1)
    amp = np.where(mask, np.take_along_axis(amp, order, axis=-1), 0.0)
    Z = np.where(mask[..., None], Z, 0.0)
    return Scans(Z, mask, origin, amp, detected)
