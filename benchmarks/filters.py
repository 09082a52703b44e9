"""kftrack's two engines against a naive broadcast, simdkalman, dynamax and filterpy: one process, same data.

Run ``make benchmark`` (installs benchmarks/requirements.txt, then runs this script with the
Makefile's deterministic environment), or ``python benchmarks/filters.py [--quick]``.

Workloads (seeded, float64):

* **KF**: 2-D constant velocity (state ``[x, vx, y, vy]``, n = 4), position measurements (m = 2),
  dt = 1 s, 1000 Monte Carlo runs x 500 steps, every implementation on the same ``zs``;
* **single track** stepped one call at a time (T = 500): ``kftrack.kalman.predict``/``update``
  against filterpy's ``KalmanFilter.predict``/``update``;
* **IMM**: constant velocity + two known-rate turns (+-3 deg/s), 1000 runs x 200 steps.

Reported: filter-steps/s = runs x steps / wall time, the median of interleaved repeats with the
min-max range (JAX: compile time excluded, reported separately); the ratios to kftrack's engines
(ratio of medians, range from the extremes); the issue's targets with PASS/FAIL only when the
whole range clears or misses them; a second size (3-D constant velocity, n = 6, m = 3); the
agreement of every filtered mean with kftrack's NumPy engine, step by step, against a round-off
bound propagated with the filter's closed loop (``agreement_bound_steps``), and a deliberately
perturbed implementation that the check must reject; the flops per filter step and each implementation's fraction of the machine's
measured peak. Then a sweep of steps/s against the number of runs (1 to 1e5).

The whole process is pinned to one CPU core (``os.sched_setaffinity``), so every engine - NumPy
with ``OPENBLAS_NUM_THREADS=1`` and XLA's own thread pool alike - gets the same single core;
the 2-core peak is measured in a subprocess and stated beside the 1-core one.

Outputs (not with ``--quick``, which only prints): ``benchmarks/results.json``,
``book/performance_results.md`` (the tables, included by ``book/performance.md``) and
``book/figures/performance_runs.png``.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PIN_CORE = 0
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, {PIN_CORE})

import numpy as np  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)  # float64 for every JAX implementation
import jax.numpy as jnp  # noqa: E402

import kftrack  # noqa: E402
from kftrack.imm import IMM, KalmanMode, imm_filter  # noqa: E402
from kftrack.kalman import KalmanStepper, kalman_filter, predict, update  # noqa: E402
from kftrack.kernels import kf_predict, kf_update  # noqa: E402
from kftrack.models import ConstantVelocity, KnownTurn  # noqa: E402

EPS = np.finfo(float).eps
DT, Q_DENSITY, SIGMA_Z = 1.0, 0.1, 5.0           # s, m^2/s^3, m
TURN_RATE = np.deg2rad(3.0)                        # rad/s, the two known-rate turns are +-3 deg/s
PI_STAY = 0.95                                     # IMM: probability of staying in a mode per step
C_BOUND = 10.0                                     # constant of the IMM's worst-case bound (agreement_bound)
C_OP = 2.0                                         # constant of one operation's round-off (agreement_bound_steps)
PERTURB_REL = 1e-12                                # the deliberate one-step error the KF check must catch
DYNAMAX_BOOST = 1e-9                               # dynamax psd_solve's diagonal_boost (added to S)

# =============================================================================================
# models and data
# =============================================================================================
def cv_model(ndim: int = 2):
    cv = ConstantVelocity(ndim=ndim, q=Q_DENSITY)
    return cv.F(DT), cv.Q(DT), cv.H, SIGMA_Z**2 * np.eye(ndim)


def simulate(rng, runs: int, steps: int, Fs, Qs, Pi=None, v0=10.0, ndim: int = 2):
    """Truth and measurements ``zs`` ``(steps, runs, ndim)`` of a constant-velocity target in ``ndim``
    dimensions (state ``n = 2 ndim``); with ``Pi`` the model switches as a Markov chain among
    ``Fs[i]``, ``Qs[i]`` (the IMM workload), otherwise ``Fs[0]``, ``Qs[0]`` throughout."""
    Fs, Ls = np.asarray(Fs), np.linalg.cholesky(np.asarray(Qs))
    H = ConstantVelocity(ndim=ndim, q=1.0).H
    n = 2 * ndim
    x = np.zeros((runs, n))
    x[:, 1] = v0
    mode = np.zeros(runs, dtype=int)
    zs = np.empty((steps, runs, ndim))
    for k in range(steps):
        zs[k] = x @ H.T + SIGMA_Z * rng.standard_normal((runs, ndim))
        if Pi is not None:
            u = rng.random(runs)
            mode = (u[:, None] > np.cumsum(Pi[mode], axis=1)).sum(axis=1).clip(0, len(Fs) - 1)
        w = np.einsum("rij,rj->ri", Ls[mode], rng.standard_normal((runs, n)))
        x = np.einsum("rij,rj->ri", Fs[mode], x) + w
    return zs


def prior(v0=10.0):
    return np.array([0.0, v0, 0.0, 0.0]), 100.0 * np.eye(4)


# =============================================================================================
# the implementations: each ``make_*`` returns a callable (no arguments) giving the filtered
# means (steps, runs, 4); data conversion and set-up happen before the clock starts
# =============================================================================================
def naive_kf(zs, x0, P0, F, Q, H, R, perturb=None):
    """The reference: the Kalman filter equations (Joseph form) broadcast over runs, no checks.
    ``perturb = (k, rel)``: multiply the filtered mean of step k by ``1 + rel`` (a deliberately wrong
    implementation, to show that the agreement check can fail)."""
    T, runs, _ = zs.shape
    n = x0.shape[0]
    x, P = np.broadcast_to(x0, (runs, n)).copy(), np.broadcast_to(P0, (runs, n, n)).copy()
    I, out = np.eye(n), np.empty((T, runs, n))
    for k in range(T):
        y = zs[k] - x @ H.T
        PHt = P @ H.T
        S = H @ PHt + R
        K = np.linalg.solve(S, PHt.swapaxes(-1, -2)).swapaxes(-1, -2)  # K = P H^T S^-1
        x = x + (K @ y[..., None])[..., 0]
        if perturb is not None and k == perturb[0]:
            x = x * (1.0 + perturb[1])
        A = I - K @ H
        P = A @ P @ A.swapaxes(-1, -2) + K @ R @ K.swapaxes(-1, -2)
        out[k] = x
        x, P = x @ F.T, F @ P @ F.T + Q
    return out


def is_jax(a) -> bool:
    return isinstance(a, jax.Array)


def block(tree):
    return jax.block_until_ready(tree)


class NotAvailable(Exception):
    """An implementation that cannot run here (the reason is printed)."""


def make_kftrack_numpy(zs, x0, P0, F, Q, H, R):
    return lambda: kalman_filter(zs, x0, P0, F, Q, H, R).x


def make_naive(zs, x0, P0, F, Q, H, R):
    return lambda: naive_kf(zs, x0, P0, F, Q, H, R)


def make_simdkalman(zs, x0, P0, F, Q, H, R):
    import simdkalman

    kf = simdkalman.KalmanFilter(state_transition=F, process_noise=Q, observation_model=H, observation_noise=R)
    data = np.ascontiguousarray(zs.transpose(1, 0, 2))  # simdkalman wants (runs, steps, m); not timed

    def run():
        res = kf.compute(data, 0, initial_value=x0, initial_covariance=P0, smoothed=False, filtered=True,
                         observations=False)
        return res.filtered.states.mean.transpose(1, 0, 2)
    return run


def make_dynamax(zs, x0, P0, F, Q, H, R, means_only: bool = False):
    from dynamax.linear_gaussian_ssm.inference import (ParamsLGSSM, ParamsLGSSMDynamics, ParamsLGSSMEmissions,
                                                       ParamsLGSSMInitial, lgssm_filter)

    n, m = F.shape[0], H.shape[0]

    def params_with(R_):
        return ParamsLGSSM(
            initial=ParamsLGSSMInitial(mean=jnp.asarray(x0), cov=jnp.asarray(P0)),
            dynamics=ParamsLGSSMDynamics(weights=jnp.asarray(F), bias=jnp.zeros(n), input_weights=jnp.zeros((n, 0)),
                                         cov=jnp.asarray(Q)),
            emissions=ParamsLGSSMEmissions(weights=jnp.asarray(H), bias=jnp.zeros(m), input_weights=jnp.zeros((m, 0)),
                                           cov=R_))
    if np.ndim(R) == 3:  # one R per run, mapped by vmap: the covariances are computed per run
        fn = jax.jit(jax.vmap(lambda y, R_: lgssm_filter(params_with(R_), y)))
        data = jax.device_put(jnp.asarray(zs.transpose(1, 0, 2)))
        Rj = jax.device_put(jnp.asarray(np.ascontiguousarray(R)))
        return lambda: jnp.swapaxes(block(fn(data, Rj)).filtered_means, 0, 1)
    params = params_with(jnp.asarray(R))
    # as a user would call it: the whole filtered posterior (means, covariances, log-likelihood) per
    # run, as kftrack returns it; or (means_only) the filtered means alone, which lets XLA drop the
    # per-run copies of the covariances that vmap would otherwise write out
    if means_only:
        fn = jax.jit(jax.vmap(lambda y: lgssm_filter(params, y).filtered_means))
    else:
        fn = jax.jit(jax.vmap(lambda y: lgssm_filter(params, y)))
    data = jax.device_put(jnp.asarray(zs.transpose(1, 0, 2)))  # (runs, steps, m)
    if means_only:
        return lambda: jnp.swapaxes(block(fn(data)), 0, 1)
    return lambda: jnp.swapaxes(block(fn(data)).filtered_means, 0, 1)


def make_dynamax_means(zs, x0, P0, F, Q, H, R):
    return make_dynamax(zs, x0, P0, F, Q, H, R, means_only=True)


def _jax_args(*arrays):
    return [jax.device_put(jnp.asarray(a)) for a in arrays]


def make_kftrack_jax(zs, x0, P0, F, Q, H, R, priors: bool = True):
    args = _jax_args(zs, x0, P0, F, Q, H, R)
    try:
        res = kalman_filter(*args, priors=priors)
    except Exception as exc:  # the engine is being written: report, do not fail
        raise NotAvailable(f"kalman_filter on jax arrays raised {type(exc).__name__}: {str(exc)[:120]}") from None
    if not is_jax(res.x):
        raise NotAvailable("kalman_filter on jax arrays returned NumPy arrays (no JAX engine yet)")
    run = lambda: block(kalman_filter(*args, priors=priors)).x  # noqa: E731
    run.warm_calls = 1  # the call above compiled and ran once: not part of the compile time
    return run


def make_kftrack_jax_posteriors(zs, x0, P0, F, Q, H, R):
    """The JAX engine with ``priors=False``: filtered means and covariances, NIS and log-likelihood
    per step (dynamax's outputs, plus the two per-step scores)."""
    return make_kftrack_jax(zs, x0, P0, F, Q, H, R, priors=False)


FLOOR_LAYOUTS = ("kftrack", "kftrack_posteriors", "dynamax")  # the result layouts of output_floor


def output_floor(T: int, runs: int, n: int, layout: str, repeats: int) -> float:
    """Steps/s of writing only the result arrays of one implementation (no filtering), as one jitted
    call. ``layout``: ``"kftrack"``, the ``FilterResult`` (priors and posteriors, NIS,
    log-likelihood: ``2n + 2n^2 + 2`` numbers per run and step); ``"kftrack_posteriors"``, the
    ``FilterResult`` of ``priors=False`` (posteriors, NIS, log-likelihood: ``n + n^2 + 2``); or
    ``"dynamax"`` (filtered means and covariances: ``n + n^2``, one log-likelihood per run).
    Fresh output buffers are written on every call, as by the filters themselves."""
    posteriors = [(T, runs, n), (T, runs, n, n), (T, runs), (T, runs)]
    shapes = {"kftrack": [(T, runs, n), (T, runs, n, n)] + posteriors, "kftrack_posteriors": posteriors,
              "dynamax": [(runs, T, n), (runs, T, n, n), (runs,)]}[layout]
    fn = jax.jit(lambda a: tuple(jnp.broadcast_to(a * (i + 1), shp) for i, shp in enumerate(shapes)))
    a = jnp.ones(())
    block(fn(a))
    times = []
    for _ in range(max(3, repeats)):
        t0 = time.perf_counter()
        block(fn(a))
        times.append(time.perf_counter() - t0)
    return runs * T / min(times)


def make_filterpy(zs, x0, P0, F, Q, H, R):
    from filterpy.kalman import KalmanFilter

    def run():
        T, runs, _ = zs.shape
        out = np.empty((T, runs, 4))
        for r in range(runs):
            kf = KalmanFilter(dim_x=4, dim_z=2)
            kf.x, kf.P, kf.F, kf.Q, kf.H, kf.R = x0.copy(), P0.copy(), F, Q, H, R
            for k in range(T):
                kf.update(zs[k, r])
                out[k, r] = kf.x
                kf.predict()
        return out
    return run


KF_IMPLS = [  # key, label, maker, engine kind, subset of runs (None: all)
    ("kftrack_numpy", "kftrack `kalman_filter`, NumPy engine (batch)", make_kftrack_numpy, "numpy", None),
    ("naive", "naive NumPy broadcast (15 lines, the reference)", make_naive, "numpy", None),
    ("simdkalman", "simdkalman 1.0.4", make_simdkalman, "numpy", None),
    ("dynamax", "dynamax 1.0.3 `lgssm_filter`, `jit(vmap)`, CPU, float64", make_dynamax, "jax", None),
    ("dynamax_means", "dynamax 1.0.3, as above, returning the filtered means only", make_dynamax_means, "jax", None),
    ("kftrack_jax", "kftrack `kalman_filter`, JAX engine (`lax.scan` under `jit`)", make_kftrack_jax, "jax", None),
    ("kftrack_jax_post", "kftrack `kalman_filter(..., priors=False)`, JAX engine (the outputs of dynamax: filtered "
     "means and covariances, plus NIS and log-likelihood per step)", make_kftrack_jax_posteriors, "jax", None),
    ("filterpy", "filterpy 2.0.0 `KalmanFilter`, loop over runs", make_filterpy, "python", 50),
]


# the same workload with R given once per run (equal values, shape (runs, 2, 2)): no implementation
# can share the covariance recursion between runs, each computes it per run
# the rows of the second size (3-D constant velocity, n = 6, m = 3): the batch engines and peers
KF3_KEYS = ("kftrack_numpy", "naive", "simdkalman", "dynamax", "kftrack_jax", "kftrack_jax_post")

KF_PERRUN_IMPLS = [
    ("kftrack_numpy", "kftrack `kalman_filter`, NumPy engine, per-run R", make_kftrack_numpy, "numpy", None),
    ("naive", "naive NumPy broadcast, per-run R", make_naive, "numpy", None),
    ("dynamax", "dynamax 1.0.3 `jit(vmap)` over data and R, float64", make_dynamax, "jax", None),
    ("kftrack_jax", "kftrack `kalman_filter`, JAX engine, per-run R", make_kftrack_jax, "jax", None),
]


# ---- IMM ------------------------------------------------------------------------------------
def imm_models():
    models = [ConstantVelocity(ndim=2, q=Q_DENSITY), KnownTurn(omega=TURN_RATE, ndim=2, q=Q_DENSITY),
              KnownTurn(omega=-TURN_RATE, ndim=2, q=Q_DENSITY)]
    r = len(models)
    Pi = np.full((r, r), (1.0 - PI_STAY) / (r - 1))
    np.fill_diagonal(Pi, PI_STAY)
    mu0 = np.full(r, 1.0 / r)  # stationary under the symmetric Pi: filterpy's first cbar = mu0 Pi = mu0
    return models, Pi, mu0


def make_imm_numpy(zs, x0, P0):
    models, Pi, mu0 = imm_models()
    R = SIGMA_Z**2 * np.eye(2)
    est = IMM([KalmanMode(m, R) for m in models], Pi, mu0)
    return lambda: imm_filter(est, zs, x0, P0, DT).x


def make_imm_jax(zs, x0, P0):
    models, Pi, mu0 = imm_models()
    R = SIGMA_Z**2 * np.eye(2)
    est = IMM([KalmanMode(m, R) for m in models], Pi, mu0)
    args = _jax_args(zs, x0, P0)
    try:
        res = imm_filter(est, *args, DT)
    except Exception as exc:
        raise NotAvailable(f"imm_filter on jax arrays raised {type(exc).__name__}: {str(exc)[:120]}") from None
    if not is_jax(res.x):
        raise NotAvailable("imm_filter on jax arrays returned NumPy arrays (no JAX engine yet)")
    run = lambda: block(imm_filter(est, *args, DT)).x  # noqa: E731
    run.warm_calls = 1
    return run


def make_imm_filterpy(zs, x0, P0):
    from filterpy.kalman import IMMEstimator, KalmanFilter

    models, Pi, mu0 = imm_models()
    H, R = models[0].H, SIGMA_Z**2 * np.eye(2)
    FQ = [(m.F(DT), m.Q(DT)) for m in models]

    def run():
        T, runs, _ = zs.shape
        out = np.empty((T, runs, 4))
        for r in range(runs):
            filters = []
            for F, Q in FQ:
                kf = KalmanFilter(dim_x=4, dim_z=2)
                kf.x, kf.P, kf.F, kf.Q, kf.H, kf.R = x0.copy(), P0.copy(), F, Q, H, R
                filters.append(kf)
            imm = IMMEstimator(filters, mu0.copy(), Pi)
            for k in range(T):
                imm.update(zs[k, r])
                out[k, r] = imm.x
                if k < T - 1:
                    imm.predict()
        return out
    return run


IMM_IMPLS = [
    ("imm_numpy", "kftrack `imm_filter`, NumPy engine (batch)", make_imm_numpy, "numpy", None),
    ("imm_jax", "kftrack `imm_filter`, JAX engine", make_imm_jax, "jax", None),
    ("imm_filterpy", "filterpy 2.0.0 `IMMEstimator`, loop over runs", make_imm_filterpy, "python", 10),
]


# =============================================================================================
# timing
# =============================================================================================
def time_impl(make, args, repeats: int, jax_kind: bool):
    """``(median wall time, compile time or None, output)``: the first call of a JAX implementation
    compiles (not a repeat); its excess over the median repeat is reported as the compile time."""
    t0 = time.perf_counter()
    run = make(*args)  # may raise NotAvailable; the kftrack JAX makers call once to detect the engine
    t_make = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = run()
    first = time.perf_counter() - t0
    times = [first]
    for _ in range(repeats - 1):
        t0 = time.perf_counter()
        out = run()
        times.append(time.perf_counter() - t0)
    best = float(np.median(times)) if not jax_kind else float(np.median(times[1:] or times))
    compile_s = (t_make + first - best * (1 + getattr(run, "warm_calls", 0))) if jax_kind else None
    return best, compile_s, np.asarray(out)


# =============================================================================================
# accuracy: agreement with kftrack's NumPy engine
# =============================================================================================
def agreement_bound(T: int, n: int, kappa: float) -> float:
    r"""Worst-case round-off bound on the normwise relative difference of two float64 implementations
    of the same recursion: ``C * T * n * kappa * eps``. Used for the IMM only, whose mixing makes the
    closed loop data-dependent and nonlinear (the Kalman filter has the tighter
    ``agreement_bound_steps``).

    Each step commits, per implementation, a relative error of at most ~``n eps`` in its matrix
    products (sums of ``n`` terms) and ``kappa eps`` in the gain (a backward-stable solve with the
    innovation covariance ``S``; ``kappa`` bounds the condition numbers of ``S`` and ``P``).
    Added over ``T`` steps without credit for the filter's contraction of old errors (a
    worst-case, linear accumulation) and for two implementations, with ``C = 10`` covering the
    constants of the individual operations.
    """
    return C_BOUND * T * n * kappa * EPS


def max_rel_diff(x, ref) -> float:
    """max over steps and runs of ``|x - ref|_inf / |ref|_inf``."""
    num = np.max(np.abs(x - ref), axis=-1)
    den = np.max(np.abs(ref), axis=-1)
    return float(np.max(num / den))


def kappa_of(P_prior, H, R):
    """max over steps of cond(P^-) and cond(S) (shared covariance: one track suffices)."""
    n = P_prior.shape[-1]
    P = P_prior.reshape((P_prior.shape[0], -1, n, n))[:, 0]
    S = H @ P @ H.T + R
    return float(max(np.linalg.cond(P).max(), np.linalg.cond(S).max()))


def closed_loop(P_prior, F, H, R):
    """Per step k the gain ``K_k = P_k^- H^T S_k^-1``, ``S_k = H P_k^- H^T + R`` and the closed-loop
    matrix ``M_k = (I - K_k H) F`` of the filtered mean, ``x_k = M_k x_{k-1} + K_k z_k``, from the
    reference's prior covariances ``P_prior`` (T, [runs,] n, n) (run 0: the covariances are those
    of every run, shared or equal per-run R)."""
    P = P_prior if P_prior.ndim == 3 else P_prior[:, 0]
    Rk = R if np.ndim(R) == 2 else R[0]
    S = H @ P @ H.T + Rk
    K = np.linalg.solve(S, (P @ H.T).swapaxes(-1, -2)).swapaxes(-1, -2)
    M = (np.eye(F.shape[0]) - K @ H) @ F
    return P, S, K, M


def propagation_norms(M):
    """``(N, N1)``, ``N[k, j] = |M_k M_{k-1} ... M_{j+1}|_inf`` and ``N1`` the same in the 1-norm
    (``N[k, k] = 1``, 0 for j > k): how much of an error committed at step j is left at step k."""
    T, n = M.shape[0], M.shape[-1]
    N, N1 = np.zeros((T, T)), np.zeros((T, T))
    Phi = np.broadcast_to(np.eye(n), (T, n, n)).copy()  # Phi[j] = M_k ... M_{j+1} after step k
    for k in range(T):
        if k:
            Phi[:k] = M[k] @ Phi[:k]
        A = np.abs(Phi[:k + 1])
        N[k, :k + 1], N1[k, :k + 1] = A.sum(axis=-1).max(axis=-1), A.sum(axis=-2).max(axis=-1)
    return N, N1


def agreement_bound_steps(ref, zs, F, H, R, boost: float = 0.0):
    r"""Round-off bound, per step and run ``(T, runs)``, on ``|x_k - x_k^ref|_inf / |x_k^ref|_inf`` for
    two float64 implementations of the same Kalman filter, accumulated with the filter's actual
    contraction instead of a worst-case ``T``.

    The filtered mean obeys ``x_k = M_k x_{k-1} + K_k z_k`` with ``M_k = (I - K_k H) F``. An error
    ``d_j`` committed at step j is left as ``M_k ... M_{j+1} d_j`` at step k, so the difference of
    the two implementations is at most ``sum_j N[k, j] (d_j + d'_j)`` (``N`` from
    ``propagation_norms``, the products of the computed closed-loop matrices: ``|M_k|`` < 1 at
    steady state, old errors are forgotten). One implementation's local error at step j, to first
    order (``gamma_p = p eps``, the bound of a p-term sum; ``C_OP`` the constant of each operation):

    * mean: predict ``F x`` (n terms) passed through ``I - K H``, then ``H x``, ``z - H x`` and
      ``x + K y`` (m + n terms): ``C_OP eps [n |I-KH| |F| |x_{j-1}| + (n+m)(|x_j^-| + |K|(|z| + |H| |x_j^-|))]``;
    * gain: ``|dK_j| |y_j|`` with ``|dK|/|K| <= (1 + kappa(S)) |dP_j^-| / |P_j^-| + C_OP kappa(S) eps``
      (perturbation of ``K = P^- H^T S^-1`` and a backward-stable solve), where the covariance error
      is the Riccati recursion's own round-off, ``C_OP n eps (1 + kappa_i) |P_i^-|`` at step i,
      propagated by ``M' dP M'^T``, ``M'_i = F (I - K_{i-1} H)``: ``|dP_j^-| <= sum_i |Phi'(j, i)|_inf |Phi'(j, i)|_1 C_OP n eps (1 + kappa_i) |P_i^-|``;
      a deliberate ``boost`` added to S (dynamax's ``diagonal_boost``) adds ``boost |S^-1|`` to the
      relative error of the gain and of S at each step the same way.

    Two implementations: twice one. Everything is computed from the reference run (its ``P^-``,
    ``x``, ``z``), so the bound follows this machine's data, not its round-off: it holds wherever
    the operations are backward stable, which is what LAPACK, OpenBLAS and XLA guarantee.
    """
    T, runs, n = ref.x.shape
    P, S, K, M = closed_loop(ref.P_prior, F, H, R)
    N, _ = propagation_norms(M)
    # the prior covariance's first-order error recursion: dP_k = M'_k dP_{k-1} M'_k^T with
    # M'_k = F (I - K_{k-1} H), so |dP_k|_inf <= |Phi'|_inf |Phi'|_1 |dP|_inf
    Mp = np.concatenate([np.eye(n)[None], F @ (np.eye(n) - K[:-1] @ H)])
    Np, Np1 = propagation_norms(Mp)
    ninf = lambda A: np.abs(A).sum(axis=-1).max(axis=-1)  # noqa: E731  (matrix inf-norm)
    vinf = lambda v: np.abs(v).max(axis=-1)  # noqa: E731
    kap = np.linalg.cond(S)
    Sinv = ninf(np.linalg.inv(S))
    m = H.shape[0]
    # covariance error: local C_OP n eps (1 + kappa) |P| + boost |K|^2-size term, propagated with N^2
    nP = ninf(P)
    local_P = C_OP * n * EPS * (1 + kap) * nP + boost * ninf(K) ** 2
    dP = (Np * Np1) @ local_P
    dK_rel = (1 + kap) * dP / nP + C_OP * kap * EPS + boost * Sinv
    x, xp = ref.x, ref.x_prior                           # (T, runs, n)
    nx, nxp, nz = vinf(x), vinf(xp), vinf(zs)
    nx_prev = np.vstack([np.zeros((1, runs)), nx[:-1]])
    y = zs - np.einsum("ij,trj->tri", H, xp)
    nKy = ninf(K)[:, None] * vinf(y)                     # |dK y| <= |dK| |y|
    IKH = ninf(np.eye(n) - K @ H)[:, None]
    d = (C_OP * EPS * (n * IKH * ninf(F) * nx_prev
                       + (n + m) * (nxp + ninf(K)[:, None] * (nz + ninf(H) * nxp)))
         + dK_rel[:, None] * nKy)
    return 2.0 * (N @ d) / nx


def check_steps(group, ref_x, bound, bound_boost=None):
    """Per implementation of ``group``: the largest ratio over steps and runs of its relative
    difference from ``ref_x`` to the per-step ``bound`` (T, runs) (``bound_boost`` for dynamax,
    whose ``diagonal_boost`` perturbs the model); ``agrees`` when it is at most 1."""
    ok_all = True
    for key, rec in group.items():
        x = rec.get("_x")
        if x is None:
            continue
        b = bound_boost if key.startswith("dynamax") and bound_boost is not None else bound
        b = b[:, :rec["runs"]]
        ratio = float(np.max(rel_diff_steps(x, ref_x[:, :rec["runs"]]) / b))
        rec.update(bound_ratio=ratio, bound=float(b.max()), bound_min=float(b.min()), agrees=bool(ratio <= 1.0),
                   boost_in_bound=b is bound_boost)
        ok_all &= ratio <= 1.0
    return ok_all


def rel_diff_steps(x, ref):
    """``|x - ref|_inf / |ref|_inf`` per step and run, (T, runs)."""
    return np.max(np.abs(x - ref), axis=-1) / np.max(np.abs(ref), axis=-1)


# =============================================================================================
# flops and the physical limit
# =============================================================================================
def kf_flops(n: int, m: int) -> int:
    """Floating-point operations of one KF step (update with Joseph form + predict) for one run,
    counted as the equations are written in kftrack.kernels (a product (a,b)@(b,c) = 2abc)."""
    mm = lambda a, b, c: 2 * a * b * c  # noqa: E731
    predict_ = mm(n, n, 1) + 2 * mm(n, n, n) + n * n + 2 * n * n                # Fx, F P F^T, + Q, sym
    update_ = (mm(m, n, 1) + m                                                    # y = z - Hx
               + mm(n, n, m) + mm(m, n, m) + m * m + 2 * m * m                    # S = H (P H^T) + R, sym
               + (2 * m**3) // 3 + 2 * m * m * n                                 # LU of S, K = P H^T S^-1
               + mm(n, m, 1) + n                                                  # x + K y
               + mm(n, m, n) + n                                                  # I - K H
               + 2 * mm(n, n, n) + mm(n, m, m) + mm(n, m, n) + n * n + 2 * n * n  # Joseph form, sym
               + 2 * m * m + 2 * m + (2 * m**3) // 3)                            # NIS, log-likelihood
    return predict_ + update_


def kf_mean_flops(n: int, m: int) -> int:
    """Flops per run of the mean recursion alone (what a run costs when the covariance, gain and
    S are shared by all runs): y = z - Hx, x + K y, F x, and the NIS/log-likelihood of y."""
    return (2 * m * n + m) + (2 * n * m + n) + 2 * n * n + (2 * m * m + 2 * m)


def imm_flops(n: int, m: int, r: int) -> int:
    """One IMM cycle for one run: r mode-matched KF steps, the mixing of r x r Gaussians (means:
    2n per term; covariances: difference, outer product, add, weighted sum, 4n^2 + n per term),
    the combination (r terms) and the mode probabilities (~10 flops per log-sum-exp term)."""
    gauss = 4 * n * n + 3 * n
    return r * kf_flops(n, m) + r * r * gauss + r * gauss + 10 * r * r + 10 * r


PEAK_CODE = r"""
import os, time, numpy as np
if hasattr(os, "sched_setaffinity"):
    os.sched_setaffinity(0, set(range({cores})))
N = 2048
rng = np.random.default_rng(0)
a, b = rng.standard_normal((N, N)), rng.standard_normal((N, N))
a @ b
best = min((lambda t0: (a @ b, time.perf_counter() - t0)[1])(time.perf_counter()) for _ in range({reps}))
print(2 * N**3 / best)
"""


def peak_flops(cores: int, reps: int) -> float | None:
    """Measured float64 peak: best of ``reps`` 2048x2048 matmuls (OpenBLAS) on ``cores`` cores,
    in a subprocess with ``OPENBLAS_NUM_THREADS=cores``."""
    if cores > (os.cpu_count() or 1):
        return None
    env = dict(os.environ, OPENBLAS_NUM_THREADS=str(cores), OMP_NUM_THREADS=str(cores),
               MKL_NUM_THREADS=str(cores))
    out = subprocess.run([sys.executable, "-c", PEAK_CODE.format(cores=cores, reps=reps)], env=env,
                         capture_output=True, text=True, check=True)
    return float(out.stdout.strip())


# =============================================================================================
# machine
# =============================================================================================
def machine() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import jaxlib
    return {
        "cpu": cpu, "logical_cores": os.cpu_count(), "pinned_to_core": PIN_CORE,
        "python": platform.python_version(), "numpy": np.__version__, "jax": jax.__version__,
        "jaxlib": jaxlib.__version__, "kftrack": getattr(kftrack, "__version__", "dev"),
        "threads": {k: os.environ.get(k, "unset") for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                             "MKL_NUM_THREADS", "XLA_FLAGS")},
        "date": datetime.date.today().isoformat(),
        "load_average_at_start": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }


# =============================================================================================
# formatting
# =============================================================================================
def fmt_rate(v) -> str:
    if v is None:
        return "n/a"
    for unit, s in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if v >= unit:
            return f"{v / unit:.3g} {s}"
    return f"{v:.3g}"


def fmt_ratio(a, b) -> str:
    if a is None or b is None:
        return "n/a"
    v = a / b
    return f"{v:.0f}" if v >= 100 else f"{v:.2g}"


def fmt_bound(v) -> str:
    """A round-off figure as the power of ten it stays below (no round-off digits printed)."""
    if v is None:
        return "n/a"
    if v == 0:
        return "0 (bitwise)"
    return f"below 1e{math.ceil(math.log10(v))}"


def md_table(header, rows) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


# =============================================================================================
# the benchmark
# =============================================================================================
def run_group(impls, make_args_full, T, runs, repeats, ref_key, label):
    """Time every implementation of a group on the same data; returns {key: record}.

    The repeats are interleaved (round robin over the implementations), so that a burst of load
    from other jobs on the machine hits every implementation alike rather than one of them; each
    implementation's rate is the median of its repeats, with the min-max range (``rate_min``,
    ``rate_max``) and every repeat (``rates``). A JAX implementation's first call (compilation)
    is not a repeat, nor is any implementation's first call (a warm-up: caches, lazy imports, and
    the compilation of the jit-compiled single-step kernels, which run_group times as NumPy)."""
    out, live = {}, {}
    for key, name, make, kind, subset in impls:
        r_used = runs if subset is None else min(subset, runs)
        rec = {"label": name, "kind": kind, "runs": r_used, "steps": T, "available": True}
        out[key] = rec
        try:
            t0 = time.perf_counter()
            run = make(*make_args_full(r_used))  # the kftrack JAX makers call once to detect the engine
            t_make = time.perf_counter() - t0
        except NotAvailable as exc:
            rec.update(available=False, reason=str(exc), rate=None)
            print(f"  {name:62s} not available: {exc}")
            continue
        t0 = time.perf_counter()
        xs = np.asarray(run())
        first = time.perf_counter() - t0
        n_rep = max(2, repeats // 2) if kind == "python" else repeats
        live[key] = {"run": run, "times": [], "first": first + t_make,  # the first call is a warm-up
                     "warm": getattr(run, "warm_calls", 0),
                     "n": n_rep, "kind": kind}
        rec["_x"] = xs
    for _ in range(repeats):
        for key, st in live.items():
            if len(st["times"]) >= st["n"]:
                continue
            t0 = time.perf_counter()
            st["run"]()
            st["times"].append(time.perf_counter() - t0)
    for key, st in live.items():
        rec = out[key]
        med = float(np.median(st["times"]))
        comp = st["first"] - med * (1 + st["warm"]) if st["kind"] == "jax" else None
        rates = [rec["runs"] * T / t for t in st["times"]]  # every repeat: the spread
        rec.update(time_s=med, rate=rec["runs"] * T / med, compile_s=comp, rates=rates,
                   rate_min=min(rates), rate_max=max(rates), repeats=len(rates))
        extra = f"  (compile {comp:.2f} s)" if comp is not None else ""
        sub = f"  [{rec['runs']} of {runs} runs]" if rec["runs"] != runs else ""
        print(f"  {rec['label']:62s} {fmt_rate(rec['rate']):>9s} steps/s ({fmt_rate(rec['rate_min'])}-"
              f"{fmt_rate(rec['rate_max'])}, {len(rates)} repeats){extra}{sub}")
    ref = out[ref_key]["_x"]
    out[ref_key]["reference"] = True
    for rec in out.values():
        if rec.get("_x") is not None:
            rec["max_rel_diff"] = max_rel_diff(rec["_x"], ref[:, :rec["runs"]])
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes, few repeats; prints only, writes nothing")
    ap.add_argument("--render-only", action="store_true",
                    help="re-write the page fragment and the figure from benchmarks/results.json, no timing")
    opts = ap.parse_args(argv)
    if opts.render_only:
        res = json.loads((ROOT / "benchmarks" / "results.json").read_text())
        (ROOT / "book" / "performance_results.md").write_text(render_markdown(res))
        fl = res["flops_per_step"]
        plot_sweep(res["sweep"], ROOT / "book" / "figures" / "performance_runs.png", res["peak_flops"]["1_core"],
                   fl["kf"], fl["kf_mean_only"])
        return res
    q = opts.quick
    RUNS, T_KF, T_IMM, T_SINGLE = (100, 100, 50, 100) if q else (1000, 500, 200, 500)
    REPEATS = 3 if q else 7
    t_start = time.perf_counter()
    mach = machine()
    print(f"machine: {mach['cpu']}, {mach['logical_cores']} logical cores (this process pinned to core "
          f"{PIN_CORE}), Python {mach['python']}, NumPy {mach['numpy']}, jax/jaxlib {mach['jax']}/{mach['jaxlib']}")
    print(f"threads: {mach['threads']}; date {mach['date']}")

    # ---- physical limit ---------------------------------------------------------------------
    peak1 = peak_flops(1, 3 if q else 10)  # best of 10: the machine is shared, the best run is the peak
    peak2 = peak_flops(2, 3 if q else 10)
    n, m, r = 4, 2, 3
    f_kf, f_mean, f_imm = kf_flops(n, m), kf_mean_flops(n, m), imm_flops(n, m, r)
    print(f"peak float64 (2048^2 matmul, OpenBLAS): 1 core {peak1 / 1e9:.1f} GFLOP/s"
          + (f", 2 cores {peak2 / 1e9:.1f} GFLOP/s" if peak2 else ""))
    print(f"flops per filter step and run: KF {f_kf} (mean recursion alone {f_mean}), IMM ({r} modes) {f_imm}")
    print(f"physical limit on 1 core: KF {fmt_rate(peak1 / f_kf)} steps/s "
          f"(mean alone {fmt_rate(peak1 / f_mean)}), IMM {fmt_rate(peak1 / f_imm)} steps/s")

    # ---- KF workload -----------------------------------------------------------------------
    F, Q, H, R = cv_model()
    x0, P0 = np.zeros(4), 100.0 * np.eye(4)
    zs = simulate(np.random.default_rng(2026), RUNS, T_KF, [F], [Q])
    print(f"\nKF: 2-D constant velocity (n = 4, m = 2, dt = 1 s), {RUNS} runs x {T_KF} steps, "
          f"median of {REPEATS} interleaved repeats (filterpy: {max(2, REPEATS // 2)})")
    kf = run_group(KF_IMPLS, lambda k: (zs[:, :k], x0, P0, F, Q, H, R), T_KF, RUNS, REPEATS, "kftrack_numpy", "KF")
    ref_full = kalman_filter(zs, x0, P0, F, Q, H, R)
    kappa_kf = kappa_of(ref_full.P_prior, H, R)
    # the per-step bound propagated with the filter's own contraction (agreement_bound_steps);
    # dynamax adds diagonal_boost = 1e-9 to S before its Cholesky solve (dynamax.utils.utils.psd_solve),
    # a model perturbation, not round-off, carried through the same propagation
    bnd_kf = agreement_bound_steps(ref_full, zs, F, H, R)
    bnd_kf_dm = agreement_bound_steps(ref_full, zs, F, H, R, boost=DYNAMAX_BOOST)
    ok_kf = check_steps(kf, ref_full.x, bnd_kf, bnd_kf_dm)
    # the check must be able to fail: the naive reference with its filtered mean multiplied by
    # 1 + PERTURB_REL at one step (T/2), a relative error of 1e-12 in one step and nothing else
    k_pert = T_KF // 2
    x_pert = naive_kf(zs, x0, P0, F, Q, H, R, perturb=(k_pert, PERTURB_REL))
    pert_ratio = float(np.max(rel_diff_steps(x_pert, ref_full.x) / bnd_kf))
    perturbation = {"step": k_pert, "rel": PERTURB_REL, "bound_ratio": pert_ratio, "detected": pert_ratio > 1.0,
                    "bound_at_step_max": float(bnd_kf[k_pert].max()), "bound_at_step_min": float(bnd_kf[k_pert].min())}
    print(f"  agreement (per-step bound, {bnd_kf.min():.2g} to {bnd_kf.max():.2g}): "
          + ", ".join(f"{k} {v['bound_ratio']:.2g} of it" for k, v in kf.items() if "bound_ratio" in v))
    print(f"  perturbed naive (x * (1 + {PERTURB_REL:g}) at step {k_pert}): {pert_ratio:.3g} x the bound -> "
          f"{'detected' if pert_ratio > 1 else 'NOT DETECTED'}")
    floor = {lay: output_floor(T_KF, RUNS, n, lay, REPEATS) for lay in FLOOR_LAYOUTS}
    print(f"  writing the result arrays alone (no filtering): kftrack's {fmt_rate(floor['kftrack'])} steps/s, "
          f"kftrack's with priors=False {fmt_rate(floor['kftrack_posteriors'])}, "
          f"dynamax's {fmt_rate(floor['dynamax'])} steps/s")

    Rb = np.broadcast_to(R, (RUNS, 2, 2))
    print(f"\nKF with one R per run (equal values, shape ({RUNS}, 2, 2)): the covariance recursion per run")
    kf_perrun = run_group(KF_PERRUN_IMPLS, lambda k: (zs[:, :k], x0, P0, F, Q, H, Rb[:k]), T_KF, RUNS, REPEATS,
                          "kftrack_numpy", "KF per-run R")
    ok_perrun = check_steps(kf_perrun, ref_full.x, bnd_kf, bnd_kf_dm)  # equal R values: the same reference

    # ---- a second size: 3-D constant velocity, n = 6, m = 3 ----------------------------------
    F3, Q3, H3, R3 = cv_model(ndim=3)
    x03, P03 = np.zeros(6), 100.0 * np.eye(6)
    zs3 = simulate(np.random.default_rng(2029), RUNS, T_KF, [F3], [Q3], ndim=3)
    print(f"\nKF 3-D constant velocity (n = 6, m = 3), {RUNS} runs x {T_KF} steps")
    kf3 = run_group([i for i in KF_IMPLS if i[0] in KF3_KEYS], lambda k: (zs3[:, :k], x03, P03, F3, Q3, H3, R3),
                    T_KF, RUNS, REPEATS, "kftrack_numpy", "KF 3-D")
    ref3 = kalman_filter(zs3, x03, P03, F3, Q3, H3, R3)
    bnd3 = agreement_bound_steps(ref3, zs3, F3, H3, R3)
    ok_kf3 = check_steps(kf3, ref3.x, bnd3, agreement_bound_steps(ref3, zs3, F3, H3, R3, boost=DYNAMAX_BOOST))

    # ---- single track stepped --------------------------------------------------------------
    print(f"\nsingle track stepped one call at a time (T = {T_SINGLE}), median of {REPEATS}")
    z1 = zs[:T_SINGLE, 0]

    def kftrack_steps():
        x, P, out = x0, P0, np.empty((T_SINGLE, 4))
        for k in range(T_SINGLE):
            u = update(x, P, z1[k], H, R)
            out[k] = u.x
            x, P = predict(u.x, u.P, F, Q)
        return out

    def object_steps(f):  # a filter object with update(z), predict() and x: filterpy's and kftrack's stepper
        out = np.empty((T_SINGLE, 4))
        for k in range(T_SINGLE):
            f.update(z1[k])
            out[k] = f.x
            f.predict()
        return out

    def filterpy_steps():
        from filterpy.kalman import KalmanFilter
        f = KalmanFilter(dim_x=4, dim_z=2)
        f.x, f.P, f.F, f.Q, f.H, f.R = x0.copy(), P0.copy(), F, Q, H, R
        return object_steps(f)

    def stepper_steps():  # validated once; the kernels, the covariances reused once they repeat to the last bit
        s = KalmanStepper(x0, P0, F, Q, H, R)
        out = object_steps(s)
        stepper_steps.reused_from = s.reused_from
        return out

    def kernel_steps():  # the unchecked kernels alone, the whole recursion at every step
        x, P, out = x0, P0, np.empty((T_SINGLE, 4))
        for k in range(T_SINGLE):
            u = kf_update(x, P, z1[k], H, R)
            out[k] = u.x
            x, P = kf_predict(u.x, u.P, F, Q)
        return out

    jstep = jax.jit(lambda x, P, z, F_, Q_, H_, R_: (lambda u: (u.x,) + tuple(kf_predict(u.x, u.P, F_, Q_)))(
        kf_update(x, P, z, H_, R_)))
    jFQHR = _jax_args(F, Q, H, R)
    jz = [jax.device_put(jnp.asarray(z)) for z in z1]
    jx0, jP0 = _jax_args(x0, P0)

    def jit_kernel_steps():  # the same kernels, one jit-compiled step per call (a JAX stepper's floor)
        x, P, out = jx0, jP0, []
        for k in range(T_SINGLE):
            xk, x, P = jstep(x, P, jz[k], *jFQHR)
            out.append(xk)
        return np.asarray(block(jnp.stack(out)))

    def as_run(fn):  # a maker for run_group: (steps, 1 run, n)
        return lambda: (lambda: fn()[:, None])

    single = run_group([("kftrack_step", "kftrack `predict` + `update`, one call each per step", as_run(kftrack_steps),
                         "numpy", None),
                        ("stepper_step", "kftrack `KalmanStepper.predict` + `update`", as_run(stepper_steps),
                         "numpy", None),
                        ("filterpy_step", "filterpy 2.0.0 `KalmanFilter.predict` + `update`", as_run(filterpy_steps),
                         "numpy", None),
                        ("kernels_step", "kftrack.kernels `kf_update` + `kf_predict` (unchecked)", as_run(kernel_steps),
                         "numpy", None),
                        ("jit_kernels_step", "the same kernels as one `jax.jit` step, called once per step",
                         as_run(jit_kernel_steps), "numpy", None)],
                       lambda k: (), T_SINGLE, 1, REPEATS, "kftrack_step", "single")
    for rec in single.values():
        rec["us_per_step"] = 1e6 * rec["time_s"] / T_SINGLE
    # the stepper's two phases: the whole recursion until the covariances repeat, the mean alone after
    rf = stepper_steps.reused_from
    if rf is not None and 0 < rf < T_SINGLE:
        phase = [np.inf, np.inf]
        for _ in range(REPEATS):
            s = KalmanStepper(x0, P0, F, Q, H, R)
            for i, ks in enumerate((range(rf), range(rf, T_SINGLE))):
                t0 = time.perf_counter()
                for k in ks:
                    s.update(z1[k])
                    s.predict()
                phase[i] = min(phase[i], time.perf_counter() - t0)
        single["stepper_step"].update(reused_from=int(rf), us_before_reuse=1e6 * phase[0] / rf,
                                      us_after_reuse=1e6 * phase[1] / (T_SINGLE - rf))
        print(f"  stepper: covariances reused from update {rf + 1} (1-based) on; {1e6 * phase[0] / rf:.1f} us per step before, "
              f"{1e6 * phase[1] / (T_SINGLE - rf):.1f} us after")
    ref_single = kalman_filter(zs[:T_SINGLE, :1], x0, P0, F, Q, H, R)  # the stepped track's data, batched
    bnd_single = agreement_bound_steps(ref_single, zs[:T_SINGLE, :1], F, H, R)
    ok_single = check_steps(single, single["kftrack_step"]["_x"], bnd_single)

    # ---- IMM ---------------------------------------------------------------------------------
    models, Pi, _ = imm_models()
    xi0, Pi0 = prior()
    zs_imm = simulate(np.random.default_rng(2027), RUNS, T_IMM, [mm.F(DT) for mm in models],
                      [mm.Q(DT) for mm in models], Pi)
    print(f"\nIMM: CV + two known-rate turns (+-{np.rad2deg(TURN_RATE):.0f} deg/s), {RUNS} runs x {T_IMM} steps, "
          f"median of {max(2, REPEATS - 2)} interleaved repeats (filterpy: 2)")
    imm = run_group(IMM_IMPLS, lambda k: (zs_imm[:, :k], xi0, Pi0), T_IMM, RUNS, max(2, REPEATS - 2),
                    "imm_numpy", "IMM")
    # kappa of the IMM: the largest condition number of P^- and S of each mode-matched filter run
    # alone on one track of the IMM data (the mixing adds spread-of-means terms to P, which
    # only make it better conditioned)
    kappa_imm = max(kappa_of(kalman_filter(zs_imm[:, :1], xi0, Pi0, mm_.F(DT), mm_.Q(DT), H, R).P_prior, H, R)
                    for mm_ in models)
    bound_imm = agreement_bound(T_IMM, n, kappa_imm)

    # ---- ratios, limits, targets -------------------------------------------------------------
    def rate(g, k):
        return g[k]["rate"] if k in g and g[k].get("available", True) else None

    np_rate, jx_rate = rate(kf, "kftrack_numpy"), rate(kf, "kftrack_jax")
    jx_post = rate(kf, "kftrack_jax_post")  # priors=False: dynamax's outputs (plus NIS, log-likelihood per step)
    f_kf3 = kf_flops(6, 3)
    for g, flops in ((kf, f_kf), (kf_perrun, f_kf), (kf3, f_kf3), (imm, f_imm)):
        for rec in g.values():
            rec["fraction_of_limit"] = None if rec["rate"] is None else rec["rate"] * flops / peak1
    for rec in single.values():
        rec["fraction_of_limit"] = rec["rate"] * f_kf / peak1

    def check(name, a, b, need, aim=None):
        sp = ratio_spread(a, b)
        ratio, lo, hi = sp if sp else (None, None, None)
        status = verdict(lo, hi, need)
        if name not in LIKE_FOR_LIKE and ratio is not None:
            status = "reported"  # different work on the two sides: a ratio, no verdict
        return {"target": name, "ratio": ratio, "ratio_min": lo, "ratio_max": hi, "need": need, "aim": aim,
                "status": status}

    targets = [
        check("NumPy engine vs naive broadcast", kf["kftrack_numpy"], kf["naive"], 1.3),
        check("NumPy engine vs simdkalman", kf["kftrack_numpy"], kf["simdkalman"], 3.0),
        check("single track stepped vs filterpy", single["stepper_step"], single["filterpy_step"], 1.5),
        check("JAX engine vs dynamax (same outputs)", kf["kftrack_jax_post"], kf["dynamax"], 1.0, 1.5),
        check("JAX IMM vs NumPy IMM", imm["imm_jax"], imm["imm_numpy"], 50.0),
    ]

    print("\nratios and targets")
    print(f"  {'implementation':62s} {'steps/s':>9s}  {'kftrack NumPy / it':>18s}  {'kftrack JAX / it':>16s}  "
          f"{'% of 1-core limit':>17s}")
    for g, ref_np, ref_jx in ((kf, np_rate, jx_rate), (kf_perrun, rate(kf_perrun, "kftrack_numpy"),
                                                        rate(kf_perrun, "kftrack_jax")),
                              (imm, rate(imm, "imm_numpy"), rate(imm, "imm_jax"))):
        for rec in g.values():
            frac = "n/a" if rec.get("fraction_of_limit") is None else f"{100 * rec['fraction_of_limit']:.2g}"
            print(f"  {rec['label']:62s} {fmt_rate(rec['rate']):>9s}  {fmt_ratio(ref_np, rec['rate']):>18s}  "
                  f"{fmt_ratio(ref_jx, rec['rate']):>16s}  {frac:>17s}")
    for t in targets:
        ratio = "n/a" if t["ratio"] is None else f"{t['ratio']:.2f}x ({t['ratio_min']:.2f}-{t['ratio_max']:.2f})"
        aim = f" (aim {t['aim']}x)" if t["aim"] else ""
        print(f"  target {t['target']:38s} >= {t['need']}x{aim}: measured {ratio:>20s}  {t['status']}")
    print(f"  (the JAX targets use kalman_filter(..., priors=False); with its full output, priors too, the JAX engine "
          f"runs at {fmt_ratio(jx_rate, rate(kf, 'dynamax'))}x dynamax's rate)")

    print("\nagreement of the filtered means with kftrack's NumPy engine (max over steps and runs of "
          "|dx|_inf / |x|_inf)")
    print(f"  KF (2-D and 3-D, per-run R, single track): the per-step bound propagated with the closed loop "
          f"(C_OP = {C_OP:g}); IMM: C*T*n*kappa*eps, C = {C_BOUND:g}, T = {T_IMM}, kappa = {kappa_imm:.3g} "
          f"-> {bound_imm:.2g}")
    ok_imm = True
    for rec in imm.values():
        d = rec.get("max_rel_diff")
        if d is not None:
            rec.update(agrees=bool(d <= bound_imm), bound=bound_imm)
            ok_imm &= d <= bound_imm
    ok_all = bool(ok_kf and ok_perrun and ok_kf3 and ok_single and ok_imm)
    for g in (kf, kf_perrun, kf3, single, imm):
        for rec in g.values():
            d = rec.get("max_rel_diff")
            if d is None:
                continue
            extra = (f", {rec['bound_ratio']:.2g} of its per-step bound (max {rec['bound']:.2g})"
                     if "bound_ratio" in rec else f" (bound {rec['bound']:.2g})")
            print(f"  {rec['label']:62s} {d:9.2e}  {'within' if rec['agrees'] else 'OUTSIDE'}{extra}")
    print(f"  all agree: {ok_all}; the perturbed implementation: {pert_ratio:.3g} x its bound "
          f"({'detected' if perturbation['detected'] else 'NOT DETECTED'})")

    # ---- the sweep -----------------------------------------------------------------------------
    sweep = run_sweep(kf, q, F, Q, H, R, x0, P0)

    total = time.perf_counter() - t_start
    load_end = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    print(f"\ntotal benchmark time {total:.0f} s; 1-minute load average {mach['load_average_at_start']:.1f} at the "
          f"start, {load_end:.1f} at the end ({mach['logical_cores']} logical cores)")
    mach["load_average_at_end"] = load_end
    results = {
        "machine": mach, "command": "make benchmark   (python benchmarks/filters.py)", "quick": q,
        "peak_flops": {"1_core": peak1, "2_cores": peak2},
        "flops_per_step": {"kf": f_kf, "kf_mean_only": f_mean, "imm": f_imm, "n": n, "m": m, "imm_modes": r},
        "workload": {"runs": RUNS, "kf_steps": T_KF, "imm_steps": T_IMM, "single_steps": T_SINGLE, "dt": DT,
                     "q": Q_DENSITY, "sigma_z": SIGMA_Z, "turn_rate_deg_s": float(np.rad2deg(TURN_RATE))},
        "kf": strip(kf), "kf_output_floor": floor, "kf_perrun": strip(kf_perrun), "single": strip(single),
        "imm": strip(imm), "targets": targets, "repeats": REPEATS,
        "kf3": strip(kf3), "kf3_flops_per_step": f_kf3,
        "agreement": {"C": C_BOUND, "C_OP": C_OP, "kappa_kf": kappa_kf, "kappa_imm": kappa_imm,
                      "bound_kf": float(bnd_kf.max()), "bound_kf_min": float(bnd_kf.min()),
                      "bound_kf_end": float(bnd_kf[-1].max()), "bound_kf3": float(bnd3.max()),
                      "bound_single": float(bnd_single.max()), "bound_imm": bound_imm,
                      "perturbation": perturbation, "all_agree": ok_all},
        "sweep": sweep, "total_s": total,
    }
    if not q:
        (ROOT / "benchmarks" / "results.json").write_text(json.dumps(results, indent=1) + "\n")
        (ROOT / "book" / "performance_results.md").write_text(render_markdown(results))
        plot_sweep(sweep, ROOT / "book" / "figures" / "performance_runs.png", peak1, f_kf, f_mean)
        print("wrote benchmarks/results.json, book/performance_results.md, book/figures/performance_runs.png")
    return results


def ratio_spread(a, b):
    """``(median ratio, min, max)`` of rate(a) / rate(b): the ratio of the medians, its range from the
    extremes (a's slowest over b's fastest to a's fastest over b's slowest), as benchmarks/compose.py;
    None when either side is not available."""
    if not (a.get("available", True) and b.get("available", True) and a.get("rate") and b.get("rate")):
        return None
    amin, amax = a.get("rate_min", a["rate"]), a.get("rate_max", a["rate"])
    bmin, bmax = b.get("rate_min", b["rate"]), b.get("rate_max", b["rate"])
    return a["rate"] / b["rate"], amin / bmax, amax / bmin


def verdict(lo, hi, need) -> str:
    """PASS only when the whole range of the ratio clears ``need``, FAIL when none of it does."""
    if lo is None:
        return "not available"
    return "PASS" if lo >= need else "FAIL" if hi < need else "not resolved by the spread"


def strip(group):
    return {k: {kk: vv for kk, vv in v.items() if not kk.startswith("_")} for k, v in group.items()}


# =============================================================================================
# sweep over the number of runs
# =============================================================================================
SWEEP_RUNS = (1, 10, 100, 1000, 10_000, 100_000)


def run_sweep(kf, quick, F, Q, H, R, x0, P0):
    """steps/s against the number of runs. Steps per point: enough for ~0.4 s at the rate
    measured above (between 10 and 500); a point that would still take more than
    ``limit`` seconds at 10 steps is skipped and listed. The point of the main table's workload
    (its number of runs, at its steps) is the main table's measurement, not a second one: measured
    twice, in two windows of a shared machine (the sweep timed each implementation in one
    contiguous window, best of 3; the main table interleaved them, best of 5), the same workload
    gave 2.85 M and 1.55 M steps/s (issue 24). Other points: the median of ``reps`` calls."""
    target, limit, reps = (0.05, 0.5, 2) if quick else (0.4, 5.0, 3)
    runs_list = SWEEP_RUNS[:-2] if quick else SWEEP_RUNS
    print(f"\nsweep: steps/s against the number of runs (steps per point for ~{target} s; median of {reps})")
    rng = np.random.default_rng(2028)
    data = {}
    out = {"runs": list(runs_list), "impls": {}}
    for key, name, make, kind, _ in KF_IMPLS:
        base = kf[key].get("rate")
        if base is None:
            out["impls"][key] = {"label": name, "available": False, "points": []}
            print(f"  {name:62s} not available")
            continue
        pts, skipped = [], []
        for runs in runs_list:
            # the slow peers' rate does not grow with runs; estimate with the measured rate
            est_rate = base if kind == "python" or runs >= 1000 else base * runs / 1000 + 1e-9
            steps = int(np.clip(est_rate * target / runs, 10, 500))
            if runs * 10 / base > limit and kind != "jax" and runs > 1000:
                skipped.append(runs)
                continue
            main = kf[key]
            if runs == main["runs"] and main.get("time_s"):  # the main table's point (its steps)
                pts.append({"runs": runs, "steps": main["steps"], "rate": main["rate"], "time_s": main["time_s"],
                            "compile_s": main.get("compile_s"), "from_main_table": True})
                continue
            if (runs, steps) not in data:
                data[(runs, steps)] = simulate(rng, runs, steps, [F], [Q])
            zs = data[(runs, steps)]
            est_t = runs * steps / est_rate
            reps_pt = reps if est_t < 1.0 else (2 if kind == "jax" else 1)
            try:
                best, comp, _ = time_impl(make, (zs, x0, P0, F, Q, H, R), reps_pt, kind == "jax")
            except (NotAvailable, MemoryError) as exc:
                skipped.append(runs)
                print(f"    {name}: {runs} runs skipped ({exc})")
                continue
            pts.append({"runs": runs, "steps": steps, "rate": runs * steps / best, "time_s": best, "compile_s": comp})
        out["impls"][key] = {"label": name, "available": True, "points": pts, "skipped_runs": skipped}
        line = "  ".join(f"{p['runs']:g}:{fmt_rate(p['rate'])}" for p in pts)
        print(f"  {name:62s} {line}" + (f"  (skipped runs {skipped}: > {limit} s)" if skipped else ""))
    return out


def plot_sweep(sweep, path, peak, f_kf, f_mean):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from kftrack.plotting import use_book_style

    use_book_style()
    fig, ax = plt.subplots(figsize=(9.0, 4.6))
    markers = dict(kftrack_numpy="o", naive="s", simdkalman="^", dynamax="D", dynamax_means="d", kftrack_jax="*",
                   kftrack_jax_post="P", filterpy="v")
    for key, rec in sweep["impls"].items():
        if not rec["points"]:
            continue
        ax.loglog([p["runs"] for p in rec["points"]], [p["rate"] for p in rec["points"]],
                  marker=markers.get(key, "o"), label=rec["label"].replace("`", ""))
    runs = np.array(sweep["runs"], dtype=float)
    ax.axhline(peak / f_kf, color="0.3", ls="--", lw=1)
    ax.text(runs[0], peak / f_kf * 1.15, f"1-core limit, full recursion ({f_kf} flops/step)", fontsize=8, color="0.3")
    ax.axhline(peak / f_mean, color="0.6", ls=":", lw=1)
    ax.text(runs[0], peak / f_mean * 1.15, f"1-core limit, mean recursion alone ({f_mean} flops/step)",
            fontsize=8, color="0.5")
    ax.set_xlabel("number of Monte Carlo runs filtered together")
    ax.set_ylabel("filter-steps per second (runs × steps / s)")
    ax.set_title("2-D constant velocity (n = 4, m = 2), one CPU core, float64", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# =============================================================================================
# the generated page fragment
# =============================================================================================
# The targets whose two sides do the same work on the same data (so a PASS or FAIL means what it says).
# "NumPy engine vs naive broadcast/simdkalman" compare kftrack's shared covariance recursion (one
# Riccati recursion for all runs) with peers that compute it per run; "single track stepped vs
# filterpy" compares a stepper that stops recomputing P, S, K once they repeat bit for bit with one
# that recomputes them: legitimate savings, but properties of the workload, reported without a verdict.
LIKE_FOR_LIKE = ("JAX engine vs dynamax (same outputs)", "JAX IMM vs NumPy IMM")
# the rates in the sweep at the main table's workload, for the targets that have them
SWEEP_KEYS = {"NumPy engine vs naive broadcast": ("kftrack_numpy", "naive"),
              "NumPy engine vs simdkalman": ("kftrack_numpy", "simdkalman"),
              "JAX engine vs dynamax (same outputs)": ("kftrack_jax_post", "dynamax")}


def target_status(t: dict, res: dict) -> tuple:
    """``(status, ratio in the sweep at the main workload or None)``: a verdict only for a
    like-for-like target (``LIKE_FOR_LIKE``), and PASS only if every measurement of the workload in
    ``res`` (the main table and, when it measured the point again, the sweep) meets it."""
    sw, w = res.get("sweep", {}).get("impls", {}), res["workload"]
    ratio2 = None
    if t["target"] in SWEEP_KEYS:
        pts = [{p["runs"]: p for p in sw.get(k, {}).get("points", [])}.get(w["runs"])  # rates: per step
               for k in SWEEP_KEYS[t["target"]]]
        if all(pts) and not any(p.get("from_main_table") for p in pts):
            ratio2 = pts[0]["rate"] / pts[1]["rate"]
    if t["ratio"] is None:
        return "not available", ratio2
    if t["target"] not in LIKE_FOR_LIKE:
        return "reported (not like for like)", ratio2
    if "ratio_min" in t and ratio2 is None:  # repeats with their spread: the whole range must clear it
        return verdict(t["ratio_min"], t["ratio_max"], t["need"]), None
    ok = [r >= t["need"] for r in (t["ratio"], ratio2) if r is not None]
    return ("PASS" if all(ok) else "FAIL" if not any(ok) else "not reproduced"), ratio2


def target_notes(res) -> dict:
    """The reason beside each target of the issue, by status, with the numbers of ``res``."""
    kf, s, imm, fl = res["kf"], res["single"], res["imm"], res["flops_per_step"]
    kp = res.get("kf_perrun") or {}

    def rt(g, k):
        return g[k]["rate"] if k in g and g[k].get("available", True) and g[k].get("rate") else None

    def ratio(a, b):
        return "n/a" if a is None or b is None else f"{a / b:.2g}×"

    per_np, per_naive = rt(kp, "kftrack_numpy"), rt(kp, "naive")
    per_jx, per_dm = rt(kp, "kftrack_jax"), rt(kp, "dynamax")
    perrun = (f"with one R per run both compute the covariances per run: kftrack JAX (full output) "
              f"{fmt_rate(per_jx)}, dynamax {fmt_rate(per_dm)} steps/s ({ratio(per_jx, per_dm)})" if per_jx and per_dm
              else "the per-run-R comparison is not in this results file")
    fo = res.get("kf_output_floor") or {}
    floor_note = (f"; writing these result arrays alone, with no filtering, runs at "
                  f"{fmt_rate(fo['kftrack_posteriors'])} steps/s for kftrack's with `priors=False`, "
                  f"{fmt_rate(fo['kftrack'])} with the priors and "
                  f"{fmt_rate(fo['dynamax'])} for dynamax's (fresh output buffers on every call)"
                  if all(fo.get(k) for k in ("kftrack", "kftrack_posteriors", "dynamax")) else "")
    jx_full, jx_post, dm = rt(kf, "kftrack_jax"), rt(kf, "kftrack_jax_post"), rt(kf, "dynamax")
    shared = ("compared like with like: kftrack `kalman_filter(..., priors=False)` returns the filtered means and "
              "covariances, NIS and log-likelihood per step (n + n² + 2 numbers per run and step), dynamax the "
              f"filtered means and covariances (n + n²): {fmt_rate(jx_post)} against {fmt_rate(dm)} steps/s "
              f"({ratio(jx_post, dm)}); with its "
              f"full output, priors too (2n + 2n² + 2), kftrack runs at {fmt_rate(jx_full)} steps/s "
              f"({ratio(jx_full, dm)} dynamax). dynamax's `jit(vmap)` with shared parameters also computes the "
              "covariances once (vmap leaves values that do not depend on the batched data unbatched), so both sides "
              "use the shared recursion" + floor_note + "; " + perrun)
    g_imm = rt(imm, "imm_jax") * fl["imm"] / 1e9 if rt(imm, "imm_jax") else None
    g_kf = per_jx * fl["kf"] / 1e9 if per_jx else None
    ceiling = (g_kf * 1e9 / fl["imm"] / rt(imm, "imm_numpy")) if g_kf and rt(imm, "imm_numpy") else None
    need50 = 50 * rt(imm, "imm_numpy") * fl["imm"] / 1e9 if rt(imm, "imm_numpy") else None
    g_dm = per_dm * fl["kf"] / 1e9 if per_dm else None
    imm_fail = ("no shared path exists: the mode probabilities depend on the data, so every run has its own "
                "covariances per mode, and the JAX IMM is bound by these per-run recursions"
                + (f" ({g_imm:.2g} GFLOP/s of counted flops)" if g_imm else "")
                + (f"; XLA reaches {g_kf:.2g} GFLOP/s on the per-run Kalman filter on this CPU, which puts the "
                   f"ceiling of the JAX IMM near {ceiling:.2g}× the NumPy IMM, not 50×" if ceiling else "")
                + (f"; 50× would need {need50:.2g} GFLOP/s ({need50 * 1e9 / res['peak_flops']['1_core']:.0%} of the "
                   f"measured 1-core peak of a large matrix product), {need50 / g_dm:.2g}× what dynamax reaches on the "
                   f"per-run Kalman filter ({g_dm:.2g} GFLOP/s)" if need50 and g_dm else ""))
    ks, fs, st, kp_ = (s.get(k, {}) for k in ("kernels_step", "filterpy_step", "stepper_step", "kftrack_step"))
    if st.get("reused_from") is not None and ks and fs and kp_:
        single_why = ("`KalmanStepper` validates its inputs once, at construction, then calls the kernels; the covariance "
                      "recursion (P, S, K) does not depend on the data; from update "
                      f"{st['reused_from'] + 1} of {res['workload']['single_steps']} on (the first whose prior "
                      "covariance has the bits of the one before it) the stepper reuses P, S and K and computes the mean "
                      f"alone, bit for bit what the kernels give: {st['us_before_reuse']:.0f} µs per step before, "
                      f"{st['us_after_reuse']:.0f} µs after ({st['us_per_step']:.0f} µs on average; the public "
                      f"`predict`/`update`, which check every covariance at every call, {kp_['us_per_step']:.0f} µs; "
                      f"the unchecked kernels {ks['us_per_step']:.0f} µs; filterpy {fs['us_per_step']:.0f} µs); the "
                      "unbatched NumPy solves and log-determinant call `numpy.linalg`'s LAPACK gufuncs without its "
                      "Python layer (the same bits)")
    else:  # a results file without the stepper
        single_why = "the stepper's phases are not in this results file (re-run `make benchmark`)"
    naive_pass = ("met through the shared-covariance path (the covariances computed once for all runs); with one "
                  f"R per run kftrack runs the same per-run recursion as the naive broadcast ({ratio(per_np, per_naive)})"
                  if per_np and per_naive else "met through the shared-covariance path (the covariances computed once "
                  "for all runs)")
    naive_fail = "not met: " + naive_pass[len("met through "):]
    simd = ("simdkalman computes the covariances per run; kftrack's margin comes from the shared path, and the ratio "
            "moves with the load of the shared machine between runs")
    return {
        "NumPy engine vs naive broadcast": {"PASS": naive_pass, "FAIL": naive_fail},
        "NumPy engine vs simdkalman": {"PASS": "met; " + simd, "FAIL": "not met; " + simd},
        "single track stepped vs filterpy": {"PASS": "met: " + single_why, "FAIL": "not met: " + single_why},
        "JAX engine vs dynamax (same outputs)": {"PASS": "met; " + shared, "FAIL": shared},
        "JAX IMM vs NumPy IMM": {"PASS": "met", "FAIL": imm_fail},
    }


def render_markdown(res) -> str:
    mach, ag = res["machine"], res["agreement"]
    w = res["workload"]
    peak1, peak2 = res["peak_flops"]["1_core"], res["peak_flops"]["2_cores"]
    fl = res["flops_per_step"]
    L = ["<!-- generated by benchmarks/filters.py: do not edit by hand -->", ""]
    L.append(f"Measured on {mach['date']}: {mach['cpu']}, {mach['logical_cores']} logical cores, the benchmark "
             f"process pinned to one core; Python {mach['python']}, NumPy {mach['numpy']}, jax/jaxlib "
             f"{mach['jax']}/{mach['jaxlib']}, float64 throughout. Command: `make benchmark` (total "
             f"{res['total_s']:.0f} s). The machine was shared with other jobs: its 1-minute load average was "
             f"{mach.get('load_average_at_start', float('nan')):.1f} at the start and "
             f"{mach.get('load_average_at_end', float('nan')):.1f} at the end, on {mach['logical_cores']} logical "
             "cores; absolute rates are pessimistic and vary between runs. "
             + (f"Each rate is the median of {res['repeats']} repeats, interleaved over the implementations of a "
                "table (filterpy: fewer), with the min–max range; a ratio is that of the medians, with the range "
                "from the extremes (slowest over fastest to fastest over slowest), as in the composition "
                "benchmark. " if "repeats" in res else "Steps/s are the best of several repeats. ")
             + "JAX compile time is excluded and listed separately.")
    L.append("")

    def agree(rec, bound):
        if rec.get("reference"):
            return "the reference"
        d = rec.get("max_rel_diff")
        b = rec.get("bound", bound)
        if d is None:
            return "n/a"
        word = "within" if rec.get("agrees") else "OUTSIDE"
        if "bound_ratio" in rec:  # the per-step bound: checked step by step, its range shown
            return f"{fmt_bound(d)} ({word} {rec['bound_min']:.1g}–{b:.1g} per step)"
        return f"{fmt_bound(d)} ({word} {b:.1g})"

    def rate_cell(rec):
        if "rate_min" not in rec:
            return fmt_rate(rec["rate"])
        return f"{fmt_rate(rec['rate'])} ({fmt_rate(rec['rate_min'])}–{fmt_rate(rec['rate_max'])})"

    def ratio_cell(a, b):
        if a is b:  # the reference against itself
            return "1"
        sp = None if a is None or b is None else ratio_spread(a, b)
        if sp is None:
            return "n/a"
        f = lambda v: f"{v:.0f}" if v >= 100 else f"{v:.2g}"  # noqa: E731
        return f"{f(sp[0])} ({f(sp[1])}–{f(sp[2])})" if "rate_min" in a and "rate_min" in b else f(sp[0])

    def group_rows(g, ref_np, ref_jx, bound):
        rows = []
        for rec in g.values():
            if not rec.get("available", True):
                rows.append([rec["label"], "not available", "", "", "", "", rec.get("reason", "")])
                continue
            note = []
            if rec.get("compile_s") is not None:
                note.append(f"compile {rec['compile_s']:.1f} s")
            if rec["runs"] != w["runs"]:
                note.append(f"timed on {rec['runs']} of {w['runs']} runs")
            rows.append([rec["label"], rate_cell(rec), ratio_cell(ref_np, rec),
                         ratio_cell(ref_jx, rec), f"{100 * rec['fraction_of_limit']:.2g} %",
                         agree(rec, bound), "; ".join(note)])
        return rows

    hdr = ["implementation", "filter-steps/s, median (min–max)", "kftrack NumPy / it", "kftrack JAX / it",
           "of 1-core limit",
           "max rel. diff. of means (bound)", "notes"]
    kf, imm = res["kf"], res["imm"]
    r = lambda g, k: g[k] if k in g and g[k].get("available", True) else None  # noqa: E731
    L.append(f"**Kalman filter**, {w['runs']} runs × {w['kf_steps']} steps:")
    L.append("")
    L.append(md_table(hdr, group_rows(kf, r(kf, "kftrack_numpy"), r(kf, "kftrack_jax"), ag["bound_kf"])))
    L.append("")
    kp = res.get("kf_perrun")
    if kp:
        L.append(f"**Kalman filter with one R per run** (the same values, given with shape ({w['runs']}, 2, 2)), "
                 f"{w['runs']} runs × {w['kf_steps']} steps: no implementation can share the covariance recursion, "
                 "every one computes it per run:")
        L.append("")
        L.append(md_table(hdr, group_rows(kp, r(kp, "kftrack_numpy"), r(kp, "kftrack_jax"), ag["bound_kf"])))
    else:
        L.append("**Kalman filter with one R per run**: not in this results file (re-run `make benchmark`).")
    L.append("")
    k3 = res.get("kf3")
    if k3:
        L.append(f"**Kalman filter, a second size**: 3-D constant velocity (n = 6, m = 3, "
                 f"{res['kf3_flops_per_step']} flops per step and run), {w['runs']} runs × {w['kf_steps']} steps, "
                 "the same rows as above without filterpy; \"of 1-core limit\" with the flops of this size:")
        L.append("")
        L.append(md_table(hdr, group_rows(k3, r(k3, "kftrack_numpy"), r(k3, "kftrack_jax"), ag.get("bound_kf3"))))
    else:
        L.append("**Kalman filter, a second size**: not in this results file (re-run `make benchmark`).")
    L.append("")
    L.append(f"**A single track stepped one call at a time**, {w['single_steps']} steps:")
    L.append("")
    s = res["single"]
    L.append(md_table(["implementation", "steps/s, median (min–max)", "µs per step (median)", "kftrack / it",
                       "of 1-core limit", "max rel. diff. of means (bound)"],
                      [[v["label"], rate_cell(v), f"{v['us_per_step']:.0f}",
                        ratio_cell(s["kftrack_step"], v), f"{100 * v['fraction_of_limit']:.2g} %",
                        agree(v, ag["bound_single"])] for v in s.values()]))
    L.append("")
    L.append(f"**IMM** (constant velocity + turns at ±{w['turn_rate_deg_s']:.0f} °/s), {w['runs']} runs × "
             f"{w['imm_steps']} steps:")
    L.append("")
    L.append(md_table(hdr, group_rows(imm, r(imm, "imm_numpy"), r(imm, "imm_jax"), ag["bound_imm"])))
    L.append("")
    L.append("**Targets of the issue:**")
    L.append("")
    why = target_notes(res)
    rows = []
    for t in res["targets"]:
        status, r2 = target_status(t, res)
        word = "PASS" if (t["ratio"] or 0) >= t["need"] else "FAIL"  # which reason text applies
        note = why.get(t["target"], {}).get(word, "")
        if status not in ("PASS", "FAIL"):  # no verdict: the reason without its "met" / "not met"
            for pre, new in (("not met: ", ""), ("not met; ", ""), ("met through ", "through "), ("met; ", ""),
                             ("met: ", "")):
                if note.startswith(pre):
                    note = new + note[len(pre):]
                    break
        meas = "n/a" if t["ratio"] is None else f"{t['ratio']:.2f}×" + (
            f" ({t['ratio_min']:.2f}–{t['ratio_max']:.2f})" if t.get("ratio_min") is not None else "")
        rows.append([t["target"], f"≥ {t['need']}×" + (f" (aim {t['aim']}×)" if t["aim"] else ""), meas,
                     "" if r2 is None else f"{r2:.2f}×", status, note])
    L.append("A verdict (PASS/FAIL) is given only where both sides do the same work on the same data; PASS only "
             "if the whole range of the ratio over the repeats (slowest over fastest to fastest over slowest) "
             "clears the target, FAIL only if none of it does, otherwise \"not resolved by the spread\": a "
             "ratio that moves across the target between repeats is no basis for a verdict.")
    L.append("")
    if any(row[3] for row in rows):
        L.append(md_table(["target", "needed", "measured, median (range)", "same workload in the sweep", "status",
                           "why"], rows))
    else:
        L.append(md_table(["target", "needed", "measured, median (range)", "status", "why"],
                          [row[:3] + row[4:] for row in rows]))
    L.append("")
    L.append("**Physical limit.** Flops per filter step and run, counted as the equations are written in "
             f"`kftrack.kernels` (Joseph form, NIS and log-likelihood included): KF {fl['kf']}, the mean "
             f"recursion alone {fl['kf_mean_only']}, IMM with {fl['imm_modes']} modes {fl['imm']}. Measured "
             f"float64 peak (2048 × 2048 matrix product, OpenBLAS): {peak1 / 1e9:.1f} GFLOP/s on one core"
             + (f", {peak2 / 1e9:.1f} GFLOP/s on two" if peak2 else "")
             + f". The limit on one core is then {fmt_rate(peak1 / fl['kf'])} KF steps/s "
             f"({fmt_rate(peak1 / fl['kf_mean_only'])} for the mean recursion alone) and "
             f"{fmt_rate(peak1 / fl['imm'])} IMM steps/s; the column \"of 1-core limit\" is the measured rate "
             "divided by the full-recursion limit.")
    L.append("")
    pt = ag.get("perturbation")
    if pt:
        L.append("**Agreement.** Kalman filter rows (both sizes, per-run R, single track): the normwise relative "
                 "difference of each filtered mean from kftrack's NumPy engine, step by step and run by run, against "
                 "a bound derived for that step (`agreement_bound_steps`): each implementation's round-off in one "
                 "step (the products of F x, H x, K y, each within p·ε of its p-term sum, and the gain's error "
                 "from the covariance recursion and the solve with S), propagated to later steps by the products of "
                 "the computed closed-loop matrices (I − K_k H) F of this run, which forget old errors, instead of "
                 f"being added T times; C_OP = {ag['C_OP']:g} per operation, twice for two implementations. On the "
                 f"2-D workload the bound lies between {ag['bound_kf_min']:.1g} and {ag['bound_kf']:.1g} per step "
                 f"({ag['bound_kf_end']:.1g} at the last step), against the worst case C·T·n·κ·ε = "
                 f"{C_BOUND * w['kf_steps'] * 4 * ag['kappa_kf'] * EPS:.1g} used before. It can fail: the naive "
                 f"broadcast with its filtered mean multiplied by 1 + {pt['rel']:g} at step {pt['step']} alone (a "
                 f"relative error of {pt['rel']:g} in one step) is "
                 + (f"caught: {pt['bound_ratio']:.1f}× the bound" if pt["detected"]
                    else f"NOT caught ({pt['bound_ratio']:.2g} of the bound)")
                 + f" (bound at that step {pt['bound_at_step_min']:.1g}–{pt['bound_at_step_max']:.1g}). dynamax "
                 "adds 1e-9 to the diagonal of S before solving (`psd_solve`'s `diagonal_boost`), a perturbation of "
                 "the model rather than round-off, carried through the same propagation as an extra error of its "
                 f"gain. IMM: the worst case C·T·n·κ·ε with C = {ag['C']:g}, κ = {ag['kappa_imm']:.0f}, "
                 f"T = {w['imm_steps']}: {ag['bound_imm']:.1g} (its mixing depends on the data, no linear closed "
                 "loop to propagate with; not tightened). Every implementation within its bound: "
                 f"{'yes' if ag['all_agree'] else 'NO'}.")
    else:
        L.append(f"**Agreement.** Bound on the normwise relative difference of the filtered means: "
                 f"C·T·n·κ·ε with C = {ag['C']:g}, n = 4, ε = 2.2e-16 and κ the largest condition number of "
                 f"P⁻ and S over the run (KF κ = {ag['kappa_kf']:.0f}, IMM κ = {ag['kappa_imm']:.0f}), "
                 f"giving {ag['bound_kf']:.1g} (KF, T = {w['kf_steps']}), {ag['bound_single']:.1g} (single track) and "
                 f"{ag['bound_imm']:.1g} (IMM, T = {w['imm_steps']}). dynamax adds 1e-9 to the diagonal of S before "
                 "solving (`psd_solve`'s `diagonal_boost`), a perturbation of the model rather than round-off; its "
                 "bound adds T·1e-9/λ_min(R) for it. Every implementation within its bound: "
                 f"{'yes' if ag['all_agree'] else 'NO'}.")
    L.append("")
    sw = res["sweep"]
    rows = []
    for rec in sw["impls"].values():
        by = {p["runs"]: p for p in rec["points"]}
        cells = [fmt_rate(by[n]["rate"]) + f" ({by[n]['steps']})" if n in by else
                 ("skipped" if n in rec.get("skipped_runs", []) else "n/a") for n in sw["runs"]]
        rows.append([rec["label"]] + cells)
    L.append("**Sweep** (filter-steps/s, steps per point in parentheses; \"skipped\": a point that would take "
             "more than a few seconds):")
    L.append("")
    L.append(md_table(["implementation"] + [f"{n:g} run" + ("s" if n != 1 else "") for n in sw["runs"]], rows))
    L.append("")
    return "\n".join(L)


if __name__ == "__main__":
    main()
