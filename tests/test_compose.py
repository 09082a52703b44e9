"""Every whole-sequence filter composes with JAX's transformations (issue 27): kalman_filter,
rts_smoother, extended_kalman_filter and unscented_kalman_filter run inside the caller's
jax.jit, jax.vmap (over data and over a noise parameter) and jax.grad of their total
log-likelihood; the static missing-row pattern (missing=) keeps the shared-covariance path
inside a trace; outputs the caller drops are not computed.

Bounds. Values: the engines' round-off bound of tests/test_engines.py, |difference| <= T n kappa
eps scale per field (T steps, n the state size, 2n + 1 for the UKF's sigma points, kappa the
largest condition number of the innovation covariances met, cond(P_prior) too for the
smoother). Gradients: the exact JAX gradient against central differences of the NumPy engine
with step h (tests/test_tuning.py's _central_difference: truncation h^2 |f'''| / 6 with f'''
estimated by a 5-point difference, plus round-off delta / h), where delta, the round-off of one
evaluation of the NumPy objective (a sum of N terms), is N times the engines' bound of one term,
N T n kappa eps max|term|; the JAX gradient's own round-off is bounded by the same delta (the
reverse pass is as many backward-stable operations per term). Each gradient check has power: a
gradient 1 % off would fail it (twice the bound is below 1 % of every component).
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kftrack import engines, tuning
from kftrack.ekf import extended_kalman_filter
from kftrack.kalman import kalman_filter, rts_smoother
from kftrack.kernels import kf_predict, kf_update
from kftrack.ukf import unscented_kalman_filter
from test_engines import EPS64, MODEL, F_jac, H_jac, _agree, cond_S, data, f, h, polar_data
from test_engines import H as H_CV
from test_engines import R as R_CV
from test_tuning import _central_difference

jax.config.update("jax_enable_x64", True)  # the engines' float64 default needs it (see kftrack.engines)

T, RUNS = 25, 4
F_CV, QBAR = MODEL.F(1.0), MODEL.Q(1.0)  # Q = q * QBAR: q a factor on the model's spectral density
R_POLAR = np.diag([1.0, 1e-4])  # range (m^2) and bearing (rad^2) variances, times r
PHI = np.log([0.8, 1.3])  # (log q, log r): away from the maximum, so the gradient is O(1-100)
STEP = 1e-3  # central-difference step in phi
# the tests' own jit: XLA's backend optimisation level 0 compiles in about half the time (as in
# tests/test_tuning.py); the same computation, so the same bounds hold
JIT = {"compiler_options": {"xla_backend_optimization_level": 0}}


def _kf(zs, x0, P0, q, r, **kw):
    return kalman_filter(zs, x0, P0, F_CV, q * QBAR, H_CV, r * R_CV, **kw)


def _ekf(zs, x0, P0, q, r, **kw):
    return extended_kalman_filter(zs, x0, P0, f, F_jac, q * QBAR, h, H_jac, r * R_POLAR, angle_components=[1],
                                  **kw)


def _ukf(zs, x0, P0, q, r, **kw):
    return unscented_kalman_filter(zs, x0, P0, f, q * QBAR, h, r * R_POLAR, angle_components=[1], **kw)


def _cond_polar(res, r):
    """Largest condition number of H P^- H^T + R, H the range-bearing Jacobian at the prediction."""
    Hs = H_jac(np.asarray(res.x_prior))
    S = Hs @ np.asarray(res.P_prior) @ np.swapaxes(Hs, -1, -2) + r * R_POLAR
    return float(np.max(np.linalg.cond(S.reshape(-1, 2, 2))))


# name: (filter, data maker, state size in the bound, condition number of a NumPy result at r)
FILTERS = {
    "kalman": (_kf, lambda: data(np.random.default_rng(21), T=T, runs=RUNS), 4,
               lambda res, r: cond_S(res, H_CV, r * R_CV)),
    "ekf": (_ekf, lambda: polar_data(np.random.default_rng(22), T=T, runs=RUNS), 4, _cond_polar),
    "ukf": (_ukf, lambda: polar_data(np.random.default_rng(23), T=T, runs=RUNS), 9, _cond_polar),
}


# --------------------------------------------------------------------------------------------
# jit and vmap: the same numbers as the NumPy engine
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", FILTERS)
def test_jit_and_vmap_agree_with_the_numpy_engine(name):
    run, make, n, cond = FILTERS[name]
    zs, x0, P0 = make()  # rows of NaN for every run and for one run only
    zj = jnp.asarray(zs)
    ref = run(zs, x0, P0, 1.0, 1.0)
    _agree(ref, jax.jit(lambda z: run(z, x0, P0, 1.0, 1.0), **JIT)(zj), T, n, cond(ref, 1.0))
    # vmap over a noise level r of vmap over the runs (each run filtered alone, batch (), its
    # missing rows found inside the trace), under jit: one compiled program
    rs = np.array([0.5, 2.0])
    over_data = lambda r: jax.vmap(lambda z: run(z, x0, P0, 1.0, r), in_axes=1, out_axes=1)(zj)  # noqa: E731
    mapped = jax.jit(jax.vmap(over_data), **JIT)(jnp.asarray(rs))
    for i, r in enumerate(rs):
        ref = run(zs, x0, P0, 1.0, r)
        _agree(ref, [None if v is None else v[i] for v in mapped], T, n, cond(ref, r), names=ref._fields)


# --------------------------------------------------------------------------------------------
# grad of the total log-likelihood: the exact JAX gradient against central differences
# --------------------------------------------------------------------------------------------
def _loglik_delta(res, n, kappa) -> float:
    """Round-off of the NumPy engine's nansum(loglik): N terms, each within the engines' bound
    T n kappa eps max|l_k| (module docstring)."""
    ll = np.asarray(res.loglik)
    return np.sum(np.isfinite(ll)) * T * n * kappa * EPS64 * float(np.nanmax(np.abs(ll)))


def _check_gradient(grad, fd, bound, what):
    for i in range(len(grad)):
        print(f"{what} d/dphi_{i}: jax {grad[i]:.9g}, central difference {fd[i]:.9g}, |diff| "
              f"{abs(grad[i] - fd[i]):.1e} <= {bound[i]:.1e} ({bound[i] / abs(grad[i]):.1e} of |grad|)")
        # power: a gradient 1 % off is at least 0.01 |g| - bound from the difference quotient, above the bound
        assert 2 * bound[i] < 0.01 * abs(grad[i]), (what, i, grad[i], bound[i])
        assert abs(grad[i] - fd[i]) <= bound[i], (what, i, grad[i], fd[i], bound[i])


def _build(params):
    """(F, Q, H, R) of the kalman case at (q, r), a build for kftrack.tuning.total_loglik."""
    return F_CV, params[0] * QBAR, H_CV, params[1] * R_CV


@pytest.mark.parametrize("name", [*FILTERS, "total_loglik"])
def test_grad_of_the_total_loglik_matches_central_differences(name):
    # total_loglik: the kalman case through kftrack.tuning.total_loglik, whose JAX engine sums the
    # log-likelihood in a loop that stores no sequence (kftrack.engines.run_total_scan)
    run, make, n, cond = FILTERS["kalman" if name == "total_loglik" else name]
    zs, x0, P0 = make()
    zj = jnp.asarray(zs)

    def ell_np(phi):
        return float(np.nansum(run(zs, x0, P0, np.exp(phi[0]), np.exp(phi[1])).loglik))

    if name == "total_loglik":
        vg = jax.jit(jax.value_and_grad(lambda p: tuning.total_loglik(p, _build, zj, x0, P0)), **JIT)
    else:
        vg = jax.jit(jax.value_and_grad(lambda p: jnp.nansum(run(zj, x0, P0, jnp.exp(p[0]), jnp.exp(p[1])).loglik)),
                     **JIT)
    value, grad = vg(jnp.asarray(PHI))
    ref = run(zs, x0, P0, *np.exp(PHI))
    delta = _loglik_delta(ref, n, cond(ref, np.exp(PHI[1])))
    assert abs(float(value) - ell_np(PHI)) <= 2 * delta
    fd, bound = _central_difference(ell_np, PHI, np.full(2, STEP), delta)
    _check_gradient(np.asarray(grad), fd, bound + delta, name)


# missing: (rows of NaN in the data, the missing= argument) of each covariance path of
# tuning.total_loglik's JAX engine (kftrack.engines.run_total_scan: the covariance loop, then the
# means loop): no row missing (one covariance recursion for all runs, no selection), a mask
# shared by the runs (one recursion, the masked rows selected out), runs missing different rows
# (a recursion per run)
TOTAL_PATHS = {"none": ("none", False), "shared": ("shared", "mask"), "per run": ("mixed", None)}


@pytest.mark.parametrize("path", TOTAL_PATHS)
def test_grad_of_total_loglik_on_each_covariance_path(path):
    rows, missing = TOTAL_PATHS[path]
    zs, x0, P0 = data(np.random.default_rng(31), T=T, runs=RUNS, missing=rows)
    if missing == "mask":  # static, one pattern for all runs; the masked rows hold NaN
        missing = np.isnan(zs).all(-1)[:, 0]
    zj = jnp.asarray(zs)
    vg = jax.jit(jax.value_and_grad(lambda p: tuning.total_loglik(p, _build, zj, x0, P0, missing=missing)), **JIT)
    value, grad = vg(jnp.asarray(PHI))
    ref = _kf(zs, x0, P0, *np.exp(PHI))
    delta = _loglik_delta(ref, 4, cond_S(ref, H_CV, np.exp(PHI[1]) * R_CV))
    ell_np = lambda phi: tuning.total_loglik(phi, _build, zs, x0, P0)  # noqa: E731  NumPy engine
    assert abs(float(value) - ell_np(PHI)) <= 2 * delta
    # a NaN in a masked row that reached the reverse pass would make the gradient NaN (0 * NaN)
    fd, bound = _central_difference(ell_np, PHI, np.full(2, STEP), delta)
    _check_gradient(np.asarray(grad), fd, bound + delta, f"total_loglik, {path}")


def test_grad_of_total_loglik_agrees_with_dynamax(monkeypatch):
    # dynamax (benchmarks/requirements.txt; skipped where it is not installed) differentiates the
    # same likelihood with per-run covariances, Cholesky solves and the short covariance update.
    # Its solve adds 1e-9 I to S (psd_solve's diagonal_boost): set to 0 here, so the two compute
    # one function and differ by round-off only, each gradient within delta of the exact one
    # (module docstring): |difference| <= 2 delta, with the power of _check_gradient
    inference = pytest.importorskip("dynamax.linear_gaussian_ssm.inference")
    from dynamax.utils.utils import psd_solve

    monkeypatch.setattr(inference, "psd_solve", functools.partial(psd_solve, diagonal_boost=0.0))
    zs, x0, P0 = data(np.random.default_rng(32), T=T, runs=RUNS, missing="none")
    zj, n, m = jnp.asarray(zs), 4, 2

    def dyn_ll(phi):
        q, r = jnp.exp(phi[0]), jnp.exp(phi[1])
        params = inference.ParamsLGSSM(
            initial=inference.ParamsLGSSMInitial(mean=jnp.asarray(x0), cov=jnp.asarray(P0)),
            dynamics=inference.ParamsLGSSMDynamics(weights=jnp.asarray(F_CV), bias=jnp.zeros(n),
                                                   input_weights=jnp.zeros((n, 0)), cov=q * QBAR),
            emissions=inference.ParamsLGSSMEmissions(weights=jnp.asarray(H_CV), bias=jnp.zeros(m),
                                                     input_weights=jnp.zeros((m, 0)), cov=r * R_CV))
        return jnp.sum(jax.vmap(lambda y: inference.lgssm_filter(params, y).marginal_loglik, in_axes=1)(zj))

    g_dyn = np.asarray(jax.jit(jax.grad(dyn_ll), **JIT)(jnp.asarray(PHI)))
    g_kf = np.asarray(jax.jit(jax.grad(lambda p: tuning.total_loglik(p, _build, zj, x0, P0, missing=False)),
                              **JIT)(jnp.asarray(PHI)))
    ref = _kf(zs, x0, P0, *np.exp(PHI))
    delta = _loglik_delta(ref, 4, cond_S(ref, H_CV, np.exp(PHI[1]) * R_CV))
    _check_gradient(g_kf, g_dyn, np.full(2, 2 * delta), "total_loglik vs dynamax")


# --------------------------------------------------------------------------------------------
# the RTS smoother
# --------------------------------------------------------------------------------------------
def test_rts_smoother_composes():
    zs, x0, P0 = data(np.random.default_rng(24), T=T, runs=RUNS)
    zj = jnp.asarray(zs)

    def smooth(z, q):
        return rts_smoother(_kf(z, x0, P0, q, 1.0), F_CV)

    ref = smooth(zs, 1.0)
    fil = _kf(zs, x0, P0, 1.0, 1.0)
    k = max(cond_S(fil, H_CV, R_CV), float(np.max(np.linalg.cond(np.asarray(fil.P_prior).reshape(-1, 4, 4)))))
    _agree(ref, jax.jit(lambda z: smooth(z, 1.0), **JIT)(zj), T, 4, k)
    qs = np.array([0.5, 2.0])  # vmap over q of vmap over the runs, under jit
    over_data = lambda q: jax.vmap(lambda z: smooth(z, q), in_axes=1, out_axes=1)(zj)  # noqa: E731
    mapped = jax.jit(jax.vmap(over_data), **JIT)(jnp.asarray(qs))
    for i, q in enumerate(qs):
        _agree(smooth(zs, q), [v[i] for v in mapped], T, 4, k, names=ref._fields)

    # grad of a smoothing fit, the squared distance of the smoothed positions to the measurements
    # (the missing rows masked with where, before the difference: a NaN there would make the
    # gradient NaN, 0 * NaN, even where its value is dropped)
    gone = np.isnan(zs)
    z0 = np.where(gone, 0.0, zs)

    def fit(x_s, xp):
        return xp.sum(xp.where(gone, 0.0, z0 - x_s[..., ::2]) ** 2)

    def fit_np(phi):
        return float(fit(smooth(zs, np.exp(phi[0])).x, np))

    g = np.asarray(jax.jit(jax.grad(lambda p: fit(smooth(zj, jnp.exp(p[0])).x, jnp)), **JIT)(jnp.asarray(PHI[:1])))
    # round-off: N squared residuals e, each |d(e^2)| <= 2 |e| |d e|, |d e| within the engines' bound of x_s
    xs = np.asarray(ref.x)
    resid = np.where(gone, 0.0, np.abs(z0 - xs[..., ::2]))
    delta = 2 * np.sum(resid) * T * 4 * k * EPS64 * np.max(np.abs(xs))
    fd, bound = _central_difference(fit_np, PHI[:1], np.full(1, STEP), delta)
    _check_gradient(g, fd, bound + delta, "rts")


# --------------------------------------------------------------------------------------------
# the static missing-row pattern: the shared-covariance path inside a trace
# --------------------------------------------------------------------------------------------
@pytest.fixture
def spy(monkeypatch):
    """Records (cov_batch, gone is None) of every call of the JAX engine's driver."""
    calls = []
    real = engines.run_scan

    def run_scan(zs, gone, x0, P0, batch, cov_batch, *args, **kw):
        calls.append((tuple(cov_batch), gone is None))
        return real(zs, gone, x0, P0, batch, cov_batch, *args, **kw)

    monkeypatch.setattr(engines, "run_scan", run_scan)
    return calls


