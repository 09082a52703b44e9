r"""Steady-state Kalman filters and the frequency view.

* Steady-state gains from the algebraic Riccati equations, continuous
  (:func:`continuous_gain`, ``scipy.linalg.solve_continuous_are``) and discrete
  (:func:`discrete_gain`, ``scipy.linalg.solve_discrete_are``), and the time-varying gain
  sequence that converges to the discrete one (:func:`gain_sequence`).
* The sampled equivalent of a continuous filter at a stated rate (:func:`sampled_gain`),
  which tends to the continuous gain as the sample time shrinks.
* The α–β and α–β–γ filters and Kalata's tracking index (:func:`tracking_index`,
  :func:`alpha_beta_gains`, :func:`alpha_beta_gamma_gains`).
* A steady-state filter as a linear system from each sensor (and known input) to the
  estimate (:func:`estimator_system`, :func:`estimator_tf`), and the complementary-filter
  identity :math:`T_\text{slow}(s) + s^k T_\text{fast}(s) = 1` (:func:`complementary_residual`).
* Observability: the matrix and its rank for a time-invariant pair
  (:func:`observability_matrix`, :func:`observability_rank`) and the Gramian of a
  time-varying one (:func:`observability_gramian`).

Conventions: continuous model :math:`\dot x = A x + B u + G w`, :math:`y = C x + D u + v`
with :math:`E[w w^\top] = Q\,\delta(\tau)` (``Q`` a **spectral density**) and
:math:`E[v v^\top] = R\,\delta(\tau)`; discrete model :math:`x_{k+1} = F x_k + w_k`,
:math:`z_k = H x_k + v_k` with per-step **variances** ``Q``, ``R``. Numerics only: no
plotting, printing or I/O.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np
import scipy.integrate
import scipy.linalg
import scipy.signal

from ._validate import as_float_array, as_matrix, check_covariance, check_finite
from .discretize import van_loan

__all__ = [
    "SteadyState", "DiscreteSteadyState", "continuous_gain", "discrete_gain", "gain_sequence",
    "sampled_gain", "sampled_model", "run_steady_filter", "tracking_index", "alpha_beta_gains", "alpha_beta_gamma_gains",
    "estimator_system", "estimator_tf", "complementary_residual", "observability_matrix",
    "observability_rank", "observability_gramian", "alpha_beta_lag", "is_detectable",
]


class SteadyState(NamedTuple):
    """Continuous steady-state filter: gain ``L`` ``(n, m)`` and error covariance ``P`` ``(n, n)``."""

    L: np.ndarray
    P: np.ndarray


class DiscreteSteadyState(NamedTuple):
    """Discrete steady-state filter.

    Attributes
    ----------
    K : (n, m) gain of the measurement update.
    P_prior : (n, n) predicted covariance (the DARE solution).
    P : (n, n) updated covariance ``(I - K H) P_prior``.
    """

    K: np.ndarray
    P_prior: np.ndarray
    P: np.ndarray


def _square(value, name: str) -> np.ndarray:
    A = as_matrix(value, name)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"{name} must have shape (n, n), got shape {A.shape}")
    return A


def _system(A, C, Q, R, G, names=("A", "C")) -> tuple[np.ndarray, ...]:
    A = _square(A, names[0])
    n = A.shape[0]
    C = as_matrix(C, names[1], cols=n)
    if C.ndim != 2:
        raise ValueError(f"{names[1]} must have shape (m, {n}), got shape {C.shape}")
    G = np.eye(n) if G is None else as_matrix(G, "G", rows=n)
    Q = check_covariance(Q, "Q", G.shape[1])
    R = check_covariance(R, "R", C.shape[0], positive_definite=True)
    return A, C, Q, R, G


def _solve_are(solver, a, b, q, r, pair: str, noise: str) -> np.ndarray:
    """Run a SciPy Riccati solver; its failure becomes a ``ValueError`` that says what to check."""
    try:
        return solver(a, b, q, r)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise ValueError(f"the algebraic Riccati equation has no stabilizing solution: ({pair}) must be "
                         f"detectable and the noise {noise} must excite every unstable mode ({exc})") from exc


def continuous_gain(A, C, Q, R, G=None) -> SteadyState:
    r"""Steady-state gain of the continuous (Kalman–Bucy) filter.

    Solves the filter algebraic Riccati equation
    :math:`A P + P A^\top - P C^\top R^{-1} C P + G Q G^\top = 0` with
    ``scipy.linalg.solve_continuous_are`` (the dual of the control ARE) and returns
    :math:`L = P C^\top R^{-1}`; the estimator is :math:`\dot{\hat x} = A\hat x + Bu + L(y - C\hat x - Du)`.
    This is what MATLAB's ``kalman()`` returns for a continuous plant with ``H = 0``.

    Parameters
    ----------
    A : (n, n). C : (m, n). Q : (p, p) spectral density of ``w``. R : (m, m) spectral
    density of ``v``, positive definite. G : (n, p) noise gain, identity by default.

    Returns
    -------
    SteadyState(L (n, m), P (n, n)).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.steady import continuous_gain
    >>> ss = continuous_gain(A=[[0.0, 1.0], [0.0, 0.0]], C=[[1.0, 0.0]], Q=[[1.0]], R=[[1.0]], G=[[0.0], [1.0]])
    >>> print(np.round(ss.L, 6))                      # [sqrt(2), 1] for q = r = 1
    [[1.414214]
     [1.      ]]
    """
    A, C, Q, R, G = _system(A, C, Q, R, G)
    P = _solve_are(scipy.linalg.solve_continuous_are, A.T, C.T, G @ Q @ G.T, R, "A, C", "G Q G^T")
    P = 0.5 * (P + P.T)
    return SteadyState(np.linalg.solve(R, C @ P).T, P)


def discrete_gain(F, H, Q, R) -> DiscreteSteadyState:
    r"""Steady-state gain of the discrete Kalman filter.

    Solves :math:`P = F P F^\top - F P H^\top (H P H^\top + R)^{-1} H P F^\top + Q` (the
    predicted covariance) with ``scipy.linalg.solve_discrete_are`` and returns
    :math:`K = P H^\top (H P H^\top + R)^{-1}`, the update gain of :func:`kftrack.kalman.update`.

    Parameters
    ----------
    F : (n, n) transition. H : (m, n). Q : (n, n) process-noise variance per step.
    R : (m, m) measurement variance, positive definite.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.steady import discrete_gain
    >>> F = np.array([[1.0, 1.0], [0.0, 1.0]]); H = [[1.0, 0.0]]
    >>> Q = np.array([[0.25, 0.5], [0.5, 1.0]])       # DWNA, sigma_w = 1 m/s², T = 1 s
    >>> print(np.round(discrete_gain(F, H, Q, [[1.0]]).K, 6))   # alpha = 0.75, beta = 0.5 at lambda = 1
    [[0.75]
     [0.5 ]]
    """
    F, H, Q, R, _ = _system(F, H, Q, R, None, names=("F", "H"))
    P = _solve_are(scipy.linalg.solve_discrete_are, F.T, H.T, Q, R, "F, H", "Q")
    P = 0.5 * (P + P.T)
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    Pu = (np.eye(F.shape[0]) - K @ H) @ P
    return DiscreteSteadyState(K, P, 0.5 * (Pu + Pu.T))


def gain_sequence(F, H, Q, R, P0, steps: int) -> tuple[np.ndarray, np.ndarray]:
    r"""Iterate the discrete Riccati recursion from ``P0`` (the prior of step 0).

    Returns ``K`` ``(steps, n, m)`` and the priors ``P_prior`` ``(steps + 1, n, n)``
    (``P_prior[0] = P0``). For a detectable, stabilizable model ``K[k]`` converges to
    :func:`discrete_gain`'s ``K``.
    """
    F, H, Q, R, _ = _system(F, H, Q, R, None, names=("F", "H"))
    P = check_covariance(P0, "P0", F.shape[0])
    if not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    n = F.shape[0]
    Ks = np.empty((steps, n, H.shape[0]))
    Ps = np.empty((steps + 1, n, n))
    Ps[0] = P
    for k in range(steps):
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        IKH = np.eye(n) - K @ H
        Pu = IKH @ P @ IKH.T + K @ R @ K.T
        P = F @ Pu @ F.T + Q
        P = 0.5 * (P + P.T)
        Ks[k], Ps[k + 1] = K, P
    return Ks, Ps


def sampled_gain(A, C, Q, R, dt: float, G=None) -> DiscreteSteadyState:
    r"""Steady-state gain of the filter that samples a continuous model every ``dt`` seconds.

    The transition is :math:`F = e^{A\,dt}`, the process noise the exact integral of the
    spectral density ``Q`` over the interval (Van Loan), and the measurement variance
    :math:`R/dt` (a sensor of noise spectral density ``R`` averaged over ``dt``). As
    ``dt -> 0``, ``K / dt`` tends to the continuous ``L`` and ``P_prior`` to the continuous
    ``P`` (:func:`continuous_gain`), with errors of order ``dt``.

    Parameters
    ----------
    A, C, Q, R, G : as in :func:`continuous_gain`. dt : sample time (s), > 0.
    """
    A, C, Q, R, G = _system(A, C, Q, R, G)
    F, _, Qd = sampled_model(A, None, Q, dt, G)
    return discrete_gain(F, C, Qd, R / dt)


def sampled_model(A, B, Q, dt: float, G=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""Sample :math:`\dot x = A x + B u + G w` every ``dt`` s with the input held (zero-order hold).

    Returns ``F = expm(A dt)`` ``(n, n)``, ``Bd`` ``(n, p)`` (zeros ``(n, 0)`` when ``B`` is
    None) and ``Qd = \int_0^{dt} e^{A\tau} G Q G^\top e^{A^\top\tau} d\tau`` ``(n, n)`` (Van Loan).
    """
    A = _square(A, "A")
    n = A.shape[0]
    dt = float(as_float_array(dt, "dt"))
    if not dt > 0:
        raise ValueError(f"dt must be a positive sample time (s), got {dt}")
    G = np.eye(n) if G is None else as_matrix(G, "G", rows=n)
    Q = check_covariance(Q, "Q", G.shape[1])
    B = np.zeros((n, 0)) if B is None else as_matrix(B, "B", rows=n)
    p = B.shape[1]
    M = np.zeros((n + p, n + p))
    M[:n, :n], M[:n, n:] = A, B
    E = scipy.linalg.expm(M * dt)
    F, Qd = van_loan(A, G, Q, dt)
    return F, E[:n, n:], Qd


