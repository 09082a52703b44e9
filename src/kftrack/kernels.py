r"""The unchecked predict/update/mixing kernels: one home for the filter equations.

**No validation happens here.** The public functions (:func:`kftrack.kalman.predict`,
:func:`kftrack.kalman.update`, :func:`kftrack.ekf.ekf_update`, :func:`kftrack.ukf.ukf_update`,
:class:`kftrack.imm.IMM`, ...) validate their arguments once at the boundary, then call these
kernels, and their time loops (:mod:`kftrack.engines`) call the kernels at every step. Call a
kernel directly only with arguments you have already checked (shapes as in
:mod:`kftrack.kalman`: ``x`` ``(..., n)``, ``P`` ``(..., n, n)``, batch axes broadcasting): a
wrong shape gives an array-library error or a wrong answer, not a message.

**One set of equations, two engines.** Every kernel takes its array namespace from its
arguments, ``xp = array_api_compat.array_namespace(...)``, and uses only operations of the
array API standard (``@``, ``matrix_transpose``, ``linalg.solve``, ``linalg.slogdet``,
``linalg.cholesky``, ``where``, ``concat``, elementwise functions): the same code runs on NumPy
arrays (the NumPy engine) and on JAX arrays and tracers under ``jax.jit`` (the JAX engine).
Branches depend only on shapes and static options, never on values, so every kernel traces.
All arguments of one call must come from the same library.

Equations (Bar-Shalom, Li & Kirubarajan 2001, §5.2, §10.3; Wan & van der Merwe 2000;
Blom & Bar-Shalom 1988; Särkkä 2013, Thm 8.2):

.. math::

    x^- = F x,\quad P^- = F P F^\top + Q;\qquad
    S = H P H^\top + R,\quad K = P H^\top S^{-1},\quad x^+ = x + K(z - Hx),

    P^+ = (I - KH) P (I - KH)^\top + K R K^\top \;\text{(Joseph)}\quad\text{or}\quad (I - KH) P.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np
from array_api_compat import array_namespace as _array_namespace
from array_api_compat import is_numpy_namespace

# NumPy >= 2 implements the array API itself: use it directly (array_api_compat's wrappers of
# NumPy add a Python call to every operation); older NumPy goes through the wrappers.
_NUMPY = np if np.lib.NumpyVersion(np.__version__) >= "2.0.0" else _array_namespace(np.zeros(1))


def array_namespace(*arrays):
    """The array namespace of the arguments (``array_api_compat.array_namespace``), with a fast
    path for the common case of NumPy arrays only (the NumPy engine calls it at every step):
    then the ``numpy`` module itself (NumPy >= 2)."""
    for a in arrays:
        if type(a) is not np.ndarray:
            return _array_namespace(*arrays)
    return _NUMPY


def _is_np(*arrays) -> bool:
    """True if every argument is a NumPy array (the NumPy engine), checked by exact type: fast."""
    for a in arrays:
        if type(a) is not np.ndarray:
            return False
    return True

__all__ = [
    "Update", "SigmaPoints", "mm", "mv", "matrix_transpose", "sym", "wrap_angle", "residual", "wrap_state",
    "kf_predict", "kf_update", "Gain", "kf_gain", "kf_correct", "kf_score", "innovation_score", "gain_update",
    "ekf_predict", "ekf_update",
    "sigma_points", "weighted_mean", "moments", "unscented", "ukf_predict", "ukf_update",
    "logsumexp", "moment_match", "mixing_log_weights", "rts_step", "solve_spd", "logdet_spd",
]

_LOG_2PI = math.log(2.0 * math.pi)


class Update(NamedTuple):
    """Result of a measurement update; every field broadcasts over the batch axes.

    Attributes
    ----------
    x : (..., n) posterior mean.
    P : (..., n, n) posterior covariance (Joseph form, symmetric; with ``form="standard"`` the
        short form :math:`(I - KH)P`, not symmetrized).
    y : (..., m) innovation ``z - H x``.
    S : (..., m, m) innovation covariance ``H P H^T + R``.
    K : (..., n, m) Kalman gain.
    nis : (...) normalized innovation squared ``y^T S^{-1} y``.
    loglik : (...) Gaussian log-likelihood ``log N(y; 0, S)``.
    """

    x: np.ndarray
    P: np.ndarray
    y: np.ndarray
    S: np.ndarray
    K: np.ndarray
    nis: np.ndarray
    loglik: np.ndarray


class SigmaPoints(NamedTuple):
    """Sigma points ``X`` ``(..., 2n+1, n)`` with mean weights ``Wm`` and covariance weights ``Wc`` ``(2n+1,)``."""

    X: np.ndarray
    Wm: np.ndarray
    Wc: np.ndarray


# --------------------------------------------------------------------------------------------
# small linear-algebra helpers
# --------------------------------------------------------------------------------------------
def mm(A, B):
    r"""Matrix product over batch axes, ``(..., r, c) @ (..., c, k) -> (..., r, k)``.

    On NumPy exactly ``A @ B``. On other namespaces (JAX, compiled), for ``r, k <= 8``, the sum
    of ``c`` outer products :math:`C = \sum_p A_{:,p} B_{p,:}` as broadcast elementwise
    products: a compiler fuses them into one loop over the batch, where a batched product of
    tiny matrices is many times slower (measured with XLA on CPU: 30 x for 4 x 4)."""
    if type(A) is np.ndarray and type(B) is np.ndarray:  # NumPy (the type test inline: a call less)
        return A @ B
    r, c, k = A.shape[-2], A.shape[-1], B.shape[-1]
    if is_numpy_namespace(array_namespace(A, B)) or max(r, k) > _UNROLL or c > 4 * _UNROLL:
        return A @ B
    C = A[..., :, 0, None] * B[..., None, 0, :]
    for p in range(1, c):
        C = C + A[..., :, p, None] * B[..., None, p, :]
    return C


def mv(A, v):
    """Matrix times vector over batch axes: ``(..., r, c) @ (..., c) -> (..., r)``.

    On NumPy always the broadcast product ``(A @ v[..., None])[..., 0]``, so a shared matrix and
    the same matrix repeated per batch member give the same bits (the book's "EKF on a linear
    model is the Kalman filter, bit for bit"). On other namespaces (JAX, compiled) a shared
    ``(r, c)`` matrix is applied to the whole batch as one product ``v @ A^T``."""
    if type(A) is np.ndarray and type(v) is np.ndarray:  # NumPy (the type test inline: a call less)
        return (A @ v[..., None])[..., 0]
    if A.ndim == 2 and not is_numpy_namespace(array_namespace(A, v)):
        return v @ matrix_transpose(A)
    return mm(A, v[..., None])[..., 0]


def matrix_transpose(A):
    """Swap the last two axes (``array_api.matrix_transpose``)."""
    if type(A) is np.ndarray:
        return A.swapaxes(-1, -2)
    return array_namespace(A).matrix_transpose(A)


def sym(A):
    """Symmetric part :math:`(A + A^\\top)/2`."""
    if type(A) is np.ndarray:  # NumPy: the transpose inline (a call less)
        return 0.5 * (A + A.swapaxes(-1, -2))
    return 0.5 * (A + matrix_transpose(A))


_UNROLL = 8  # largest matrix that a compiled engine factors with unrolled elementwise code


def _cholesky_entries(xp, A):
    """Lower Cholesky factor of ``A`` (..., m, m) as a nested list of ``(...)`` arrays, unrolled."""
    m = A.shape[-1]
    L = [[None] * m for _ in range(m)]
    for j in range(m):
        d = A[..., j, j]
        for p in range(j):
            d = d - L[j][p] * L[j][p]
        L[j][j] = xp.sqrt(d)
        for i in range(j + 1, m):
            e = A[..., i, j]
            for p in range(j):
                e = e - L[i][p] * L[j][p]
            L[i][j] = e / L[j][j]
    return L


@lru_cache(maxsize=1)
def _np_fast():
    """``(dpotrf, solve, solve1, slogdet)``: SciPy's LAPACK ``dpotrf`` and the gufuncs that
    ``numpy.linalg.solve``/``slogdet`` call, imported at the first use; ``None`` if NumPy has
    moved them (then the public ``numpy.linalg`` functions serve)."""
    try:
        from numpy.linalg import _umath_linalg as u
        from scipy.linalg.lapack import dpotrf

        return dpotrf, u.solve, u.solve1, u.slogdet
    except (ImportError, AttributeError):
        return None


_NP_SPD = "numpy: LAPACK dpotrf factored A"  # the factor "L" of an unbatched float64 NumPy A


def _spd_factor(xp, A):
    """The unrolled lower Cholesky factor of ``A`` (nested list, ``_cholesky_entries``) on a
    compiled namespace (JAX) for ``m <= 8``; on NumPy (see below) or for larger ``A`` no factor (LAPACK:
    on NumPy one LAPACK call per solve costs less than the unrolled entry-by-entry operations,
    measured for a single track with ``m = 2``).

    NumPy, unbatched float64 ``A`` ``(m, m)``: the marker ``_NP_SPD`` when ``A`` is exactly
    symmetric (bit for bit) and LAPACK ``dpotrf`` factors it (``info == 0`` and a finite diagonal:
    numerically positive definite, hence not singular); ``_spd_solve``/``_spd_logdet`` then call the gufuncs of
    ``numpy.linalg.solve``/``slogdet`` directly, without their Python layer (its error-state
    context, ~3 us, serves only a singular matrix): the same LAPACK calls on the same arrays, so
    the same bits. Otherwise (not symmetric, not positive definite, NaN) the result is ``None``:
    ``numpy.linalg`` as before, with its errors."""
    if type(A) is np.ndarray:
        if A.ndim == 2 and A.dtype == np.float64 and A.size and A.tobytes() == A.T.tobytes():
            fast = _np_fast()
            if fast is not None:
                c, info = fast[0](A, lower=1, clean=0)
                if info == 0 and all(map(math.isfinite, c.diagonal().tolist())):  # inf, NaN: not accepted
                    return _NP_SPD
        return None
    if is_numpy_namespace(xp) or A.shape[-1] > _UNROLL:
        return None
    return _cholesky_entries(xp, A)


def _spd_solve(xp, A, L, B):
    """``A^{-1} B`` with the factor ``L`` of ``_spd_factor`` (``linalg.solve`` if ``L`` is None)."""
    if L is _NP_SPD and type(B) is np.ndarray and B.dtype == np.float64:  # numpy.linalg.solve's gufunc
        fast = _np_fast()
        return (fast[2] if B.ndim == 1 else fast[1])(A, B, signature="dd->d")
    if L is None or L is _NP_SPD:
        return xp.linalg.solve(A, B)
    m = A.shape[-1]
    Y = []
    for i in range(m):  # L Y = B
        e = B[..., i, :]
        for p in range(i):
            e = e - L[i][p][..., None] * Y[p]
        Y.append(e / L[i][i][..., None])
    X = [None] * m
    for i in range(m - 1, -1, -1):  # L^T X = Y
        e = Y[i]
        for p in range(i + 1, m):
            e = e - L[p][i][..., None] * X[p]
        X[i] = e / L[i][i][..., None]
    return xp.stack(X, axis=-2)


def _spd_logdet(xp, A, L):
    """``log det A`` with the factor ``L`` of ``_spd_factor`` (``linalg.slogdet`` if ``L`` is None)."""
    if L is _NP_SPD:  # numpy.linalg.slogdet's gufunc (slogdet has no error-state context to skip)
        return _np_fast()[3](A, signature="d->dd")[1]
    if L is None:
        return xp.linalg.slogdet(A)[1]
    out = xp.log(L[0][0])
    for i in range(1, len(L)):
        out = out + xp.log(L[i][i])
    return 2.0 * out


def solve_spd(A, B):
    r"""``A^{-1} B`` for symmetric positive definite ``A`` (..., m, m) and ``B`` (..., m, k).

    NumPy: ``linalg.solve`` (LU with pivoting, LAPACK), as the chapters have always computed it.
    Other namespaces (JAX, compiled), for ``m <= 8``: the Cholesky factorization
    :math:`A = LL^\top` and two triangular solves written out entry by entry, which a compiler
    fuses over the batch (a batched LAPACK call per small matrix is slow there). Both are
    backward stable for SPD ``A``: they agree to :math:`O(m\,\kappa(A)\,\varepsilon)`."""
    xp = array_namespace(A, B)
    return _spd_solve(xp, A, _spd_factor(xp, A), B)


def logdet_spd(A):
    r"""``log det A`` of symmetric positive definite ``A`` (..., m, m): ``linalg.slogdet`` on NumPy,
    :math:`2\sum_i \log L_{ii}` of the unrolled Cholesky factor elsewhere (``m <= 8``)."""
    xp = array_namespace(A)
    return _spd_logdet(xp, A, _spd_factor(xp, A))


def wrap_angle(a):
    r"""Wrap angles (rad) to :math:`(-\pi, \pi]`: :math:`\pi - ((\pi - a) \bmod 2\pi)`.

    ``wrap_angle(pi) == pi`` and ``wrap_angle(-pi) == pi``; any shape. A Python number or list
    becomes a float64 NumPy array.
    """
    if not hasattr(a, "__array_namespace__"):
        a = np.asarray(a, dtype=float)
    xp = array_namespace(a)
    if not xp.isdtype(a.dtype, "real floating"):
        a = xp.astype(a, xp.float64)
    return xp.pi - xp.remainder(xp.pi - a, 2.0 * xp.pi)


def _angle_mask(xp, d: int, angles: tuple[int, ...]):
    """Boolean ``(d,)`` vector, True at the (static) component indices ``angles``."""
    return xp.asarray([i in angles for i in range(d)])


def residual(a, b, angles: tuple[int, ...]):
    """``a - b`` with the components ``angles`` (already validated indices) wrapped to (-pi, pi]."""
    d = a - b
    if not angles:
        return d
    xp = array_namespace(d)
    return xp.where(_angle_mask(xp, d.shape[-1], angles), wrap_angle(d), d)


def wrap_state(x, x_angles):
    """Wrap the state components ``x_angles`` to (-pi, pi] (``x`` itself when there are none)."""
    if not x_angles:
        return x
    xp = array_namespace(x)
    return xp.where(_angle_mask(xp, x.shape[-1], x_angles), wrap_angle(x), x)


# --------------------------------------------------------------------------------------------
# linear Kalman filter
# --------------------------------------------------------------------------------------------
def kf_predict(x, P, F, Q):
    r"""Time update :math:`x^- = F x`, :math:`P^- = \operatorname{sym}(F P F^\top + Q)`.

    With ``P`` None the mean alone: ``(F x, None)`` (the covariance recursion does not depend on
    the data; :class:`kftrack.kalman.KalmanStepper` skips it once it repeats to the last bit)."""
    x_next = mv(F, x)
    if P is None:
        return x_next, None
    return x_next, sym(mm(mm(F, P), matrix_transpose(F)) + Q)


def innovation_score(y, S):
    r"""NIS :math:`y^\top S^{-1} y` and Gaussian log-likelihood :math:`\log N(y; 0, S)` of an innovation."""
    xp = array_namespace(y, S)
    L = _spd_factor(xp, S)
    return _score(xp, y, S, L, _spd_logdet(xp, S, L))


def _score(xp, y, S, L, logdet):
    """:func:`innovation_score` with the factor ``L`` of ``S`` (``_spd_factor``) and ``log det S``
    already computed."""
    Sinv_y = _spd_solve(xp, S, L, y[..., None])[..., 0]
    nis = xp.sum(y * Sinv_y, axis=-1)
    return nis, -0.5 * (nis + logdet + y.shape[-1] * _LOG_2PI)


@lru_cache(maxsize=16)
def _np_eye(n: int, dtype):
    """A read-only NumPy identity ``(n, n)``, made once per size and dtype."""
    eye = np.eye(n, dtype=dtype)
    eye.flags.writeable = False
    return eye


class Gain(NamedTuple):
    """The covariance part of a measurement update (:func:`kf_gain`), which does not depend on the
    measurement; every field broadcasts over the batch axes.

    Attributes
    ----------
    S : (..., m, m) innovation covariance ``H P H^T + R``.
    K : (..., n, m) Kalman gain ``P H^T S^{-1}``.
    P : (..., n, n) posterior covariance, as in :class:`Update`.
    factor : the factorization of ``S`` that :func:`kf_score` reuses (its form depends on the
        engine: treat it as opaque).
    logdet : (...) ``log det S``.
    """

    S: np.ndarray
    K: np.ndarray
    P: np.ndarray
    factor: object
    logdet: np.ndarray


def kf_gain(P, H, R, form: str = "joseph") -> Gain:
    r"""The covariance part of the update, which does not depend on the measurement:
    :math:`S = \operatorname{sym}(H P H^\top + R)`, :math:`K = P H^\top S^{-1}` and
    :math:`P^+ = \operatorname{sym}((I - KH) P (I - KH)^\top + K R K^\top)` (``form="joseph"``) or
    the short form :math:`(I - KH)P` as computed (``form="standard"``, not symmetrized), with the
    factorization and :math:`\log\det S` that :func:`kf_score` uses."""
    xp = array_namespace(P, H, R)
    _T = matrix_transpose
    PHt = mm(P, _T(H))
    S = sym(mm(H, PHt) + R)
    L = _spd_factor(xp, S)  # one factorization of S for the gain, the NIS and the log-likelihood
    K = _T(_spd_solve(xp, S, L, _T(PHt)))  # S symmetric: K^T = S^{-1} H P
    n = P.shape[-1]
    eye = _np_eye(n, P.dtype) if xp is np else xp.eye(n, dtype=P.dtype)
    I_KH = eye - mm(K, H)
    if form == "joseph":
        P_post = sym(mm(mm(I_KH, P), _T(I_KH)) + mm(mm(K, R), _T(K)))
    else:  # "standard": the short form (I - KH) P, as computed (not symmetrized)
        P_post = mm(I_KH, P)
    return Gain(S, K, P_post, L, _spd_logdet(xp, S, L))


def kf_correct(x, z, H, K):
    r"""The mean part of the update: innovation :math:`y = z - H x`, :math:`x^+ = x + K y`.
    Returns ``(x_post, y)``."""
    y = z - mv(H, x)
    return x + mv(K, y), y


def kf_score(y, gain: Gain):
    r"""NIS :math:`y^\top S^{-1} y` and log-likelihood :math:`\log N(y; 0, S)` of an innovation ``y``,
    with the factorization and log-determinant of ``S`` kept in ``gain`` (:func:`kf_gain`)."""
    return _score(array_namespace(y, gain.S), y, gain.S, gain.factor, gain.logdet)


def kf_update(x, P, z, H, R, form: str = "joseph") -> Update:
    """Measurement update: :func:`kf_gain` (the covariances, Joseph form with ``form="joseph"``,
    symmetrized, or the short form :math:`(I - KH)P` as computed with ``form="standard"``), then
    :func:`kf_correct` (the mean) and :func:`kf_score` (NIS, log-likelihood).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.kernels import kf_update
    >>> u = kf_update(np.array([1.0, 1.0]), np.diag([2.0, 1.0]), np.array([1.5]), np.array([[1.0, 0.0]]), np.eye(1))
    >>> print(np.round(u.x, 6), np.round(u.S, 6))     # unchecked: kftrack.kalman.update validates, then calls this
    [1.333333 1.      ] [[3.]]
    """
    g = kf_gain(P, H, R, form)
    x_post, y = kf_correct(x, z, H, g.K)
    return Update(x_post, g.P, y, g.S, g.K, *kf_score(y, g))


def _rts_gain_t(xp, A, P, F):
    r"""``G^T`` of the RTS gain :math:`G = P F^\top A^{-1}`, ``A`` the prediction :math:`P^-_{k+1}`:
    :func:`solve_spd` (the same bits) for a positive definite ``A``. On NumPy, where ``A`` is only
    positive semi-definite (its Cholesky factorization fails), :math:`A^{+} F P` with the
    pseudo-inverse of the eigendecomposition, eigenvalues ``<= 1e3 n eps max|lambda|`` (round-off
    of a singular ``A``) counted as zero, after checking the range condition that makes it the
    smoother gain: :math:`F P` has no component along the null space of ``A`` beyond what those
    eigenvalues allow (:math:`|v^\top F P u| \le \sqrt{v^\top F P F^\top v}\,\sqrt{u^\top P u}`); an ``A``
    that is not :math:`F P F^\top + Q` raises ``numpy.linalg.LinAlgError``. The JAX engine solves
    as before (no value branch inside a trace: a singular ``A`` gives inf/NaN)."""
    B = mm(F, P)
    L = _spd_factor(xp, A)
    if type(A) is np.ndarray and type(B) is np.ndarray and L is not _NP_SPD:
        try:
            np.linalg.cholesky(A)  # positive definite: the solve as before
        except np.linalg.LinAlgError:
            w, V = np.linalg.eigh(A)
            n = A.shape[-1]
            eps = np.finfo(A.dtype).eps
            wmax = np.abs(w).max(axis=-1, keepdims=True)
            tol = 1e3 * n * eps * wmax
            keep = w > tol
            VtB = V.swapaxes(-1, -2) @ B
            pmax = np.abs(P).max(axis=(-2, -1))[..., None, None]
            bmax = np.abs(B).max(axis=(-2, -1))[..., None, None]
            bound = 10.0 * np.sqrt(n * tol[..., :, None] * pmax) + 1e3 * n * eps * bmax
            if (np.abs(np.where(keep[..., :, None], 0.0, VtB)) > bound).any():
                raise np.linalg.LinAlgError("the prediction P_prior is singular and F P has a component in its null "
                                            "space: P_prior is not F P F^T + Q of this filter")
            inv_w = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
            return V @ (inv_w[..., :, None] * VtB)
    return _spd_solve(xp, A, L, B)


def rts_step(x, P, x_prior_next, P_prior_next, xs_next, Ps_next, F):
    r"""One Rauch–Tung–Striebel step back in time: :math:`G = P F^\top (P^-_{k+1})^{-1}`,
    :math:`x^s = x + G(x^s_{k+1} - x^-_{k+1})`, :math:`P^s = \operatorname{sym}(P + G(P^s_{k+1} - P^-_{k+1})G^\top)`.
    Returns ``(x^s, P^s, G)``.

    A singular :math:`P^-_{k+1}` (a known start ``P0 = 0`` with ``Q = 0`` or a rank-deficient
    ``Q``) takes the pseudo-inverse on NumPy: :math:`G = P F^\top (P^-_{k+1})^{+}` is the
    smoother gain there, because the range of :math:`F P F^\top` lies in that of
    :math:`P^-_{k+1} = F P F^\top + Q` (both positive semi-definite), so
    :math:`G P^-_{k+1} = P F^\top` still holds. A positive definite :math:`P^-_{k+1}` is solved
    as always (the same bits); a singular one that is not :math:`F P F^\top + Q` raises
    ``numpy.linalg.LinAlgError``."""
    xp = array_namespace(x, P, F)
    G = matrix_transpose(_rts_gain_t(xp, P_prior_next, P, F))  # (P^-)^T G^T = F P
    xs = x + mv(G, xs_next - x_prior_next)
    Ps = sym(P + mm(mm(G, Ps_next - P_prior_next), matrix_transpose(G)))
    return xs, Ps, G


# --------------------------------------------------------------------------------------------
# extended Kalman filter
# --------------------------------------------------------------------------------------------
def gain_update(x, P, y, H, R) -> Update:
    """Update with a given innovation ``y``. Runs :func:`kf_update` linearized at zero (where its
    innovation is ``y`` exactly) and shifts the mean back by ``x``; every number is then the one
    the Kalman filter computes, to the last bit."""
    xp = array_namespace(x, P, y, H, R)
    u = kf_update(xp.zeros_like(x), P, y, H, R)
    return u._replace(x=x + u.x)


def ekf_predict(x, P, f, F_jac, Q, x_angles=()):
    r"""EKF time update :math:`x^- = f(x)`, :math:`P^- = F P F^\top + Q`, :math:`F = F_{jac}(x)`."""
    F = F_jac(x)
    _, P_pred = kf_predict(x, P, F, Q)
    return wrap_state(f(x), x_angles), P_pred


def ekf_update(x, P, z, h, H_jac, R, angles, x_angles=()) -> Update:
    r"""EKF update with innovation :math:`z \ominus h(x)` and :math:`H = H_{jac}(x)` (Joseph form)."""
    y = residual(z, h(x), angles)
    u = gain_update(x, P, y, H_jac(x), R)
    return u._replace(x=wrap_state(u.x, x_angles)) if x_angles else u


# --------------------------------------------------------------------------------------------
# unscented transform and filter
# --------------------------------------------------------------------------------------------
def _sqrt_psd(xp, A):
    r"""A square root :math:`L` of :math:`A = L L^\top` (..., n, n): the lower Cholesky factor; on
    NumPy, where it does not exist (a positive semi-definite ``A``, e.g. a known start ``P = 0``),
    the symmetric root :math:`V \operatorname{diag}(\sqrt{\lambda}) V^\top` of the eigendecomposition,
    with eigenvalues within round-off of zero (``|lambda| <= 1e3 n eps max|lambda|``) set to zero.
    A clearly negative eigenvalue raises ``numpy.linalg.LinAlgError`` as the factorization did."""
    if not _is_np(A):
        return xp.linalg.cholesky(A)  # JAX: NaN for a singular A (no value branch inside a trace)
    try:
        return np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(A)
        n = A.shape[-1]
        tol = 1e3 * n * np.finfo(A.dtype).eps * np.abs(w).max(axis=-1, keepdims=True)
        if (w < -tol).any():
            raise np.linalg.LinAlgError(f"the covariance of the sigma points is not positive semi-definite "
                                        f"(smallest eigenvalue {w.min():.3g})") from None
        return (V * np.sqrt(np.clip(w, 0.0, None))[..., None, :]) @ V.swapaxes(-1, -2)


def sigma_points(x, P, c, Wm, Wc) -> SigmaPoints:
    r"""Points :math:`x`, :math:`x \pm [\sqrt{cP}]_i` (columns of the lower Cholesky factor; of the
    symmetric square root where that does not exist, see ``_sqrt_psd``)."""
    xp = array_namespace(x, P)
    L = _sqrt_psd(xp, c * P)  # lower Cholesky factor: columns are the offsets
    offsets = matrix_transpose(L)  # (..., n, n), row i = column i of L
    zero = xp.zeros(offsets.shape[:-2] + (1, x.shape[-1]), dtype=x.dtype)
    X = x[..., None, :] + xp.concat([zero, offsets, -offsets], axis=-2)
    return SigmaPoints(X, Wm, Wc)


def _wsum(W, Y):
    """``sum_i W_i Y[..., i, :]`` for weights ``W`` ``(N,)`` and points ``Y`` ``(..., N, d)``."""
    xp = array_namespace(Y)
    return xp.sum(xp.asarray(W, dtype=Y.dtype)[:, None] * Y, axis=-2)


def weighted_mean(Y, Wm, angles: tuple[int, ...]):
    """Weighted mean of points ``Y`` ``(..., 2n+1, d)``; circular mean on the ``angles`` components."""
    y = _wsum(Wm, Y)
    if not angles:
        return y
    xp = array_namespace(Y)
    circ = xp.atan2(_wsum(Wm, xp.sin(Y)), _wsum(Wm, xp.cos(Y)))
    return xp.where(_angle_mask(xp, Y.shape[-1], angles), circ, y)


def moments(Y, Wm, Wc, angles):
    """``(mean, cov, deviations)`` of weighted points ``Y`` (wrapped deviations on ``angles``)."""
    xp = array_namespace(Y)
    y = weighted_mean(Y, Wm, angles)
    dY = residual(Y, y[..., None, :], angles)
    Wc = xp.asarray(Wc, dtype=Y.dtype)
    return y, sym(mm(matrix_transpose(dY * Wc[:, None]), dY)), dY


def unscented(fn, x, P, points, x_angles, y_angles):
    """The unscented transform of ``N(x, P)`` through ``fn`` with the weights of ``points``
    (an object with ``weights(n) -> (Wm, Wc, c)``). Returns ``(mean, cov, cross, sigma)``."""
    xp = array_namespace(x, P)
    n = x.shape[-1]
    Wm, Wc, c = points.weights(n)
    sp = sigma_points(x, P, c, Wm, Wc)
    Y = fn(sp.X)
    y, C, dY = moments(Y, Wm, Wc, y_angles)
    dX = residual(sp.X, x[..., None, :], x_angles)
    cross = mm(matrix_transpose(dX * xp.asarray(Wc, dtype=dX.dtype)[:, None]), dY)
    return y, C, cross, sp


def ukf_predict(x, P, f, Q, points, x_angles):
    """UKF time update: unscented moments of ``f`` plus ``Q``."""
    mean, cov, _, _ = unscented(f, x, P, points, x_angles, x_angles)
    return mean, sym(cov + Q)


def ukf_update(x, P, z, h, R, points, x_angles, z_angles) -> Update:
    r"""UKF update: :math:`S = P_{zz} + R`, :math:`K = P_{xz} S^{-1}`, :math:`P^+ = P - K S K^\top`."""
    xp = array_namespace(x, P, z, R)
    _T = xp.matrix_transpose
    zhat, Pzz, cross, _ = unscented(h, x, P, points, x_angles, z_angles)
    S = sym(Pzz + R)
    y = residual(z, zhat, z_angles)
    K = _T(solve_spd(S, _T(cross)))  # K = Pxz S^{-1}, S symmetric
    x_post = wrap_state(x + mv(K, y), x_angles)
    P_post = sym(P - mm(mm(K, S), _T(K)))
    return Update(x_post, P_post, y, S, K, *innovation_score(y, S))


# --------------------------------------------------------------------------------------------
# multiple models: mixing
# --------------------------------------------------------------------------------------------
def logsumexp(a, axis: int, keepdims: bool = False):
    """log(sum(exp(a))) along ``axis``, shifted by the maximum; all ``-inf`` gives ``-inf``."""
    xp = array_namespace(a)
    m = xp.max(a, axis=axis, keepdims=True)
    m = xp.where(xp.isfinite(m), m, xp.zeros_like(m))
    with np.errstate(divide="ignore"):  # log(0) = -inf is the intended value (NumPy would warn)
        out = xp.log(xp.sum(xp.exp(a - m), axis=axis, keepdims=True)) + m
    return out if keepdims else xp.squeeze(out, axis=axis)


def moment_match(w, xs, Ps):
    r"""Moment-matched Gaussian of a mixture: ``w`` (..., r), ``xs`` (r, ..., n), ``Ps`` (r, ..., n, n)
    -> :math:`\bar x = \sum w_i x_i`, :math:`\bar P = \sum w_i [P_i + (x_i - \bar x)(x_i - \bar x)^\top]`.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.kernels import moment_match
    >>> x, P = moment_match(np.array([0.5, 0.5]), np.array([[-1.0], [1.0]]), np.array([[[1.0]], [[1.0]]]))
    >>> print(np.round(x, 6) + 0.0, np.round(P, 6))   # mean 0, variance 1 + spread 1
    [0.] [[2.]]
    """
    xp = array_namespace(w, xs, Ps)
    wr = xp.moveaxis(w, -1, 0)  # (r, ...); the sums over the r components run term by term
    r = wr.shape[0]
    x = wr[0][..., None] * xs[0]
    for i in range(1, r):
        x = x + wr[i][..., None] * xs[i]
    P = None
    for i in range(r):
        d = xs[i] - x
        term = wr[i][..., None, None] * (Ps[i] + d[..., :, None] * d[..., None, :])
        P = term if P is None else P + term
    return x, sym(P)


def mixing_log_weights(log_mu, Pi):
    r"""IMM mixing in log space: ``log mu_{i|j}`` (..., r_i, r_j) and ``log cbar_j`` (..., r_j),
    :math:`\bar c_j = \sum_i \Pi_{ij}\mu_i`, :math:`\mu_{i|j} = \Pi_{ij}\mu_i/\bar c_j`. A mode ``j``
    that cannot be reached (:math:`\bar c_j = 0`) keeps its own estimate (weight 1 on itself)."""
    xp = array_namespace(log_mu, Pi)
    r = Pi.shape[-1]
    with np.errstate(divide="ignore"):
        logPi = xp.log(Pi)
    joint = log_mu[..., :, None] + logPi  # (..., i, j)
    log_cbar = logsumexp(joint, axis=-2)
    dead = xp.isinf(log_cbar) & (log_cbar < 0)
    safe = xp.where(dead, xp.zeros_like(log_cbar), log_cbar)  # no -inf - -inf
    logw = joint - safe[..., None, :]
    eye = xp.where(xp.eye(r, dtype=xp.bool), xp.asarray(0.0, dtype=logw.dtype),
                   xp.asarray(-math.inf, dtype=logw.dtype))
    logw = xp.where(dead[..., None, :], eye, logw)
    return logw, log_cbar

