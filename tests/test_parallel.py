"""The parallel-in-time filter and smoother (kftrack.parallel, issue 27) against the sequential
engine (kalman_filter, rts_smoother on NumPy arrays), at T = 16 and 1024 with missing rows (the
bound's growth with T exercised over a factor 64); benchmarks/compose.py records the agreement at
T = 10^2 ... 10^4. Each shape is compiled
once, inside the test's own jit at XLA's backend optimisation level 0 (as tests/test_compose.py:
the same computation, so the same bounds, compiled in about half the time).

Bound (kftrack.parallel's module docstring). Every field differs from the sequential engine's by
at most C T n kappa eps max|field|: T steps, n = 4 the state size, C = 10 for the constants of the
operations and the two implementations (as benchmarks/filters.py), added over the T combinations
that feed a step without credit for the filter forgetting old errors, and kappa the largest of

* cond(P^-) and cond(S) over the run (the gains; the smoother's solves with P^-),
* (1 + c j)^2, the bound on cond(I + C_i J_j) of every combination: c bounds the covariance of
  every segment of steps (a segment's C is the covariance of a filter started from Q, which by the
  monotonicity of the Riccati map stays below the full filter's P_k over the same steps: c = max
  ||P_k||), j its information about the state before it (growing with the segment: at most the
  backward information filter's J over the rest of the run, computed below).

Power: the bound is at most 1e-6 relative here; a wrong element or combination (a transposed
gain, a missed step) gives O(1) differences.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kftrack.kalman import kalman_filter, rts_smoother
from kftrack.models import ConstantVelocity
from kftrack.parallel import parallel_filter, parallel_smoother, prefix_scan

jax.config.update("jax_enable_x64", True)  # the engines' float64 default needs it

EPS64, C_BOUND = np.finfo(np.float64).eps, 10.0
MODEL = ConstantVelocity(ndim=2, q=0.5)
F, Q, H = MODEL.F(1.0), MODEL.Q(1.0), MODEL.H
R = np.array([[4.0, 1.5], [1.5, 3.0]])  # correlated, as in tests/test_engines.py
X0, P0 = np.zeros(4), np.diag([50.0, 10.0, 50.0, 10.0])
JIT = {"compiler_options": {"xla_backend_optimization_level": 0}}


def _data(rng, T, runs, missing):
    zs = rng.normal(scale=3.0, size=(T, runs, 2)).cumsum(0)
    if missing in ("shared", "mixed"):
        zs[[0, 7, T // 2]] = np.nan  # every run, the first step too
    if missing == "mixed":
        zs[5, 1] = np.nan  # one run only: per-run covariances
        zs[T - 1, 0] = np.nan
    return zs


def _kappa(res) -> float:
    """The kappa of the module docstring for a sequential result (all runs)."""
    n = F.shape[0]
    Pp = np.asarray(res.P_prior).reshape(-1, n, n)
    S = H @ Pp @ H.T + R
    c = float(np.max(np.linalg.norm(np.asarray(res.P).reshape(-1, n, n), 2, axis=(-2, -1))))
    # backward information filter: Lam = information about x_k from z_k..z_{T-1} (rows used by any run)
    T = res.x.shape[0]
    HRH = H.T @ np.linalg.solve(R, H)
    lam, j = np.zeros((n, n)), 0.0
    for k in range(T - 1, 0, -1):
        lam = lam + HRH
        lam = F.T @ np.linalg.solve(np.eye(n) + lam @ Q, lam) @ F  # about x_{k-1} from z_k..
        j = max(j, float(np.linalg.norm(lam, 2)))
    return float(max(np.linalg.cond(Pp).max(), np.linalg.cond(S).max(), (1.0 + c * j) ** 2))


def _agree(ref, got, T, kappa, names):
    worst = 0.0
    for name, u, v in zip(names, ref, got):
        u, v = np.asarray(u), np.asarray(v)
        assert u.shape == v.shape, name
        assert np.array_equal(np.isnan(u), np.isnan(v)), name
        bound = C_BOUND * T * 4 * kappa * EPS64 * np.nanmax(np.abs(u))
        diff = np.nanmax(np.abs(u - v))
        assert diff <= bound, (name, diff, bound)
        worst = max(worst, diff / bound)
    return worst


# T = 10^4 is recorded by benchmarks/compose.py, not here: under jit with optimisation level 0 the
# one-run 10^4 case stalled for minutes on a loaded 2-core machine (21 s of CPU in 400 s of wall time).
@pytest.mark.parametrize("T, runs, missing", [(16, 3, "mixed"), (1024, 2, "shared")])
def test_parallel_filter_and_smoother_agree_with_the_sequential_engine(T, runs, missing):
    zs = _data(np.random.default_rng(T), T, runs, missing)
    seq = kalman_filter(zs, X0, P0, F, Q, H, R)
    par = jax.jit(lambda z: parallel_filter(z, X0, P0, F, Q, H, R), **JIT)(jnp.asarray(zs))
    assert all(isinstance(v, jax.Array) for v in par)
    kappa = _kappa(seq)
    bound = C_BOUND * T * 4 * kappa * EPS64
    assert bound < 1e-6  # power: far below an O(1) error
    worst = _agree(seq, par, T, kappa, seq._fields)
    # the smoother too (its combination is the filter's algebra's dual)
    sm_seq = rts_smoother(seq, F)
    sm_par = jax.jit(lambda r: parallel_smoother(r, F), **JIT)(par)
    worst = max(worst, _agree(sm_seq, sm_par, T, kappa, sm_seq._fields))
    print(f"T = {T}: kappa {kappa:.3g}, relative bound {bound:.2g}, largest difference / bound {worst:.2g}")


def test_parallel_filter_composes_and_takes_a_mask():
    """Inside jit with a static mask (shared covariances) and under vmap over q, the same numbers."""
    T = 12
    zs = _data(np.random.default_rng(5), T, 2, "shared")
    gone = np.isnan(zs).all(-1)[:, 0]
    z0 = np.where(np.isnan(zs), 0.0, zs)  # missing rows hold anything: the mask says not to use them
    seq = kalman_filter(zs, X0, P0, F, Q, H, R)
    got = jax.jit(lambda z: parallel_filter(z, X0, P0, F, Q, H, R, missing=gone).x, **JIT)(jnp.asarray(z0))
    kappa = _kappa(seq)
    _agree([seq.x], [got], T, kappa, ["x"])
    qs = np.array([0.5, 2.0])
    ll = jax.jit(jax.vmap(lambda q: jnp.nansum(parallel_filter(jnp.asarray(zs), X0, P0, F, q * Q, H, R).loglik)),
                 **JIT)(jnp.asarray(qs))
    for i, q in enumerate(qs):
        ref = kalman_filter(zs, X0, P0, F, q * Q, H, R).loglik
        # a sum of N terms, each within the bound of its own size
        tol = np.sum(np.isfinite(ref)) * C_BOUND * T * 4 * _kappa(kalman_filter(zs, X0, P0, F, q * Q, H, R)) \
            * EPS64 * np.nanmax(np.abs(ref))
        assert abs(float(ll[i]) - np.nansum(ref)) <= tol


def test_parallel_smoother_needs_priors_and_bad_input_names_the_argument():
    zs = _data(np.random.default_rng(0), 5, 1, "none")
    with pytest.raises(ValueError, match="R"):
        parallel_filter(zs, X0, P0, F, Q, H, -R)
    with pytest.raises(ValueError, match="x0"):
        parallel_filter(zs, np.zeros(3), P0, F, Q, H, R)
    with pytest.raises(TypeError, match="result"):
        parallel_smoother(zs, F)
    res = kalman_filter(zs, X0, P0, F, Q, H, R, priors=False)
    with pytest.raises(ValueError, match="priors"):
        parallel_smoother(res, F)


@pytest.mark.parametrize("T", [1, 3, 17, 100, 1000])
def test_prefix_scan_is_the_sequential_fold(T):
    """Blocks of ceil(log2 T) steps, the last padded, then the block totals: every prefix exactly the
    sequential fold, for an associative, non-commutative operation in exact integer arithmetic
    (affine maps x -> a x + b mod p composed), at lengths that fill the blocks and lengths that do not."""
    p = 10007
    rng = np.random.default_rng(T)
    a, b = rng.integers(1, p, T), rng.integers(0, p, T)
    op = lambda f, g: ((g[0] * f[0]) % p, (g[0] * f[1] + g[1]) % p)  # noqa: E731  f first, then g
    got = prefix_scan(op, (jnp.asarray(a), jnp.asarray(b)), (jnp.asarray(1), jnp.asarray(0)))
    ref, acc = [], (1, 0)
    for k in range(T):
        acc = op(acc, (int(a[k]), int(b[k])))
        ref.append(acc)
    assert np.array_equal(np.asarray(got[0]), [r[0] for r in ref])
    assert np.array_equal(np.asarray(got[1]), [r[1] for r in ref])