def test_missing_makes_the_traced_call_take_the_direct_path(spy):
    zs, x0, P0 = data(np.random.default_rng(25), T=T, runs=RUNS, missing="none")
    zj = jnp.asarray(zs)
    ref = _kf(zs, x0, P0, 1.0, 1.0)
    k = cond_S(ref, H_CV, R_CV)
    direct = _kf(zj, x0, P0, 1.0, 1.0)
    assert spy[-1] == ((), True)  # a direct call: shared covariances, no selection (no row missing)
    for missing, path in ((None, ((RUNS,), False)), (False, ((), True)), (np.zeros(T, bool), ((), True)),
                          (np.zeros((T, RUNS), bool), ((), True))):
        res = jax.jit(lambda z, m=missing: _kf(z, x0, P0, 1.0, 1.0, missing=m), **JIT)(zj)
        assert spy[-1] == path, missing  # None: per run, found inside the trace; static: as a direct call
        _agree(ref, res, T, 4, k)
    _agree(ref, direct, T, 4, k)
    # a pattern shared by the runs stays shared (selection in the loop), one run's own pattern does not
    shared, one_run = np.zeros(T, bool), np.zeros((T, RUNS), bool)
    shared[[3, 8]] = True
    one_run[5, 2] = True
    for mask, cov_batch in ((shared, ()), (one_run, (RUNS,))):
        z = zs.copy()
        z[np.broadcast_to(mask if mask.ndim == 2 else mask[:, None], z.shape[:-1])] = np.nan
        ref = _kf(z, x0, P0, 1.0, 1.0)
        res = jax.jit(lambda zz, m=mask: _kf(zz, x0, P0, 1.0, 1.0, missing=m), **JIT)(jnp.asarray(z))
        assert spy[-1] == (cov_batch, False)
        _agree(ref, res, T, 4, cond_S(ref, H_CV, R_CV))
    # under vmap a covariance recursion that depends on no mapped input stays unbatched
    spy.clear()
    jax.vmap(lambda z: _kf(z, x0, P0, 1.0, 1.0, missing=False).x, in_axes=1)(zj)
    assert spy[-1] == ((), True)


