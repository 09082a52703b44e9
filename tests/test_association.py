"""Tests of kftrack.association, kftrack.clutter and kftrack.trackmanagement."""
import datetime

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.stats import binom, chi2

from kftrack import association as asc, clutter, imm, models, trackmanagement as tm
from kftrack.kalman import update as kalman_update

EPS = np.finfo(float).eps
H2 = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])


def _binom_ok(k, n, p, level=1e-3):
    """Two-sided binomial acceptance at the stated level."""
    return binom.ppf(level / 2, n, p) <= k <= binom.isf(level / 2, n, p)


def _random_case(rng, n=4, m=2, M=6):
    A = rng.normal(size=(n, n))
    P = A @ A.T + 0.5 * np.eye(n)
    x = rng.normal(size=n)
    H = rng.normal(size=(m, n))
    B = rng.normal(size=(m, m))
    R = B @ B.T + 0.5 * np.eye(m)
    S = H @ P @ H.T + R
    L = np.linalg.cholesky(S)
    Z = H @ x + (L @ rng.normal(size=(M, m, 1)))[..., 0] * 1.2
    return x, P, H, R, Z


# ---------------------------------------------------------------- gate
@pytest.mark.parametrize("m", [1, 2, 3])
def test_gate_volume_closed_form(m):
    rng = np.random.default_rng(m)
    B = rng.normal(size=(m, m))
    S = B @ B.T + np.eye(m)
    g = chi2.ppf(0.99, m)
    closed = {1: 2 * np.sqrt(g * S[0, 0]), 2: np.pi * g * np.sqrt(np.linalg.det(S)),
              3: 4 / 3 * np.pi * g ** 1.5 * np.sqrt(np.linalg.det(S))}[m]
    # slogdet/exp of an m x m SPD matrix: relative error a few hundred eps at most
    assert abs(asc.gate_volume(S, 0.99) - closed) <= 200 * EPS * closed
    assert asc.unit_ball_volume(m) == pytest.approx({1: 2.0, 2: np.pi, 3: 4 * np.pi / 3}[m], rel=1e-15)


@pytest.mark.parametrize("P_G", [0.9, 0.99])
def test_gate_contains_true_measurement_with_probability_PG(P_G):
    rng = np.random.default_rng(16)
    N = 20000
    x, P, H, R, _ = _random_case(rng)
    S = H @ P @ H.T + R
    truth = x + (np.linalg.cholesky(P) @ rng.normal(size=(N, 4, 1)))[..., 0]
    z = (H @ truth[..., None])[..., 0] + (np.linalg.cholesky(R) @ rng.normal(size=(N, 2, 1)))[..., 0]
    g = asc.validation_gate(x, P, z[:, None, :], H, R, P_G=P_G)
    assert _binom_ok(int(g.inside.sum()), N, P_G)  # two-sided, level 1e-3
    assert np.allclose(g.S, S, rtol=1e-12)


# ---------------------------------------------------------------- PDAF against Stone Soup
def _stonesoup_pda(x, P, H, R, Z, P_D, P_G, lam, gm_method=False):
    from stonesoup.hypothesiser.probability import PDAHypothesiser
    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, RandomWalk
    from stonesoup.types.detection import Detection
    from stonesoup.types.state import GaussianState
    from stonesoup.types.track import Track
    from stonesoup.updater.probability import PDAUpdater

    class _Exact(LinearGaussian):  # a general (m, n) matrix, not a mapping
        def matrix(self, **kwargs):
            return self._H

    n, m = H.shape[1], H.shape[0]
    t0 = datetime.datetime(2026, 1, 1)
    mm = _Exact(ndim_state=n, mapping=tuple(range(m)), noise_covar=R)
    mm._H = H
    tm_ = CombinedLinearGaussianTransitionModel([RandomWalk(0.0)] * n)
    pred = KalmanPredictor(tm_)
    upd = PDAUpdater(mm, gm_method=gm_method)
    hyp = PDAHypothesiser(pred, upd, clutter_spatial_density=lam, prob_detect=P_D, prob_gate=P_G)
    track = Track([GaussianState(x.reshape(-1, 1), P, timestamp=t0)])
    dets = [Detection(z.reshape(-1, 1), timestamp=t0, measurement_model=mm) for z in Z]
    hs = hyp.hypothesise(track, set(dets), t0)
    post = upd.update(hs)
    return np.asarray(post.state_vector, float).ravel(), np.asarray(post.covar, float)


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("parametric", [True, False])
@pytest.mark.parametrize("gm_method", [False, True])
def test_pdaf_matches_stonesoup(seed, parametric, gm_method):
    rng = np.random.default_rng(100 + seed)
    x, P, H, R, Z = _random_case(rng, n=4, m=2, M=int(rng.integers(1, 7)))
    P_D, P_G = float(rng.uniform(0.5, 0.99)), float(rng.uniform(0.8, 0.999))
    lam = float(rng.uniform(0.01, 0.5)) if parametric else None
    ours = asc.pdaf_update(x, P, Z, H, R, P_D=P_D, P_G=P_G, clutter_density=lam)
    xs, Ps = _stonesoup_pda(x, P, H, R, Z, P_D, P_G, lam, gm_method)
    # Stone Soup computes the same posterior by another route: either its innovation form
    # (P - K S K^T, log-domain weights) or, with gm_method=True, moment matching of the M + 1
    # per-hypothesis Kalman posteriors; ours uses the Joseph form and the spread term. Each of
    # the ~ n^2 m (+ M) operations is exact to eps relative, S^{-1} amplifies by cond(S) and the
    # weights' log/exp by at most ~ |log beta| < 50, so |dx|, |dP| <= 100 cond(S) eps scale.
    # Observed on these cases: below 1 cond(S) eps scale. The 1e-9 would be 10^5 looser.
    scale = max(1.0, np.abs(P).max(), np.abs(x).max())
    cond = np.linalg.cond(H @ P @ H.T + R)
    assert cond < 1e3
    tol = 100 * cond * EPS * scale
    np.testing.assert_allclose(ours.x, xs, rtol=0, atol=tol)
    np.testing.assert_allclose(ours.P, Ps, rtol=0, atol=tol)


