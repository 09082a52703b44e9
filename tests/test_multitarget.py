"""Tests of kftrack.multitarget: GNN and JPDA multi-target tracking with track management.

Synthetic scenarios generated here (straight-line targets, range-bearing noise, Poisson clutter,
per-detection times of a rotating antenna) until the recorded-traffic radar exists.
"""
import numpy as np
import pytest

from kftrack import association, ekf
from kftrack.models import ConstantVelocity
from kftrack.multitarget import MultiTargetTracker, Tracks, track_scans
from kftrack.sensors import surveillance
from kftrack.sensors.radar import RangeBearing
from kftrack.trackmanagement import m_of_n_confirm, sprt_thresholds, two_point_initiation

CV = ConstantVelocity(ndim=2, q=1.0)


def Scan(time, times, z, origin=None):
    """A scan of the surveillance radar's type (origin -1, clutter, unless given: never read)."""
    z = np.asarray(z, dtype=float)
    return surveillance.Scan(time, np.asarray(times, dtype=float), z,
                             np.full(len(z), -1) if origin is None else np.asarray(origin))
RADAR = RangeBearing(sigmas=(30.0, np.deg2rad(0.15)))


class PositionSensor:
    """A linear position sensor z = [x, y] + v (duck-typed like RangeBearing), for comparisons
    with the linear single-target filters of kftrack.association."""

    H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    angle_components = ()

    def __init__(self, sigma=20.0):
        self.R = sigma**2 * np.eye(2)

    def h(self, x):
        return np.asarray(x)[..., [0, 2]]

    def jacobian(self, x):
        return np.broadcast_to(self.H, np.shape(x)[:-1] + (2, 4)).copy()

    def to_cartesian(self, z):
        z = np.asarray(z, dtype=float)
        return z, np.broadcast_to(self.R, z.shape + (2,)).copy()


def rotating_scenario(N, K=25, period=4.0, P_D=0.9, clutter_per_scan=20, seed=0, rmax=100e3, sensor=RADAR):
    """N straight-line targets 20-80 km out, a clockwise antenna (detection time from azimuth),
    Poisson clutter uniform over the disc of radius rmax. Returns scans, truth positions at scan
    starts and the clutter density per scan per m²."""
    rng = np.random.default_rng(seed)
    r0, th0 = rng.uniform(20e3, 80e3, N), rng.uniform(-np.pi, np.pi, N)
    sp, hd = rng.uniform(100, 250, N), rng.uniform(-np.pi, np.pi, N)
    X0 = np.stack([r0 * np.cos(th0), sp * np.cos(hd), r0 * np.sin(th0), sp * np.sin(hd)], 1)
    scans, truths = [], []
    for k in range(K):
        t0 = k * period
        p0 = X0[:, [0, 2]] + X0[:, [1, 3]] * t0
        az = np.mod(np.pi / 2 - np.arctan2(p0[:, 1], p0[:, 0]), 2 * np.pi)
        td = t0 + period * az / (2 * np.pi)
        xs = X0.copy()
        xs[:, 0] += X0[:, 1] * td
        xs[:, 2] += X0[:, 3] * td
        det = rng.random(N) < P_D
        z = sensor.simulate(xs[det], rng)
        nc = rng.poisson(clutter_per_scan)
        zc = np.stack([rmax * np.sqrt(rng.random(nc)), rng.uniform(-np.pi, np.pi, nc)], 1)  # uniform in the disc
        tc = t0 + period * np.mod(np.pi / 2 - zc[:, 1], 2 * np.pi) / (2 * np.pi)
        Z, T = np.concatenate([z, zc]), np.concatenate([td[det], tc])
        O = np.concatenate([np.flatnonzero(det), -np.ones(nc, int)])
        o = np.argsort(T)
        scans.append(Scan(t0, T[o], Z[o], O[o]))
        truths.append(p0)
    return scans, truths, clutter_per_scan / (np.pi * rmax**2)


def ekf_reference(scans, x0, P0, t0, sensor):
    """The EKF on one target's detections, predicted to each detection's own time."""
    x, P, t, xs, Ps = x0, P0, t0, [], []
    for s in scans:
        dt = float(s.times[0] - t)
        x, P = ekf.ekf_predict(x, P, lambda v: CV.F(dt) @ v, lambda v: CV.F(dt), CV.Q(dt))
        u = ekf.ekf_update(x, P, s.z[0], sensor.h, sensor.jacobian, sensor.R, angle_components=(1,))
        x, P, t = u.x, u.P, float(s.times[0])
        xs.append(x)
        Ps.append(P)
    return np.array(xs), np.array(Ps)


