"""Tests of the chunked Monte Carlo harness of kftrack.montecarlo: running moments (Chan et al.
1983), independence of the chunk size, constant memory, progress bar, JAX outputs."""
from __future__ import annotations

import tracemalloc
from typing import NamedTuple

import numpy as np
import pytest
import scipy.stats

from kftrack import kalman, models
from kftrack.montecarlo import Moments, RunningMoments, chunked_study, per_run_error, run_generators

EPS = np.finfo(float).eps
CV = models.ConstantVelocity(ndim=2, q=0.5)
R2 = 4.0 * np.eye(2)
X0, P0 = np.array([0.0, 10.0, 0.0, 5.0]), np.diag([25.0, 4.0, 25.0, 4.0])


class Runs(NamedTuple):
    truth: np.ndarray  # (T, n, 4)
    zs: np.ndarray  # (T, n, 2)


def make_simulate(T=50, dt=1.0):
    F, Q = CV.F(dt), CV.Q(dt)
    LQ, LP = np.linalg.cholesky(Q), np.linalg.cholesky(P0)

    def simulate(rngs):
        # run i draws only from rngs[i]: (T + 1) state noises, T measurement noises
        w = np.stack([g.standard_normal((T + 1, 4 + 2)) for g in rngs], axis=1)  # (T+1, n, 6)
        x = X0 + w[0, :, :4] @ LP.T
        truth = np.empty((T, len(rngs), 4))
        for k in range(T):
            truth[k] = x
            x = x @ F.T + w[k + 1, :, :4] @ LQ.T
        zs = truth[..., [0, 2]] + 2.0 * w[1:, :, 4:]
        return Runs(truth, zs)

    return simulate, F, Q


def kf_estimate(F, Q):
    return lambda d: kalman.kalman_filter(d.zs, X0, P0, F, Q, CV.H, R2)


def score(d, res):
    e = d.truth - res.x
    nees = np.einsum("...i,...i->...", e, np.linalg.solve(res.P, e[..., None])[..., 0])  # (T, n)
    return {"mse": per_run_error(d.truth, res.x, components=[0, 2]), "nees": nees.mean(0), "nees_curve": nees.T}


# --------------------------------------------------------------------------------------------
# running moments
# --------------------------------------------------------------------------------------------
def test_running_moments_equal_the_two_pass_moments():
    rng = np.random.default_rng(1)
    v = 1e3 + rng.normal(size=(1000, 3))  # an offset: the naive sum-of-squares formula would lose digits
    acc = RunningMoments()
    cuts = np.sort(rng.choice(np.arange(1, 1000), size=30, replace=False))
    for part in np.split(v, cuts):
        acc.update(part)
    m = acc.moments()
    assert m.count == 1000
    # summation round-off: a few N eps relative to the largest term
    np.testing.assert_allclose(m.mean, v.mean(0), rtol=10 * 1000 * EPS)
    np.testing.assert_allclose(m.var, v.var(0, ddof=1), rtol=10 * 1000 * EPS * (1e3 / 1.0))
    np.testing.assert_allclose(m.sem, np.sqrt(v.var(0, ddof=1) / 1000), rtol=10 * 1000 * EPS * 1e3)


def test_running_moments_errors_name_the_argument():
    acc = RunningMoments()
    with pytest.raises(ValueError, match="update"):
        acc.moments()
    with pytest.raises(ValueError, match="values"):
        acc.update(np.float64(1.0))
    acc.update(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="values"):
        acc.update(np.zeros((3, 4)))
    assert np.isnan(RunningMoments().update([2.0]).moments().var)


def test_run_generators_do_not_depend_on_the_chunk():
    gens = run_generators(np.random.default_rng(5), 20)
    a = [g.standard_normal() for g in gens(0, 20)]
    b = [g.standard_normal() for g in gens(0, 7) + gens(7, 14) + gens(14, 20)]
    assert a == b
    assert len(set(a)) == 20
    with pytest.raises(ValueError, match="runs"):
        run_generators(np.random.default_rng(5), 0)
    with pytest.raises(ValueError, match="stop"):
        gens(15, 21)


# --------------------------------------------------------------------------------------------
# the harness
# --------------------------------------------------------------------------------------------
def test_results_do_not_depend_on_the_chunk_size():
    simulate, F, Q = make_simulate()
    runs = 60
    a = chunked_study(simulate, kf_estimate(F, Q), score, runs, runs, np.random.default_rng(7))
    b = chunked_study(simulate, kf_estimate(F, Q), score, runs, 7, np.random.default_rng(7))
    assert set(a) == {"mse", "nees", "nees_curve"}
    for name in a:
        assert a[name].count == b[name].count == runs
        assert a[name].mean.shape == b[name].mean.shape
        # same per-run values (own generator per run, the batched filter is run-by-run
        # elementwise); only the summation order differs: N eps relative, with a factor 10
        scale = np.abs(a[name].mean).max()
        assert np.max(np.abs(a[name].mean - b[name].mean)) <= 10 * runs * EPS * scale
        assert np.max(np.abs(a[name].var - b[name].var)) <= 10 * runs * EPS * np.abs(a[name].var).max() * 10
    assert a["nees_curve"].mean.shape == (50,)


