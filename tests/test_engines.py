"""The two engines of kftrack.engines run the same kernels: the JAX engine (jax.lax.scan under
jax.jit) agrees with the NumPy engine (the Python loop) to a derived round-off bound on every
whole-sequence filter, JAX in gives JAX out, float32 is an explicit choice with its documented
loss, and bad input is named.

Round-off bound used throughout. The engines evaluate the same equations with different
floating-point orderings (XLA fuses and reorders products; for SPD matrices up to 8 x 8 the JAX
engine solves by an unrolled Cholesky factorization, NumPy by LAPACK's LU). Each step is backward
stable, with a relative perturbation of at most about c * n * eps per step in every output
(c a small constant, n the state size). The filter recursion is stable (errors are damped, not
amplified, by (I - KH) F), and the solves amplify a relative perturbation by at most cond(S)
(cond(P_prior) in the smoother), so after T steps

    |engine difference| <= T * n * cond * eps * scale,

with scale the largest magnitude of the compared quantity and cond the largest condition number
of the innovation covariances met. Measured on these problems: the differences are 20 to 300
times below the bound for the linear filters and the IMM (with n -> r n for the IMM's mixing),
about 1e3 times for the RTS smoother (cond(P_prior) in the bound), and about 3e4 times below for the range-bearing EKF/UKF, whose cond(S) ~ 1.6e4 comes from mixing
units (m and rad), not from instability. The bound stays informative: below 1e-9 relative
(1e-4 with float32's eps).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from array_api_compat import array_namespace

from kftrack import engines, imm
from kftrack.ekf import extended_kalman_filter
from kftrack.kalman import kalman_filter, rts_smoother
from kftrack.models import ConstantVelocity, KnownTurn
from kftrack.ukf import unscented_kalman_filter

jax.config.update("jax_enable_x64", True)  # the engines' float64 default needs it (see kftrack.engines)

EPS64 = np.finfo(np.float64).eps
EPS32 = np.finfo(np.float32).eps
MODEL = ConstantVelocity(ndim=2, q=0.5)
H = MODEL.H
# correlated measurement noise: S then has off-diagonal entries at every step, so the unrolled
# Cholesky solve of the JAX engine is exercised in full (with a diagonal R and this model S stays
# diagonal, and a wrong off-diagonal term of the solve would go unnoticed)
R = np.array([[4.0, 1.5], [1.5, 3.0]])


def data(rng, T=60, runs=20, missing="mixed"):
    zs = rng.normal(scale=3.0, size=(T, runs, 2)).cumsum(0)
    if missing in ("mixed", "shared"):
        zs[7] = np.nan  # every run
    if missing == "mixed":
        zs[11, 3] = np.nan  # one run only: per-run covariances
        zs[T - 1, 0] = np.nan
    return zs, np.zeros(4), np.diag([50.0, 10.0, 50.0, 10.0])


def cond_S(res, H, R):
    """Largest condition number of the innovation covariances H P^- H^T + R met by a result."""
    P = np.asarray(res.P_prior)
    S = H @ P @ H.T + R
    return float(np.max(np.linalg.cond(S.reshape((-1,) + S.shape[-2:]))))


def _agree(a, b, T, n, cond, eps=EPS64, names=None):
    """Every field of NumPy result ``a`` and JAX result ``b`` agree within T n cond eps scale;
    NaN exactly where the other has NaN. Returns the largest ratio difference / bound."""
    worst = 0.0
    names = names or getattr(a, "_fields", None) or range(len(a))
    for name, u, v in zip(names, a, b):
        if u is None:
            continue
        u, v = np.asarray(u), np.asarray(v)
        assert u.shape == v.shape, name
        assert np.array_equal(np.isnan(u), np.isnan(v)), name
        scale = np.nanmax(np.abs(u)) + np.finfo(float).tiny
        bound = T * n * cond * eps * scale
        diff = np.nanmax(np.abs(u - v))
        assert diff <= bound, (name, diff, bound)
        worst = max(worst, diff / bound)
    return worst


def jx(*arrays):
    return tuple(jnp.asarray(a) for a in arrays)


# --------------------------------------------------------------------------------------------
# the linear filter
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("missing", ["none", "shared", "mixed"])
def test_kalman_filter_engines_agree(missing):
    zs, x0, P0 = data(np.random.default_rng(1), missing=missing)
    F, Q = MODEL.F(1.0), MODEL.Q(1.0)
    a = kalman_filter(zs, x0, P0, F, Q, H, R)
    b = kalman_filter(*jx(zs), x0, P0, F, Q, H, R)
    assert all(isinstance(v, jax.Array) for v in b)
    assert b.x.dtype == jnp.float64
    _agree(a, b, zs.shape[0], 4, cond_S(a, H, R))


def test_kalman_filter_irregular_and_time_varying_engines_agree():
    rng = np.random.default_rng(2)
    zs, x0, P0 = data(rng)
    T = zs.shape[0]
    dts = rng.choice([0.3, 1.0, 2.2], size=T)
    a = kalman_filter(zs, x0, P0, MODEL.F, MODEL.Q, H, R, dt=dts)
    b = kalman_filter(jnp.asarray(zs), x0, P0, MODEL.F, MODEL.Q, H, R, dt=dts)
    _agree(a, b, T, 4, cond_S(a, H, R))
    Fs = np.stack([MODEL.F(d) for d in dts])
    Qs = np.stack([MODEL.Q(d) for d in dts])
    c = kalman_filter(jnp.asarray(zs), x0, P0, *jx(Fs, Qs), H, R, time_varying=True)
    _agree(a, c, T, 4, cond_S(a, H, R))


def test_batched_parameters_run_per_run_covariances_on_both_engines():
    rng = np.random.default_rng(3)
    zs, x0, P0 = data(rng, runs=6, missing="shared")
    Rb = np.stack([R * s for s in np.linspace(0.5, 3.0, 6)])  # one R per run
    a = kalman_filter(zs, x0, P0, MODEL.F(1.0), MODEL.Q(1.0), H, Rb)
    b = kalman_filter(*jx(zs, x0, P0), MODEL.F(1.0), MODEL.Q(1.0), H, jnp.asarray(Rb))
    _agree(a, b, zs.shape[0], 4, cond_S(a, H, Rb))
    # and the runs really differ: run 0 (small R) follows the data more closely than run 5
    assert np.asarray(b.P)[-1, 0, 0, 0] < np.asarray(b.P)[-1, 5, 0, 0]


def test_shared_covariance_recursion_equals_the_batched_one():
    # the same equations on an unbatched P: NumPy gives the same bits; JAX agrees to the bound
    zs, x0, P0 = data(np.random.default_rng(4), missing="shared")
    F, Q = MODEL.F(1.0), MODEL.Q(1.0)
    shared = kalman_filter(zs, x0, P0, F, Q, H, R)
    batched = kalman_filter(zs, x0, np.broadcast_to(P0, (20, 4, 4)), F, Q, H, R)
    assert all(np.array_equal(u, v, equal_nan=True) for u, v in zip(shared, batched))
    bj = kalman_filter(*jx(zs), x0, np.broadcast_to(P0, (20, 4, 4)), F, Q, H, R)
    sj = kalman_filter(*jx(zs), x0, P0, F, Q, H, R)
    _agree(batched, bj, zs.shape[0], 4, cond_S(shared, H, R))
    _agree(shared, sj, zs.shape[0], 4, cond_S(shared, H, R))


@pytest.mark.parametrize("form", ["shared", "mixed", "per_run_R", "time_varying"])
def test_priors_false_drops_the_predictions_and_keeps_the_rest(form):
    rng = np.random.default_rng(16)
    zs, x0, P0 = data(rng, missing="shared" if form == "shared" else "mixed")
    T = zs.shape[0]
    F, Q, R_, kw = MODEL.F(1.0), MODEL.Q(1.0), R, {}
    if form == "per_run_R":
        R_ = np.stack([R * s for s in np.linspace(0.5, 3.0, zs.shape[1])])
    elif form == "time_varying":
        dts = rng.choice([0.3, 1.0, 2.2], size=T)
        F, Q, kw = np.stack([MODEL.F(d) for d in dts]), np.stack([MODEL.Q(d) for d in dts]), {"time_varying": True}
    a = kalman_filter(zs, x0, P0, F, Q, H, R_, **kw)
    a0 = kalman_filter(zs, x0, P0, F, Q, H, R_, priors=False, **kw)
    assert a0.x_prior is None and a0.P_prior is None
    # NumPy engine: the same operations in the same order, only fewer stores: the same bits
    for name in ("x", "P", "nis", "loglik"):
        assert np.array_equal(getattr(a, name), getattr(a0, name), equal_nan=True), name
    b = kalman_filter(*jx(zs), x0, P0, F, Q, H, R_, **kw)
    b0 = kalman_filter(*jx(zs), x0, P0, F, Q, H, R_, priors=False, **kw)
    assert b0.x_prior is None and b0.P_prior is None
    assert all(isinstance(getattr(b0, k), jax.Array) for k in ("x", "P", "nis", "loglik"))
    # JAX engine: another compiled program (fewer outputs), which XLA may fuse differently, so the
    # engines' bound T n cond eps scale (measured on x86-64 with jax 0.10.2: the same bits)
    post = b._fields[2:]  # x, P, nis, loglik
    _agree(b[2:], b0[2:], T, 4, cond_S(a, H, R_), names=post)
    _agree(a[2:], b0[2:], T, 4, cond_S(a, H, R_), names=post)
    for res in (a0, b0):
        with pytest.raises(ValueError, match=r"^result has no priors .*priors=True"):
            rts_smoother(res, F, **kw)


def test_priors_false_compiled_program_writes_only_the_posteriors():
    # the JAX engine's compiled program: its outputs are x, P, nis, loglik only (no predictions)
    zs, x0, P0 = data(np.random.default_rng(17), T=50, runs=30, missing="none")
    T, runs, n = zs.shape[0], zs.shape[1], 4
    F, Q = MODEL.F(1.0), MODEL.Q(1.0)
    size = {}
    for priors in (True, False):
        fn = jax.jit(lambda z, p=priors: kalman_filter(z, x0, P0, F, Q, H, R, priors=p))
        mem = fn.lower(jnp.asarray(zs)).compile().memory_analysis()
        if mem is None:
            pytest.skip("this JAX backend reports no memory analysis")
        size[priors] = mem.output_size_in_bytes
    per_step = {True: 2 * (n + n * n) + 2, False: n + n * n + 2}  # numbers per run and step
    for priors, count in per_step.items():
        data_bytes = T * runs * count * 8
        assert data_bytes <= size[priors] < data_bytes + 1024, (priors, size[priors], data_bytes)  # + a few pointers


@pytest.mark.parametrize("which", ["P0", "F", "Q", "H", "R", "missing"])
def test_per_run_covariances_are_never_shared(which):
    # one input differs between runs (or one run misses a row the others have): the covariance
    # recursion differs per run and the shared path would be wrong. Both engines must equal, run
    # by run, the filter of that run alone (NumPy: the same operations, to a few eps; JAX: the bound)
    rng = np.random.default_rng(15)
    runs = 4
    zs, x0, P0 = data(rng, T=30, runs=runs, missing="shared")
    T = zs.shape[0]
    s = np.linspace(0.5, 2.0, runs)
    F, Q = MODEL.F(1.0), MODEL.Q(1.0)
    kw = dict(P0=P0, F=F, Q=Q, H=H, R=R)
    tv = which in ("F", "Q")  # per-run transitions as (T, runs, n, n) stacks
    if tv:
        kw["F"], kw["Q"] = np.broadcast_to(F, (T, runs, 4, 4)), np.broadcast_to(Q, (T, runs, 4, 4))
    if which == "P0":
        kw["P0"] = P0 * s[:, None, None]
    elif which == "F":
        kw["F"] = np.stack([[ConstantVelocity(ndim=2, q=0.5).F(d) for d in s]] * T)
    elif which == "Q":
        kw["Q"] = np.broadcast_to(Q * s[:, None, None], (T, runs, 4, 4))
    elif which == "H":
        kw["H"] = H * s[:, None, None]
    elif which == "R":
        kw["R"] = R * s[:, None, None]
    else:
        zs[11, 2] = np.nan
    a = kalman_filter(zs, x0, kw["P0"], kw["F"], kw["Q"], kw["H"], kw["R"], time_varying=tv)
    b = kalman_filter(*jx(zs), x0, kw["P0"], kw["F"], kw["Q"], kw["H"], kw["R"], time_varying=tv)
    for i in range(runs):
        one = {k: (v[:, i] if tv and k in ("F", "Q") else v[i]) if np.ndim(v) > {"P0": 2, "F": 2, "Q": 2, "H": 2,
               "R": 2}[k] else v for k, v in kw.items()}
        ref = kalman_filter(zs[:, i], x0, one["P0"], one["F"], one["Q"], one["H"], one["R"], time_varying=tv)
        got = [u[:, i] for u in a]
        _agree(ref, got, T, 4, cond_S(ref, one["H"], one["R"]), names=ref._fields)
        _agree(ref, [u[:, i] for u in b], T, 4, cond_S(ref, one["H"], one["R"]), names=ref._fields)
    # and the runs really differ (a shared recursion would make them equal at every step)
    assert np.max(np.abs(a.P[:, 0] - a.P[:, 2])) > 1e-3 * np.max(np.abs(a.P[:, 0]))


def test_float32_is_explicit_and_loses_what_is_documented():
    zs, x0, P0 = data(np.random.default_rng(5))
    F, Q = MODEL.F(1.0), MODEL.Q(1.0)
    a = kalman_filter(zs, x0, P0, F, Q, H, R)
    b = kalman_filter(*jx(zs), x0, P0, F, Q, H, R, dtype="float32")
    assert b.x.dtype == jnp.float32 and b.P.dtype == jnp.float32
    # the documented loss: round-off 2**-24 instead of 2**-53 per operation, so the bound with eps32
    ratio = _agree(a, b, zs.shape[0], 4, cond_S(a, H, R), eps=EPS32)
    assert ratio > 0  # float32 really was used (not silently float64)
    assert np.nanmax(np.abs(np.asarray(b.x) - a.x)) > 1e3 * EPS64 * np.max(np.abs(a.x))
    c = kalman_filter(zs, x0, P0, F, Q, H, R, dtype="float32")  # the NumPy engine honours it too
    assert all(v.dtype == np.float32 for v in c)
    assert _agree(a, c, zs.shape[0], 4, cond_S(a, H, R), eps=EPS32) > 0
    # the carried state really is float32 (not float64 rounded only on output): a float64 recursion
    # stored as float32 would differ from float64 by at most eps32/2 relative in every entry (the
    # rounding of the output), plus the float64 round-off T n cond eps64, far below it
    excess = np.abs(c.x - a.x) - (EPS32 / 2 + 60 * 4 * cond_S(a, H, R) * EPS64) * np.abs(a.x)
    assert np.nanmax(excess) > 0


def test_float64_without_x64_names_the_fix():
    zs, x0, P0 = data(np.random.default_rng(6), T=5, runs=2, missing="none")
    z32 = jnp.asarray(zs, dtype=jnp.float32)
    jax.config.update("jax_enable_x64", False)
    try:
        with pytest.raises(ValueError, match="^dtype: the JAX engine computes in float64.*jax_enable_x64"):
            kalman_filter(z32, x0, P0, MODEL.F(1.0), MODEL.Q(1.0), H, R)
        b = kalman_filter(z32, x0, P0, MODEL.F(1.0), MODEL.Q(1.0), H, R, dtype="float32")
        assert b.x.dtype == jnp.float32
    finally:
        jax.config.update("jax_enable_x64", True)


def test_bad_input_is_named_on_the_jax_path():
    zs, x0, P0 = data(np.random.default_rng(7), T=5, runs=2, missing="none")
    F, Q = MODEL.F(1.0), MODEL.Q(1.0)
    z = jnp.asarray(zs)
    with pytest.raises(ValueError, match=r"^P0 must have shape \(\.\.\., 4, 4\), got shape \(3, 3\)"):
        kalman_filter(z, x0, jnp.eye(3), F, Q, H, R)
    with pytest.raises(ValueError, match=r"^H must have shape \(\.\.\., 2, 4\)"):
        kalman_filter(z, x0, P0, F, Q, jnp.eye(3, 4), R)
    with pytest.raises(ValueError, match="^R must be positive definite"):
        kalman_filter(z, x0, P0, F, Q, H, -jnp.asarray(R))
    with pytest.raises(ValueError, match="^zs must be finite or NaN"):
        kalman_filter(z.at[0, 0, 0].set(jnp.inf), x0, P0, F, Q, H, R)
    with pytest.raises(ValueError, match="^dtype must be None, 'float64' or 'float32'"):
        kalman_filter(z, x0, P0, F, Q, H, R, dtype="float16")
    with pytest.raises(ValueError, match=r"^F must have shape \(\.\.\., 4, 4\)"):
        rts_smoother(kalman_filter(z, x0, P0, F, Q, H, R), jnp.eye(3))


@pytest.mark.parametrize("form", ["constant", "dt", "time_varying"])
def test_rts_smoother_engines_agree(form):
    rng = np.random.default_rng(14)
    zs, x0, P0 = data(rng, T=40, runs=5)
    T = zs.shape[0]
    dts = rng.choice([0.5, 1.0, 2.0], size=T)
    if form == "constant":
        Fa, Qa, kw = MODEL.F(1.0), MODEL.Q(1.0), {}
    elif form == "dt":
        Fa, Qa, kw = MODEL.F, MODEL.Q, {"dt": dts}
    else:
        Fa, Qa, kw = np.stack([MODEL.F(d) for d in dts]), np.stack([MODEL.Q(d) for d in dts]), {"time_varying": True}
    a = kalman_filter(zs, x0, P0, Fa, Qa, H, R, **kw)
    b = kalman_filter(jnp.asarray(zs), x0, P0, Fa, Qa, H, R, **kw)
    sa, sb = rts_smoother(a, Fa, **kw), rts_smoother(b, Fa, **kw)
    assert isinstance(sb.x, jax.Array)
    # the smoother solves with P_prior: its condition number enters the bound
    cond = max(cond_S(a, H, R), float(np.max(np.linalg.cond(np.asarray(a.P_prior).reshape(-1, 4, 4)))))
    _agree(sa, sb, T, 4, cond)


def test_jax_engine_traces_for_gradients():
    # inside jax.grad the noise is abstract: shapes are still checked, values cannot be
    zs, x0, P0 = data(np.random.default_rng(8), T=30, runs=3, missing="shared")
    z = jnp.asarray(zs)

    def total_loglik(log_r):
        res = kalman_filter(z, x0, P0, MODEL.F(1.0), MODEL.Q(1.0), H, jnp.exp(log_r) * jnp.eye(2))
        return jnp.nansum(res.loglik)

    g = float(jax.grad(total_loglik)(jnp.log(4.0)))
    h = 1e-4  # central difference: truncation h^2 |f'''| / 6, with |f'''| ~ |f'| here: ~1e-9 |f'|
    fd = (float(total_loglik(jnp.log(4.0) + h)) - float(total_loglik(jnp.log(4.0) - h))) / (2 * h)
    # round-off of the difference quotient: eps |f| / h
    tol = 1e-8 * abs(fd) + 10 * EPS64 * abs(float(total_loglik(jnp.log(4.0)))) / h
    assert abs(g - fd) <= tol
    with pytest.raises(ValueError, match=r"^R must have shape \(\.\.\., 2, 2\)"):
        jax.grad(lambda s: jnp.nansum(kalman_filter(z, x0, P0, MODEL.F(1.0), MODEL.Q(1.0), H,
                                                    s * jnp.eye(3)).loglik))(1.0)


# --------------------------------------------------------------------------------------------
# the IMM
# --------------------------------------------------------------------------------------------
def bank():
    modes = [imm.KalmanMode(ConstantVelocity(ndim=2, q=0.1), R), imm.KalmanMode(KnownTurn(omega=0.15, q=0.1), R),
             imm.KalmanMode(KnownTurn(omega=-0.15, q=0.1), R)]
    return modes, np.full((3, 3), 0.05) + 0.85 * np.eye(3)


@pytest.mark.parametrize("kind", ["IMM", "GPB1", "sojourn"])
def test_imm_filter_engines_agree(kind):
    rng = np.random.default_rng(9)
    zs, x0, P0 = data(rng, T=40, runs=10)
    modes, Pi = bank()
    if kind == "IMM":
        est, dt = imm.IMM(modes, Pi, np.ones(3) / 3), 1.0
    elif kind == "GPB1":
        est, dt = imm.GPB1(modes, Pi, np.ones(3) / 3), 1.0
    else:  # irregular sampling, Pi(dt) from sojourn times
        est, dt = imm.IMM(modes, imm.SojournTransition([20.0, 8.0, 8.0]), np.ones(3) / 3), rng.choice([0.5, 1.5], 40)
    a = imm.imm_filter(est, zs, x0, P0, dt)
    b = imm.imm_filter(est, jnp.asarray(zs), x0, P0, dt)
    assert isinstance(b.x, jax.Array) and isinstance(b.xs[0], jax.Array)
    # mixing adds r modes' terms per step: n -> r n in the bound
    cond = max(float(np.max(np.linalg.cond((H @ np.asarray(Pm) @ H.T + R).reshape(-1, 2, 2)))) for Pm in a.Ps)
    _agree(tuple(a[:7]), tuple(b[:7]), 40, 3 * 4, cond, names=a._fields[:7])
    _agree(a.xs + a.Ps, b.xs + b.Ps, 40, 3 * 4, cond)


def test_imm_jax_engine_refuses_what_it_cannot_run():
    modes, Pi = bank()
    from kftrack.models import CoordinatedTurn

    ekf_bank = imm.IMM([modes[0], imm.EKFMode(CoordinatedTurn(q=0.1, q_omega=0.01), R)], np.full((2, 2), 0.5),
                       np.ones(2) / 2)
    zs, x0, P0 = data(np.random.default_rng(10), T=5, runs=2, missing="none")
    with pytest.raises(TypeError, match="^estimator: the JAX engine of imm_filter runs banks of KalmanMode"):
        imm.imm_filter(ekf_bank, jnp.asarray(zs), np.zeros(5), np.eye(5), 1.0)


# --------------------------------------------------------------------------------------------
# EKF and UKF with model functions written once for both array libraries
# --------------------------------------------------------------------------------------------
SENSOR = np.array([-40.0, 30.0])


def f(x):  # constant velocity, dt = 1 (written with the array API, so NumPy and JAX both run it)
    xp = array_namespace(x)
    F = xp.asarray(MODEL.F(1.0), dtype=x.dtype)
    return (F @ x[..., None])[..., 0]


def F_jac(x):
    xp = array_namespace(x)
    return xp.broadcast_to(xp.asarray(MODEL.F(1.0), dtype=x.dtype), x.shape[:-1] + (4, 4))


def h(x):  # range and bearing from SENSOR
    xp = array_namespace(x)
    dx, dy = x[..., 0] - SENSOR[0], x[..., 2] - SENSOR[1]
    return xp.stack([xp.sqrt(dx**2 + dy**2), xp.atan2(dy, dx)], axis=-1)


def H_jac(x):
    xp = array_namespace(x)
    dx, dy = x[..., 0] - SENSOR[0], x[..., 2] - SENSOR[1]
    r2 = dx**2 + dy**2
    r = xp.sqrt(r2)
    z = xp.zeros_like(r)
    return xp.stack([xp.stack([dx / r, z, dy / r, z], axis=-1), xp.stack([-dy / r2, z, dx / r2, z], axis=-1)],
                    axis=-2)


def polar_data(rng, T=40, runs=8):
    truth = np.zeros((T, runs, 4))
    truth[0] = [10.0, 1.0, 5.0, 0.5]
    for k in range(1, T):
        truth[k] = truth[k - 1] @ MODEL.F(1.0).T + rng.multivariate_normal(np.zeros(4), MODEL.Q(1.0), runs)
    zs = h(truth) + rng.normal(size=(T, runs, 2)) * [1.0, 0.01]
    zs[9] = np.nan
    zs[13, 2] = np.nan
    return zs, truth[0].mean(0), np.diag([20.0, 4.0, 20.0, 4.0])


def test_extended_kalman_filter_engines_agree():
    zs, x0, P0 = polar_data(np.random.default_rng(11))
    Rp = np.diag([1.0, 1e-4])
    a = extended_kalman_filter(zs, x0, P0, f, F_jac, MODEL.Q(1.0), h, H_jac, Rp, angle_components=[1])
    b = extended_kalman_filter(jnp.asarray(zs), x0, P0, f, F_jac, MODEL.Q(1.0), h, H_jac, Rp, angle_components=[1])
    assert isinstance(b.x, jax.Array)
    Hs = H_jac(np.asarray(a.x_prior))
    S = Hs @ a.P_prior @ np.swapaxes(Hs, -1, -2) + Rp
    _agree(a, b, zs.shape[0], 4, float(np.max(np.linalg.cond(S.reshape(-1, 2, 2)))))
    # a linear measurement given as a matrix, per-step R
    Rs = np.broadcast_to(R, (zs.shape[0], 2, 2))
    zc = np.random.default_rng(12).normal(size=zs.shape).cumsum(0)
    c = extended_kalman_filter(zc, x0, P0, f, F_jac, MODEL.Q(1.0), H, None, Rs, R_per_step=True)
    d = extended_kalman_filter(jnp.asarray(zc), x0, P0, f, F_jac, MODEL.Q(1.0), H, None, Rs, R_per_step=True)
    _agree(c, d, zs.shape[0], 4, cond_S(c, H, R))


def test_unscented_kalman_filter_engines_agree():
    zs, x0, P0 = polar_data(np.random.default_rng(13))
    Rp = np.diag([1.0, 1e-4])
    a = unscented_kalman_filter(zs, x0, P0, f, MODEL.Q(1.0), h, Rp, angle_components=[1])
    b = unscented_kalman_filter(jnp.asarray(zs), x0, P0, f, MODEL.Q(1.0), h, Rp, angle_components=[1])
    assert isinstance(b.x, jax.Array)
    Hs = H_jac(np.asarray(a.x_prior))
    S = Hs @ a.P_prior @ np.swapaxes(Hs, -1, -2) + Rp
    # the sigma points add a Cholesky factor and 2n + 1 weighted terms: n -> 2n + 1
    _agree(a, b, zs.shape[0], 9, float(np.max(np.linalg.cond(S.reshape(-1, 2, 2)))))


def test_engine_choice():
    assert not engines.use_jax(np.zeros(2), 1.0, None)
    assert engines.use_jax(np.zeros(2), jnp.zeros(2))
