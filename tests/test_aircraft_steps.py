"""The named steps of the chapter-18 recipe's loop (``kftrack.aircraft._run``), each on its own:
restart (``_track_start``), hold (``_held_copy``), the resampler's frame (``_interpolated``) and the
IMM step's update (``_imm_update``). ``tests/test_aircraft.py`` checks the loop they make up."""
from __future__ import annotations

import math

import numpy as np

from kftrack import aircraft as A


def test_track_start_is_the_two_point_start():
    mu0 = np.full(4, 0.25)
    z0, z1, dt = np.array([0.0, 0.0]), np.array([100.0, 50.0]), 5.0
    mu, xs, Ps = A._track_start(z0, z1, dt, mu0, 200.0, 1.0, 6)
    x, P = A.two_point_init(z0, z1, dt, 300.0)          # a track's start: white r0 + 100 on both positions
    assert mu is mu0 and xs.shape == (4, 4) and Ps.shape == (4, 4, 4)
    assert np.array_equal(xs, np.tile(x, (4, 1))) and np.array_equal(Ps, np.tile(P, (4, 1, 1)))
    # a restart inside a track with no lag term: R = (r0 + r_q) I, the two-point start with r = r0 + r_q
    # (the same divisions: equal to round-off, 1e-15 relative)
    rq = (111_320.0 * 1e-6) ** 2 / 12.0
    _, xs2, Ps2 = A._track_start(z0, z1, dt, mu0, 200.0, 0.0, 6, delta=5.0)
    _, P2 = A.two_point_init(z0, z1, dt, 200.0 + rq)
    assert np.allclose(Ps2[0], P2, rtol=1e-15, atol=0) and np.array_equal(xs2, xs)
    # with the lag term the along-track variance grows by c Delta^2 |v|^2 / 12 (v = (20, 10) m/s)
    _, _, Ps3 = A._track_start(z0, z1, dt, mu0, 200.0, 1.0, 6, delta=5.0)
    v = np.array([20.0, 10.0])
    u = v / np.linalg.norm(v)
    along = u @ Ps3[0][np.ix_([0, 2], [0, 2])] @ u
    assert abs(along - (200.0 + rq + 25.0 * 500.0 / 12.0)) <= 1e-9 * along


def test_held_copy_is_nearer_held_than_flown():
    spike = (100.0, 0.0, 0.0, 52.0, 4.0)                 # E, N, t, lat, lon of the spike
    zf, v = np.array([0.0, 0.0]), np.array([10.0, 0.0])  # the filter's prediction, velocity 10 m/s east
    # 5 m from the spike after 2 s: less than half of the 20 m the aircraft would have flown
    assert A._held_copy(np.array([95.0, 0.0]), zf, spike, v, 2.0, 51.0, 3.0, False)
    # as far from the spike as from the prediction: not nearer the spike
    assert not A._held_copy(np.array([50.0, 0.0]), zf, spike, v, 2.0, 51.0, 3.0, False)
    # 10 m after 1 s (more than half of 10 m) is "flown", unless it repeats a coordinate of the spike
    # exactly, which counts only when no undo is pending
    assert not A._held_copy(np.array([90.0, 0.0]), zf, spike, v, 1.0, 51.0, 3.0, False)
    assert A._held_copy(np.array([90.0, 0.0]), zf, spike, v, 1.0, 52.0, 3.0, False)
    assert not A._held_copy(np.array([90.0, 0.0]), zf, spike, v, 1.0, 52.0, 3.0, True)


def test_interpolated_row_is_on_the_segment_at_its_time():
    tl = [0.0, 5.0, 15.0]
    la, lo = [52.0, 52.001, 52.003], [4.0, 4.002, 4.006]  # row 1 at a third of the segment, at a third of the time
    assert A._interpolated(la, lo, tl, 0, 1, 2) == 1
    la_off = [52.0, 52.001 + 1e-8, 52.003]               # 1e-8 deg off (1 mm): a recorded fix
    assert A._interpolated(la_off, lo, tl, 0, 1, 2) == 0
    assert A._interpolated(la, lo, [0.0, 7.5, 15.0], 0, 1, 2) == 0   # on the line, not at the time-proportional point


def test_imm_update_is_the_kalman_update_per_mode():
    rng = np.random.default_rng(18)
    r = 3
    L = rng.standard_normal((r, 4, 4))
    Pp = L @ L.transpose(0, 2, 1) + 4 * np.eye(4)
    xp = rng.standard_normal((r, 4))
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    R = np.array([[2.0, 0.3], [0.3, 1.5]])
    S = H @ Pp @ H.T + R
    z = np.array([0.4, -0.7])
    y = z - xp[:, [0, 2]]
    for infl in (1.0, 4.0):
        xs, Ps = A._imm_update(xp, Pp, S[:, 0, 0], S[:, 0, 1], S[:, 1, 1], np.linalg.det(S), y[:, 0], y[:, 1], infl)
        for j in range(r):
            K = Pp[j] @ H.T @ np.linalg.inv(infl * S[j])
            # 4x4 products of O(10) numbers: round-off ~1e-14; 1e-12 is a wide bound
            assert np.allclose(xs[j], xp[j] + K @ y[j], rtol=0, atol=1e-12)
            assert np.allclose(Ps[j], Pp[j] - K @ H @ Pp[j], rtol=0, atol=1e-12)
            assert np.array_equal(Ps[j], Ps[j].T)