def test_the_study_measures_what_theory_says():
    """Model-matched Kalman filter: the time-averaged NEES of a run has mean n = 4 (two-sided
    t bound at level 0.001 over 400 runs, in chunks of 64)."""
    simulate, F, Q = make_simulate()
    m = chunked_study(simulate, kf_estimate(F, Q), score, 400, 64, np.random.default_rng(11))["nees"]
    t = scipy.stats.t.ppf(1 - 0.0005, 399)
    assert abs(m.mean - 4.0) <= t * m.sem, m


def _peak(runs, chunk, simulate, estimate):
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        chunked_study(simulate, estimate, score, runs, chunk, np.random.default_rng(3))
        return tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


def test_memory_stays_that_of_one_chunk():
    simulate, F, Q = make_simulate(T=200)
    est = kf_estimate(F, Q)
    chunk = 100
    one = _peak(chunk, chunk, simulate, est)
    twenty = _peak(20 * chunk, chunk, simulate, est)
    # one chunk holds ~ 200 x 100 x (2 x 16 + 2 x 4 + ...) doubles ~ 7 MB; keeping the 20 chunks
    # would be ~ 20 times that. Allowance: 25 % of one chunk plus 256 KiB (the moments, the
    # per-run seed objects of a chunk, allocator noise)
    assert one > 4e6, one
    assert twenty <= 1.25 * one + 256 * 1024, (one, twenty)


def test_progress_bar(capsys):
    simulate, F, Q = make_simulate(T=5)
    chunked_study(simulate, kf_estimate(F, Q), score, 30, 10, np.random.default_rng(0), progress=True)
    err = capsys.readouterr().err
    assert "30/30" in err and "run" in err


def test_a_single_array_score_and_chunk_larger_than_runs():
    simulate, F, Q = make_simulate(T=5)
    out = chunked_study(simulate, kf_estimate(F, Q), lambda d, r: per_run_error(d.truth, r.x), 9, 100,
                        np.random.default_rng(0))
    assert set(out) == {"score"} and isinstance(out["score"], Moments) and out["score"].count == 9


def test_jax_outputs_are_converted_per_chunk():
    jnp = pytest.importorskip("jax.numpy")
    simulate, F, Q = make_simulate(T=20)
    kf = kf_estimate(F, Q)
    seen = []

    def jax_estimate(d):  # a filter returning JAX arrays (a named tuple of them)
        return kalman.FilterResult(*(jnp.asarray(a) for a in kf(d)))

    def checking_score(d, res):
        seen.append(all(isinstance(a, np.ndarray) for a in res))
        return score(d, res)

    a = chunked_study(simulate, jax_estimate, checking_score, 40, 15, np.random.default_rng(2))
    b = chunked_study(simulate, kf, score, 40, 15, np.random.default_rng(2))
    assert seen == [True, True, True]
    # JAX may hold float32 (without jax_enable_x64): relative round-off 2^-24 per value, amplified
    # by the NEES solve (cond(P) < 1e3 here) -> bound 1e3 x 10 x 2^-24
    tol = 0.0 if jnp.asarray(1.0).dtype == np.float64 else 1e3 * 10 * 2.0**-24
    for name in a:
        np.testing.assert_allclose(a[name].mean, b[name].mean, rtol=tol, atol=0)


def test_errors_name_the_argument():
    simulate, F, Q = make_simulate(T=5)
    est, rng = kf_estimate(F, Q), np.random.default_rng(0)
    with pytest.raises(TypeError, match="simulate"):
        chunked_study(None, est, score, 10, 5, rng)
    with pytest.raises(TypeError, match="estimate"):
        chunked_study(simulate, 3, score, 10, 5, rng)
    with pytest.raises(TypeError, match="score"):
        chunked_study(simulate, est, "mse", 10, 5, rng)
    with pytest.raises(ValueError, match="runs"):
        chunked_study(simulate, est, score, 0, 5, rng)
    with pytest.raises(ValueError, match="chunk"):
        chunked_study(simulate, est, score, 10, 2.5, rng)
    with pytest.raises((TypeError, ValueError), match="rng"):
        chunked_study(simulate, est, score, 10, 5, 42)
    with pytest.raises(ValueError, match="score"):  # time first instead of runs first
        chunked_study(simulate, est, lambda d, r: np.zeros((6, 5)), 10, 5, rng)
    with pytest.raises(ValueError, match="score"):
        names = iter([{"a": np.zeros(5)}, {"b": np.zeros(5)}])
        chunked_study(simulate, est, lambda d, r: next(names), 10, 5, rng)