def test_pdaf_zero_clutter_full_detection_is_kalman_exactly():
    rng = np.random.default_rng(7)
    x, P, H, R, Z = _random_case(rng, M=1)
    Z = (H @ x)[None] + 0.1 * rng.normal(size=(1, 2))  # well inside the gate
    kf = kalman_update(x, P, Z[0], H, R)
    pd = asc.pdaf_update(x, P, Z, H, R, P_D=1.0, P_G=0.999, clutter_density=0.0)
    assert np.array_equal(pd.x, kf.x) and np.array_equal(pd.P, kf.P)
    assert pd.beta[0] == 0.0 and pd.beta[1] == 1.0
    # lambda -> 0: beta_0 ~ lambda (1 - P_G)/N falls below eps, then the update is Kalman's to round-off
    pd2 = asc.pdaf_update(x, P, Z, H, R, P_D=1.0, P_G=0.999, clutter_density=1e-30)
    assert np.array_equal(pd2.x, kf.x)
    np.testing.assert_allclose(pd2.P, kf.P, rtol=0, atol=4 * EPS * np.abs(kf.P).max())


def test_pdaf_broadcasts_over_runs_with_padding():
    rng = np.random.default_rng(3)
    runs = [_random_case(rng, M=int(k)) for k in (1, 3, 5)]
    x = np.stack([r[0] for r in runs])
    P = np.stack([r[1] for r in runs])
    H, R = runs[0][2], runs[0][3]
    Zp = np.zeros((3, 5, 2))
    mask = np.zeros((3, 5), bool)
    for i, r in enumerate(runs):
        Zp[i, :len(r[4])] = r[4]
        mask[i, :len(r[4])] = True
    batched = asc.pdaf_update(x, P, Zp, H, R, P_D=0.9, P_G=0.99, clutter_density=0.05, mask=mask)
    for i, r in enumerate(runs):
        one = asc.pdaf_update(r[0], r[1], r[4], H, R, P_D=0.9, P_G=0.99, clutter_density=0.05)
        np.testing.assert_allclose(batched.x[i], one.x, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(batched.P[i], one.P, rtol=1e-13, atol=1e-13)
        assert np.all(batched.beta[i, 1 + len(r[4]):] == 0)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), M=st.integers(1, 8), P_D=st.floats(0.05, 1.0),
       P_G=st.floats(0.5, 0.9999), lam=st.one_of(st.none(), st.floats(1e-6, 10.0)))
def test_pdaf_laws(seed, M, P_D, P_G, lam):
    rng = np.random.default_rng(seed)
    x, P, H, R, Z = _random_case(rng, M=M)
    u = asc.pdaf_update(x, P, Z, H, R, P_D=P_D, P_G=P_G, clutter_density=lam)
    assert np.isclose(u.beta.sum(), 1.0, rtol=0, atol=10 * EPS * (M + 1))  # probabilities sum to 1
    assert np.all(u.beta >= 0)
    assert np.array_equal(u.P, u.P.T)  # symmetric (symmetrized)
    scale = np.abs(P).max()
    assert np.linalg.eigvalsh(u.P).min() >= -1e3 * EPS * scale  # PSD up to round-off
    assert np.linalg.eigvalsh(u.spread).min() >= -1e3 * EPS * scale  # the spread term is PSD


# ---------------------------------------------------------------- JPDA, GNN
def _brute_jpda_beta(xs, Ps, Z, H, R, P_D, P_G, lam):
    T, M = len(xs), len(Z)
    gates = [asc.validation_gate(x, P, Z, H, R, P_G=P_G) for x, P in zip(xs, Ps)]
    beta = np.zeros((T, M + 1))
    import itertools
    for a in itertools.product(range(M + 1), repeat=T):
        used = [v for v in a if v]
        if len(used) != len(set(used)):
            continue
        w = 1.0
        for t, v in enumerate(a):
            g = gates[t]
            if v == 0:
                w *= 1 - P_D * P_G
            else:
                w *= P_D * np.exp(g.logN[v - 1]) / lam if g.inside[v - 1] else 0.0
        for t, v in enumerate(a):
            beta[t, v] += w
    return beta / beta[0].sum()