def test_a_mask_ignores_what_the_masked_rows_hold():
    zs, x0, P0 = data(np.random.default_rng(26), T=T, runs=RUNS)  # NaN rows: step 7, and two single runs
    gone = np.isnan(zs).all(-1)
    junk = zs.copy()
    junk[gone] = 1e300  # anything: never used
    junk[7, 1, 0] = np.nan  # a partly NaN row, masked
    ref = _kf(zs, x0, P0, 1.0, 1.0)
    got = _kf(junk, x0, P0, 1.0, 1.0, missing=gone)
    assert all(np.array_equal(u, v, equal_nan=True) for u, v in zip(ref, got))  # the same operations: same bits
    jit = jax.jit(lambda z: _kf(z, x0, P0, 1.0, 1.0, missing=gone), **JIT)(jnp.asarray(junk))
    _agree(ref, jit, T, 4, cond_S(ref, H_CV, R_CV))
    # the EKF and UKF take the same argument
    for run in (_ekf, _ukf):
        a = run(zs, x0, P0, 1.0, 1.0)
        b = run(junk, x0, P0, 1.0, 1.0, missing=gone)
        assert all(np.array_equal(u, v, equal_nan=True) for u, v in zip(a, b))


def test_bad_missing_is_named():
    zs, x0, P0 = data(np.random.default_rng(27), T=6, runs=2, missing="none")
    zs[2, 1] = np.nan
    with pytest.raises(ValueError, match=r"^zs has NaN at step 2 in a row that missing does not mark"):
        _kf(zs, x0, P0, 1.0, 1.0, missing=False)
    with pytest.raises(ValueError, match=r"^missing must have shape \(6,\) or \(6, \.\.\.\).*got shape \(5,\)"):
        _kf(zs, x0, P0, 1.0, 1.0, missing=np.zeros(5, bool))
    with pytest.raises(ValueError, match=r"^missing must have shape .*got shape \(6, 3\)"):
        _kf(zs, x0, P0, 1.0, 1.0, missing=np.zeros((6, 3), bool))
    with pytest.raises(TypeError, match=r"^missing must be None, False or a boolean array .*float64"):
        _kf(zs, x0, P0, 1.0, 1.0, missing=np.zeros(6))
    with pytest.raises(TypeError, match=r"^missing must be None, False or a boolean array"):
        _kf(zs, x0, P0, 1.0, 1.0, missing=True)
    with pytest.raises(TypeError, match=r"^missing must be concrete"):
        jax.jit(lambda m: _kf(zs, x0, P0, 1.0, 1.0, missing=m).x)(jnp.zeros(6, bool))
    with pytest.raises(ValueError, match=r"^R must have shape \(\.\.\., 2, 2\)"):  # shapes of tracers are checked
        jax.grad(lambda s: jnp.nansum(extended_kalman_filter(jnp.asarray(zs), x0, P0, f, F_jac, MODEL.Q(1.0), h,
                                                             H_jac, s * jnp.eye(3)).loglik))(1.0)