def single_target_scans(K=30, seed=1, x0=(30e3, -150.0, 40e3, 120.0)):
    rng = np.random.default_rng(seed)
    x0 = np.array(x0)
    times = 4.0 * np.arange(K) + rng.uniform(0, 4.0, K)  # a per-detection time inside each 4 s scan
    scans = []
    for k in range(K):
        xt = CV.F(times[k]) @ x0
        scans.append(Scan(4.0 * k, times[k:k + 1], RADAR.simulate(xt, rng)[None], np.zeros(1, int)))
    return scans, x0


# --------------------------------------------------------------------------------------------
# single target: the multi-target machinery reduces to the single-target filters
# --------------------------------------------------------------------------------------------
def test_gnn_single_target_equals_ekf():
    scans, x0 = single_target_scans()
    P0 = np.diag([100.0**2, 20.0**2, 100.0**2, 20.0**2])
    tr = track_scans(scans, method="gnn", sensor=RADAR, motion=CV, P_D=1.0, initiate=False,
                     initial_tracks=[(0.0, x0, P0)])
    assert len(tr) == 1
    xs, Ps = ekf_reference(scans, x0, P0, 0.0, RADAR)
    t = tr.tracks[0]
    # the first row is the initial track itself, at its start
    assert np.array_equal(t.times, np.concatenate([[0.0]] + [s.times for s in scans]))
    assert np.array_equal(t.x[0], x0) and np.array_equal(t.P[0], P0)
    ids, x = tr.snapshot(0.0)
    assert ids.tolist() == [t.id] and np.array_equal(x[0], x0)
    # The same kernels in the same order; only the batched matrix products may sum in another
    # order: a relative difference of a few eps per operation, not amplified (the filter
    # contracts). 30 scans x ~100 flops x eps = 7e-13; 1e-10 leaves a margin of 100.
    np.testing.assert_allclose(t.x[1:], xs, rtol=1e-10, atol=1e-10 * np.abs(xs).max())
    np.testing.assert_allclose(t.P[1:], Ps, rtol=1e-10, atol=1e-10 * np.abs(Ps).max())
    assert t.confirmed.all()


def _pdaf_case(max_events):
    rng = np.random.default_rng(7)
    sensor = PositionSensor(20.0)
    x0 = np.array([0.0, 30.0, 0.0, -10.0])
    P0 = np.diag([20.0**2, 5.0**2, 20.0**2, 5.0**2])
    scans, padded = [], []
    for k in range(30):
        xt = CV.F(2.0 * k) @ x0
        z = [xt[[0, 2]] + 20.0 * rng.standard_normal(2)] if rng.random() < 0.8 else []
        clutter = xt[[0, 2]] + rng.uniform(-150, 150, (rng.poisson(4), 2))  # dense clutter around the target
        Z = np.array(list(z) + list(clutter)).reshape(-1, 2)
        scans.append(Scan(2.0 * k, np.full(len(Z), 2.0 * k), Z))
        padded.append((Z, np.ones(len(Z), bool)))
    lam = 4 / 300.0**2
    tr = track_scans(scans, method="jpda", sensor=sensor, motion=CV, P_D=0.8, clutter_density=lam, P_G=0.99,
                     initiate=False, initial_tracks=[(0.0, x0, P0)], deletion=(30, 30), max_events=max_events)
    ref = association.filter_scans("pdaf", padded, x0, P0, CV.F(2.0), CV.Q(2.0), sensor.H, sensor.R, P_G=0.99,
                                   P_D=0.8, clutter_density=lam)
    return tr, ref


