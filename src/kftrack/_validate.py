"""Input checks shared by the public functions (private module).

Every check raises ``ValueError`` (or ``TypeError``) whose message names the argument,
what was expected and what was received. Checks run once at a public boundary; the
inner loops of the filters call the unchecked kernels.
"""
from __future__ import annotations

import operator
import sys

import numpy as np

__all__ = ["as_float_array", "as_vector", "as_matrix", "check_covariance", "check_finite", "check_rng",
           "finite_scalar", "positive_scalar", "broadcast_batch", "check_state", "check_sequence", "check_form",
           "check_angles", "call_checked", "as_measurement_sequence", "check_missing", "is_tracer", "stand_in"]

_EPS = float(np.finfo(float).eps)
_TINY = float(np.finfo(float).tiny)
# Largest n for which a successful Cholesky factorization decides the semi-definiteness test of
# check_covariance exactly as the eigenvalue test would (see there); larger matrices go to eigvalsh.
_CHOLESKY_MAX_N = 32


def is_tracer(a) -> bool:
    """True for an abstract JAX value (inside ``jit``, ``grad``, ``vmap``): shapes only, no values."""
    jax = sys.modules.get("jax")  # nobody imported jax: nothing can be a tracer
    return jax is not None and isinstance(a, jax.core.Tracer)


def stand_in(value, kind: str):
    """A NumPy stand-in of the same shape for an abstract JAX value (inside ``jit``/``grad``/``vmap``),
    so the boundary checks still check its shape (values cannot be checked there); the value
    itself otherwise. ``kind``: ``"cov"`` (identity matrices), ``"matrix"``/``"vector"`` (zeros)."""
    if not is_tracer(value):
        return value
    shape = tuple(value.shape)
    if kind == "cov" and len(shape) >= 2 and shape[-1] == shape[-2]:
        return np.broadcast_to(np.eye(shape[-1]), shape)
    return np.zeros(shape)


def as_float_array(value, name: str) -> np.ndarray:
    """Convert ``value`` to a float ndarray or raise ``TypeError`` naming ``name``.

    ``None`` and complex values are refused (NumPy would turn them into NaN or silently drop
    the imaginary part).
    """
    if type(value) is np.ndarray and value.dtype == np.float64:
        return value  # fast path: what the general path returns for a float64 ndarray (itself)
    if value is None:
        raise TypeError(f"{name} must be an array of real numbers, got None")
    try:
        raw = np.asarray(value)
        arr = None if np.iscomplexobj(raw) else raw.astype(float, copy=False)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be an array of real numbers, got {type(value).__name__}") from exc
    if arr is None:
        raise TypeError(f"{name} must be an array of real numbers, got complex values ({raw.dtype})")
    return arr


def check_finite(arr: np.ndarray, name: str) -> np.ndarray:
    """Raise ``ValueError`` if ``arr`` holds NaN or inf."""
    if not np.isfinite(arr).all():
        bad = "NaN" if np.isnan(arr).any() else "inf"
        raise ValueError(f"{name} must be finite, but it contains {bad}")
    return arr


def as_vector(value, name: str, n: int | None = None, allow_nan: bool = False) -> np.ndarray:
    """A stack of vectors, shape ``(..., n)``; ``n`` checked when given."""
    arr = as_float_array(value, name)
    if arr.ndim == 0:
        raise ValueError(f"{name} must have shape (..., n) with at least one axis, got a scalar")
    if n is not None and arr.shape[-1] != n:
        raise ValueError(f"{name} must have shape (..., {n}), got shape {arr.shape}")
    if not allow_nan:
        check_finite(arr, name)
    return arr


def as_matrix(value, name: str, rows: int | None = None, cols: int | None = None, *,
              origin: str = "") -> np.ndarray:
    """A stack of matrices, shape ``(..., rows, cols)``, finite.

    ``origin`` says where the expected sizes come from (``"m = 2 from z"``); it is appended
    to a shape error.
    """
    arr = as_float_array(value, name)
    why = f" ({origin})" if origin else ""
    if arr.ndim < 2:
        raise ValueError(f"{name} must have shape (..., {rows or 'r'}, {cols or 'c'}), got shape {arr.shape}{why}")
    r, c = arr.shape[-2:]
    if (rows is not None and r != rows) or (cols is not None and c != cols):
        raise ValueError(
            f"{name} must have shape (..., {rows if rows is not None else r}, "
            f"{cols if cols is not None else c}), got shape {arr.shape}{why}"
        )
    return check_finite(arr, name)