def run_steady_filter(F, B, H, D, K, zs, us=None, x0=None) -> np.ndarray:
    r"""Run a discrete steady-state (fixed-gain) filter over a sequence.

    At each step ``k``: :math:`x^-_k = F x_{k-1} + B u_{k-1}`,
    :math:`x_k = x^-_k + K(z_k - H x^-_k - D u_k)`, with :math:`x^-_0 = x_0` (zeros by
    default). A NaN measurement row skips the update.

    Parameters
    ----------
    F : (n, n). B : (n, p) or None. H : (m, n). D : (m, p) or None. K : (n, m).
    zs : (T, m) measurements. us : (T, p) known inputs (needed when ``p > 0``). x0 : (n,).

    Returns
    -------
    xs : (T, n) updated estimates.
    """
    F = _square(F, "F")
    n = F.shape[0]
    H = as_matrix(H, "H", cols=n)
    m = H.shape[0]
    K = as_matrix(K, "K", n, m)
    B = np.zeros((n, 0)) if B is None else as_matrix(B, "B", rows=n)
    p = B.shape[1]
    D = np.zeros((m, p)) if D is None else as_matrix(D, "D", m, p)
    zs = as_float_array(zs, "zs")
    if zs.ndim != 2 or zs.shape[1] != m:
        raise ValueError(f"zs must have shape (T, {m}), got shape {zs.shape}")
    T = zs.shape[0]
    if p:
        if us is None:
            raise ValueError(f"us must be given, shape ({T}, {p}), since B has {p} columns")
        us = as_matrix(us, "us", T, p)
    else:
        us = np.zeros((T, 0))
    x = np.zeros(n) if x0 is None else check_finite(as_float_array(x0, "x0"), "x0")
    if x.size != n:
        raise ValueError(f"x0 must have shape ({n},), the state of F, got shape {x.shape}")
    x = x.reshape(n)
    xs = np.empty((T, n))
    for k in range(T):
        if k:
            x = F @ x + B @ us[k - 1]
        z = zs[k]
        if not np.isnan(z).any():
            x = x + K @ (z - H @ x - D @ us[k])
        xs[k] = x
    return xs