def test_jpda_single_target_equals_pdaf():
    tr, ref = _pdaf_case(10_000)
    t = tr.tracks[0]
    assert len(tr) == 1 and len(t.times) == 1 + 30 and tr.fallbacks == 0  # the start, then each scan
    assert (ref.n_gated >= 2).sum() >= 5  # the clutter does enter the gate: the weights matter
    # same kernels (gate, weights, PDA combination) on the same numbers: round-off only (the
    # augmented state adds exact zeros); 30 scans x ~200 flops x eps ~ 1e-12, margin 100
    np.testing.assert_allclose(t.x[1:], ref.x, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(t.P[1:], ref.P, rtol=1e-10, atol=1e-9)


def test_cheap_jpda_fallback_is_exact_for_an_isolated_target():
    # max_events = 1: every scan with a gated detection goes to the fall-back, which for a lone
    # target is the PDAF: beta_j = G_j / (sum G + 1) = L_j / (L_0 + sum L)
    tr, ref = _pdaf_case(1)
    assert tr.fallbacks == int((ref.n_gated > 0).sum()) > 0
    np.testing.assert_allclose(tr.tracks[0].x[1:], ref.x, rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(tr.tracks[0].P[1:], ref.P, rtol=1e-9, atol=1e-8)


# --------------------------------------------------------------------------------------------
# JPDA over clusters equals JPDA over the whole scan
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(6))
def test_cluster_jpda_equals_full_jpda(seed):
    rng = np.random.default_rng(seed)
    sensor = PositionSensor(15.0)
    # two groups of close targets (multi-target clusters) and one lone target
    centres = np.array([[0.0, 0.0], [0.0, 0.0], [40.0, 10.0], [5000.0, 0.0], [5030.0, 20.0], [-4000.0, 3000.0]])
    x0 = np.zeros((len(centres), 4))
    x0[:, [0, 2]] = centres + rng.normal(0, 5, centres.shape)
    x0[:, [1, 3]] = rng.normal(0, 10, (len(centres), 2))
    P0 = np.diag([30.0**2, 10.0**2, 30.0**2, 10.0**2])
    trk = MultiTargetTracker(method="jpda", sensor=sensor, motion=CV, P_D=0.9, clutter_density=1e-4,
                             initiate=False, initial_tracks=[(0.0, x, P0) for x in x0])
    xp, Pp = CV.F(1.0) @ x0[..., None], CV.F(1.0) @ P0 @ CV.F(1.0).T + CV.Q(1.0)
    xp = xp[..., 0]
    Z = np.concatenate([xp[:, [0, 2]] + rng.normal(0, 15, (len(x0), 2)),
                        centres[[0, 0, 3, 3]] + rng.uniform(-60, 60, (4, 2))])
    states = trk.step(Scan(1.0, np.ones(len(Z)), Z))
    full = association.jpda_update(xp, np.broadcast_to(Pp, (len(x0), 4, 4)), Z, sensor.H, sensor.R, P_D=0.9,
                                   P_G=0.99, clutter_density=1e-4)
    assert full.n_events > len(x0) + 2  # shared measurements: the clusters are real
    x = np.array([s.x for s in states])
    P = np.array([s.P for s in states])
    # per-cluster enumeration gives the same marginals as the whole; round-off (1e-12 relative)
    np.testing.assert_allclose(x, full.x, rtol=1e-10, atol=1e-8)
    np.testing.assert_allclose(P, full.P, rtol=1e-10, atol=1e-8)


def test_jpda_guard_fallback_on_a_large_cluster():
    sensor = PositionSensor(15.0)
    x0 = np.array([[0.0, 0.0, 0.0, 0.0], [10.0, 0.0, 0.0, 0.0], [0.0, 0.0, 10.0, 0.0]])
    P0 = np.diag([30.0**2, 1.0, 30.0**2, 1.0])
    Z = np.array([[0.0, 0.0], [5.0, 5.0], [10.0, 0.0], [0.0, 10.0]])
    kw = dict(method="jpda", sensor=sensor, motion=CV, P_D=0.9, clutter_density=1e-4, initiate=False,
              initial_tracks=[(0.0, x, P0) for x in x0])
    exact = MultiTargetTracker(**kw)
    s_exact = exact.step(Scan(1.0, np.ones(4), Z))
    cheap = MultiTargetTracker(**kw, max_events=10)  # 3 targets x 4 measurements: 73 events
    s_cheap = cheap.step(Scan(1.0, np.ones(4), Z))
    assert exact.fallbacks == 0 and cheap.fallbacks == 1 and cheap.tracks().fallbacks == 1
    d = np.abs(np.array([s.x for s in s_exact]) - np.array([s.x for s in s_cheap]))[:, [0, 2]]
    assert 0 < d.max() < 5.0  # an approximation, within a third of a noise sigma here


# --------------------------------------------------------------------------------------------
# track management
# --------------------------------------------------------------------------------------------
def _pattern_scans(pattern, sensor, x0=(1000.0, 20.0, 2000.0, -10.0)):
    """A target detected without noise at the scans where pattern is 1 (two leading hits start it)."""
    x0 = np.array(x0)
    scans = []
    for k, h in enumerate([1, 1] + list(pattern)):
        z = (CV.F(float(k)) @ x0)[[0, 2]][None] if h else np.zeros((0, 2))
        scans.append(Scan(float(k), np.full(len(z), float(k)), z))
    return scans


@pytest.mark.parametrize("pattern, confirmed_at, deleted_at", [
    ([1, 1, 1, 1], 3, None),       # 2 of 3: the second hit after birth (scan 3) confirms
    ([1, 0, 1, 1], 4, None),
    ([0, 1, 1], 3 + 1, None),
    ([1, 0, 0, 0, 0], None, 4),    # tentative and not confirmed within 3 scans of its birth: deleted
    ([0, 0, 0], None, 4),
    ([1, 1, 0, 0, 0, 1], 3, 6),    # confirmed, then 3 misses in the last 3 scans delete it
    ([1, 1, 0, 0, 1, 0, 0, 1], 3, None),
])
def test_m_of_n_confirmation_and_deletion(pattern, confirmed_at, deleted_at):
    sensor = PositionSensor(1.0)
    scans = _pattern_scans(pattern, sensor)
    tr = track_scans(scans, method="gnn", sensor=sensor, motion=CV, P_D=0.9, confirmation=(2, 3), deletion=(3, 3))
    assert len(tr) == 1
    t = tr.tracks[0]
    times = np.array([s.time for s in scans])
    assert t.times[0] == 1.0  # born at the second scan
    k_conf = np.flatnonzero(t.confirmed)
    assert (times.tolist().index(t.times[k_conf[0]]) if len(k_conf) else None) == confirmed_at
    if len(k_conf):
        assert t.confirmed[k_conf[0]:].all()
    assert tr.ends[t.id] == (np.inf if deleted_at is None else float(deleted_at))
    if deleted_at is not None:
        assert t.times[-1] == deleted_at - 1  # last recorded at the scan before its deletion


@pytest.mark.parametrize("pattern, candidate_scans, born_at, confirmed_at", [
    ([1, 0, 1, 1, 1, 1], 1, 3, 5),         # the 2nd detection missed: the start restarts at scan 2 ...
    ([1, 0, 1, 1, 1, 1], 2, 2, 4),         # ... or (memory 2) pairs scans 0 and 2: confirmed a scan earlier
    ([1, 0, 0, 1, 1, 1, 1], 2, 4, 6),      # two misses: the first detection is out of a 2-scan memory
    ([1, 0, 0, 1, 1, 1, 1], 3, 3, 5),
    ([1, 1, 1, 1], 2, 1, 3),               # consecutive detections: the same start as memory 1
    ([1, 1, 1, 1], 1, 1, 3),
])
def test_candidate_memory(pattern, candidate_scans, born_at, confirmed_at):
    sensor = PositionSensor(1.0)
    x0 = np.array([1000.0, 20.0, 2000.0, -10.0])
    z = [(CV.F(float(k)) @ x0)[[0, 2]][None] if h else np.zeros((0, 2)) for k, h in enumerate(pattern)]
    scans = [Scan(float(k), np.full(len(zk), float(k)), zk) for k, zk in enumerate(z)]
    tr = track_scans(scans, method="gnn", sensor=sensor, motion=CV, P_D=0.9, candidate_scans=candidate_scans)
    assert len(tr) == 1
    t = tr.tracks[0]
    assert t.times[0] == born_at and t.times[np.flatnonzero(t.confirmed)[0]] == confirmed_at
    # the start is the two-point differencing over the pair's own interval (detections born_at - first
    # apart): the same operations, vectorised, so the same bits up to the batched products' order
    first = max(k for k in range(born_at) if pattern[k])
    x, P = two_point_initiation(z[first][0], z[born_at][0], dt=float(born_at - first), R=sensor.R)
    np.testing.assert_allclose(t.x[0], x, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(t.P[0], P, rtol=1e-12, atol=1e-12)


def test_candidate_scans_is_checked():
    scans = _pattern_scans([1], PositionSensor(1.0))
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match=r"candidate_scans.*positive integer.*got"):
            track_scans(scans, sensor=PositionSensor(1.0), motion=CV, P_D=0.9, candidate_scans=bad)


def test_score_confirmation_and_deletion():
    sensor = PositionSensor(10.0)
    scans = _pattern_scans([1] * 6 + [0] * 12, sensor)
    up, down = sprt_thresholds(0.01, 0.1)
    tr = track_scans(scans, method="gnn", sensor=sensor, motion=CV, P_D=0.9, clutter_density=1e-6,
                     confirmation=("score", 0.01, 0.1))
    t = tr.tracks[0]
    assert t.confirmed.any() and not t.confirmed[0]
    # each miss adds log(1 - P_D P_G) = log(0.109) = -2.22; the peak-drop threshold is
    # log(0.1 / 0.99) = -2.29: the second miss after the last hit deletes the track
    assert np.log1p(-0.9 * 0.99) > down > 2 * np.log1p(-0.9 * 0.99)
    assert tr.ends[t.id] == 2.0 + 6 + 1


def test_max_std_deletes_a_coasting_track():
    sensor = PositionSensor(10.0)
    scans = _pattern_scans([1] * 4 + [0] * 30, sensor)
    kw = dict(method="gnn", sensor=sensor, motion=ConstantVelocity(ndim=2, q=100.0), P_D=0.9, deletion=(40, 40))
    assert track_scans(scans, **kw).ends[0] == np.inf
    tr = track_scans(scans, **kw, max_std=200.0)
    t = tr.tracks[0]
    std = np.sqrt(t.P[:, 0, 0] + t.P[:, 2, 2])
    q100 = ConstantVelocity(ndim=2, q=100.0)
    P_next = q100.F(1.0) @ t.P[-1] @ q100.F(1.0).T + q100.Q(1.0)  # the coasting prediction that deleted it
    assert std.max() <= 200.0 < np.sqrt(P_next[0, 0] + P_next[2, 2])
    assert tr.ends[t.id] < np.inf


# --------------------------------------------------------------------------------------------
# many targets, clutter, per-detection times
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def cluttered():
    return rotating_scenario(12, K=25, seed=3)


def test_coarse_test_keeps_every_gated_pair(cluttered):
    scans, _, lam = cluttered
    trk = MultiTargetTracker(method="gnn", sensor=RADAR, motion=CV, P_D=0.9, clutter_density=lam)
    checked = 0
    for s in scans:
        T, M = len(trk._t), len(s.z)
        if T and M:
            t_ref = float(s.times.mean())
            xr, Pr = trk._predict(np.arange(T), np.full(T, t_ref))
            ti, dj = trk._candidates(xr, Pr, s.times, s.z, t_ref)
            ai, aj = np.repeat(np.arange(T), M), np.tile(np.arange(M), T)
            nis = trk._fine(ai, aj, s.times[aj], s.z)[5]
            gated = set(zip(ai[nis <= trk.gamma].tolist(), aj[nis <= trk.gamma].tolist()))
            assert gated <= set(zip(ti.tolist(), dj.tolist()))
            assert len(ti) < T * M / 5  # and it is a real pre-filter
            checked += len(gated)
        trk.step(s)
    assert checked > 100


@pytest.mark.parametrize("method", ["gnn", "jpda"])
def test_tracks_every_target(cluttered, method):
    scans, truths, lam = cluttered
    tr = track_scans(scans, method=method, sensor=RADAR, motion=CV, P_D=0.9, clutter_density=lam)
    # After the start-up (birth at scan 1, confirmation by scan 3-5) every target is held, except
    # one the logic had to drop: 3 misses in a row (P_D = 0.9: p = 1e-3 per target and scan)
    # delete its track, and a new one needs 2 scans to start and 2 more to confirm, so a target
    # may be missing at scan k only if it went undetected 3 scans in a row within scans k-7..k-1.
    # No false track may survive: 20 clutter points over 2 pi x 100 km pair up (within
    # v_max dt) rarely, and such a pair must then be hit twice more within 3 scans.
    false_total = 0
    for k in range(10, 25):
        ids, x = tr.snapshot(scans[k].time)
        D = np.linalg.norm(truths[k][:, None] - x[None, :, [0, 2]], axis=-1)
        held = (D < 1000.0).any(1)
        false_total += int((~(D < 1000.0).any(0)).sum())
        for i in np.flatnonzero(~held):
            seen = np.array([(scans[j].origin == i).any() for j in range(k - 7, k)])
            assert m_of_n_confirm(~seen, 3, 3) >= 0, f"target {i} lost at scan {k} without 3 misses"
        assert np.sqrt(np.mean(D.min(1)[held] ** 2)) < 300.0  # cross-range sigma at 80 km: 210 m
    assert false_total == 0


@pytest.mark.parametrize("method", ["gnn", "jpda"])
def test_step_equals_track_scans(cluttered, method):
    scans, _, lam = cluttered
    kw = dict(method=method, sensor=RADAR, motion=CV, P_D=0.9, clutter_density=lam)
    batch = track_scans(scans, **kw)
    trk = MultiTargetTracker(**kw)
    for s in scans:
        states = trk.step(s)
    stream = trk.tracks()
    assert [t.id for t in stream] == [t.id for t in batch] and stream.ends == batch.ends
    for a, b in zip(stream, batch):
        for f in ("times", "x", "P", "confirmed"):
            assert np.array_equal(getattr(a, f), getattr(b, f))
    alive = [t for t in batch if batch.ends[t.id] == np.inf]
    assert sorted(s.id for s in states) == sorted(t.id for t in alive)
    assert all(np.array_equal(s.x, next(t for t in alive if t.id == s.id).x[-1]) for s in states)


def test_snapshot(cluttered):
    scans, _, lam = cluttered
    tr = track_scans(scans, sensor=RADAR, motion=CV, P_D=0.9, clutter_density=lam)
    t = 20 * 4.0 + 1.3
    ids, x = tr.snapshot(t)
    assert len(ids) == len(set(ids.tolist())) > 0
    expected = set()  # every track whose row in force at t (at or before, not yet deleted) is confirmed
    for track in tr:
        k = np.searchsorted(track.times, t, side="right") - 1
        if k >= 0 and track.confirmed[k] and (k < len(track.times) - 1 or t < tr.ends[track.id]):
            expected.add(track.id)
    assert set(ids.tolist()) == expected
    for i, xi in zip(ids, x):
        track = next(tt for tt in tr if tt.id == i)
        k = np.searchsorted(track.times, t, side="right") - 1
        assert track.confirmed[k]
        np.testing.assert_array_equal(xi, CV.F(t - track.times[k]) @ track.x[k])
    assert len(tr.snapshot(-1.0)[0]) == 0


def test_csv_round_trip(cluttered, tmp_path):
    scans, _, lam = cluttered
    tr = track_scans(scans[:12], sensor=RADAR, motion=CV, P_D=0.9, clutter_density=lam)
    path = tmp_path / "tracks.csv"
    tr.to_csv(path)
    back = Tracks.from_csv(path, motion=CV)
    assert back.ends == tr.ends and len(back) == len(tr)
    for a, b in zip(tr, back):
        assert a.id == b.id
        for f in ("times", "x", "P", "confirmed"):
            assert np.array_equal(getattr(a, f), getattr(b, f))  # %.17g: float64 exactly
    np.testing.assert_array_equal(back.snapshot(30.0)[1], tr.snapshot(30.0)[1])
    with open(path) as fh:
        assert fh.readline().startswith("id,time,confirmed,end,x,vx,y,vy,P00")


# --------------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------------
def test_bad_input(tmp_path):
    good = dict(sensor=RADAR, motion=CV, P_D=0.9, clutter_density=1e-6)
    scans = [Scan(0.0, np.zeros(1), np.array([[1000.0, 0.1]]))]
    with pytest.raises(ValueError, match="method"):
        track_scans(scans, method="mht", **good)
    with pytest.raises(TypeError, match="sensor"):
        track_scans(scans, **{**good, "sensor": object()})
    with pytest.raises(TypeError, match="motion"):
        track_scans(scans, **{**good, "motion": "cv"})
    with pytest.raises(ValueError, match="P_D"):
        track_scans(scans, **{**good, "P_D": 1.5})
    with pytest.raises(ValueError, match="P_G"):
        track_scans(scans, P_G=1.0, **good)
    with pytest.raises(ValueError, match="confirmation"):
        track_scans(scans, confirmation=(4, 3), **good)
    with pytest.raises(ValueError, match="deletion"):
        track_scans(scans, deletion=("score", 0.1, 0.1), **good)
    with pytest.raises(ValueError, match="clutter_density"):
        track_scans(scans, method="jpda", **{**good, "clutter_density": None})
    with pytest.raises(ValueError, match="clutter_density"):
        track_scans(scans, **{**good, "clutter_density": -1.0})
    with pytest.raises(ValueError, match="v_max"):
        track_scans(scans, v_max=0.0, **good)
    with pytest.raises(ValueError, match="max_events"):
        track_scans(scans, max_events=0, **good)
    with pytest.raises(ValueError, match=r"initial_tracks\[0\].*shape \(3,\)"):
        track_scans(scans, initial_tracks=[(0.0, np.zeros(3), np.eye(4))], **good)
    with pytest.raises(ValueError, match=r"scans\[0\].*scan.z.*shape \(1, 3\)"):
        track_scans([Scan(0.0, np.zeros(1), np.zeros((1, 3)))], **good)
    with pytest.raises(ValueError, match=r"scans\[0\].*scan.times.*shape \(2,\)"):
        track_scans([Scan(0.0, np.zeros(2), np.zeros((1, 2)))], **good)
    with pytest.raises(ValueError, match=r"scans\[1\].*time order"):
        track_scans([Scan(5.0, np.full(1, 5.0), np.ones((1, 2))), Scan(4.0, np.full(1, 4.0), np.ones((1, 2)))], **good)
    with pytest.raises(TypeError, match=r"scans\[0\].*time, times"):
        track_scans([np.zeros((1, 2))], **good)
    with pytest.raises(TypeError, match="scans"):
        track_scans(3, **good)
    (tmp_path / "x.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="header"):
        Tracks.from_csv(tmp_path / "x.csv")


def test_phd_method_delegates_to_kftrack_phd(cluttered):
    try:
        from kftrack import phd
    except ImportError:
        with pytest.raises(NotImplementedError, match="kftrack.phd"):
            track_scans([], method="phd", sensor=RADAR, motion=CV, P_D=0.9, clutter_density=1e-6)
        return
    scans, _, lam = cluttered
    tr = track_scans(scans[:8], method="phd", sensor=RADAR, motion=CV, P_D=0.9, clutter_density=lam)
    steps = phd.phd_filter(scans[:8], RADAR, CV, P_D=0.9, clutter_density=lam)
    assert len(tr.steps) == 8 and tr.seconds.shape == (8,) and (tr.seconds > 0).all()  # each step timed
    for k in range(7):
        ids, x = tr.snapshot(steps[k].time)
        np.testing.assert_array_equal(x, steps[k].states)
        assert len(ids) == len(steps[k].states)
    with pytest.raises(TypeError, match="unexpected keyword"):
        track_scans(scans, method="gnn", sensor=RADAR, motion=CV, P_D=0.9, birth_rate=0.1)


def test_plot_tracks_draws_confirmed_tracks_over_truth(cluttered):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from kftrack.plotting import plot_tracks
    scans, truths, lam = cluttered
    tr = track_scans(scans, sensor=RADAR, motion=CV, P_D=0.9, clutter_density=lam)
    paths = np.stack(truths, axis=1)  # (targets, scans, 2)
    fig, ax = plt.subplots()
    plot_tracks(ax, tr, truth=list(paths))
    n_conf = sum(bool(t.confirmed.any()) for t in tr)
    assert len(ax.lines) == len(paths) + n_conf
    line = ax.lines[len(paths)]
    first = next(t for t in tr if t.confirmed.any())
    np.testing.assert_allclose(line.get_xdata(), 1e-3 * first.x[first.confirmed, 0])
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# IMM modes per track
# --------------------------------------------------------------------------------------------
def _imm_cv_ct(Pi=((0.95, 0.05), (0.05, 0.95))):
    from kftrack.imm import IMM, EKFMode
    from kftrack.models import CoordinatedTurn
    ekf = dict(h=RADAR.h, H_jac=RADAR.jacobian, angle_components=(1,))
    return IMM([EKFMode(CV, RADAR.R, **ekf), EKFMode(CoordinatedTurn(ndim=2, q=1.0, q_omega=1e-4), RADAR.R, **ekf)],
               transition=np.array(Pi), mu0=[0.8, 0.2], components=[(0, 1, 2, 3), (0, 1, 2, 3, 4)])


@pytest.mark.parametrize("method", ["gnn", "jpda"])
def test_imm_single_target_equals_imm_filter(method):
    from kftrack.imm import imm_filter
    scans, x0 = single_target_scans()
    est = _imm_cv_ct()
    x0 = np.append(x0, 0.0)
    P0 = np.diag([100.0**2, 20.0**2, 100.0**2, 20.0**2, 0.02**2])
    # no clutter: P_G = 1 - 1e-9 keeps every detection in the gate; JPDA's clutter density 1e-30
    # makes beta_0 < 1e-30 / N (N ~ 1e-4 per m rad here): the PDAF is the Kalman update to 1e-20
    tr = track_scans(scans, method=method, sensor=RADAR, motion=est, P_D=1.0, clutter_density=1e-30,
                     P_G=1 - 1e-9, initiate=False, initial_tracks=[(0.0, x0, P0)])
    times = np.concatenate([[0.0], [s.times[0] for s in scans]])
    zs = np.concatenate([np.full((1, 2), np.nan), [s.z[0] for s in scans]])
    ref = imm_filter(est, zs, x0, P0, times=times)
    t = tr.tracks[0]
    assert len(tr) == 1 and np.array_equal(t.times, times)  # the start at t = 0, then each detection
    np.testing.assert_allclose(tr.mu[t.id][0], [0.8, 0.2], rtol=1e-15)  # the start: mu0
    # the same kernels per mode; only batch shapes (an array dt, per-track rows) may change the
    # summation order: round-off of a few eps per operation over 30 contracting steps (1e-10, as
    # the EKF test above)
    np.testing.assert_allclose(t.x[1:], ref.x[1:, :4], rtol=1e-10, atol=1e-10 * np.abs(ref.x).max())
    np.testing.assert_allclose(t.P[1:], ref.P[1:, :4, :4], rtol=1e-10, atol=1e-10 * np.abs(ref.P).max())
    np.testing.assert_allclose(tr.mu[t.id][1:], ref.mu[1:], rtol=1e-9, atol=1e-12)
    assert ref.mu[1:, 1].max() > 0.2 > 0.1 > ref.mu[1:, 1].min()  # the modes' weights move: the mixing matters


@pytest.mark.parametrize("method", ["gnn", "jpda"])
@pytest.mark.parametrize("kind", ["kalman", "ekf"])
def test_imm_with_one_mode_equals_plain_tracker(cluttered, method, kind):
    from kftrack.imm import IMM, EKFMode, KalmanMode
    scans, _, lam = cluttered
    mode = KalmanMode(CV, RADAR.R) if kind == "kalman" else EKFMode(CV, RADAR.R, h=RADAR.h, H_jac=RADAR.jacobian,
                                                                     angle_components=(1,))
    kw = dict(method=method, sensor=RADAR, P_D=0.9, clutter_density=lam)
    plain = track_scans(scans, motion=CV, **kw)
    imm = track_scans(scans, motion=IMM([mode], transition=np.eye(1), mu0=[1.0]), **kw)
    assert [t.id for t in imm] == [t.id for t in plain] and imm.ends == plain.ends and len(plain) > 12
    for a, b in zip(imm, plain):
        assert np.array_equal(a.times, b.times) and np.array_equal(a.confirmed, b.confirmed)
        # one mode: mixing and combination with weight 1 are exact; the GNN cost -2 log L - m log 2 pi
        # equals d^2 + log|S| to round-off (1e-12 relative), so the same decisions and round-off only
        np.testing.assert_allclose(a.x, b.x, rtol=1e-9, atol=1e-9 * np.abs(b.x).max())
        np.testing.assert_allclose(a.P, b.P, rtol=1e-9, atol=1e-9 * np.abs(b.P).max())
        assert np.array_equal(imm.mu[a.id], np.ones((len(a.times), 1)))


@pytest.mark.parametrize("method", ["gnn", "jpda"])
def test_imm_tracks_every_target_and_mode_probabilities(cluttered, method):
    scans, truths, lam = cluttered
    trk = MultiTargetTracker(method=method, sensor=RADAR, motion=_imm_cv_ct(), P_D=0.9, clutter_density=lam)
    for s in scans:
        trk.step(s)
    ids, mu = trk.mode_probabilities
    np.testing.assert_allclose(mu.sum(1), 1.0, rtol=1e-12)
    tr = trk.tracks()
    ids, x = tr.snapshot(scans[-1].time)
    D = np.linalg.norm(truths[-1][:, None] - x[None, :, [0, 2]], axis=-1)
    assert (D.min(1) < 1000.0).all() and len(ids) == len(truths[-1])  # every straight-line target held, no false track
    # straight lines: the CV mode dominates the confirmed tracks at the end
    assert np.median([tr.mu[i][-1, 0] for i in ids]) > 0.5
    with pytest.raises(ValueError, match="mode_probabilities"):
        MultiTargetTracker(sensor=RADAR, motion=CV, P_D=0.9).mode_probabilities


@pytest.mark.parametrize("max_events", [10, 10_000])
def test_imm_with_one_mode_equals_plain_jpda_on_a_cluster(max_events):
    # the IMM cluster path (marginals from the combined predictions, each mode in PDA form with
    # them): with one mode it is the plain cluster JPDA, exact (10 000) or cheap (10: 73 events)
    from kftrack.imm import IMM, KalmanMode
    sensor = PositionSensor(15.0)
    x0 = np.array([[0.0, 0.0, 0.0, 0.0], [10.0, 0.0, 0.0, 0.0], [0.0, 0.0, 10.0, 0.0]])
    P0 = np.diag([30.0**2, 1.0, 30.0**2, 1.0])
    Z = np.array([[0.0, 0.0], [5.0, 5.0], [10.0, 0.0], [0.0, 10.0]])
    kw = dict(method="jpda", sensor=sensor, P_D=0.9, clutter_density=1e-4, initiate=False,
              initial_tracks=[(0.0, x, P0) for x in x0], max_events=max_events)
    plain = MultiTargetTracker(motion=CV, **kw)
    imm = MultiTargetTracker(motion=IMM([KalmanMode(CV, sensor.R)], transition=np.eye(1), mu0=[1.0]), **kw)
    a, b = plain.step(Scan(1.0, np.ones(4), Z)), imm.step(Scan(1.0, np.ones(4), Z))
    assert plain.fallbacks == imm.fallbacks == (1 if max_events == 10 else 0)
    # the same marginals and PDA combination; weight-1 mixing and combination are exact: round-off
    np.testing.assert_allclose([s.x for s in b], [s.x for s in a], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose([s.P for s in b], [s.P for s in a], rtol=1e-12, atol=1e-9)


def test_imm_bad_input():
    from kftrack.imm import IMM, KalmanMode
    good = dict(sensor=RADAR, P_D=0.9, clutter_density=1e-6)
    one_d = IMM([KalmanMode(ConstantVelocity(ndim=1, q=1.0), np.eye(1))], transition=np.eye(1), mu0=[1.0])
    with pytest.raises(ValueError, match=r"motion.*N >= 4.*N = 2"):
        MultiTargetTracker(motion=one_d, **good)
    with pytest.raises(ValueError, match="turn_rate_std"):
        MultiTargetTracker(motion=_imm_cv_ct(), turn_rate_std=0.0, **good)
    with pytest.raises(ValueError, match=r"initial_tracks\[0\].*x \(5,\).*shape \(3,\)"):
        MultiTargetTracker(motion=_imm_cv_ct(), initial_tracks=[(0.0, np.zeros(3), np.eye(3))], **good)