def check_covariance(value, name: str, n: int | None = None, positive_definite: bool = False, *,
                     origin: str = "") -> np.ndarray:
    """A stack of symmetric positive semi-definite (or definite) matrices ``(..., n, n)``.

    Symmetry and the sign of the smallest eigenvalue are judged relative to the largest
    entry, with a tolerance of a few thousand machine epsilons: round-off passes, a real
    asymmetry or a negative variance does not. ``origin`` as in :func:`as_matrix`.
    """
    arr = as_matrix(value, name, n, n, origin=origin)
    why = f" ({origin})" if origin else ""
    if arr.shape[-1] != arr.shape[-2]:
        raise ValueError(f"{name} must be square, shape (..., n, n), got shape {arr.shape}")
    n_ = arr.shape[-1]
    if n_ == 0:
        raise ValueError(f"{name} must have shape (..., n, n) with n >= 1, got shape {arr.shape}{why}")
    scale = np.abs(arr).max(axis=(-2, -1), keepdims=True) + _TINY
    tol = 1e3 * n_ * _EPS
    arr_t = arr.swapaxes(-1, -2)
    asym = (np.abs(arr - arr_t) / scale).max()
    if asym > tol:
        raise ValueError(f"{name} must be symmetric, but |{name} - {name}.T| / max|{name}| = {asym:.3g}")
    sym = 0.5 * (arr + arr_t)
    if 0 < n_ <= _CHOLESKY_MAX_N and arr.size:
        # Fast accept without eigenvalues, the same decision as the eigenvalue test below. A
        # Cholesky factorization that succeeds proves lambda_min >= -c n^2 eps max|A| (its backward
        # error, c ~ 1), and eigvalsh's own error is of that order too; for n <= 32 both are
        # below 32 c n eps, far inside tol = 1e3 n eps: the PSD test passes. For the PD test,
        # factorize sym - 2 tol scale I: success proves lambda_min > (2 tol - c n^2 eps) scale,
        # above tol scale with the same margin. A failed factorization decides nothing: it falls
        # through to the eigenvalue test, which decides and words the error as before.
        try:
            np.linalg.cholesky(sym - (2.0 * tol) * scale * np.eye(n_) if positive_definite else sym)
            return arr
        except np.linalg.LinAlgError:
            pass
    eig = np.linalg.eigvalsh(sym)
    worst = np.min(eig[..., 0] / scale[..., 0, 0])
    if positive_definite and worst <= tol:
        raise ValueError(f"{name} must be positive definite, but its smallest eigenvalue is {np.min(eig[..., 0]):.3g}")
    if worst < -tol:
        raise ValueError(
            f"{name} must be positive semi-definite, but its smallest eigenvalue is {np.min(eig[..., 0]):.3g}"
        )
    return arr


def as_measurement_sequence(value, name: str = "zs") -> tuple[np.ndarray, np.ndarray]:
    """A measurement sequence ``(T, ..., m)``, time first, where a row of NaN marks a missing
    measurement. Returns the array and the ``(T, ...)`` mask of missing rows; inf or a partly
    NaN row raises ``ValueError``."""
    arr = as_vector(value, name, allow_nan=True)
    if arr.ndim < 2:
        raise ValueError(f"{name} must have shape (T, ..., m) with time first, got shape {arr.shape}")
    if np.isinf(arr).any():
        raise ValueError(f"{name} must be finite or NaN (missing), but it contains inf")
    missing = np.isnan(arr)
    row_missing = missing[..., 0]
    # one flat comparison instead of any/all reductions over the short last axis (10x faster)
    if (missing != row_missing[..., None]).any():
        partial = missing.any(-1) & ~missing.all(-1)
        k = int(np.argwhere(partial)[0][0])
        raise ValueError(f"{name} has a row at step {k} that is only partly NaN; a missing measurement is a row of NaN")
    return arr, np.ascontiguousarray(row_missing)


