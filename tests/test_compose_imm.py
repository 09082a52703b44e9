"""The IMM composes with JAX's transformations (issue 27): kftrack.imm.imm_loglik, the IMM of a
linear mode bank as a pure function of one NamedTuple of arrays (IMMParams), runs inside the
caller's jax.jit and jax.vmap (over a mode's noise level) and under jax.grad of its total
log-likelihood with respect to the modes' log noise levels and the logits of the Markov matrix.

Bounds (those of tests/test_compose.py, with the IMM's n -> r n of tests/test_engines.py: the
mixing adds r modes' terms per step). Values: |difference| <= T r n kappa eps scale per field,
kappa the largest condition number of the innovation covariances H P H^T + R met (over the
modes' posteriors and the combined prior). The total log-likelihood, a sum of N per-step terms
each within that bound of its own size: delta = N T r n kappa eps max|term|. Gradients: the
exact JAX gradient against central differences of the NumPy engine (tests/test_tuning.py's
_central_difference: truncation h^2 |f'''| / 6, f''' from a 5-point difference, plus round-off
delta / h), plus delta for the JAX gradient's own round-off. Power: a gradient 1 % off would
fail (twice the bound is below 1 % of every component).

The IMM smoother (kftrack.imm.imm_smoother, Kim's backward pass) on the JAX engine: after the
filter's T steps, T - 1 backward steps, each an RTS step per pair of modes whose gain solves
with the pair's prediction F_j P^i F_j^T + Q_j; so the bound 2T r n kappa eps scale per field,
kappa the largest condition number of the innovation covariances (as above) and of those pair
predictions. A scalar of the smoothed means, f = sum of squares of the smoothed positions:
delta_f = 2 sum|x| times the bound of x (first order).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from kftrack import imm
from kftrack.kalman import kalman_filter
from kftrack.models import ConstantVelocity, KnownTurn
from test_compose import _check_gradient
from test_engines import EPS64, _agree, cond_S
from test_tuning import _central_difference

jax.config.update("jax_enable_x64", True)  # the engines' float64 default needs it (see kftrack.engines)

T, RUNS, N, DT = 20, 3, 4, 1.0
R = np.array([[4.0, 1.5], [1.5, 3.0]])  # correlated, as in tests/test_engines.py
H = ConstantVelocity(ndim=2, q=1.0).H
# two modes: nearly constant velocity and a known turn; Q_i = q_i * QBAR[i]
F_MODES = np.stack([ConstantVelocity(ndim=2, q=1.0).F(DT), KnownTurn(omega=0.15, q=1.0).F(DT)])
QBAR = np.stack([ConstantVelocity(ndim=2, q=1.0).Q(DT), KnownTurn(omega=0.15, q=1.0).Q(DT)])
# phi = (log q_0, log q_1, L_00, L_01, L_10, L_11): away from the maximum, gradient O(1)
PHI = np.array([np.log(0.1), np.log(0.5), 2.0, -0.5, -0.3, 1.2])
LOG_MU0 = np.log([0.6, 0.4])
STEP = 1e-3  # central-difference step in phi
JIT = {"compiler_options": {"xla_backend_optimization_level": 0}}  # as tests/test_compose.py


class _Fixed:
    """A linear model with fixed F, Q (the NumPy engine's reference for given arrays)."""

    def __init__(self, F, Q):
        self.n, self.H, self._F, self._Q = F.shape[-1], H, F, Q

    def F(self, dt):
        return self._F

    def Q(self, dt):
        return self._Q


def _softmax(a):
    e = np.exp(a - a.max(-1, keepdims=True))
    return e / e.sum(-1, keepdims=True)


def _params(phi, xp=np):
    q = xp.exp(phi[:2])
    return imm.IMMParams(F_MODES, q[:, None, None] * QBAR, H, R, xp.reshape(phi[2:], (2, 2)), LOG_MU0)


def _numpy_bank(phi):
    """The IMM (KalmanMode bank) that IMMParams(phi) describes."""
    q = np.exp(phi[:2])
    return imm.IMM([imm.KalmanMode(_Fixed(F_MODES[i], q[i] * QBAR[i]), R) for i in range(2)],
                   _softmax(phi[2:].reshape(2, 2)), _softmax(LOG_MU0))


def _numpy_run(phi, zs, x0, P0):
    """imm_filter on the NumPy engine with the IMM that IMMParams(phi) describes."""
    return imm.imm_filter(_numpy_bank(phi), zs, x0, P0, DT)


def _total(res):
    """sum over measured steps of log sum_j mu_prior_j exp(loglik_j), per run (NumPy)."""
    ll = np.asarray(res.loglik)
    gone = np.isnan(ll).all(-1)
    step = np.log(np.sum(np.asarray(res.mu_prior) * np.exp(np.where(gone[..., None], 0.0, ll)), -1))
    return np.where(gone, 0.0, step).sum(0)


def _kappa(res):
    Ps = [np.asarray(P) for P in res.Ps] + [np.asarray(res.P_prior)]
    return max(float(np.max(np.linalg.cond((H @ P @ H.T + R).reshape(-1, 2, 2)))) for P in Ps)


def _delta(res):
    """Round-off bound of a total log-likelihood (module docstring)."""
    ll = np.asarray(res.loglik)
    return np.sum(np.isfinite(ll)) * T * 2 * N * _kappa(res) * EPS64 * float(np.nanmax(np.abs(ll)))


def _data(seed, missing=True):
    rng = np.random.default_rng(seed)
    zs = rng.normal(scale=3.0, size=(T, RUNS, 2)).cumsum(0)
    if missing:
        zs[7] = np.nan  # every run
        zs[11, 1] = np.nan  # one run only
    return zs, np.zeros(N), np.diag([50.0, 10.0, 50.0, 10.0])


def _agree_imm(ref, res, kappa):
    _agree(tuple(ref[:7]), tuple(res[:7]), T, 2 * N, kappa, names=ref._fields[:7])
    _agree(ref.xs + ref.Ps, res.xs + res.Ps, T, 2 * N, kappa)


# --------------------------------------------------------------------------------------------
# (a) the entry point is imm_filter
# --------------------------------------------------------------------------------------------
def test_imm_loglik_equals_imm_filter_on_the_numpy_engine():
    zs, x0, P0 = _data(31)
    ref = _numpy_run(PHI, zs, x0, P0)
    # imm_params of the same estimator gives the same arrays
    est = _numpy_bank(PHI)
    p = imm.imm_params(est, DT)
    assert np.allclose(p.Q, _params(PHI).Q, rtol=0, atol=0) and np.allclose(_softmax(p.logits), est.transition(DT))
    for missing in (None, np.isnan(zs).all(-1)):  # NaN rows found, or a concrete mask
        ell, res = jax.jit(lambda z, m=missing: imm.imm_loglik(p, z, x0, P0, missing=m), **JIT)(jnp.asarray(zs))
        assert isinstance(res.x, jax.Array) and ell.shape == (RUNS,)
        _agree_imm(ref, res, _kappa(ref))
        assert np.all(np.abs(np.asarray(ell) - _total(ref)) <= _delta(ref))
    # independent of the formula of _total: one mode is the Kalman filter, ell its summed loglik;
    # a direct call with NumPy data of one run, no row missing (missing=False)
    zs1 = _data(32, missing=False)[0][:, 0]
    kf = kalman_filter(zs1, x0, P0, F_MODES[0], QBAR[0], H, R)
    one = imm.IMMParams(F_MODES[:1], QBAR[:1], H, R, np.zeros((1, 1)), np.zeros(1))
    ell1, res1 = imm.imm_loglik(one, zs1, x0, P0, missing=False)
    assert ell1.shape == () and res1.x.shape == (T, N)
    ll = np.asarray(kf.loglik)
    bound = np.sum(np.isfinite(ll)) * T * N * cond_S(kf, H, R) * EPS64 * float(np.nanmax(np.abs(ll)))
    assert abs(float(ell1) - np.sum(ll)) <= bound
    _agree((kf.x, kf.P), (res1.x, res1.P), T, N, cond_S(kf, H, R))


# --------------------------------------------------------------------------------------------
# (b) jit and vmap over a mode's noise level
# --------------------------------------------------------------------------------------------
def test_vmap_over_a_noise_level_agrees_with_separate_calls():
    zs, x0, P0 = _data(33)
    qs = np.geomspace(0.05, 5.0, 8)  # q_1 of the turning mode

    def run(q1):
        phi = jnp.asarray(PHI).at[1].set(jnp.log(q1))
        return imm.imm_loglik(_params(phi, jnp), jnp.asarray(zs), x0, P0)

    ells, mapped = jax.jit(jax.vmap(run), **JIT)(jnp.asarray(qs))
    assert ells.shape == (8, RUNS)
    for i, q1 in enumerate(qs):
        phi = PHI.copy()
        phi[1] = np.log(q1)
        ref = _numpy_run(phi, zs, x0, P0)
        k = _kappa(ref)
        _agree_imm(ref, jax.tree_util.tree_map(lambda v: v[i], mapped), k)
        assert np.all(np.abs(np.asarray(ells[i]) - _total(ref)) <= _delta(ref))


# --------------------------------------------------------------------------------------------
# (c) grad of the total log-likelihood: noise levels and transition logits
# --------------------------------------------------------------------------------------------
def test_grad_wrt_log_noise_levels_and_logits_matches_central_differences():
    zs, x0, P0 = _data(34)
    zj = jnp.asarray(zs)

    def ell_np(phi):
        return float(_total(_numpy_run(phi, zs, x0, P0)).sum())

    # jax.grad over the NamedTuple itself (has_aux: the per-run values ride along), then the
    # chain rule to phi: d/dlog q_i = <dl/dQ_i, Q_i>, the logits directly
    params = jax.tree_util.tree_map(jnp.asarray, _params(PHI))
    # sequence=False: the sum alone, from a loop that stores nothing per step (engines.run_imm_total_scan)
    g, ell = jax.jit(jax.grad(lambda p: (lambda e, r: (e.sum(), e))(*imm.imm_loglik(p, zj, x0, P0, sequence=False)),
                              has_aux=True), **JIT)(params)
    value = float(np.sum(ell))
    grad = np.concatenate([np.sum(np.asarray(g.Q) * np.asarray(params.Q), axis=(1, 2)), np.asarray(g.logits).ravel()])
    ref = _numpy_run(PHI, zs, x0, P0)
    delta = _delta(ref)
    assert abs(value - ell_np(PHI)) <= 2 * delta
    # per run too (the sum of the NumPy engine's terms, test (a)'s reference)
    assert np.all(np.abs(np.asarray(ell) - _total(ref)) <= 2 * delta)
    # a row's logits shifted together leave Pi unchanged: each row of dl/dL sums to 0 (round-off: delta)
    assert abs(grad[2] + grad[3]) <= 2 * delta and abs(grad[4] + grad[5]) <= 2 * delta
    fd, bound = _central_difference(ell_np, PHI, np.full(PHI.size, STEP), delta)
    _check_gradient(grad, fd, bound + delta, "imm")


# --------------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------------
def test_bad_params_are_named():
    zs, x0, P0 = _data(35, missing=False)
    p = _params(PHI)
    with pytest.raises(TypeError, match=r"^params must be an IMMParams, got tuple"):
        imm.imm_loglik(tuple(p), zs, x0, P0)
    with pytest.raises(ValueError, match=r"^params.logits must have shape \(r, r\).*got shape \(2, 3\)"):
        imm.imm_loglik(p._replace(logits=np.zeros((2, 3))), zs, x0, P0)
    with pytest.raises(ValueError, match=r"^params.log_mu0 must have shape \(2,\).*got shape \(3,\)"):
        imm.imm_loglik(p._replace(log_mu0=np.zeros(3)), zs, x0, P0)
    with pytest.raises(ValueError, match=r"^params.logits must be real logits"):
        imm.imm_loglik(p._replace(logits=np.array([[0.0, np.nan], [0.0, 0.0]])), zs, x0, P0)
    with pytest.raises(ValueError, match=r"^params.Q must have shape \(2, 4, 4\).*got shape \(3, 4, 4\)"):
        imm.imm_loglik(p._replace(Q=np.stack([QBAR[0]] * 3)), zs, x0, P0)
    with pytest.raises(ValueError, match=r"^params.F must have shape \(\.\.\., 4, 4\)"):
        imm.imm_loglik(p._replace(F=np.zeros((2, 3, 3))), zs, x0, P0)
    with pytest.raises(ValueError, match=r"^params.R must have shape \(\.\.\., 2, 2\)"):  # checked inside a trace
        jax.grad(lambda s: imm.imm_loglik(p._replace(R=s * jnp.eye(3)), zs, x0, P0)[0].sum())(1.0)
    with pytest.raises(TypeError, match=r"^sequence must be True or False, got 'no'"):
        imm.imm_loglik(p, zs, x0, P0, sequence="no")
    with pytest.raises(ValueError, match=r"^params.Q"):  # a concrete value is checked: not symmetric
        imm.imm_loglik(p._replace(Q=np.stack([QBAR[0], QBAR[1] + np.eye(4, k=1)])), zs, x0, P0)
    modes = [imm.KalmanMode(ConstantVelocity(ndim=2, q=1.0), R)] * 2
    with pytest.raises(TypeError, match=r"^estimator must be an IMM .*got GPB1"):
        imm.imm_params(imm.GPB1(modes, np.full((2, 2), 0.5), np.full(2, 0.5)), DT)
    with pytest.raises(ValueError, match=r"^dt must be a scalar interval"):
        imm.imm_params(imm.IMM(modes, np.full((2, 2), 0.5), np.full(2, 0.5)), np.ones(3))


# --------------------------------------------------------------------------------------------
# (d) the smoother: imm_smoother's JAX engine, under jit, vmap and grad
# --------------------------------------------------------------------------------------------
BANK = _numpy_bank(PHI)  # one bank object: its JAX filter compiles once for the tests below
POS = [0, 2]  # the positions x, y of the state [x, vx, y, vy]
FIELDS = ("x", "P", "mu", "xs[0]", "xs[1]", "Ps[0]", "Ps[1]")


def _kappa_s(res, phi):
    """kappa of the smoother's bound (module docstring): that of the filter's innovations, and
    the largest condition number of the pair predictions F_j P^i F_j^T + Q_j over the steps,
    runs and pairs of the NumPy result ``res`` at ``phi``."""
    Q = np.exp(phi[:2])[:, None, None] * QBAR
    pairs = [F_MODES[j] @ np.asarray(P) @ F_MODES[j].T + Q[j] for P in res.Ps for j in range(2)]
    return max(_kappa(res), max(float(np.max(np.linalg.cond(A.reshape(-1, N, N)))) for A in pairs))


def _agree_s(ref, res, kappa):
    """Every field of two smoothed results within 2T r n kappa eps scale (module docstring)."""
    return _agree((ref.x, ref.P, ref.mu, *ref.xs, *ref.Ps), (res.x, res.P, res.mu, *res.xs, *res.Ps), 2 * T,
                  2 * N, kappa, names=FIELDS)


def _smooth(p, zs, x0, P0):
    """The pure pipeline: imm_loglik's filtered sequence, smoothed with the same IMMParams (the
    JAX engines of filter and smoother in one trace)."""
    return imm.imm_smoother(p, imm.imm_loglik(p, zs, x0, P0)[1])


def _jax_result(res):
    """A filtered result as JAX arrays (the NumPy engine's numbers: the smoothers then start from
    the same input, and no JAX filter is compiled for it)."""
    return jax.tree_util.tree_map(jnp.asarray, res)


def test_imm_smoother_jax_engine_agrees_with_the_numpy_engine():
    zs, x0, P0 = _data(36)  # RUNS runs; a row missing in every run, one in one run only
    filt = imm.imm_filter(BANK, zs, x0, P0, DT)
    ref = imm.imm_smoother(BANK, filt, DT)
    kappa = _kappa_s(filt, PHI)
    jres = _jax_result(filt)
    for first in (BANK, _params(PHI)):  # an IMM; the IMMParams of the same bank
        back = imm.imm_smoother(first, jres, DT if first is BANK else None)
        assert all(isinstance(a, jax.Array) for a in (back.x, back.P, back.mu, *back.xs, *back.Ps))
        print(f"JAX engine against NumPy: largest difference / bound {_agree_s(ref, back, kappa):.2g} "
              f"(kappa {kappa:.3g})")
        # at T - 1 the smoother is the filter, bit for bit
        for a, b in zip((back.x, back.P, back.mu, *back.xs, *back.Ps), (jres.x, jres.P, jres.mu, *jres.xs, *jres.Ps)):
            assert np.array_equal(np.asarray(a[-1]), np.asarray(b[-1]))
    # power: the turning mode's q off by 1e-6 (relative) fails the check
    with pytest.raises(AssertionError):
        _agree_s(ref, imm.imm_smoother(_params(PHI + np.array([0.0, 1e-6, 0, 0, 0, 0])), jres), kappa)


def test_imm_smoother_under_jit_equals_the_direct_call():
    zs, x0, P0 = _data(37)
    filt = imm.imm_filter(BANK, zs, x0, P0, DT)
    kappa = _kappa_s(filt, PHI)
    jres = _jax_result(filt)
    direct = imm.imm_smoother(BANK, jres, DT)
    # the filtered result enters the caller's jit as an argument: abstract inside, shapes checked
    jitted = jax.jit(lambda res: imm.imm_smoother(BANK, res, DT), **JIT)(jres)
    print(f"jit against the direct call: largest difference / bound {_agree_s(direct, jitted, kappa):.2g}")
    with pytest.raises(AssertionError):  # power: the direct call with q_1 (1 + 1e-6) fails the check
        _agree_s(imm.imm_smoother(_params(PHI + np.array([0.0, 1e-6, 0, 0, 0, 0])), jres), jitted, kappa)


QS = np.array([0.05, 0.5, 5.0])  # q_1 of the turning mode mapped by vmap; PHI's own (0.5) among them
AT_PHI = 1


@pytest.fixture(scope="module")
def mapped():
    """f = sum of squares of the smoothed positions, its gradient and the smoothed sequence, for
    IMMParams whose turning mode's Q is mapped over QS: jax.jit(jax.vmap(jax.value_and_grad(f))),
    one compilation for the vmap test and the grad test (the filter, imm_loglik, and the smoother
    in one trace)."""
    zs, x0, P0 = _data(38)
    zj = jnp.asarray(zs)

    def f(p):
        back = _smooth(p, zj, x0, P0)
        return jnp.sum(back.x[..., POS] ** 2), back

    Qs = np.stack([_params(_phi_at(q)).Q for q in QS])
    assert np.array_equal(Qs[AT_PHI], _params(PHI).Q)
    params = jax.tree_util.tree_map(jnp.asarray, _params(PHI)._replace(Q=Qs))
    axes = imm.IMMParams(None, 0, None, None, None, None)
    (value, back), g = jax.jit(jax.vmap(jax.value_and_grad(f, has_aux=True), in_axes=(axes,)), **JIT)(params)
    return zs, x0, P0, params, value, back, g


def _phi_at(q1):
    phi = PHI.copy()
    phi[1] = np.log(q1)
    return phi


def test_imm_smoother_vmap_over_a_noise_level_equals_a_loop_of_calls(mapped):
    # each mapped value against a call of the NumPy engine (filter and smoother) at that q_1
    zs, x0, P0, _, _, back, _ = mapped
    assert back.x.shape == (QS.size, T, RUNS, N) and back.Ps[0].shape == (QS.size, T, RUNS, N, N)
    for i, q1 in enumerate(QS):
        phi = _phi_at(q1)
        filt = _numpy_run(phi, zs, x0, P0)
        kappa = _kappa_s(filt, phi)
        one = jax.tree_util.tree_map(lambda v: v[i], back)
        _agree_s(imm.imm_smoother(_numpy_bank(phi), filt, DT), one, kappa)
        # power: the call at q_1 (1 + 1e-6) fails the check
        phi[1] += 1e-6
        with pytest.raises(AssertionError):
            _agree_s(imm.imm_smoother(_numpy_bank(phi), _numpy_run(phi, zs, x0, P0), DT), one, kappa)


def test_grad_of_smoothed_positions_wrt_log_noise_levels_matches_central_differences(mapped):
    # the gradient at PHI, one of the mapped values: jax.grad over the IMMParams, then the chain
    # rule d/dlog q_i = <df/dQ_i, Q_i>
    zs, x0, P0, params, value, _, g = mapped
    grad = np.sum(np.asarray(g.Q[AT_PHI]) * np.asarray(params.Q[AT_PHI]), axis=(1, 2))

    def f_np(log_q):  # sum of squares of the smoothed positions, NumPy engine
        est = _numpy_bank(np.concatenate([log_q, PHI[2:]]))
        return float(np.sum(imm.imm_smoother(est, imm.imm_filter(est, zs, x0, P0, DT), DT).x[..., POS] ** 2))

    filt = _numpy_run(PHI, zs, x0, P0)
    x = imm.imm_smoother(BANK, filt, DT).x
    # delta_f = 2 sum|x_pos| (2T r n kappa eps max|x|), first order (module docstring)
    delta = 2 * np.sum(np.abs(x[..., POS])) * 2 * T * 2 * N * _kappa_s(filt, PHI) * EPS64 * np.max(np.abs(x))
    assert abs(float(value[AT_PHI]) - f_np(PHI[:2])) <= 2 * delta
    fd, bound = _central_difference(f_np, PHI[:2], np.full(2, STEP), delta)
    _check_gradient(grad, fd, bound + delta, "imm smoother")
    with pytest.raises(AssertionError):  # power: a gradient 1 % off fails
        _check_gradient(grad * 1.01, fd, bound + delta, "imm smoother, 1 % off")


def test_imm_smoother_bad_input_is_named():
    zs, x0, P0 = _data(40)
    jres = _jax_result(imm.imm_filter(BANK, zs, x0, P0, DT))
    p = _params(PHI)
    with pytest.raises(TypeError, match=r"^estimator must be an IMM .* or an IMMParams, got tuple"):
        imm.imm_smoother(tuple(p), jres)
    with pytest.raises(ValueError, match=r"^dt and times must be None when the first argument is an IMMParams"):
        imm.imm_smoother(p, jres, DT)
    with pytest.raises(TypeError, match=r"^result must be an IMMResult .*got tuple"):
        imm.imm_smoother(p, tuple(jres))
    with pytest.raises(ValueError, match=r"^params.F must have shape \(\.\.\., 4, 4\).*from result.x"):
        imm.imm_smoother(p._replace(F=np.zeros((2, 3, 3))), jres)
    with pytest.raises(ValueError, match=r"^params.Q must have shape \(2, 4, 4\).*got shape \(3, 4, 4\)"):
        imm.imm_smoother(p._replace(Q=np.stack([QBAR[0]] * 3)), jres)
    # inside a trace the shapes are checked (values are not known there)
    with pytest.raises(ValueError, match=r"^result.x must have shape \(20, 3, 4\), got \(20, 3, 2\)"):
        jax.jit(lambda res: imm.imm_smoother(BANK, res._replace(x=res.x[..., :2]), DT))(jres)
    with pytest.raises(ValueError, match=r"^result.mu must have shape \(T, \.\.\., 2\)"):
        jax.jit(lambda q: imm.imm_smoother(p._replace(Q=q), jres._replace(mu=jres.mu[..., :1])))(p.Q)
    # a concrete JAX result is checked as a NumPy one
    with pytest.raises(ValueError, match=r"^result.mu must hold finite mode probabilities"):
        imm.imm_smoother(p, jres._replace(mu=jres.mu.at[3, 0, 0].set(jnp.nan)))
    # the JAX engine takes the banks imm_filter's JAX engine takes
    modes = [imm.KalmanMode(ConstantVelocity(ndim=2, q=1.0), R)] * 2
    swapped = imm.IMM(modes, np.full((2, 2), 0.5), np.full(2, 0.5), components=[(0, 1, 2, 3), (2, 3, 0, 1)])
    with pytest.raises(TypeError, match=r"^estimator: the JAX engine of imm_smoother runs banks of KalmanMode"):
        imm.imm_smoother(swapped, jres, DT)
