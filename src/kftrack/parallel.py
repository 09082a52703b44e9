r"""The linear Kalman filter and RTS smoother parallel in time: associative scans over the steps.

Särkkä & García-Fernández (2021), "Temporal parallelization of Bayesian smoothers", IEEE TAC 66(1):
the filter and the smoother are written as prefix (suffix) products of one element per step
under an associative operation, evaluated by :func:`prefix_scan` (span :math:`O(\log T)` rounds,
work :math:`O(T)`: at most :math:`3T` combinations for :math:`T \le 10^4`). On a GPU with lanes
enough for a round's combinations the span is what counts; on one CPU core the work does, and a
combination (two ``n x n`` solves and some ten matrix products) costs more than a step of the
sequential recursion: the parallel form lost there at every length measured, :math:`T = 10^2` to
:math:`10^4` (``benchmarks/compose.py``).

**Built from the kernels** (:mod:`kftrack.kernels`), with the step convention of
:func:`kftrack.kalman.kalman_filter` (at step ``k`` update with ``zs[k]``, then predict with
``F[k]``, ``Q[k]``). The filter's element of step ``k`` is the conditional
:math:`p(x_k \mid x_{k-1}, z_k) = N(A_k x_{k-1} + b_k, C_k)` with the information
:math:`(\eta_k, J_k)` that :math:`z_k` carries about :math:`x_{k-1}`:

.. math::

    S = H Q H^\top + R,\quad K = Q H^\top S^{-1}:\quad
    A = (I - KH)F,\quad b = K z,\quad C = (I - KH)Q,\quad
    \eta = (HF)^\top S^{-1} z,\quad J = (HF)^\top S^{-1} HF

(``F``, ``Q`` those of step ``k - 1``). :math:`(b, C)` is :func:`~kftrack.kernels.kf_update` of
the prior :math:`N(0, Q)` with ``z`` (its Joseph form, the same numbers as the sequential
filter's), and step 0 is :func:`~kftrack.kernels.kf_update` of ``(x0, P0)`` with ``zs[0]``
(:math:`A = 0`, :math:`\eta = 0`, :math:`J = 0`). A missing row keeps the prediction alone:
:math:`A = F`, :math:`b = 0`, :math:`C = Q`, :math:`\eta = 0`, :math:`J = 0`. Two elements
combine (``i`` before ``j``) as

.. math::

    M = A_j (I + C_i J_j)^{-1},\quad A = M A_i,\quad b = M(b_i + C_i \eta_j) + b_j,\quad
    C = M C_i A_j^\top + C_j,

    N = A_i^\top (I + J_j C_i)^{-1},\quad \eta = N(\eta_j - J_j b_i) + \eta_i,\quad J = N J_j A_i + J_i,

and the prefix product up to step ``k`` holds the filtered mean :math:`b` and covariance
:math:`C`. The smoother's element of step ``k < T - 1`` is :func:`~kftrack.kernels.rts_step`
with a zero next state: :math:`E_k = G_k` (the RTS gain), :math:`g_k = x_k - G_k x^-_{k+1}`,
:math:`L_k = P_k - G_k P^-_{k+1} G_k^\top`; the last is :math:`(0, x_{T-1}, P_{T-1})`; they combine as
:math:`(E_i E_j,\; E_i g_j + g_i,\; E_i L_j E_i^\top + L_i)`, a suffix product. The predictions,
NIS and log-likelihood of every step come from the filtered sequence by
:func:`~kftrack.kernels.kf_predict` and :func:`~kftrack.kernels.kf_update` with the time axis as
a batch axis (no recursion).

**Shared covariances.** As in :mod:`kftrack.engines`: when no covariance input has batch axes and
all runs miss the same rows (``missing=`` as in :func:`kftrack.kalman.kalman_filter`), the
elements :math:`A, C, J` carry no run axes, and only :math:`b, \eta` are per run.

**Round-off.** Each element and each combination is a few backward-stable operations (a solve
with :math:`I + C_i J_j` whose condition number is at most :math:`(1 + \|C_i\|\,\|J_j\|)^2`, since
the eigenvalues of :math:`C_i J_j` are those of the positive semi-definite
:math:`C_i^{1/2} J_j C_i^{1/2}`); added over the at most :math:`T` combinations that feed a step,
without credit for the filter forgetting old errors, the filtered means differ from the
sequential engine's by at most about :math:`C\,T\,n\,\kappa\,\varepsilon` relative, :math:`\kappa`
the largest of the condition numbers of :math:`P^-`, :math:`S` and :math:`(1 + c\,j)^2`, where
:math:`c` bounds the covariance and :math:`j` the information of every segment of steps
(``tests/test_parallel.py`` computes them).

JAX only: the inputs may be NumPy or JAX arrays, the result is JAX arrays; inside the caller's
``jax.jit``, ``jax.grad`` and ``jax.vmap`` the shapes are checked, not the values (as
:func:`kftrack.kalman.kalman_filter`).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from ._validate import as_matrix, broadcast_batch, check_covariance, check_missing, check_state, stand_in
from .engines import check_dtype, to_engine, use_jax
from .kalman import _smoother_transitions, _transitions
from .kernels import kf_predict, kf_update, matrix_transpose, mm, mv, rts_step, solve_spd, sym
from .results import FilterResult, SmootherResult

__all__ = ["parallel_filter", "parallel_smoother", "filter_elements", "combine_filter", "smoother_elements",
           "combine_smoother", "prefix_scan"]


def _jax():
    import jax  # only when called

    return jax


# --------------------------------------------------------------------------------------------
# elements and their combination (unchecked, JAX arrays; time first, batch axes broadcasting)
# --------------------------------------------------------------------------------------------
def filter_elements(zs, gone, x0, P0, F, Q, H, R):
    r"""The filter's elements ``(A, b, C, eta, J)`` of every step (module docstring), time first.

    ``zs`` (T, ..., m); ``gone`` None (no row missing) or (T, ...) bool; ``x0`` (..., n), ``P0``
    (..., n, n); ``F``, ``Q`` (T, ..., n, n), ``F[k]`` mapping step ``k`` to ``k + 1`` (only
    ``F[:-1]`` is used); ``H``, ``R`` (..., m, n), (..., m, m). Unchecked."""
    jnp = _jax().numpy
    T, n = zs.shape[0], x0.shape[-1]
    z = zs if gone is None else jnp.where(gone[..., None], jnp.zeros((), zs.dtype), zs)
    Fp, Qp = F[:-1], Q[:-1]  # the transition into steps 1 .. T-1
    zk = z[1:]
    u = kf_update(jnp.zeros(zk.shape[:-1] + (n,), zs.dtype), Qp, zk, H, R)  # b = K z, C = (I - KH) Q (Joseph)
    HF = mm(H, Fp)
    W = solve_spd(u.S, HF)  # S^{-1} H F
    A = Fp - mm(u.K, HF)
    eta = mv(matrix_transpose(W), zk)
    J = sym(mm(matrix_transpose(HF), W))
    b, C = u.x, u.P
    u0 = kf_update(x0, P0, z[0], H, R)
    b0, C0 = u0.x, u0.P
    if gone is not None:
        g0, g = gone[0], gone[1:]
        b0 = jnp.where(g0[..., None], x0, b0)
        C0 = jnp.where(g0[..., None, None], P0, C0)
        gv, gm = g[..., None], g[..., None, None]
        A, C = jnp.where(gm, Fp, A), jnp.where(gm, Qp, C)
        b, eta = jnp.where(gv, 0.0, b), jnp.where(gv, 0.0, eta)
        J = jnp.where(gm, 0.0, J)
    cat = lambda first, rest: jnp.concatenate(  # noqa: E731  step 0 first, both broadcast to one shape
        [jnp.broadcast_to(first, (1,) + jnp.broadcast_shapes(first.shape, rest.shape[1:])),
         jnp.broadcast_to(rest, (T - 1,) + jnp.broadcast_shapes(first.shape, rest.shape[1:]))])
    zero_m = jnp.zeros(A.shape[1:], zs.dtype)
    return (cat(zero_m, A), cat(b0, b), cat(C0, C), cat(jnp.zeros(eta.shape[1:], zs.dtype), eta),
            cat(jnp.zeros(J.shape[1:], zs.dtype), J))


def combine_filter(first, second):
    """The associative operation of the filter: ``first`` (the earlier segment) then ``second``,
    each ``(A, b, C, eta, J)`` (module docstring). Unchecked."""
    jnp = _jax().numpy
    A1, b1, C1, e1, J1 = first
    A2, b2, C2, e2, J2 = second
    n = A1.shape[-1]
    eye = jnp.eye(n, dtype=A1.dtype)
    # M = A2 (I + C1 J2)^{-1}: M^T = (I + J2 C1)^{-1} A2^T; N = A1^T (I + J2 C1)^{-1}: N^T = (I + C1 J2)^{-1} A1
    I_JC = eye + mm(J2, C1)
    I_CJ = eye + mm(C1, J2)
    M = matrix_transpose(jnp.linalg.solve(I_JC, matrix_transpose(A2)))
    N = matrix_transpose(jnp.linalg.solve(I_CJ, A1))
    A = mm(M, A1)
    b = mv(M, b1 + mv(C1, e2)) + b2
    C = sym(mm(mm(M, C1), matrix_transpose(A2)) + C2)
    eta = mv(N, e2 - mv(J2, b1)) + e1
    J = sym(mm(mm(N, J2), A1) + J1)
    return A, b, C, eta, J


def smoother_elements(x, P, x_prior, P_prior, F):
    """The smoother's elements ``(E, g, L)`` of every step (module docstring), from a filtered
    sequence ``x`` (T, ..., n), ``P`` (T, ..., n, n) and its predictions; ``F`` (T, ..., n, n).
    Unchecked."""
    jnp = _jax().numpy
    xk = x[:-1]
    g, L, E = rts_step(xk, P[:-1], x_prior[1:], P_prior[1:], jnp.zeros_like(xk), jnp.zeros_like(P[:-1]), F[:-1])
    E = jnp.broadcast_to(E, jnp.broadcast_shapes(E.shape, L.shape))
    shp = lambda a, last: jnp.broadcast_shapes(a.shape[1:], last.shape)  # noqa: E731
    cat = lambda rest, last: jnp.concatenate([jnp.broadcast_to(rest, (rest.shape[0],) + shp(rest, last)),  # noqa: E731
                                              jnp.broadcast_to(last, (1,) + shp(rest, last))])
    return cat(E, jnp.zeros(E.shape[1:], x.dtype)), cat(g, x[-1]), cat(L, P[-1])


def combine_smoother(later, earlier):
    """The associative operation of the smoother: ``later`` (a segment after ``earlier``), each
    ``(E, g, L)``; the result maps the smoothed state after both segments to the one before them
    (:func:`prefix_scan` over the reversed sequence calls it as ``op(later, earlier)``). Unchecked."""
    E2, g2, L2 = later
    E1, g1, L1 = earlier
    return mm(E1, E2), mv(E1, g2) + g1, sym(mm(mm(E1, L2), matrix_transpose(E1)) + L1)


def prefix_scan(op, elems, identity):
    r"""Inclusive prefix products ``out[k] = elems[0] op elems[1] op ... op elems[k]`` along the leading
    (time) axis of the pytree ``elems``, for an associative ``op(earlier, later)`` with two-sided
    ``identity`` (a pytree of one element, broadcasting to an element).

    Work-efficient with logarithmic span (Brent's blocking): the ``T`` steps are cut into
    :math:`\lceil T/L \rceil` blocks of :math:`L = \lceil \log_2 T \rceil` steps (the last padded with
    ``identity``); (1) the prefixes inside every block, all blocks at once, one step of the block
    after another (``jax.lax.scan``, :math:`L - 1` rounds); (2) the prefixes of the block totals,
    Hillis & Steele (1986) (``_doubling_scan``, :math:`\lceil \log_2 (T/L) \rceil` rounds);
    (3) each block's prefixes combined with the total of the blocks before it (one round). Span
    :math:`L + \lceil \log_2 (T/L) \rceil` rounds, :math:`O(\log T)`; work about
    :math:`2T + (T/L) \lceil \log_2 (T/L) \rceil` combinations, :math:`O(T)` (26 455 at
    :math:`T = 10^4`), where the doubling scan alone does :math:`T \lceil \log_2 T \rceil`
    (140 000). ``op`` is traced three times whatever ``T``, so the compile time does not grow
    with ``T`` (``jax.lax.associative_scan``, with about :math:`2T` combinations against these :math:`2.6T`,
    traces ``op`` twice per level: on the shared two-core CPU of the book, under load, the filter
    took more than two minutes to compile at ``T = 10^3``, a run made while developing, not
    stored)."""
    jax = _jax()
    jnp, tree = jax.numpy, jax.tree_util
    T = tree.tree_leaves(elems)[0].shape[0]
    if T < 2:
        return elems
    L = max(2, int(np.ceil(np.log2(T))))
    nb = -(-T // L)
    fit = lambda ref, a: jnp.broadcast_to(a, ref.shape)  # noqa: E731  op's result to its operand's shape

    def blocks(a, e):  # (T, ...) -> (L, nb, ...): step i of every block, the padding the identity
        a = jnp.concatenate([a, jnp.broadcast_to(e, (nb * L - T,) + a.shape[1:])])
        return jnp.swapaxes(jnp.reshape(a, (nb, L) + a.shape[1:]), 0, 1)

    x = tree.tree_map(blocks, elems, identity)
    first = tree.tree_map(lambda a: a[0], x)

    def step(carry, xi):
        y = tree.tree_map(fit, xi, op(carry, xi))
        return y, y

    total, rest = jax.lax.scan(step, first, tree.tree_map(lambda a: a[1:], x))  # (1)
    inner = tree.tree_map(lambda f, r: jnp.concatenate([f[None], r]), first, rest)
    before = tree.tree_map(lambda a, e: jnp.concatenate([jnp.broadcast_to(e, (1,) + a.shape[1:]), a[:-1]]),
                           _doubling_scan(op, total, identity), identity)  # (2), shifted: the blocks before
    out = tree.tree_map(fit, inner, op(tree.tree_map(lambda a: a[None], before), inner))  # (3)
    return tree.tree_map(lambda a: jnp.reshape(jnp.swapaxes(a, 0, 1), (nb * L,) + a.shape[2:])[:T], out)


def _doubling_scan(op, elems, identity):
    r""":func:`prefix_scan` by recursive doubling (Hillis & Steele 1986): :math:`\lceil \log_2 T \rceil`
    rounds, round ``d`` combining every ``out[k]`` with ``out[k - 2^d]`` (the entries before ``2^d``
    with the identity, selected away), as one ``jax.lax.fori_loop``; work :math:`T \lceil \log_2 T
    \rceil` combinations, ``op`` traced once."""
    jax = _jax()
    jnp, tree = jax.numpy, jax.tree_util
    T = tree.tree_leaves(elems)[0].shape[0]
    if T < 2:
        return elems
    rounds = int(np.ceil(np.log2(T)))
    k = jnp.arange(T)

    def body(d, x):
        s = jnp.left_shift(1, d)
        before = k < s
        prev = tree.tree_map(lambda a, e: jnp.where(jnp.reshape(before, (T,) + (1,) * (a.ndim - 1)),
                                                    jnp.broadcast_to(e, a.shape), jnp.roll(a, s, axis=0)),
                             x, identity)
        y = op(prev, x)
        return tree.tree_map(lambda a, b: jnp.broadcast_to(b, a.shape), x, y)

    return jax.lax.fori_loop(0, rounds, body, elems)


# --------------------------------------------------------------------------------------------
# the scans (compiled once per shapes and options)
# --------------------------------------------------------------------------------------------
def _filter_impl(zs, gone, x0, P0, F, Q, H, R, *, batch, cov_batch, per_step):
    jax = _jax()
    jnp = jax.numpy
    nb, n, T = len(batch), x0.shape[-1], zs.shape[0]
    if not per_step:  # one transition for every step
        F, Q = jnp.broadcast_to(F, (T,) + F.shape), jnp.broadcast_to(Q, (T,) + Q.shape)
    pad = (1,) * (nb - len(cov_batch)) + tuple(cov_batch)  # covariance axes aligned with the run axes

    def cov(a, lead):  # (lead..., *its batch, r, c) -> (lead..., *pad, r, c), broadcast to cov_batch
        own = a.shape[lead:-2]
        a = jnp.reshape(a, a.shape[:lead] + (1,) * (len(cov_batch) - len(own)) + own + a.shape[-2:])
        return jnp.reshape(jnp.broadcast_to(a, a.shape[:lead] + tuple(cov_batch) + a.shape[-2:]),
                           a.shape[:lead] + pad + a.shape[-2:])

    F, Q = cov(F, 1), cov(Q, 1)
    H, R, P0 = cov(H, 0), cov(R, 0), cov(P0, 0)
    g = None if gone is None else jnp.reshape(gone, gone.shape[:1] + (1,) * (nb - gone.ndim + 1) + gone.shape[1:])
    elems = filter_elements(zs, g, x0, P0, F, Q, H, R)
    eye = jnp.eye(n, dtype=zs.dtype)
    zero_v, zero_m = jnp.zeros(n, zs.dtype), jnp.zeros((n, n), zs.dtype)
    _, xs, Ps, _, _ = prefix_scan(combine_filter, elems, (eye, zero_v, zero_m, zero_v, zero_m))
    xs = jnp.broadcast_to(xs, (zs.shape[0],) + tuple(batch) + (n,))
    # the predictions and scores of every step from the filtered sequence: no recursion
    x_pred, P_pred = kf_predict(xs[:-1], Ps[:-1], F[:-1], Q[:-1])
    x_prior = jnp.concatenate([jnp.broadcast_to(x0, (1,) + xs.shape[1:]), jnp.broadcast_to(x_pred, xs[1:].shape)])
    P_prior = jnp.concatenate([jnp.broadcast_to(P0, (1,) + Ps.shape[1:]), jnp.broadcast_to(P_pred, Ps[1:].shape)])
    z = zs if g is None else jnp.where(g[..., None], jnp.zeros((), zs.dtype), zs)
    u = kf_update(x_prior, P_prior, z, H, R)
    nis, ll = (jnp.broadcast_to(a, xs.shape[:-1]) for a in (u.nis, u.loglik))
    if g is not None:
        gb = jnp.broadcast_to(g, xs.shape[:-1])
        nis, ll = jnp.where(gb, jnp.nan, nis), jnp.where(gb, jnp.nan, ll)
    full = (zs.shape[0],) + tuple(batch) + (n, n)
    return (x_prior, jnp.broadcast_to(P_prior, full), xs, jnp.broadcast_to(Ps, full), nis, ll)


def _smoother_impl(x, P, x_prior, P_prior, F):
    jax = _jax()
    jnp = jax.numpy
    elems = smoother_elements(x, P, x_prior, P_prior, F)
    n = x.shape[-1]
    back = lambda tr: jax.tree_util.tree_map(lambda a: jnp.flip(a, 0), tr)  # noqa: E731  last step first
    ident = (jnp.eye(n, dtype=x.dtype), jnp.zeros(n, x.dtype), jnp.zeros((n, n), x.dtype))
    _, xs, Ps = back(prefix_scan(combine_smoother, back(elems), ident))
    return xs, Ps, elems[0][:-1]


@lru_cache(maxsize=1)
def _jits():
    jax = _jax()
    return (jax.jit(_filter_impl, static_argnames=("batch", "cov_batch", "per_step")), jax.jit(_smoother_impl))


# --------------------------------------------------------------------------------------------
# the public functions: validate, then one call
# --------------------------------------------------------------------------------------------
def _engine(raw, checked, dtype):
    """The caller's JAX value (tracers keep flowing), or the checked NumPy value, as a JAX array."""
    return to_engine(raw if use_jax(raw) else checked, True, dtype)


def parallel_filter(zs, x0, P0, F, Q, H, R, *, dt=None, times=None, time_varying: bool = False, dtype=None,
                    missing=None) -> FilterResult:
    r"""The linear Kalman filter of a whole sequence as an associative scan over time
    (Särkkä & García-Fernández 2021; the module docstring gives the elements and their combination).

    The same arguments, conventions and result as :func:`kftrack.kalman.kalman_filter` (which
    runs the sequential recursion), computed with :math:`O(\log T)` span: at step ``k`` update
    with ``zs[k]``, then predict with ``F[k]``, ``Q[k]``.

    Parameters
    ----------
    zs : (T, ..., m) measurements, time first; rows of NaN are missing (or say so with ``missing``).
    x0, P0 : (..., n), (..., n, n) prior of step 0.
    F, Q : ``(n, n)`` or ``(..., n, n)`` constant; callables of ``dt`` with ``dt`` or ``times``; or
        ``(T, ..., n, n)`` stacks with ``time_varying=True`` (as in ``kalman_filter``).
    H, R : (..., m, n), (..., m, m), constant over time; ``R`` positive definite.
    dt, times, time_varying, missing : as in :func:`kftrack.kalman.kalman_filter`.
    dtype : None or ``"float64"`` (default; needs ``jax_enable_x64``), or ``"float32"``.

    Returns
    -------
    FilterResult
        JAX arrays (NumPy or JAX input alike): ``x_prior``, ``P_prior``, ``x``, ``P`` ``(T, ..., n)``,
        ``(T, ..., n, n)``; ``nis``, ``loglik`` ``(T, ...)``, NaN at missing rows. They agree with
        ``kalman_filter`` to round-off (module docstring).

    Raises
    ------
    ValueError, TypeError
        On bad input, naming the argument.

    Examples
    --------
    >>> import jax, numpy as np
    >>> jax.config.update("jax_enable_x64", True)
    >>> from kftrack.models import ConstantVelocity
    >>> from kftrack.kalman import kalman_filter
    >>> from kftrack.parallel import parallel_filter
    >>> cv = ConstantVelocity(ndim=1, q=0.1)
    >>> zs = np.array([[0.0], [1.1], [np.nan], [2.9], [4.2]])
    >>> args = (np.zeros(2), 10 * np.eye(2), cv.F(1.0), cv.Q(1.0), cv.H, np.eye(1))
    >>> par, seq = parallel_filter(zs, *args), kalman_filter(zs, *args)
    >>> print(np.round(np.asarray(par.x[-1]), 6), bool(np.allclose(par.x, seq.x, rtol=0, atol=1e-12)))
    [4.077435 1.02663 ] True
    """
    zs_h, gone = check_missing(zs, missing)
    T, m = zs_h.shape[0], zs_h.shape[-1]
    x0_h, P0_h, n = check_state(stand_in(x0, "vector"), stand_in(P0, "cov"), ("x0", "P0"))
    R_h = check_covariance(stand_in(R, "cov"), "R", m, positive_definite=True, origin=f"m = {m} from zs")
    F_h, Q_h, per_step = _transitions(F, Q, n, T, dt, time_varying, times=times)
    H_h = as_matrix(stand_in(H, "matrix"), "H", m, n, origin=f"m = {m} from zs, n = {n} from x0")
    tb = 1 if per_step else 0
    batch = broadcast_batch({"zs[k]": zs_h.shape[1:-1], "x0": x0_h.shape[:-1], "P0": P0_h.shape[:-2],
                             "F": F_h.shape[tb:-2], "Q": Q_h.shape[tb:-2], "H": H_h.shape[:-2], "R": R_h.shape[:-2]})
    dt_ = check_dtype(dtype, True)
    jnp = _jax().numpy
    timed = dt is not None or times is not None  # F, Q callables: their checked values
    Fj, Qj = _engine(None if timed else F, F_h, dt_), _engine(None if timed else Q, Q_h, dt_)
    cov_shapes = (P0_h.shape[:-2], F_h.shape[tb:-2], Q_h.shape[tb:-2], H_h.shape[:-2], R_h.shape[:-2])
    zs_j = _engine(zs, zs_h, dt_)
    if gone is None:  # only the trace knows the missing rows: per run
        gone_j, cov_batch = jnp.isnan(zs_j).all(-1), batch
    else:
        if gone.ndim > 1:
            flat = gone.reshape(T, -1)
            if (flat == flat[:, :1]).all():
                gone = flat[:, 0]
        cov_batch = np.broadcast_shapes(*cov_shapes, tuple(gone.shape[1:]))
        gone_j = None if not gone.any() else jnp.asarray(gone)
    return FilterResult(*_jits()[0](zs_j, gone_j, _engine(x0, x0_h, dt_), _engine(P0, P0_h, dt_), Fj, Qj,
                                    _engine(H, H_h, dt_), _engine(R, R_h, dt_), batch=tuple(batch),
                                    cov_batch=tuple(cov_batch), per_step=bool(per_step)))


def parallel_smoother(result: FilterResult, F, *, dt=None, times=None, time_varying: bool = False) -> SmootherResult:
    r"""The Rauch–Tung–Striebel smoother as an associative scan backwards in time (Särkkä &
    García-Fernández 2021): the result of :func:`kftrack.kalman.rts_smoother`, with
    :math:`O(\log T)` span.

    Parameters
    ----------
    result : a :class:`~kftrack.results.FilterResult` with its priors (of :func:`parallel_filter`
        or :func:`kftrack.kalman.kalman_filter`).
    F, dt, times, time_varying : the filter's transition, as in :func:`kftrack.kalman.rts_smoother`.

    Returns
    -------
    SmootherResult
        JAX arrays: ``x`` ``(T, ..., n)``, ``P`` ``(T, ..., n, n)``, gains ``G`` ``(T-1, ..., n, n)``.

    Raises
    ------
    ValueError, TypeError
        On bad input, naming the argument.
    """
    if not isinstance(result, FilterResult):
        raise TypeError(f"result must be a FilterResult of parallel_filter or kalman_filter, got "
                        f"{type(result).__name__}")
    if result.x_prior is None or result.P_prior is None:
        raise ValueError("result has no priors (x_prior, P_prior are None): the smoother needs them; run the filter "
                         "with priors=True (the default)")
    shape = tuple(result.x.shape)
    T, n, batch = shape[0], shape[-1], shape[1:-1]
    F_h, per_step = _smoother_transitions(F, dt, times, time_varying, T, n, batch)
    timed = dt is not None or times is not None  # F a function of the interval: the checked stack F_h
    jnp = _jax().numpy
    dt_ = np.dtype(str(result.x.dtype))
    Fj = _engine(None if timed else F, F_h, dt_)
    if not per_step:
        Fj = jnp.broadcast_to(Fj, (T,) + Fj.shape)
    Fb = Fj.shape[1:-2]  # the run axes of F aligned with those of the states
    Fj = jnp.reshape(Fj, (T,) + (1,) * (len(batch) - len(Fb)) + Fb + (n, n))
    if T < 2:
        x, P = (jnp.asarray(a) for a in (result.x, result.P))
        return SmootherResult(x, P, P[:0])
    x, P, x_prior, P_prior = (jnp.asarray(a, dtype=dt_) for a in (result.x, result.P, result.x_prior, result.P_prior))
    return SmootherResult(*_jits()[1](x, P, x_prior, P_prior, Fj))