def check_rng(rng) -> np.random.Generator:
    """``rng`` itself if it is a ``numpy.random.Generator``, else a ``TypeError`` naming it."""
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    return rng


def finite_scalar(value, name: str) -> float:
    """A finite real scalar, as a float (a ``ValueError``/``TypeError`` naming ``name`` otherwise)."""
    arr = check_finite(as_float_array(value, name), name)
    if arr.ndim != 0:
        raise ValueError(f"{name} must be a scalar, got shape {arr.shape}")
    return float(arr)


def positive_scalar(value, name: str, unit: str = "") -> float:
    """A finite real scalar ``> 0`` (``unit`` is named in the error), as a float."""
    v = finite_scalar(value, name)
    if not v > 0:
        raise ValueError(f"{name} must be > 0{f' ({unit})' if unit else ''}, got {value!r}")
    return v


# --------------------------------------------------------------------------------------------
# checks shared by the filters (kalman, ekf, ukf, imm)
# --------------------------------------------------------------------------------------------
def broadcast_batch(name_shapes: dict[str, tuple]) -> tuple:
    """The broadcast of the batch shapes ``{argument: shape}``, or a ``ValueError`` naming them."""
    try:
        return np.broadcast_shapes(*name_shapes.values())
    except ValueError:
        desc = ", ".join(f"{k} {v}" for k, v in name_shapes.items())
        raise ValueError(f"batch axes do not broadcast: {desc}; the leading (batch) axes of the arguments "
                         "must be equal or 1 (NumPy broadcasting), or absent for a shared matrix") from None


def check_state(x, P, names: tuple[str, str] = ("x", "P")):
    """A state ``x`` ``(..., n)`` and its covariance ``P`` ``(..., n, n)``; returns ``(x, P, n)``."""
    x = as_vector(x, names[0])
    n = x.shape[-1]
    if n == 0:
        raise ValueError(f"{names[0]} must have shape (..., n) with n >= 1 state components, got shape {x.shape}")
    P = check_covariance(P, names[1], n, origin=f"n = {n} from {names[0]}")
    return x, P, n


def check_sequence(zs, x0, P0, Q, R, missing=None):
    """Boundary checks shared by the whole-sequence filters (KF, EKF, UKF).

    Abstract JAX values (inside ``jit``, ``grad``, ``vmap``) are checked for their shapes through
    :func:`stand_in`. Returns ``zs, x0, P0, Q, R, n, m, batch, row_missing``, the arrays checked
    (stand-ins for abstract values), where ``row_missing`` ``(T, ...)`` marks the measurement rows
    not to use (:func:`check_missing`), or is None when only the trace knows them.
    """
    x0, P0, n = check_state(stand_in(x0, "vector"), stand_in(P0, "cov"), ("x0", "P0"))
    zs, row_missing = check_missing(zs, missing)
    m = zs.shape[-1]
    Q = check_covariance(stand_in(Q, "cov"), "Q", n, origin=f"n = {n} from x0")
    R = check_covariance(stand_in(R, "cov"), "R", m, positive_definite=True, origin=f"m = {m} from zs")
    batch = broadcast_batch({"zs[k]": zs.shape[1:-1], "x0": x0.shape[:-1], "P0": P0.shape[:-2],
                             "Q": Q.shape[:-2], "R": R.shape[:-2]})
    return zs, x0, P0, Q, R, n, m, batch, row_missing


