"""Continuous to discrete: Van Loan's method for any linear time-invariant model.

Numerics layer: :mod:`kftrack.models` (exact closed forms per model) and
:mod:`kftrack.steady` (sampled filters) both build on it.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg

from ._validate import as_float_array, as_matrix, check_finite

__all__ = ["van_loan"]


def van_loan(A, G, Qc, dt: float) -> tuple[np.ndarray, np.ndarray]:
    r"""Van Loan's (1978) method: ``F = expm(A dt)`` and the continuous-white-noise
    :math:`Q = \int_0^{dt} e^{A\tau} G Q_c G^\top e^{A^\top\tau} d\tau` from one matrix exponential,

    .. math::

        \exp\left(\begin{bmatrix} -A & G Q_c G^\top \\ 0 & A^\top \end{bmatrix} dt\right)
        = \begin{bmatrix} \cdot & F^{-1} Q \\ 0 & F^\top \end{bmatrix} .

    Parameters
    ----------
    A : (n, n) continuous-time system matrix. G : (n, m) noise gain.
    Qc : (m, m) spectral densities of the white noise. dt : interval (s), ``>= 0``.

    Returns
    -------
    F, Q : (n, n) each.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.discretize import van_loan
    >>> A = np.array([[0.0, 1.0], [0.0, 0.0]])        # x' = v, v' = w: constant velocity
    >>> F, Q = van_loan(A, G=[[0.0], [1.0]], Qc=[[1.0]], dt=1.0)
    >>> print(np.round(F, 6) + 0.0)
    [[1. 1.]
     [0. 1.]]
    >>> print(np.round(Q, 6) + 0.0)                   # q [[T³/3, T²/2], [T²/2, T]]
    [[0.333333 0.5     ]
     [0.5      1.      ]]
    """
    A = as_matrix(A, "A")
    n = A.shape[-1]
    if A.shape != (n, n):
        raise ValueError(f"A must have shape (n, n), got shape {A.shape}")
    G = as_matrix(G, "G", n)
    Qc = as_matrix(Qc, "Qc", G.shape[1], G.shape[1])
    d = check_finite(as_float_array(dt, "dt"), "dt")
    if d.ndim != 0:
        raise ValueError(f"dt must be a scalar, got shape {d.shape}")
    if d < 0:
        raise ValueError(f"dt must be >= 0 for the process noise, got {float(d):.6g}")
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A
    M[:n, n:] = G @ Qc @ G.T
    M[n:, n:] = A.T
    E = scipy.linalg.expm(M * float(d))
    F = E[n:, n:].T
    Q = F @ E[:n, n:]
    return F, 0.5 * (Q + Q.T)
