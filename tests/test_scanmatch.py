"""Tests of kftrack.scanmatch: pose algebra, the Kabsch step (exact, reflection guarded), ICP
recovering a known rigid transform to round-off without noise and within its stated
standard deviations with noise (Monte Carlo, chi-square), outlier rejection, bad input."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from kftrack import scanmatch as sm
from kftrack import scenarios as sc
from kftrack.sensors import lidar

angles = st.floats(-np.pi, np.pi)
coords = st.floats(-50, 50)


@settings(max_examples=50, deadline=None)
@given(coords, coords, angles, coords, coords, angles)
def test_compose_inverse_between(x1, y1, t1, x2, y2, t2):
    a, b = np.array([x1, y1, t1]), np.array([x2, y2, t2])
    assert np.allclose(sm.compose(a, sm.inverse(a)), 0, atol=1e-9)
    assert np.allclose(sm.compose(a, sm.between(a, b))[:2], b[:2], atol=1e-9)
    # composing poses = composing the point maps
    p = np.array([[1.0, 2.0], [-3.0, 0.5]])
    assert np.allclose(sm.transform_points(sm.compose(a, b), p), sm.transform_points(a, sm.transform_points(b, p)),
                       atol=1e-9)


def test_kabsch_exact_to_round_off():
    rng = np.random.default_rng(0)
    p = rng.uniform(-5, 5, (30, 2))
    R, t = sm.rotation(0.7), np.array([1.5, -2.0])
    Rh, th = sm.kabsch(p, p @ R.T + t)
    assert np.allclose(Rh, R, atol=1e-14) and np.allclose(th, t, atol=1e-13)


def test_kabsch_guards_against_reflection():
    # a mirrored set: the bare V U^T is the reflection diag(1, -1); the guarded step must
    # return a proper rotation
    rng = np.random.default_rng(1)
    p = rng.uniform(-5, 5, (20, 2))
    q = p * [1.0, -1.0]
    U, _, Vt = np.linalg.svd((p - p.mean(0)).T @ (q - q.mean(0)))
    assert np.linalg.det(Vt.T @ U.T) < 0  # the unguarded answer would be a reflection
    R, _ = sm.kabsch(p, q)
    assert np.linalg.det(R) == pytest.approx(1.0) and np.allclose(R.T @ R, np.eye(2))
    # and it is the best rotation, not just any: in 2-D the least-squares angle has the closed
    # form atan2(sum p x q, sum p . q) over the centred pairs
    pc, qc = p - p.mean(0), q - q.mean(0)
    best = np.arctan2(np.sum(pc[:, 0] * qc[:, 1] - pc[:, 1] * qc[:, 0]), np.sum(pc * qc))
    assert np.allclose(R, sm.rotation(best), atol=1e-12)


def test_icp_recovers_known_transform_without_noise():
    # scan of the floor plan in the sensor frame, matched to the same points in the world:
    # one-to-one pairs once aligned, so ICP converges to the exact pose (round-off: coordinates
    # of ~10 m carry errors of a few eps * 10 m = 1e-15 m per operation; 1e-12 allows ~100 of them)
    walls = sc.floor_plan()
    sensor = lidar.Lidar(1.0, 0.0, 15.0)
    pose = np.array([3.0, 2.0, 0.4])
    body = lidar.scan_to_points(sensor.ranges(walls, pose), sensor.angles)
    world = sm.transform_points(pose, body)
    res = sm.icp(body, world, initial=pose + [0.15, -0.1, np.deg2rad(3)], tol=0.0, max_iterations=100)
    assert np.allclose(res.pose, pose, rtol=0, atol=1e-12)
    assert res.rmse < 1e-12


def test_icp_with_noise_within_stated_bounds():
    # known pairs (rigid copy plus N(0, s^2) noise): the Gauss-Newton covariance is exact for
    # this linear-in-translation problem, so the NEES of the 3-vector (x, y, heading) over 200
    # seeded trials must lie in the chi-square(3*200)/200 interval (99.9 %)
    rng = np.random.default_rng(2)
    s, N = 0.05, 200
    p = rng.uniform(-4, 4, (150, 2))
    pose = np.array([0.3, -0.2, 0.25])
    C = sm.pose_covariance(p, s, pose)
    nees = []
    for _ in range(N):
        q = sm.transform_points(pose, p) + s * rng.standard_normal(p.shape)
        est = sm.icp(p, q, initial=pose).pose
        e = est - pose
        nees.append(e @ np.linalg.solve(C, e))
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], 3 * N) / N
    assert lo < np.mean(nees) < hi
    # and no single trial beyond the chi-square(3) quantile that all N stay below with
    # probability 0.999 (Bonferroni: P(any exceeds) <= N * 0.001 / N)
    assert np.max(nees) < stats.chi2.isf(0.001 / N, 3)


def test_icp_max_distance_rejects_outliers():
    rng = np.random.default_rng(3)
    p = rng.uniform(-4, 4, (100, 2))
    pose = np.array([0.2, 0.1, 0.1])
    q = sm.transform_points(pose, p)
    src = np.vstack([p, rng.uniform(20, 30, (10, 2))])  # 10 far outliers in the source
    bad = sm.icp(src, q, initial=pose + [0.05, 0.05, 0.02])
    good = sm.icp(src, q, initial=pose + [0.05, 0.05, 0.02], max_distance=0.5)
    assert np.allclose(good.pose, pose, atol=1e-9) and good.pairs == 100
    assert np.max(np.abs(bad.pose - pose)) > 1e-3


@pytest.mark.parametrize("call,name", [
    (lambda: sm.kabsch(np.zeros((3, 3)), np.zeros((3, 3))), "source"),
    (lambda: sm.kabsch(np.zeros((3, 2)), np.zeros((4, 2))), "target"),
    (lambda: sm.icp(np.zeros((2, 2)), np.zeros((5, 2))), "source"),
    (lambda: sm.icp(np.ones((5, 2)), np.ones((5, 2)), initial=[0, 0]), "initial"),
    (lambda: sm.icp(np.ones((5, 2)), np.ones((5, 2)), max_iterations=0), "max_iterations"),
    (lambda: sm.icp(np.ones((5, 2)), np.ones((5, 2)), max_distance=-1.0), "max_distance"),
    (lambda: sm.transform_points([0, 0], np.ones((3, 2))), "pose"),
    (lambda: sm.pose_covariance(np.ones((3, 2)), 0.0), "sigma"),
])
def test_bad_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()