def check_missing(zs, missing=None, name: str = "zs"):
    """The measurement sequence ``zs`` ``(T, ..., m)`` and its missing rows, from one of

    * ``missing=None``: the rows of NaN of ``zs`` (:func:`as_measurement_sequence`); for an
      abstract ``zs`` (inside a JAX trace) they are not known here: the pattern is None and the
      filter derives it inside the trace, run by run;
    * ``missing=False``: no row is missing (``zs`` must then be finite);
    * ``missing`` a concrete boolean array ``(T,)`` or ``(T, ...)`` whose batch axes broadcast to
      those of ``zs``: True marks a row not to use, whatever it holds; the other rows must be
      finite.

    A concrete pattern is static information: it is known when the filter is traced, so it may
    keep the covariances shared by all runs inside ``jax.jit``. Returns ``(zs, pattern)``, ``zs``
    checked (a :func:`stand_in` for an abstract value) and the pattern a NumPy bool array or None.
    """
    abstract = is_tracer(zs)
    if missing is None:
        if not abstract:
            return as_measurement_sequence(zs, name)
        arr = as_vector(stand_in(zs, "vector"), name)
        if arr.ndim < 2:
            raise ValueError(f"{name} must have shape (T, ..., m) with time first, got shape {arr.shape}")
        return arr, None
    if is_tracer(missing):
        raise TypeError("missing must be concrete (a NumPy boolean array, or False): it decides how the filter is "
                        "compiled; inside jax.jit pass it from outside the traced function, got a traced value "
                        f"of shape {tuple(missing.shape)}")
    arr = as_vector(stand_in(zs, "vector"), name, allow_nan=True)
    if arr.ndim < 2:
        raise ValueError(f"{name} must have shape (T, ..., m) with time first, got shape {arr.shape}")
    T, zb = arr.shape[0], arr.shape[1:-1]
    if missing is False or (isinstance(missing, np.bool_) and not missing):
        gone = np.zeros(T, dtype=bool)
    else:
        gone = np.asarray(missing)
        if gone.dtype != bool or gone.ndim == 0:
            raise TypeError(f"missing must be None, False or a boolean array of shape ({T},) or ({T}, ...) (True: "
                            f"the row of {name} is not used), got {type(missing).__name__}"
                            + (f" of dtype {gone.dtype} and shape {gone.shape}" if hasattr(missing, "shape") else ""))
        if gone.shape[0] != T or len(gone.shape) - 1 > len(zb) or not all(
                a in (1, b) for a, b in zip(gone.shape[:0:-1], zb[::-1])):
            raise ValueError(f"missing must have shape ({T},) or ({T}, ...) with batch axes that broadcast to those "
                             f"of {name} {zb} (one flag per step and run), got shape {gone.shape}")
    if not abstract:
        used = ~np.broadcast_to(gone.reshape((T,) + (1,) * (len(zb) + 1 - gone.ndim) + gone.shape[1:]), arr.shape[:-1])
        bad = used[..., None] & ~np.isfinite(arr)
        if bad.any():
            k = int(np.argwhere(bad)[0][0])
            what = "NaN" if np.isnan(arr[bad]).any() else "inf"
            raise ValueError(f"{name} has {what} at step {k} in a row that missing does not mark as missing: a "
                             "measurement used must be finite (mark the row True in missing, or pass missing=None "
                             "to take rows of NaN as missing)")
    return arr, gone


_FORMS = ("joseph", "standard")


def check_form(form) -> str:
    """The covariance-update form, ``"joseph"`` or ``"standard"``."""
    if form not in _FORMS:
        raise ValueError(f"form must be one of {_FORMS} (covariance update), got {form!r}")
    return form


def check_angles(angle_components, m: int, name: str = "angle_components") -> tuple[int, ...]:
    """Validate a sequence of component indices into a vector of length ``m``; sorted, unique, >= 0."""
    try:
        items = tuple(angle_components)
        if any(isinstance(i, (bool, np.bool_)) for i in items):
            raise TypeError
        idx = tuple(operator.index(i) for i in items)  # an int or NumPy integer; 0.5 or 1.0 is refused
    except TypeError:
        raise TypeError(f"{name} must be a sequence of integer indices, got {angle_components!r}") from None
    bad = [i for i in idx if not -m <= i < m]
    if bad:
        raise ValueError(f"{name} must index a vector of length {m}, got {bad}")
    return tuple(sorted({i % m for i in idx}))


def call_checked(fn, x, name: str, shape: tuple) -> np.ndarray:
    """Call a user function once at the boundary and check the shape of what it returns."""
    try:
        out = fn(x)
        # an abstract JAX value (fn closes over a traced parameter): its shape is checked, not its values
        out = stand_in(out, "matrix") if is_tracer(out) else np.asarray(out, dtype=float)
    except Exception as exc:  # report which argument failed, keep the cause
        raise ValueError(f"{name} failed on x of shape {x.shape}: {exc}") from exc
    if shape and (out.ndim < len(shape) or out.shape[-len(shape):] != shape):
        raise ValueError(f"{name}(x) must return shape (..., {', '.join(map(str, shape))}), got {out.shape}")
    return out