def test_outputs_the_caller_drops_are_not_computed():
    # jit(lambda z: kalman_filter(...).x) compiles to the program of the means alone: the same
    # output and temporary memory with or without the predictions (XLA drops the dead outputs)
    zs, x0, P0 = data(np.random.default_rng(28), T=50, runs=30, missing="none")
    zj = jnp.asarray(zs)
    mem = {}
    for priors in (True, False):
        fn = jax.jit(lambda z, p=priors: _kf(z, x0, P0, 1.0, 1.0, priors=p, missing=False).x)
        mem[priors] = fn.lower(zj).compile().memory_analysis()
    if mem[True] is None:
        pytest.skip("this JAX backend reports no memory analysis")
    assert mem[True].output_size_in_bytes == mem[False].output_size_in_bytes == zs.shape[0] * 30 * 4 * 8
    assert mem[True].temp_size_in_bytes == mem[False].temp_size_in_bytes


# --------------------------------------------------------------------------------------------
# total_loglik(..., checkpoint=c): the same sum in segments under jax.checkpoint
# --------------------------------------------------------------------------------------------
T_CK, C_CK = 4096, 60  # 68 segments of 60 steps (c near sqrt(T)) and a remainder of 16


def _per_step_cotangents(zs, x0, P0, phi):
    """sum_k |dl/dQ_k| * |dQ/dphi_q| and sum_k |dl/dR_k| * |dR/dphi_r| (summed over the entries):
    the derivatives with respect to the Q and R used at each step, from the engine's general loop
    given per-step stacks (kftrack.engines.run_total_scan with pred_steps, upd_steps; no row
    missing)."""
    q, r = np.exp(phi)
    stack = lambda a: jnp.asarray(np.broadcast_to(a, (zs.shape[0],) + a.shape))  # noqa: E731

    def ell(Qs, Rs):
        return jnp.sum(engines.run_total_scan(jnp.asarray(zs), None, jnp.asarray(x0), jnp.asarray(P0),
                                              (zs.shape[1],), (), engines.Kernel(kf_predict),
                                              engines.Kernel(kf_update), pred_steps=(stack(F_CV), Qs),
                                              upd_args=(jnp.asarray(H_CV),), upd_steps=(Rs,)))

    cQ, cR = jax.jit(jax.grad(ell, argnums=(0, 1)), **JIT)(stack(q * QBAR), stack(r * R_CV))
    return np.array([q * np.sum(np.abs(cQ).sum(0) * np.abs(QBAR)), r * np.sum(np.abs(cR).sum(0) * np.abs(R_CV))])