@pytest.mark.parametrize("T", [1, 2, 3])
def test_jpda_against_brute_force_and_pdaf(T):
    rng = np.random.default_rng(20 + T)
    x, P, H, R, Z = _random_case(rng, M=4)
    xs = x + 0.5 * rng.normal(size=(T, 4))
    Ps = np.stack([P] * T)
    j = asc.jpda_update(xs, Ps, Z, H, R, P_D=0.9, P_G=0.99, clutter_density=0.02)
    np.testing.assert_allclose(j.beta, _brute_jpda_beta(xs, Ps, Z, H, R, 0.9, 0.99, 0.02), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(j.beta.sum(-1), 1.0, rtol=0, atol=1e-14)
    if T == 1:  # one target: JPDA is the PDAF
        p = asc.pdaf_update(xs[0], Ps[0], Z, H, R, P_D=0.9, P_G=0.99, clutter_density=0.02)
        np.testing.assert_allclose(j.x[0], p.x, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(j.P[0], p.P, rtol=1e-13, atol=1e-13)


def test_jpda_clusters_equal_the_unclustered_enumeration():
    # 40 random scans of 2-4 targets spread so that gates overlap in some places and not in others
    # (1 to 4 clusters), a batch of 3 runs each: the clustered marginals equal the unclustered
    # enumeration of every joint event (rtol 1e-12: both sum the same <= 625 positive weights,
    # relative round-off ~ 625 eps ~ 1.4e-13), and so do the updated states.
    rng = np.random.default_rng(77)
    H, R = H2, np.eye(2)
    n_shared = n_multi = 0
    for _ in range(40):
        T, M = int(rng.integers(2, 5)), int(rng.integers(1, 5))
        xs = np.zeros((T, 4))
        xs[:, [0, 2]] = rng.uniform(0, 12, size=(T, 2))
        Ps = np.stack([np.eye(4)] * T)
        Z = xs[rng.integers(0, T, size=(3, M))][..., [0, 2]] + 1.5 * rng.normal(size=(3, M, 2))
        mask = rng.random((3, M)) < 0.9
        j = asc.jpda_update(xs, Ps, Z, H, R, P_D=0.9, P_G=0.99, clutter_density=0.01, mask=mask)
        for r in range(3):
            Zr = Z[r][mask[r]]
            beta = _brute_jpda_beta(xs, Ps, Zr, H, R, 0.9, 0.99, 0.01)
            np.testing.assert_allclose(j.beta[r][:, np.r_[0, 1 + np.flatnonzero(mask[r])]], beta, rtol=1e-12, atol=1e-15)
            for t in range(T):  # the PDAF-form update with the brute-force marginals
                ku = kalman_update(xs[t], Ps[t], H @ xs[t], H, R)
                nu = Zr - H @ xs[t]
                nu_c = beta[t, 1:] @ nu
                spread = ku.K @ (np.einsum("i,ij,ik->jk", beta[t, 1:], nu, nu) - np.outer(nu_c, nu_c)) @ ku.K.T
                Pt = beta[t, 0] * Ps[t] + (1 - beta[t, 0]) * ku.P + spread
                np.testing.assert_allclose(j.x[r, t], xs[t] + ku.K @ nu_c, rtol=1e-12, atol=1e-12)
                np.testing.assert_allclose(j.P[r, t], 0.5 * (Pt + Pt.T), rtol=1e-12, atol=1e-12)
            shared = (j.gate.inside[r].sum(0) > 1).any()  # else every target is a cluster of its own
            n_shared += shared
            n_multi += shared and len(asc._gating_clusters(j.gate.inside[r])) > 1
    assert n_shared >= 30 and n_multi >= 10, (n_shared, n_multi)  # both paths, and several clusters in one scan


def test_jpda_event_count_is_exact():
    # the dynamic-programming count equals the number of events enumerated, on random gate patterns
    rng = np.random.default_rng(8)
    for _ in range(200):
        T, M = int(rng.integers(1, 6)), int(rng.integers(0, 6))
        adj = tuple(tuple(int(j) for j in np.flatnonzero(rng.random(M) < 0.5)) for _ in range(T))
        count, exact = asc._count_events(adj, 10**9)
        assert exact and count == len(asc._cluster_events(adj))


def test_jpda_guard_on_the_number_of_events():
    P, H, R = 10 * np.eye(4), H2, 4 * np.eye(2)
    one = dict(P_D=0.9, P_G=0.99, clutter_density=1e-3)
    # 12 targets gating the same 12 measurements: sum_k C(12, k)^2 k! = 53 334 454 417 events, now
    # within the subset programme (no error), which also counts them
    j = asc.jpda_update(np.zeros((12, 4)), np.broadcast_to(P, (12, 4, 4)), np.zeros((12, 2)), H, R, **one)
    assert j.n_events == 53_334_454_417
    # 30 x 30: beyond the programme (> 16 measurements); the count stops early (a lower bound)
    with pytest.raises(ValueError, match=r"at least .* joint events .* 30 targets and 30 measurements"):
        asc.jpda_update(np.zeros((30, 4)), np.broadcast_to(P, (30, 4, 4)), np.zeros((30, 2)), H, R, **one)
    # two groups of 6 targets and 6 measurements 1 km apart: two clusters of 13 327 events each
    # (sum_k C(6, k)^2 k!), while one unclustered enumeration would hold 13 327^2 of them
    xs = np.zeros((12, 4))
    xs[6:, 0] = 1000.0
    Z = xs[:, [0, 2]] + 0.1 * np.arange(12)[:, None]
    j = asc.jpda_update(xs, np.broadcast_to(P, (12, 4, 4)), Z, H, R, **one)
    assert j.n_events == 2 * 13327
    np.testing.assert_allclose(j.beta.sum(-1), 1.0, rtol=0, atol=1e-13)
    # max_events bounds the enumeration of clusters beyond the programme: 2 targets sharing 25
    # measurements have 1 + 2*25 + 25*24 = 651 events
    Z25 = 0.1 * np.arange(50.0).reshape(25, 2)
    x2, P2 = np.zeros((2, 4)), np.broadcast_to(P, (2, 4, 4))
    assert asc.jpda_update(x2, P2, Z25, H, R, max_events=651, **one).n_events == 651
    with pytest.raises(ValueError, match="651 joint events .* 2 targets and 25 measurements.*at most 16"):
        asc.jpda_update(x2, P2, Z25, H, R, max_events=650, **one)
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="max_events"):
            asc.jpda_update(xs[:2], np.broadcast_to(P, (2, 4, 4)), Z[:2], H, R, max_events=bad, **one)


def _enumerated_marginals(W):
    """Marginals of a cluster's weight table ``W`` (T, 1 + M) by listing every joint event."""
    adj = tuple(tuple(int(j) for j in np.flatnonzero(W[t, 1:] > 0)) for t in range(len(W)))
    ev = asc._cluster_events(adj)
    w = np.prod(W[np.arange(len(W))[None, :], ev], axis=1)
    beta = np.stack([np.bincount(ev[:, t], weights=w, minlength=W.shape[1]) for t in range(len(W))])
    return beta / w.sum(), len(ev)


def test_subset_programme_equals_the_enumeration():
    # 300 random clusters (1-6 targets, 0-7 measurements, random gating, weights spread over 1e-6..1):
    # every marginal is a ratio of sums of positive products, so both ways carry a relative
    # round-off below (E + 4 T M) eps each for E events (E <= 7^6 ~ 1.2e5 here, but the bound is
    # checked per case); the count equals the number of events listed.
    rng = np.random.default_rng(28)
    for _ in range(300):
        T, M = int(rng.integers(1, 7)), int(rng.integers(0, 8))
        W = np.exp(rng.uniform(np.log(1e-6), 0, size=(T, 1 + M)))
        W[:, 1:] *= rng.random((T, M)) < 0.6
        beta, count = asc._subset_marginals(W)
        ref, E = _enumerated_marginals(W)
        assert count == E
        np.testing.assert_allclose(beta, ref, rtol=2 * (E + 4 * T * (M + 1)) * EPS, atol=0)


def test_jpda_12_by_12_dense_cluster_has_the_closed_form_marginals():
    # 12 targets at one point, 12 measurements at another (all gated): every target has the same
    # weights (a missed, l any measurement), so with k targets assigned the events number
    # C(12, k)^2 k! and beta_0 = sum_k (12 - k)/12 C(12,k)^2 k! l^k a^(12-k) / sum_k C(12,k)^2 k! l^k a^(12-k)
    # (each target is missed in a fraction (12 - k)/12 of them); the rest splits equally over the 12.
    from math import comb, factorial
    P, H, R = 10 * np.eye(4), H2, 4 * np.eye(2)
    Z = np.full((12, 2), 1.0)
    j = asc.jpda_update(np.zeros((12, 4)), np.broadcast_to(P, (12, 4, 4)), Z, H, R, P_D=0.9, P_G=0.99,
                        clutter_density=1e-3)
    a = 1 - 0.9 * 0.99
    l = 0.9 * np.exp(j.gate.logN[0, 0]) / 1e-3
    terms = np.array([comb(12, k) ** 2 * factorial(k) * l**k * a ** (12 - k) for k in range(13)])
    b0 = (terms * (12 - np.arange(13)) / 12).sum() / terms.sum()
    # relative round-off of both sides: ~ 13 terms and 12 x 13 x 3 programme steps, below 1e-12
    np.testing.assert_allclose(j.beta[:, 0], b0, rtol=1e-12)
    np.testing.assert_allclose(j.beta[:, 1:], (1 - b0) / 12, rtol=1e-12)


@pytest.mark.parametrize("seed, T", [(5, 4), (6, 5), (7, 4)])
def test_jpda_large_cluster_equals_brute_force(seed, T):
    # T targets sharing 6 measurements (events > 256: the subset programme) against the
    # brute-force enumeration of the test module (rtol as in test_jpda_against_brute_force_and_pdaf)
    rng = np.random.default_rng(seed)
    x, P, H, R, Z = _random_case(rng, M=6)
    xs = x + 0.3 * rng.normal(size=(T, 4))
    Ps = np.stack([P] * T)
    j = asc.jpda_update(xs, Ps, Z, H, R, P_D=0.9, P_G=0.999, clutter_density=0.02)
    assert j.n_events > 256
    np.testing.assert_allclose(j.beta, _brute_jpda_beta(xs, Ps, Z, H, R, 0.9, 0.999, 0.02), rtol=1e-12, atol=1e-15)


def _brute_gnn(cost, gate, miss):
    """Least total cost over every assignment (each track a gated measurement or -1, none shared)."""
    import itertools
    T, M = cost.shape
    best = np.inf
    for cand in itertools.product(range(-1, M), repeat=T):
        used = [c for c in cand if c >= 0]
        if len(used) != len(set(used)) or any(c >= 0 and not gate[t, c] for t, c in enumerate(cand)):
            continue
        best = min(best, sum(cost[t, c] if c >= 0 else miss[t] for t, c in enumerate(cand)))
    return best


def test_gnn_documented_example():
    # the docstring's rule: "no measurement" costs the gate's edge, largest gated cost + 1 = 11
    cost, gate = np.array([[5.0, 0.0], [0.0, 10.0]]), np.array([[True, False], [True, True]])
    np.testing.assert_array_equal(asc.gnn_assignment(cost, gate), [-1, 0])  # total 11, not [0, 1] (15)
    np.testing.assert_array_equal(asc.gnn_assignment(cost, gate, miss_cost=20.0), [0, 1])  # 15 < 20 + 0
    np.testing.assert_array_equal(asc.gnn_assignment(cost, np.zeros((2, 2), bool)), [-1, -1])


@pytest.mark.parametrize("default_miss", [True, False])
def test_gnn_against_exhaustive_search(default_miss):
    # 300 random scans (T <= 4 tracks, M <= 5 measurements, random gates, costs of either sign):
    # the total cost of gnn_assignment equals the exhaustive minimum. Tolerance: sums of at most
    # 4 terms of size <= 20, round-off <= 4 * 20 * eps ~ 2e-14; 1e-12 is far below the gap
    # between two different sums of continuous random costs.
    rng = np.random.default_rng(2026)
    for _ in range(300):
        T, M = int(rng.integers(1, 5)), int(rng.integers(0, 6))
        cost = rng.uniform(-5, 15, size=(T, M))
        gate = rng.random((T, M)) < rng.uniform(0.2, 1.0)
        cost[~gate] = rng.choice([np.inf, np.nan, -1e3], size=int((~gate).sum()))  # never used
        if default_miss:
            miss, a = np.full(T, cost[gate].max() + 1.0 if gate.any() else 0.0), asc.gnn_assignment(cost, gate)
        else:
            miss = rng.uniform(-5, 20, size=T)
            a = asc.gnn_assignment(cost, gate, miss)
        used = a[a >= 0]
        assert len(set(used.tolist())) == len(used) and all(gate[t, j] for t, j in enumerate(a) if j >= 0)
        total = sum(cost[t, j] if j >= 0 else miss[t] for t, j in enumerate(a))
        assert total == pytest.approx(_brute_gnn(cost, gate, miss), abs=1e-12)


# ---------------------------------------------------------------- GOSPA / OSPA
@pytest.mark.parametrize("seed", range(10))
def test_gospa_matches_stonesoup(seed):
    from stonesoup.metricgenerator.ospametric import GOSPAMetric
    from stonesoup.measures import Euclidean
    from stonesoup.types.state import State
    rng = np.random.default_rng(seed)
    N, M = rng.integers(0, 6, size=2)
    X, Y = rng.uniform(0, 10, size=(N, 2)), rng.uniform(0, 10, size=(M, 2))
    c, p = float(rng.uniform(1, 5)), float(rng.choice([1.0, 2.0, 3.0]))
    t0 = datetime.datetime(2026, 1, 1)
    metric = GOSPAMetric(c=c, p=p, measure=Euclidean())
    res, _ = metric.compute_gospa_metric([State(y.reshape(-1, 1), timestamp=t0) for y in Y],
                                         [State(x.reshape(-1, 1), timestamp=t0) for x in X])
    ss = res.value
    ours = asc.gospa(X, Y, c=c, p=p)
    # both solve the same assignment; the sums differ only in order: ~ (N + M) eps relative.
    assert ours.distance == pytest.approx(ss["distance"], rel=1e-12, abs=1e-12)
    # Stone Soup's breakdown decides "at the cut-off" by an exact float comparison that can go
    # either way on another machine (tests/test_peers.py): compare it only where no pair reaches c.
    d = np.linalg.norm(X[:, None] - Y[None], axis=-1) if N and M else np.zeros(0)
    if not np.any(d >= c):
        assert ours.localisation == pytest.approx(ss["localisation"], rel=1e-12, abs=1e-12)


def test_ospa_closed_cases():
    X = np.array([[0.0, 0.0], [10.0, 0.0]])
    assert asc.ospa(X, X, c=5.0) == 0.0
    assert asc.ospa(X, X[:1], c=5.0) == pytest.approx(np.sqrt(25.0 / 2), rel=1e-15)
    assert asc.ospa(X, np.zeros((0, 2)), c=5.0) == 5.0
    g = asc.gospa(X, X[:1] + [3.0, 4.0], c=10.0)
    assert g.distance == pytest.approx(np.sqrt(25.0 + 50.0), rel=1e-15) and (g.missed, g.false) == (1, 0)


# ---------------------------------------------------------------- clutter simulation
def test_clutter_counts_are_poisson_and_detection_rate_is_PD():
    rng = np.random.default_rng(11)
    N, lam, lo, hi = 4000, 2e-3, np.array([-50.0, -50.0]), np.array([50.0, 50.0])
    s = clutter.simulate_scans(np.zeros((N, 2)), P_D=0.8, clutter_density=lam, region=(lo, hi), rng=rng)
    n_fa = (s.mask & (s.origin < 0)).sum(-1)
    mean = lam * 1e4
    # the mean of N Poisson(mean) counts: normal bound at level 1e-3 (z = 3.29)
    assert abs(n_fa.mean() - mean) < 3.29 * np.sqrt(mean / N)
    assert _binom_ok(int(s.detected.sum()), N, 0.8)
    # Poisson, not just the right mean: the dispersion index sum (n - mean)^2 / mean is
    # chi-square with N - 1 dof; two-sided at level 1e-3 (fails for fixed or over-dispersed counts)
    disp = ((n_fa - n_fa.mean()) ** 2).sum() / n_fa.mean()
    assert chi2.ppf(5e-4, N - 1) <= disp <= chi2.isf(5e-4, N - 1)
    fa = s.Z[s.mask & (s.origin < 0)]
    assert np.all((fa >= lo) & (fa <= hi))
    # uniform: chi-square goodness of fit of the 10 x 10 cell counts, 99 dof, two-sided 1e-3
    counts = np.histogram2d(fa[:, 0], fa[:, 1], bins=10, range=[[-50, 50], [-50, 50]])[0].ravel()
    stat = ((counts - len(fa) / 100) ** 2 / (len(fa) / 100)).sum()
    assert chi2.ppf(5e-4, 99) <= stat <= chi2.isf(5e-4, 99)
    assert np.all(s.Z[~s.mask] == 0) and np.array_equal(s.Z[s.origin == 0], np.zeros((int(s.detected.sum()), 2)))


# ---------------------------------------------------------------- track management
def test_initiation_closed_forms():
    R = np.diag([4.0, 9.0])
    x, P = tm.two_point_initiation([1.0, 2.0], [3.0, 6.0], 2.0, R)
    np.testing.assert_allclose(x, [3.0, 1.0, 6.0, 2.0], rtol=1e-15)
    np.testing.assert_allclose(P[:2, :2], 4.0 * np.array([[1, 0.5], [0.5, 2 / 4]]), rtol=1e-14)
    x3, P3 = tm.three_point_initiation([0.0, 0.0], [1.0, 1.0], [2.5, 2.0], 1.0, R)
    np.testing.assert_allclose(x3[[0, 1]], [(-0 + 2 * 1 + 5 * 2.5) / 6, 2.5 / 2], rtol=1e-14)
    np.testing.assert_allclose(P3[:2, :2], 4.0 * np.array([[5 / 6, 0.5], [0.5, 0.5]]), rtol=1e-14)


def test_initiation_covariance_is_the_error_covariance():
    rng = np.random.default_rng(2)
    N, R = 20000, np.diag([4.0, 1.0])
    truth = np.array([0.0, 3.0, 5.0, -1.0])  # at the last scan
    t = np.array([-2.0, -1.0, 0.0])
    clean = np.stack([truth[[0, 2]] + truth[[1, 3]] * tk for tk in t])
    zs = clean[:, None] + rng.normal(size=(3, N, 2)) * np.sqrt(np.diag(R))
    x, P = tm.three_point_initiation(zs[0], zs[1], zs[2], 1.0, R)
    e = x - truth
    nees = np.einsum("ni,ij,nj->n", e, np.linalg.inv(P), e)
    # mean NEES of N chi2_4 draws: chi-square bound at level 1e-3, two-sided
    tot = nees.sum()
    assert chi2.ppf(5e-4, 4 * N) <= tot <= chi2.isf(5e-4, 4 * N)


@pytest.mark.parametrize("M,N,p", [(2, 3, 0.3), (3, 5, 0.6), (2, 2, 0.9)])
def test_m_of_n_confirmation_probability(M, N, p):
    rng = np.random.default_rng(M * 10 + N)
    runs = 20000
    hits = rng.random((N, runs)) < p
    conf = tm.m_of_n_confirm(hits, M, N) >= 0
    assert _binom_ok(int(conf.sum()), runs, float(tm.m_of_n_probability(p, M, N)))


def test_m_of_n_confirm_first_scan():
    h = np.array([1, 0, 0, 1, 1, 0, 1], bool)
    assert tm.m_of_n_confirm(h, 2, 3) == 4
    assert tm.m_of_n_confirm(h, 3, 3) == -1
    assert tm.m_of_n_confirm(h, 1, 1) == 0


# ---------------------------------------------------------------- IMM-PDAF
def test_imm_pdaf_single_mode_is_pdaf():
    cv = models.ConstantVelocity(ndim=2, sigma2=1.0)
    R = 25.0 * np.eye(2)
    est = imm.IMM([imm.KalmanMode(cv, R), imm.KalmanMode(cv, R)], np.array([[0.9, 0.1], [0.1, 0.9]]), [0.5, 0.5])
    rng = np.random.default_rng(0)
    x0, P0 = np.array([0.0, 10.0, 0.0, 5.0]), np.diag([100.0, 25.0, 100.0, 25.0])
    s = est.predict(est.initialize(x0, P0), 1.0)
    Z = np.array([10.0, 5.0]) + 8.0 * rng.normal(size=(4, 2))
    out = asc.imm_pdaf_update(est, s, Z, P_D=0.9, P_G=0.99, clutter_density=1e-3)
    ref = asc.pdaf_update(s.xs[0], s.Ps[0], Z, cv.H, R, P_D=0.9, P_G=0.99, clutter_density=1e-3)
    np.testing.assert_allclose(out.x, ref.x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out.P, ref.P, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out.mu, [0.5, 0.5], rtol=1e-12)


def test_imm_pdaf_mode_probabilities_against_direct_computation():
    # two different modes, so that the mode likelihoods differ: mu_j must be cbar_j Lambda_j
    # normalised, Lambda_j = 1 - P_D P_G + sum_gated P_D N(z_i; H x_j, S_j) / lambda (computed
    # here with scipy's multivariate normal), and x, P the moment-matched mixture of the PDAFs
    from scipy.stats import multivariate_normal
    quiet, agile = models.ConstantVelocity(ndim=2, sigma2=0.05), models.ConstantVelocity(ndim=2, sigma2=9.0)
    R = 25.0 * np.eye(2)
    est = imm.IMM([imm.KalmanMode(quiet, R), imm.KalmanMode(agile, R)], np.array([[0.95, 0.05], [0.2, 0.8]]),
                  [0.7, 0.3])
    rng = np.random.default_rng(31)
    x0, P0 = np.array([0.0, 10.0, 0.0, 5.0]), np.diag([100.0, 25.0, 100.0, 25.0])
    s = est.predict(est.initialize(x0, np.diag([25.0, 1.0, 25.0, 1.0])), 2.0)
    Z = np.array([32.0, 2.0]) + 5.0 * rng.normal(size=(5, 2))  # off the quiet prediction (20, 10)
    P_D, P_G, lam = 0.9, 0.99, 2e-4
    out = asc.imm_pdaf_update(est, s, Z, P_D=P_D, P_G=P_G, clutter_density=lam)
    Lam, xs, Ps = [], [], []
    for j, mode in enumerate(est.modes):
        Sj = mode.H @ s.Ps[j] @ mode.H.T + R
        zhat = mode.H @ s.xs[j]
        d2 = np.einsum("mi,ij,mj->m", Z - zhat, np.linalg.inv(Sj), Z - zhat)
        inside = d2 <= chi2.ppf(P_G, 2)
        Lam.append(1 - P_D * P_G + sum(P_D * multivariate_normal(zhat, Sj).pdf(z) / lam for z in Z[inside]))
        u = asc.pdaf_update(s.xs[j], s.Ps[j], Z, mode.H, R, P_D=P_D, P_G=P_G, clutter_density=lam)
        xs.append(u.x)
        Ps.append(u.P)
    mu = np.asarray(s.mu) * np.array(Lam)
    mu /= mu.sum()
    assert abs(np.log(Lam[1] / Lam[0])) > 0.25  # teeth: the likelihoods move mu by > 25 %, far above tol
    x = mu[0] * xs[0] + mu[1] * xs[1]
    P = sum(m_ * (Pj + np.outer(xj - x, xj - x)) for m_, xj, Pj in zip(mu, xs, Ps))
    # a few dozen operations on well-conditioned 2x2 / 4x4 matrices: <= 1e3 eps relative
    np.testing.assert_allclose(out.mu, mu, rtol=1e3 * EPS)
    np.testing.assert_allclose(out.x, x, rtol=0, atol=1e3 * EPS * np.abs(x).max())
    np.testing.assert_allclose(out.P, P, rtol=0, atol=1e3 * EPS * np.abs(P).max())
    with pytest.raises(ValueError, match="clutter_density"):
        asc.imm_pdaf_update(est, s, Z, P_D=P_D, P_G=P_G, clutter_density=None)


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize("kw,word", [
    (dict(clutter_density=-1.0), "clutter_density"), (dict(P_D=0.0), "P_D"), (dict(P_D=1.5), "P_D"),
    (dict(P_G=1.0), "P_G"), (dict(P_G=0.0), "P_G"),
])
def test_bad_input_names_the_argument(kw, word):
    rng = np.random.default_rng(0)
    x, P, H, R, Z = _random_case(rng)
    args = dict(P_D=0.9, P_G=0.99, clutter_density=0.1) | kw
    with pytest.raises(ValueError, match=word):
        asc.pdaf_update(x, P, Z, H, R, **args)
    with pytest.raises(ValueError, match=word):
        asc.jpda_update(np.stack([x, x]), np.stack([P, P]), Z, H, R, **args)


def test_bad_measurement_width_and_mask():
    rng = np.random.default_rng(0)
    x, P, H, R, Z = _random_case(rng)
    with pytest.raises(ValueError, match=r"Z must have shape \(\.\.\., M_max, 2\)"):
        asc.pdaf_update(x, P, np.zeros((3, 3)), H, R, P_D=0.9, P_G=0.99)
    with pytest.raises(ValueError, match="Z must have shape"):
        asc.nearest_neighbour(x, P, np.zeros(2), H, R, P_G=0.99)
    with pytest.raises(ValueError, match="mask"):
        asc.pdaf_update(x, P, Z, H, R, P_D=0.9, P_G=0.99, mask=np.ones(2, bool))
    with pytest.raises(TypeError, match="mask"):
        asc.pdaf_update(x, P, Z, H, R, P_D=0.9, P_G=0.99, mask=np.ones(len(Z)))
    with pytest.raises(ValueError, match="P_G"):
        asc.gate_volume(np.eye(2), 1.5)
    with pytest.raises(ValueError, match="clutter_density"):
        clutter.simulate_scans(np.zeros((3, 2)), P_D=0.9, clutter_density=-1, region=([0, 0], [1, 1]),
                               rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="region"):
        clutter.simulate_scans(np.zeros((3, 2)), P_D=0.9, clutter_density=1, region=([0, 0, 0], [1, 1, 1]),
                               rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="truth and estimate"):
        asc.gospa(np.zeros((2, 2)), np.zeros((2, 3)), c=1.0)
    with pytest.raises(ValueError, match="M and N"):
        tm.m_of_n_probability(0.5, 4, 3)
    with pytest.raises(ValueError, match="amplitude"):
        asc.strongest_neighbour(x, P, Z, H, R, np.ones(len(Z) + 1), P_G=0.99)
    with pytest.raises(ValueError, match="P_G"):
        asc.strongest_neighbour(x, P, Z, H, R, np.ones(len(Z)), P_G=1.0)
    with pytest.raises(ValueError, match="xs must have shape"):
        asc.jpda_update(x, P, Z, H, R, P_D=0.9, P_G=0.99, clutter_density=0.1)
    with pytest.raises(ValueError, match="c \\(cut-off"):
        asc.gospa(np.zeros((2, 2)), np.zeros((2, 2)), c=0.0)


# ---------------------------------------------------------------- neighbours, empty gates, drivers
def test_nearest_and_strongest_neighbour_choose_correctly():
    rng = np.random.default_rng(9)
    x, P, H, R, Z = _random_case(rng, M=6)
    amp = rng.uniform(0, 5, size=len(Z))
    g = asc.validation_gate(x, P, Z, H, R, P_G=0.999)
    nn = asc.nearest_neighbour(x, P, Z, H, R, P_G=0.999)
    sn = asc.strongest_neighbour(x, P, Z, H, R, amp, P_G=0.999)
    inside = np.flatnonzero(g.inside)
    assert nn.index == inside[np.argmin(g.d2[inside])]
    assert sn.index == inside[np.argmax(amp[inside])]
    kf = kalman_update(x, P, Z[nn.index], H, R)
    np.testing.assert_allclose(nn.x, kf.x, rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(nn.P, kf.P)


def test_empty_gate_gives_the_prediction():
    rng = np.random.default_rng(4)
    x, P, H, R, _ = _random_case(rng)
    far = (H @ x)[None] + 1e6
    for lam in (None, 0.1, 0.0):
        u = asc.pdaf_update(x, P, far, H, R, P_D=0.9, P_G=0.99, clutter_density=lam)
        assert u.beta[0] == 1.0 and np.array_equal(u.x, x)
        np.testing.assert_allclose(u.P, P, rtol=0, atol=4 * EPS * np.abs(P).max())
    nn = asc.nearest_neighbour(x, P, far, H, R, P_G=0.99)
    assert nn.index == -1 and np.array_equal(nn.x, x) and np.array_equal(nn.P, P)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), T=st.integers(1, 3), M=st.integers(0, 5), P_D=st.floats(0.05, 1.0),
       lam=st.floats(1e-6, 10.0))
