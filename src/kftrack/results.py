"""The result types of the whole-sequence filters and smoothers (the bottom layer: no imports
from the rest of :mod:`kftrack`, so the drivers of :mod:`kftrack.engines` and the public
filters of :mod:`kftrack.kalman`, :mod:`kftrack.ekf`, :mod:`kftrack.ukf` can all build them).
:mod:`kftrack.kalman` re-exports them; the measurement :class:`kftrack.kernels.Update` lives
with the kernels that return it."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["FilterResult", "SmootherResult"]


class FilterResult(NamedTuple):
    """A filtered sequence, time first.

    ``x_prior[k]``, ``P_prior[k]`` are the predictions for step ``k`` before its measurement
    (``x_prior[0] = x0``); ``x[k]``, ``P[k]`` the estimates after it. ``nis`` and ``loglik`` are
    NaN at steps without a measurement. ``x_prior`` and ``P_prior`` are None when the filter ran
    with ``priors=False``.
    """

    x_prior: np.ndarray | None
    P_prior: np.ndarray | None
    x: np.ndarray
    P: np.ndarray
    nis: np.ndarray
    loglik: np.ndarray


class SmootherResult(NamedTuple):
    """Rauch–Tung–Striebel smoothed sequence: means ``x`` ``(T, ..., n)``, covariances ``P``
    ``(T, ..., n, n)`` and smoother gains ``G`` ``(T-1, ..., n, n)``."""

    x: np.ndarray
    P: np.ndarray
    G: np.ndarray