def test_checkpoint_gives_the_same_value_and_gradient_in_less_memory():
    # the shared-covariance path (missing=False), as benchmarks/compose.py; the segments
    # (kftrack.engines._segmented) wrap the same step on every path
    zs, x0, P0 = data(np.random.default_rng(33), T=T_CK, runs=3, missing="none")
    zj, phi = jnp.asarray(zs), jnp.asarray(PHI)
    prog = {c: jax.jit(jax.value_and_grad(lambda p, c=c: tuning.total_loglik(p, _build, zj, x0, P0, missing=False,
                                                                               checkpoint=c)), **JIT)
            .lower(phi).compile() for c in (None, C_CK)}
    (v0, g0), (v1, g1) = prog[None](phi), prog[C_CK](phi)
    # the value: the same steps in the same order, segment after segment: bit for bit
    assert v1 == v0
    # the gradient: reverse mode sums the contributions c_k of the T steps to the cotangents of Q and
    # R (shared by every step), the plain loop one after the other, the checkpointed one segment by
    # segment, then the segments: two orders of one sum of the same computed terms (the forward pass
    # run again is the same arithmetic), each within gamma_{T-1} sum_k |c_k| of the exact sum
    # (Higham 2002, eq. 4.4, any order), so |difference| <= 2 gamma_T sum_k |c_k| entry by entry,
    # then times |dQ/dphi| (the chain rule, applied alike to both). sum_k |c_k| from the derivatives
    # with respect to per-step stacks Q_k, R_k (a second program: a factor 2 for its round-off)
    gamma = T_CK * EPS64 / (1 - T_CK * EPS64)
    bound = 2 * 2 * gamma * _per_step_cotangents(zs, x0, P0, PHI)
    diff = np.abs(np.asarray(g1) - np.asarray(g0))
    print("gradient", np.asarray(g0), "|difference|", diff, "bound", bound)
    assert np.all(diff <= bound), (diff, bound)
    # memory: reverse mode keeps the residuals of every step, T b bytes (b per step: per run the
    # state and the innovations); with c steps per segment it keeps the state at the start of each
    # segment, b0 <= about b (x, P, s), and the residuals of one segment at a time:
    # (T/c) b0 + c b (+ the remainder's, < c b). At T = 4096, c = 60 the ratio is T / (T/c + c) = 32
    # for b0 = b (21 for b0 = 2 b); asserted: > 8, a further factor 2.5 for the temporaries whose
    # size does not grow with T (the covariance step, one segment's gains). memory_analysis is
    # XLA's buffer assignment of the compiled program, not a measurement: the same on every machine
    # of a backend
    mem = {c: p.memory_analysis() for c, p in prog.items()}
    if mem[None] is None:
        pytest.skip("this JAX backend reports no memory analysis")
    print("temp bytes", mem[None].temp_size_in_bytes, "with checkpoint", mem[C_CK].temp_size_in_bytes)
    assert mem[None].temp_size_in_bytes > 8 * mem[C_CK].temp_size_in_bytes


def test_bad_checkpoint_is_named():
    zs, x0, P0 = data(np.random.default_rng(34), T=10, runs=2, missing="none")
    for bad in (0, -3):
        with pytest.raises(ValueError, match=r"^checkpoint must be a positive int .*got " + str(bad)):
            tuning.total_loglik(jnp.asarray(PHI), _build, zs, x0, P0, checkpoint=bad)
    for bad in (2.5, True, "64", np.array([4])):
        with pytest.raises(TypeError, match=r"^checkpoint must be None or a positive int"):
            tuning.total_loglik(jnp.asarray(PHI), _build, zs, x0, P0, checkpoint=bad)
    # the NumPy engine keeps no residuals: a valid checkpoint changes nothing there
    assert tuning.total_loglik(PHI, _build, zs, x0, P0, checkpoint=np.int64(3)) == tuning.total_loglik(
        PHI, _build, zs, x0, P0)
