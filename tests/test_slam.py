"""Tests of kftrack.slam: every SymPy Jacobian against 4th-order central differences; the
landmark observation against its closed form and its inverse; the SLAM prediction, update and
state augmentation against the dense textbook equations (symmetric PSD, cross-covariances);
Mahalanobis gating of injected outliers; EKF-SLAM with known associations inside its 3-sigma
bounds on a seeded run (and a broken initialisation failing the same test); ICP localization
(seed 003's Algorithm 2 done right); bad input."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from kftrack import ekf, slam
from kftrack import scenarios as sc
from kftrack.sensors import lidar
from test_radar import central_jacobian  # 4th-order central differences


RNG = np.random.default_rng(0)
POSES = np.column_stack([RNG.uniform(-5, 5, (20, 2)), RNG.uniform(-3, 3, 20)])
LMS = POSES[:, :2] + np.column_stack([RNG.uniform(1, 4, 20) * np.cos(a := RNG.uniform(-3, 3, 20)),
                                      RNG.uniform(1, 4, 20) * np.sin(a)])
U = np.column_stack([RNG.uniform(0, 2, 20), RNG.uniform(-0.5, 0.5, 20)])
TOL = dict(rtol=1e-7, atol=1e-8)


def test_motion_jacobians_against_finite_differences():
    m = slam.Unicycle(0.1, 0.05)
    dt = 0.7
    raw = lambda p, u: slam._generated()["f"](*slam._split(p), *slam._split(u), dt)[..., 0]  # noqa: E731
    assert np.allclose(m.jacobian(POSES, U, dt), central_jacobian(lambda p: raw(p, U), POSES, 1e-3), **TOL)
    assert np.allclose(m.input_jacobian(POSES, U, dt), central_jacobian(lambda u: raw(POSES, u), U, 1e-3), **TOL)
    # the closed forms of Thrun et al. (2005)
    th, v = POSES[:, 2], U[:, 0]
    G = m.jacobian(POSES, U, dt)
    assert np.allclose(G[:, 0, 2], -v * dt * np.sin(th)) and np.allclose(G[:, 1, 2], v * dt * np.cos(th))
    V = m.input_jacobian(POSES, U, dt)
    assert np.allclose(m.Q(POSES, U, dt), V @ np.diag([0.01, 0.0025]) @ np.swapaxes(V, -1, -2))


def test_observation_closed_form_and_jacobians():
    z = slam.observe(POSES, LMS)
    d = LMS - POSES[:, :2]
    assert np.allclose(z[:, 0], np.hypot(d[:, 0], d[:, 1]), rtol=1e-14)
    assert np.allclose(z[:, 1], ekf.wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - POSES[:, 2]), atol=1e-14)
    raw = lambda p, m: slam._generated()["h"](*slam._split(p), *slam._split(m))[..., 0]  # noqa: E731  unwrapped
    Hr, Hm = slam.observation_jacobians(POSES, LMS)
    assert np.allclose(Hr, central_jacobian(lambda p: raw(p, LMS), POSES, 1e-4), **TOL)
    assert np.allclose(Hm, central_jacobian(lambda m: raw(POSES, m), LMS, 1e-4), **TOL)
    # the textbook form: robot part [[-dx/r, -dy/r, 0], [dy/q, -dx/q, -1]]
    q = np.sum(d * d, -1)
    assert np.allclose(Hr[:, 1], np.column_stack([d[:, 1] / q, -d[:, 0] / q, -np.ones(20)]))
    assert np.allclose(Hm, -Hr[:, :, :2])


def test_inverse_observation_round_trip_and_jacobians():
    z = slam.observe(POSES, LMS)
    assert np.allclose(slam.inverse_observation(POSES, z), LMS, atol=1e-12)
    Gr, Gz = slam.inverse_jacobians(POSES, z)
    assert np.allclose(Gr, central_jacobian(lambda p: slam.inverse_observation(p, z), POSES, 1e-4), **TOL)
    assert np.allclose(Gz, central_jacobian(lambda zz: slam.inverse_observation(POSES, zz), z, 1e-4), **TOL)
    # chain rule: h(g(x, z)) = z, so Hm Gz = I and Hr + Hm Gr = 0
    Hr, Hm = slam.observation_jacobians(POSES, LMS)
    assert np.allclose(Hm @ Gz, np.eye(2), atol=1e-12) and np.allclose(Hr + Hm @ Gr, 0, atol=1e-12)


def _state(rng, N):
    """A random SLAM state with N landmarks near the robot and a random SPD covariance."""
    x = np.concatenate([[0.5, -0.3, 0.4], (rng.uniform(-4, 4, (N, 2)) + [5, 0]).ravel()])
    A = rng.normal(size=(3 + 2 * N, 3 + 2 * N)) * 0.1
    return x, A @ A.T + 0.01 * np.eye(3 + 2 * N)


def test_add_landmark_grows_state_and_covariance_consistently():
    rng = np.random.default_rng(4)
    x, P = _state(rng, 3)
    R = np.diag([0.1**2, np.deg2rad(2) ** 2])
    z = np.array([3.0, 0.6])
    xa, Pa = slam.add_landmark(x, P, z, R)
    assert xa.shape == (11,) and Pa.shape == (11, 11)
    assert np.array_equal(xa[:9], x) and np.array_equal(Pa[:9, :9], P)
    assert np.allclose(xa[9:], slam.inverse_observation(x[:3], z))
    assert np.allclose(Pa, Pa.T, atol=0) and np.linalg.eigvalsh(Pa).min() > -1e-12
    # the joint linearization: [x; m] = J [x; z] with J = [[I, 0], [Gr 0 ..., Gz]]
    Gr, Gz = slam.inverse_jacobians(x[:3], z)
    J = np.zeros((11, 11))
    J[:9, :9] = np.eye(9)
    J[9:, :3], J[9:, 9:] = Gr, Gz
    joint = np.zeros((11, 11))
    joint[:9, :9], joint[9:, 9:] = P, R
    assert np.allclose(Pa, J @ joint @ J.T, atol=1e-14)
    # cross-covariance with an earlier landmark is Gr P_r,l (non-zero: the map is correlated)
    assert np.allclose(Pa[9:, 3:5], Gr @ P[:3, 3:5]) and np.abs(Pa[9:, 3:5]).max() > 1e-3


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 4), st.floats(0.2, 20.0), st.floats(-np.pi, np.pi))
def test_add_landmark_keeps_covariance_symmetric_psd(seed, N, r, phi):
    # for any prior and any first sighting: the grown covariance is symmetric positive
    # semi-definite (it is J joint J^T), the old block is untouched, and the new block is at least
    # the measurement part Gz R Gz^T (the robot's uncertainty can only add to it)
    rng = np.random.default_rng(seed)
    x, P = _state(rng, N)
    R = np.diag([0.1**2, np.deg2rad(2) ** 2])
    xa, Pa = slam.add_landmark(x, P, [r, phi], R)
    n = 3 + 2 * N
    assert xa.shape == (n + 2,) and Pa.shape == (n + 2, n + 2)
    scale = np.abs(Pa).max()
    assert np.abs(Pa - Pa.T).max() <= 1e-15 * scale and np.array_equal(Pa[:n, :n], P)  # symmetric to round-off
    assert np.linalg.eigvalsh(Pa).min() > -1e-12 * scale
    _, Gz = slam.inverse_jacobians(x[:3], [r, phi])
    assert np.linalg.eigvalsh(Pa[n:, n:] - Gz @ R @ Gz.T).min() > -1e-12 * scale


def test_ekf_slam_state_grows_with_each_new_landmark():
    # along a seeded loop: after step k the state holds exactly the landmarks seen so far, in the
    # order of their first sighting; every covariance is symmetric positive definite, and each new
    # landmark is correlated with the robot and with the landmarks mapped before it
    lm, s, res = _loop(15)
    seen: list[int] = []
    for k, (ids, _) in enumerate(s.observations):
        new = [int(i) for i in ids if i not in seen]
        seen += new
        x, P = res.x[k], res.P[k]
        assert res.ids[:len(seen)] == seen and x.shape == (3 + 2 * len(seen),) and P.shape == (x.size, x.size)
        assert np.abs(P - P.T).max() <= 1e-15 * np.abs(P).max() and np.linalg.eigvalsh(P).min() > 0
        assert np.array_equal(res.pose[k], x[:3]) and np.array_equal(res.pose_P[k], P[:3, :3])
        for lid in new:
            b = slam.landmark_block(seen.index(lid))
            assert np.abs(P[b, :3]).max() > 0 and (b.start == 3 or np.abs(P[b, 3:b.start]).max() > 0)
    assert sorted(seen) == list(range(len(lm)))


def test_predict_and_update_equal_the_dense_equations():
    rng = np.random.default_rng(5)
    x, P = _state(rng, 4)
    m = slam.Unicycle(0.05, 0.03)
    u, dt = np.array([0.8, 0.2]), 0.5
    xp, Pp = slam.slam_predict(x, P, u, dt, m)
    F = np.eye(11)
    F[:3, :3] = m.jacobian(x[:3], u, dt)
    Q = np.zeros((11, 11))
    Q[:3, :3] = m.Q(x[:3], u, dt)
    assert np.allclose(Pp, F @ P @ F.T + Q, atol=1e-14) and np.array_equal(xp[3:], x[3:])
    # update with landmark 2 = the generic EKF update with the full measurement function
    R = np.diag([0.1**2, np.deg2rad(2) ** 2])
    z = slam.observe(xp[:3], xp[7:9]) + [0.05, -0.02]
    got = slam.slam_update(xp, Pp, z, 2, R)

    def h(s):
        return slam.observe(s[..., :3], s[..., 7:9])

    def H(s):
        Hr, Hm = slam.observation_jacobians(s[..., :3], s[..., 7:9])
        out = np.zeros(Hr.shape[:-1] + (11,))
        out[..., :3], out[..., 7:9] = Hr, Hm
        return out

    want = ekf.ekf_update(xp, Pp, z, h, H, R, angle_components=(1,))
    assert np.allclose(got.x, want.x, atol=1e-14) and np.allclose(got.P, want.P, atol=1e-14)
    assert np.allclose(got.P, got.P.T, atol=0) and np.linalg.eigvalsh(got.P).min() > 0


def test_gating_rejects_injected_outliers():
    rng = np.random.default_rng(6)
    lms = np.array([[3.0, 0.0], [0.0, 3.0], [-3.0, 0.5]])
    x = np.concatenate([[0.0, 0.0, 0.0], lms.ravel()])
    P = np.diag([0.01, 0.01, 0.001] + [0.02] * 6)
    R = np.diag([0.1**2, np.deg2rad(2) ** 2])
    true = slam.observe(np.zeros((3, 3)), lms) + rng.normal(size=(3, 2)) * [0.1, np.deg2rad(2)]
    outlier = np.array([[8.0, 2.0]])              # far from every landmark: a new landmark
    near = slam.observe(np.zeros(3), lms[0] + [0.0, 0.8])[None]  # 0.8 m off landmark 0: ambiguous
    zs = np.vstack([true[[2, 0, 1]], outlier, near])
    out = slam.associate(x, P, zs, R, gate=0.99, new=0.9999)
    assert list(out) == [2, 0, 1, slam.NEW, slam.REJECTED]
    d2 = [np.min([y @ np.linalg.solve(S, y) for y, S in zip(*slam.landmark_innovation(x, P, z, R))])
          for z in zs[3:]]
    assert min(d2) > stats.chi2.ppf(0.99, 2)     # both injected measurements are outside every gate
    assert d2[1] < stats.chi2.ppf(0.9999, 2) < d2[0]  # the second one too close to landmark 0 to be new
    # with new=None every ungated measurement starts a landmark
    assert list(slam.associate(x, P, zs, R, new=None))[3:] == [slam.NEW, slam.NEW]


def _excursions(res, s):
    e = res.pose - s.truth
    e[:, 2] = ekf.wrap_angle(e[:, 2])
    sd = np.sqrt(np.diagonal(res.pose_P, axis1=-2, axis2=-1))
    return int(np.sum(np.abs(e[1:]) > 3 * sd[1:])), e[1:].size


MODEL = slam.Unicycle(0.05, np.deg2rad(3.0))
R_LM = np.diag([0.1**2, np.deg2rad(2.0) ** 2])


def _loop(seed: int, known: bool = True):
    """One seeded loop around 12 ring landmarks, filtered from the exactly known start pose."""
    rng = np.random.default_rng(seed)
    lm = sc.ring_landmarks(rng)
    s = sc.slam_loop(rng, lm, loops=1.0)
    return lm, s, slam.ekf_slam(s.truth[0], 1e-12 * np.eye(3), s.odometry, 0.25, s.observations, R_LM, MODEL,
                                known=known)


def test_ekf_slam_known_associations_inside_3_sigma_bounds():
    # one loop (152 steps, 3 components = 453 checks). A consistent filter leaves the 3-sigma
    # band with probability 0.0027 per check: E[count] = 1.2. The errors are correlated in
    # time, so the binomial law does not hold, but Markov's inequality does:
    # P(count >= 25) <= 1.2 / 25 < 0.05 for any correlation. Bound: at most 24 excursions.
    lm, s, res = _loop(15)
    count, checks = _excursions(res, s)
    assert checks == 453
    assert count <= 0.0027 * checks / 0.05
    # every landmark mapped, the state grew to 3 + 2 L, heading wrapped, P symmetric PSD
    assert sorted(res.ids) == list(range(len(lm))) and res.x[-1].shape == (3 + 2 * len(lm),)
    assert np.all(np.abs(res.pose[:, 2]) <= np.pi)
    Pend = res.P[-1]
    assert np.array_equal(Pend, Pend.T) and np.linalg.eigvalsh(Pend).min() > 0
    # the same test fails a filter that initialises landmarks without the robot's uncertainty
    # (P_mm = Gz R Gz^T, no cross-covariances): the map is then overconfident
    orig = slam._add

    def broken(x, P, z, R):
        xa, Pa = orig(x, P, z, R)
        n = x.shape[-1]
        Gr, Gz = slam.inverse_jacobians(x[..., :3], z)
        Pa[..., n:, :n] = Pa[..., :n, n:] = 0.0
        Pa[..., n:, n:] = Gz @ R @ np.swapaxes(Gz, -1, -2)
        return xa, Pa

    slam._add = broken
    try:
        bad = slam.ekf_slam(s.truth[0], 1e-12 * np.eye(3), s.odometry, 0.25, s.observations, R_LM, MODEL)
    finally:
        slam._add = orig
    assert _excursions(bad, s)[0] > 0.0027 * checks / 0.05


def test_batched_slam_equals_single_runs():
    rng = np.random.default_rng(8)
    lm = sc.ring_landmarks(rng, count=8)
    s = sc.slam_loop(rng, lm, loops=0.3, runs=3)
    model = slam.Unicycle(0.05, np.deg2rad(3.0))
    R = np.diag([0.1**2, np.deg2rad(2.0) ** 2])
    x0 = np.broadcast_to(s.truth[0], (3, 3))
    batch = slam.ekf_slam(x0, 1e-6 * np.eye(3), s.odometry, 0.25, s.observations, R, model)
    one = slam.ekf_slam(s.truth[0], 1e-6 * np.eye(3), s.odometry[:, 1], 0.25,
                        [(ids, z[:, 1]) for ids, z in s.observations], R, model)
    assert np.allclose(batch.pose[:, 1], one.pose, atol=1e-12) and np.allclose(batch.x[-1][1], one.x[-1], atol=1e-12)


def test_data_association_run_matches_known_associations():
    # nearest neighbour with a 99 % gate on a seeded loop: every accepted association is the true
    # landmark, no landmark is duplicated, and the rejected true measurements are about the
    # 1 % outside the gate (bound: the 99.9 % binomial quantile)
    lm, s, nn = _loop(9, known=False)
    assert nn.x[-1].shape == (3 + 2 * len(lm),)
    slot_to_id, rejected, total = [], 0, 0
    for (ids, _), dec in zip(s.observations, nn.ids):
        for lid, d in zip(ids, dec):
            if d >= 0:
                assert slot_to_id[d] == lid
        slot_to_id += [int(lid) for lid, d in zip(ids, dec) if d == slam.NEW]
        rejected += int(np.sum(dec == slam.REJECTED))
        total += len(ids)
    assert sorted(slot_to_id) == list(range(len(lm)))
    assert rejected <= stats.binom.ppf(0.999, total, 0.01)


def test_icp_localization_beats_dead_reckoning():
    rng = np.random.default_rng(10)
    walls = sc.floor_plan()
    truth, u = sc.apartment_loop()
    sensor = lidar.Lidar(2.0, 0.05, 10.0)
    scans = sensor.scan(walls, truth, rng)
    model = slam.Unicycle(0.05, np.deg2rad(5.0))
    odo = u + rng.standard_normal(u.shape) * [0.05, np.deg2rad(5.0)]
    R = np.diag([0.01**2, 0.01**2, np.deg2rad(0.3) ** 2])
    res = slam.icp_localization(scans, sensor.angles, lidar.sample_walls(walls, 0.02), odo, 0.5, truth[0],
                                np.diag([0.01, 0.01, 0.001]), model, R)
    dead = sc.drive([(0.5, *uk) for uk in odo[:-1]], 0.5, truth[0])[0]
    err = np.linalg.norm(res.x[:, :2] - truth[:, :2], axis=1)
    assert err.max() < 0.05 < np.linalg.norm(dead[:, :2] - truth[:, :2], axis=1).max()


@pytest.mark.parametrize("call,name", [
    (lambda: slam.Unicycle(-0.1, 0.1), "sigma_v"),
    (lambda: slam.observe([0, 0], [1, 1]), "pose"),
    (lambda: slam.observe([0, 0, 0], [1, 1, 1]), "landmark"),
    (lambda: slam.slam_update(np.zeros(5), np.eye(5), [1.0, 0.0], 3, np.eye(2)), "j"),
    (lambda: slam.slam_update(np.zeros(4), np.eye(4), [1.0, 0.0], 0, np.eye(2)), "x"),
    (lambda: slam.landmark_block(-1), "j must be a landmark index"),
    (lambda: slam.add_landmark(np.zeros(3), np.eye(3), [1.0, 0.0, 0.0], np.eye(2)), "z"),
    (lambda: slam.associate(np.zeros(5), np.eye(5), np.ones((2, 2)), np.eye(2), gate=1.5), "gate"),
    (lambda: slam.ekf_slam(np.zeros(3), np.eye(3), np.zeros((4, 2)), 0.1, [], np.eye(2), slam.Unicycle(1, 1)),
     "observations"),
    (lambda: slam.ekf_slam(np.zeros(3), np.eye(3), np.zeros((2, 2)), 0.1, [([0, 1], np.ones((1, 2)))] * 2, np.eye(2),
                           slam.Unicycle(1, 1)), r"observations\[0\] must be \(ids \(M,\), z"),  # 2 ids, 1 measurement
    (lambda: slam.ekf_slam(np.zeros(3), np.eye(3), np.zeros((2, 2)), 0.1, [([0], [[1.0, np.nan]])] * 2, np.eye(2),
                           slam.Unicycle(1, 1)), r"observations\[0\] z must be finite"),
    (lambda: slam.pose_nees(slam.ekf_slam(np.zeros(3), np.eye(3), np.zeros((2, 2)), 0.1, [([], np.zeros((0, 2)))] * 2,
                                          np.eye(2), slam.Unicycle(1, 1)), np.zeros((3, 3))), r"truth must have shape \(2,"),
    (lambda: sc.slam_loop(np.random.default_rng(0), np.ones((3, 3))), "landmarks"),
    (lambda: sc.slam_loop(np.random.default_rng(0), np.ones((3, 2)), sigma_bearing=-0.1), "sigma_bearing"),
    (lambda: sc.slam_loop(np.random.default_rng(0), np.ones((3, 2)), max_range=0.0), "max_range"),
    (lambda: slam.slam_predict(np.zeros(3), np.eye(3), [1.0, 0.0], np.nan, MODEL), "dt"),
    (lambda: slam.ekf_slam(np.zeros(3), np.eye(3), np.zeros((2, 2)), -0.25, [([], np.zeros((0, 2)))] * 2, np.eye(2),
                           MODEL), "dt"),
    (lambda: slam.icp_localization(np.ones((2, 4)), np.ones(4), np.ones((10, 2)), np.zeros((2, 2)), 0.0, np.zeros(3),
                                   np.eye(3), MODEL, np.eye(3)), "dt"),
    (lambda: slam.landmark_sd(slam.ekf_slam(np.zeros(3), np.eye(3), np.zeros((2, 2)), 0.1, [([1], [[1.0, 0.0]])] * 2,
                                            np.eye(2), MODEL), 1), "count"),
])
def test_bad_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()


@pytest.mark.parametrize("call,name", [
    (lambda: slam.slam_predict(np.zeros(3), np.eye(3), [1.0, 0.0], 0.1, "unicycle"), "model"),
    (lambda: slam.ekf_slam(np.zeros(3), np.eye(3), np.zeros((2, 2)), 0.1, [([], np.zeros((0, 2)))] * 2, np.eye(2),
                           None), "model"),
    (lambda: sc.slam_loop(42, np.ones((3, 2))), "rng"),
    (lambda: sc.ring_landmarks(42), "rng"),
])
def test_wrong_types_name_the_argument(call, name):
    with pytest.raises(TypeError, match=name):
        call()


def test_worlds_close_their_loops():
    poses, u = sc.apartment_loop()
    assert np.allclose(poses[-1], poses[0], atol=1e-9) and u.shape == poses.shape[:1] + (2,)
    s = sc.slam_loop(np.random.default_rng(0), sc.ring_landmarks(np.random.default_rng(0)), loops=1.0)
    assert np.allclose(s.truth[-1, :2], s.truth[0, :2], atol=0.1)  # a whole number of 0.25 m steps
    assert all(np.all(z[:, 0] > 0) and len(ids) == len(z) for ids, z in s.observations)