# --------------------------------------------------------------------------------------------
# alpha-beta(-gamma) filters
# --------------------------------------------------------------------------------------------
def tracking_index(sigma_w, sigma_v, dt):
    r"""Kalata's tracking index :math:`\lambda = \sigma_w T^2 / \sigma_v`.

    ``sigma_w`` is the standard deviation of the discrete white acceleration (DWNA model,
    m/s²) or of the acceleration increment (DWPA model), ``sigma_v`` that of the position
    measurement (m), ``dt`` the sample time (s). Broadcasts.

    Examples
    --------
    >>> from kftrack.steady import tracking_index
    >>> print(tracking_index(sigma_w=2.0, sigma_v=10.0, dt=1.0))   # sigma_w T² / sigma_v
    0.2
    """
    sw = as_float_array(sigma_w, "sigma_w")
    sv = as_float_array(sigma_v, "sigma_v")
    T = as_float_array(dt, "dt")
    if np.any(sw < 0):
        raise ValueError("sigma_w must be >= 0")
    if np.any(sv <= 0):
        raise ValueError("sigma_v must be > 0")
    if np.any(T <= 0):
        raise ValueError("dt must be > 0")
    return sw * T**2 / sv


def _lam(lam) -> np.ndarray:
    lam = as_float_array(lam, "lam")
    if np.any(~np.isfinite(lam)) or np.any(lam < 0):
        raise ValueError(f"lam (the tracking index) must be finite and >= 0, got {lam}")
    return lam


