"""Tests of kftrack.sensors.lidar: ray casting against hand-computed distances, the beam count
of seed 003's Algorithm 1 (360/θ, no duplicated 0°/360° beam), no-returns, the range noise
(chi-square), scan-to-points in the sensor and world frames, bad input."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from kftrack import scenarios as sc
from kftrack.sensors import lidar

SQUARE = np.array([[[0, 0], [10, 0]], [[10, 0], [10, 10]], [[10, 10], [0, 10]], [[0, 10], [0, 0]]], float)


def test_ray_cast_hand_computed_square():
    # from (2, 3): east 8, north 7, west 2, south 3; at 45 deg the beam hits the north wall
    # (y = 10) at x = 9 before the east wall (x = 10 would need y = 11): range 7*sqrt(2)
    a = np.deg2rad([0, 90, 180, 270, 45, 135])
    r = lidar.ray_cast(SQUARE, [2, 3], a)
    want = [8, 7, 2, 3, 7 * np.sqrt(2), 2 * np.sqrt(2)]
    assert np.allclose(r, want, rtol=0, atol=1e-12)


def test_ray_cast_nearest_wall_and_segment_ends():
    walls = np.array([[[5, -2], [5, 2]], [[3, -1], [3, 1]], [[1, 2], [1, 4]]], float)
    r = lidar.ray_cast(walls, [0, 0], [0.0, np.pi / 2, np.arctan2(1, 3), np.arctan2(1.0001, 3)])
    assert r[0] == pytest.approx(3.0, abs=1e-12)            # the nearer of two parallel walls
    assert np.isinf(r[1])                                     # passes beside x = 1 wall (x = 0)
    assert r[2] == pytest.approx(np.hypot(3, 1), abs=1e-12)  # hits the end point (3, 1) exactly
    assert r[3] == pytest.approx(np.hypot(5, 5 / 3 * 1.0001), rel=1e-9)  # just misses it, hits the far wall


def test_ray_cast_broadcasts_over_origins_and_max_range():
    origins = np.array([[2.0, 3.0], [5.0, 5.0]])
    r = lidar.ray_cast(SQUARE, origins, [0.0, np.pi])
    assert r.shape == (2, 2)
    assert np.allclose(r, [[8, 2], [5, 5]])
    r = lidar.ray_cast(SQUARE, [2, 3], [0.0, np.pi], max_range=5.0)
    assert np.isinf(r[0]) and r[1] == pytest.approx(2.0)


@pytest.mark.parametrize("theta,count", [(1.0, 360), (0.5, 720), (2.0, 180), (90.0, 4)])
def test_beam_count_is_360_over_theta_without_duplicate(theta, count):
    a = lidar.beam_angles(theta)
    assert a.shape == (count,)
    assert a[0] == 0.0 and a[-1] == pytest.approx(np.deg2rad(360 - theta))
    assert np.allclose(np.diff(a), np.deg2rad(theta))


def test_scan_noise_is_gaussian_with_stated_sigma():
    sensor = lidar.Lidar(resolution_deg=1.0, sigma_range=0.05, max_range=20.0)
    rng = np.random.default_rng(3)
    pose = np.array([4.0, 4.0, 0.3])
    clean = sensor.ranges(SQUARE, pose)
    noisy = np.stack([sensor.scan(SQUARE, pose, rng) for _ in range(20)])
    ss = np.sum(((noisy - clean) / 0.05) ** 2)
    dof = noisy.size
    assert stats.chi2.ppf(0.0005, dof) < ss < stats.chi2.ppf(0.9995, dof)


def test_scan_to_points_sensor_and_world_frames():
    sensor = lidar.Lidar(resolution_deg=90.0, sigma_range=0.0, max_range=20.0)
    pose = np.array([2.0, 3.0, np.pi / 2])  # facing north: beams N, W, S, E in the world
    r = sensor.ranges(SQUARE, pose)
    assert np.allclose(r, [7, 2, 3, 8])
    body = lidar.scan_to_points(r, sensor.angles)
    assert np.allclose(body, [[7, 0], [0, 2], [-3, 0], [0, -8]], atol=1e-12)
    world = lidar.scan_to_points(r, sensor.angles, pose)
    assert np.allclose(world, [[2, 10], [0, 3], [2, 0], [10, 3]], atol=1e-12)
    # no-returns are dropped
    assert lidar.scan_to_points(np.array([1.0, np.inf, np.nan, 2.0]), np.zeros(4)).shape == (2, 2)


def test_every_world_point_lies_on_a_wall_of_the_floor_plan():
    walls = sc.floor_plan()
    sensor = lidar.Lidar(1.0, 0.0, 15.0)
    pose = np.array([2.0, 1.5, 0.4])
    pts = lidar.scan_to_points(sensor.ranges(walls, pose), sensor.angles, pose)
    assert len(pts) == 360  # a closed room: every beam returns
    p0, e = walls[:, 0], walls[:, 1] - walls[:, 0]
    s = np.clip(np.einsum("kwi,wi->kw", pts[:, None] - p0, e) / np.sum(e * e, -1), 0, 1)
    d = np.linalg.norm(pts[:, None] - (p0 + s[..., None] * e), axis=-1).min(1)
    assert d.max() < 1e-9


def test_sample_walls_spacing():
    pts = lidar.sample_walls(SQUARE, 0.5)
    assert len(pts) == 4 * 21
    assert np.allclose(pts[:21, 0], np.linspace(0, 10, 21)) and np.allclose(pts[:21, 1], 0)


@pytest.mark.parametrize("call,name", [
    (lambda: lidar.beam_angles(0.7), "resolution_deg"),
    (lambda: lidar.beam_angles(-1.0), "resolution_deg"),
    (lambda: lidar.Lidar(1.0, -0.1), "sigma_range"),
    (lambda: lidar.Lidar(1.0, 0.1, 0.0), "max_range"),
    (lambda: lidar.ray_cast(np.zeros((3, 2)), [0, 0], [0.0]), "walls"),
    (lambda: lidar.ray_cast(SQUARE, [0, 0, 0], [0.0]), "origin"),
    (lambda: lidar.ray_cast(np.array([[[1, 1], [1, 1]]], float), [0, 0], [0.0]), "walls"),
    (lambda: lidar.Lidar().ranges(SQUARE, [1.0, 2.0]), "pose"),
    (lambda: lidar.scan_to_points(np.ones(3), np.ones(4)), "ranges"),
    (lambda: lidar.sample_walls(SQUARE, 0.0), "spacing"),
])
def test_bad_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()


def test_scan_needs_a_generator():
    with pytest.raises(TypeError, match="rng"):
        lidar.Lidar().scan(SQUARE, [1.0, 1.0, 0.0], 42)