def test_jpda_marginals_are_probabilities(seed, T, M, P_D, lam):
    rng = np.random.default_rng(seed)
    x, P, H, R, Z = _random_case(rng, M=max(M, 1))
    mask = np.arange(len(Z)) < M
    xs = x + rng.normal(size=(T, 4))
    j = asc.jpda_update(xs, np.stack([P] * T), Z, H, R, P_D=P_D, P_G=0.99, clutter_density=lam, mask=mask)
    np.testing.assert_allclose(j.beta.sum(-1), 1.0, rtol=0, atol=10 * EPS * (len(Z) + 1) ** T)
    assert np.all(j.beta >= 0) and np.all(j.beta[:, 1:][:, ~mask] == 0)
    # a measurement is the target of at most one track: its marginals over the tracks sum to <= 1
    assert np.all(j.beta[:, 1:].sum(0) <= 1 + 1e-12)
    for t in range(T):
        assert np.array_equal(j.P[t], j.P[t].T) and np.linalg.eigvalsh(j.P[t]).min() >= -1e3 * EPS * np.abs(P).max()


def test_filter_scans_runs_each_method():
    rng = np.random.default_rng(12)
    cv = models.ConstantVelocity(ndim=2, sigma2=0.25)
    F, Q, H, R = cv.F(1.0), cv.Q(1.0), cv.H, 100.0 * np.eye(2)
    z = 10 * rng.normal(size=(5, 7, 2))
    scans = [clutter.simulate_scans(z[k], P_D=0.9, clutter_density=1e-4, region=([-100, -100], [100, 100]), rng=rng)
             for k in range(5)]
    for method in ("nn", "snn", "pdaf"):
        r = asc.filter_scans(method, scans, np.zeros((7, 4)), 100 * np.eye(4), F, Q, H, R, P_G=0.99, P_D=0.9,
                             clutter_density=1e-4)
        assert r.x.shape == (5, 7, 4) and r.P.shape == (5, 7, 4, 4) and r.n_gated.shape == (5, 7)
    with pytest.raises(ValueError, match="method"):
        asc.filter_scans("jpda", scans, np.zeros(4), np.eye(4), F, Q, H, R, P_G=0.99)
    with pytest.raises(ValueError, match=r"F must have shape \(4, 4\)"):
        asc.filter_scans("nn", scans, np.zeros(4), np.eye(4), F[:2, :2], Q, H, R, P_G=0.99)
    with pytest.raises(ValueError, match="Q"):
        asc.jpda_filter(scans, np.zeros((1, 4)), np.eye(4), F, -Q - np.eye(4), H, R, P_G=0.99, P_D=0.9,
                        clutter_density=1e-4)


def test_track_score_and_sprt_closed_forms():
    inc = tm.score_increment([True, False], [-3.0, 0.0], P_D=0.9, P_G=0.99, clutter_density=1e-4)
    np.testing.assert_allclose(inc, [np.log(0.9 / 1e-4) - 3.0, np.log(1 - 0.9 * 0.99)], rtol=1e-15)
    up, down = tm.sprt_thresholds(0.01, 0.1)
    assert up == pytest.approx(np.log(0.9 / 0.01), rel=1e-15) and down == pytest.approx(np.log(0.1 / 0.99), rel=1e-15)
    with pytest.raises(ValueError, match="clutter_density"):
        tm.score_increment(True, 0.0, P_D=0.9, P_G=0.99, clutter_density=0.0)
    err = np.array([[1.0, 99.0], [99.0, 99.0], [99.0, 1.0], [99.0, 99.0]])
    np.testing.assert_array_equal(tm.lost_track(err, 50.0, 3), [True, False])