def alpha_beta_gains(lam) -> tuple[np.ndarray, np.ndarray]:
    r"""Steady-state α and β of the position-measured DWNA (constant-velocity) model.

    Closed form (Kalata 1984; Bar-Shalom, Li & Kirubarajan 2001, eq. 6.5.2-9/10):

    .. math::

        \alpha = -\tfrac18\left(\lambda^2 + 8\lambda - (\lambda + 4)\sqrt{\lambda^2 + 8\lambda}\right),
        \qquad
        \beta = \tfrac14\left(\lambda^2 + 4\lambda - \lambda\sqrt{\lambda^2 + 8\lambda}\right).

    The Kalman gain is :math:`K = [\alpha, \beta / T]^\top`. ``lam`` broadcasts.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.steady import alpha_beta_gains
    >>> alpha, beta = alpha_beta_gains(1.0)           # the same gains as discrete_gain's K for lambda = 1
    >>> print(np.round([alpha, beta], 6))
    [0.75 0.5 ]
    """
    lam = _lam(lam)
    r = np.sqrt(lam**2 + 8 * lam)
    alpha = -(lam**2 + 8 * lam - (lam + 4) * r) / 8
    beta = (lam**2 + 4 * lam - lam * r) / 4
    return alpha, beta


def alpha_beta_gamma_gains(lam) -> tuple[float, float, float]:
    r"""Steady-state α, β, γ of the position-measured DWPA (constant-acceleration) model.

    The model has :math:`\Gamma = [T^2/2, T, 1]^\top`, acceleration-increment standard
    deviation :math:`\sigma_w`, and :math:`\lambda = \sigma_w T^2/\sigma_v`. There is no
    compact closed form; the gains come from the DARE of the model normalised to
    :math:`T = 1`, :math:`\sigma_v = 1`, as :math:`K = [\alpha, \beta/T, \gamma/(2T^2)]^\top`
    (Bar-Shalom, Li & Kirubarajan 2001, §6.5.3). They satisfy
    :math:`\beta = 2(2-\alpha) - 4\sqrt{1-\alpha}`, :math:`\gamma = \beta^2/\alpha` and
    :math:`\lambda^2 = \gamma^2 / (4(1-\alpha))` (checked in the tests). ``lam`` is a scalar.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.steady import alpha_beta_gamma_gains
    >>> a, b, g = alpha_beta_gamma_gains(0.5)
    >>> print(np.round([a, b, g], 6))
    [0.795374 0.599827 0.452356]
    >>> bool(np.isclose(g, b * b / a, rtol=1e-9))      # gamma = beta² / alpha
    True
    """
    lam = float(_lam(lam))
    if lam == 0:
        return 0.0, 0.0, 0.0
    F = np.array([[1.0, 1.0, 0.5], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    g = np.array([[0.5], [1.0], [1.0]])
    K = discrete_gain(F, [[1.0, 0.0, 0.0]], lam**2 * (g @ g.T), [[1.0]]).K[:, 0]
    return float(K[0]), float(K[1]), float(2 * K[2])


# --------------------------------------------------------------------------------------------
# the filter as a linear system, transfer functions
# --------------------------------------------------------------------------------------------
def estimator_system(A, B, C, D, L, outputs=None) -> tuple[np.ndarray, ...]:
    r"""State-space form of the steady-state estimator, inputs ``[y; u]``.

    .. math::

        \dot{\hat x} = (A - LC)\hat x + [\,L,\; B - LD\,]\begin{bmatrix} y \\ u\end{bmatrix},
        \qquad \hat z = C_o \hat x

    (or, for a discrete steady-state filter with ``A = F``, the same map in ``z``).

    Parameters
    ----------
    A : (n, n). B : (n, p) known-input matrix (``p`` may be 0). C : (m, n). D : (m, p).
    L : (n, m) steady-state gain. outputs : (r, n) output matrix ``C_o``; by default the
        state itself (``I``).

    Returns
    -------
    Ae (n, n), Be (n, m + p), Ce (r, n), De (r, m + p) zeros.
    """
    A = _square(A, "A")
    n = A.shape[0]
    C = as_matrix(C, "C", cols=n)
    m = C.shape[0]
    B = np.zeros((n, 0)) if B is None else as_matrix(B, "B", rows=n)
    p = B.shape[1]
    D = np.zeros((m, p)) if D is None else as_matrix(D, "D", m, p)
    L = as_matrix(L, "L", n, m)
    Co = np.eye(n) if outputs is None else as_matrix(outputs, "outputs", cols=n)
    Ae = A - L @ C
    Be = np.hstack([L, B - L @ D])
    return Ae, Be, Co, np.zeros((Co.shape[0], m + p))


def estimator_tf(A, B, C, D, L, outputs=None) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    r"""Transfer functions from each sensor and known input to each estimated output.

    ``result[i][j] = (num, den)`` is the transfer function from input ``j`` of
    ``[y_1..y_m, u_1..u_p]`` to output ``i`` (numpy polynomial coefficients, highest power
    first; coefficients below 1e-12 of the largest, round-off of ``ss2tf``, set to zero and
    leading zeros trimmed), :math:`C_o (sI - A + LC)^{-1} [L, B - LD]`.
    Arguments as in :func:`estimator_system`.
    """
    Ae, Be, Co, De = estimator_system(A, B, C, D, L, outputs)
    out = [[None] * Be.shape[1] for _ in range(Co.shape[0])]
    for j in range(Be.shape[1]):
        num, den = scipy.signal.ss2tf(Ae, Be[:, [j]], Co, De[:, [j]])
        for i in range(Co.shape[0]):
            ni = np.where(np.abs(num[i]) < 1e-12 * np.abs(num[i]).max(initial=0.0), 0.0, num[i])
            out[i][j] = (np.trim_zeros(ni, "f") if np.any(ni) else np.zeros(1), den)
    return out


def complementary_residual(slow, fast, k: int) -> np.ndarray:
    r"""Numerator of :math:`T_\text{slow}(s) + s^k T_\text{fast}(s) - 1` over a common denominator.

    A filter fusing a slow sensor of the quantity with a fast sensor of its ``k``-th
    derivative is *complementary* when the residual is the zero polynomial: the estimate
    then passes the true signal undistorted whatever the filter's gains. ``slow`` and
    ``fast`` are ``(num, den)`` pairs with the same denominator (as :func:`estimator_tf`
    returns); the result is a coefficient array, highest power first.
    """
    (ns, ds), (nf, df) = slow, fast
    ds, df = np.atleast_1d(np.asarray(ds, float)), np.atleast_1d(np.asarray(df, float))
    if ds.shape != df.shape or not np.allclose(ds, df, rtol=1e-12, atol=0):
        raise ValueError("slow and fast must share their denominator polynomial")
    if not isinstance(k, (int, np.integer)) or k < 0:
        raise ValueError(f"k must be a non-negative integer, got {k!r}")
    sk = np.zeros(k + 1)
    sk[0] = 1.0
    return np.polysub(np.polyadd(ns, np.polymul(sk, nf)), ds)


# --------------------------------------------------------------------------------------------
# observability
# --------------------------------------------------------------------------------------------
def observability_matrix(A, C) -> np.ndarray:
    r"""Kalman observability matrix :math:`[C; CA; \dots; CA^{n-1}]`, shape ``(n m, n)``."""
    A = _square(A, "A")
    C = as_matrix(C, "C", cols=A.shape[0])
    blocks = [C]
    for _ in range(A.shape[0] - 1):
        blocks.append(blocks[-1] @ A)
    return np.vstack(blocks)


def observability_rank(A, C, tol: float | None = None) -> int:
    """Rank of :func:`observability_matrix` (``numpy.linalg.matrix_rank`` with ``tol``)."""
    return int(np.linalg.matrix_rank(observability_matrix(A, C), tol=tol))


def observability_gramian(A: Callable[[float], np.ndarray], C, t0: float, t1: float,
                          rtol: float = 1e-9) -> np.ndarray:
    r"""Observability Gramian of a time-varying system on ``[t0, t1]``.

    .. math::

        W(t_0, t_1) = \int_{t_0}^{t_1} \Phi(\tau, t_0)^\top C(\tau)^\top C(\tau)\,\Phi(\tau, t_0)\,d\tau,
        \qquad \partial_\tau \Phi(\tau, t_0) = A(\tau)\Phi(\tau, t_0),

    integrated jointly with ``scipy.integrate.solve_ivp``. The system is observable on the
    interval iff ``W`` is nonsingular (Rugh, *Linear System Theory*, Thm. 9.8).

    Parameters
    ----------
    A : callable ``t -> (n, n)``. C : an ``(m, n)`` matrix or a callable ``t -> (m, n)``.
    t0 < t1 : interval (s). rtol : relative tolerance of the integrator.

    Returns
    -------
    W : (n, n) symmetric positive semi-definite.
    """
    if not callable(A):
        raise TypeError(f"A must be a callable t -> (n, n) array, got {type(A).__name__}")
    A0 = _square(A(t0), "A(t0)")
    n = A0.shape[0]
    Cf = C if callable(C) else (lambda _t, _C=as_matrix(C, "C", cols=n): _C)
    as_matrix(Cf(t0), "C(t0)", cols=n)
    if not t1 > t0:
        raise ValueError(f"t1 must be greater than t0, got t0={t0}, t1={t1}")

    def rhs(t, y):
        Phi = y[: n * n].reshape(n, n)
        CP = Cf(t) @ Phi
        return np.concatenate([(A(t) @ Phi).ravel(), (CP.T @ CP).ravel()])

    y0 = np.concatenate([np.eye(n).ravel(), np.zeros(n * n)])
    sol = scipy.integrate.solve_ivp(rhs, (t0, t1), y0, method="DOP853", rtol=rtol, atol=1e-12)
    W = sol.y[n * n:, -1].reshape(n, n)
    return 0.5 * (W + W.T)


def alpha_beta_lag(alpha, beta, accel, dt) -> tuple[np.ndarray, np.ndarray]:
    r"""Steady-state error of an α–β filter tracking a constant acceleration.

    A target with constant acceleration :math:`a` is followed by the α–β filter
    :math:`K = [\alpha, \beta/T]^\top` (constant-velocity model, sample time :math:`T`). The
    error of the updated estimate, :math:`e = \hat x - x`, settles to the constant

    .. math::

        e_x = -\frac{1 - \alpha}{\beta}\,a T^2, \qquad
        e_v = -\frac{\alpha - \beta/2}{\beta}\,a T

    (Bar-Shalom, Li & Kirubarajan 2001, §6.5.2; Kalata 1984): the estimate lags behind an
    accelerating target. Derivation: with :math:`x^-_k = F\hat x_{k-1}`, the truth obeys
    :math:`x_k = F x_{k-1} + [T^2/2, T]^\top a`, so the steady error solves
    :math:`e = (I - KH)(F e - [T^2/2, T]^\top a)`.

    Parameters
    ----------
    alpha, beta : gains, ``0 < alpha < 1`` (or ``alpha = 1``), ``beta > 0``. Broadcast.
    accel : acceleration (m/s²). dt : sample time :math:`T` (s), > 0.

    Returns
    -------
    (e_x, e_v) : steady position error (m) and velocity error (m/s) of the updated estimate.
    """
    a_, b_ = as_float_array(alpha, "alpha"), as_float_array(beta, "beta")
    acc, T = as_float_array(accel, "accel"), as_float_array(dt, "dt")
    if np.any(~((a_ > 0) & (a_ <= 1))):
        raise ValueError(f"alpha must lie in (0, 1], got {alpha!r}")
    if np.any(~(b_ > 0)):
        raise ValueError(f"beta must be > 0 (a zero beta has no steady state under acceleration), got {beta!r}")
    if np.any(~(T > 0)):
        raise ValueError(f"dt must be > 0, got {dt!r}")
    return -(1 - a_) / b_ * acc * T**2, -(a_ - b_ / 2) / b_ * acc * T


def is_detectable(A, C, discrete: bool = False, tol: float = 1e-9) -> bool:
    r"""Whether the pair ``(A, C)`` is detectable (Popov–Belevitch–Hautus test).

    Every mode that is not asymptotically stable must be observable:

    .. math:: \operatorname{rank}\begin{bmatrix}\lambda I - A\\ C\end{bmatrix} = n
              \quad\text{for every eigenvalue } \lambda \text{ of } A \text{ with }
              \operatorname{Re}\lambda \ge 0 \ (\text{continuous}) \text{ or } |\lambda| \ge 1
              \ (\text{discrete, } A = F).

    Detectability (with stabilizability of the noise) is what the algebraic Riccati equation
    needs; observability (full rank of :func:`observability_matrix`) is stronger: an
    unobservable but stable mode is allowed. ``tol`` is the margin on the stability test and
    the relative rank tolerance (singular values below ``tol * max(1, |lambda|, ||A||)``).
    """
    A = _square(A, "A")
    n = A.shape[0]
    C = as_matrix(C, "C", cols=n)
    scale = max(1.0, float(np.linalg.norm(A, 2)))
    for lam in np.linalg.eigvals(A):
        unstable = abs(lam) >= 1 - tol if discrete else lam.real >= -tol
        if not unstable:
            continue
        M = np.vstack([lam * np.eye(n) - A, C.astype(complex)])
        sv = np.linalg.svd(M, compute_uv=False)
        if sv[-1] <= tol * max(scale, abs(lam)):
            return False
    return True
