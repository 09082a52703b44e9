"""kftrack.sensors.surveillance: each detection time is where the clockwise beam meets the target
(exactly), the clutter count is Poisson and uniform over the coverage annulus, the detection
fraction is P_D, the plot noise has the stated covariance, the coverage is respected; bad
arguments name themselves. Statistical bounds are derived in comments (fixed seeds)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from kftrack import adsb
from kftrack.ekf import wrap_angle
from kftrack.sensors.radar import RangeBearing
from kftrack.sensors.surveillance import Scan, SurveillanceRadar, compass_azimuth, truth_at_scan

PERIOD = 4.8


def _still(points, duration=2000.0):
    """A window of aircraft standing still at ``points`` (k, 2), reported every 10 s (= MAX_GAP_S)."""
    points = np.asarray(points, float)
    t = np.arange(0.0, duration + 10.0, 10.0)
    k = len(points)
    aircraft = np.repeat(np.arange(k), t.size)
    return adsb.TrafficWindow([f"a{i}" for i in range(k)], [""] * k, aircraft, np.tile(t, k),
                              np.repeat(points, t.size, axis=0), np.zeros((k * t.size, 2)),
                              t1=duration, start_unix=0.0, site=adsb.RADAR_SITE, skipped={})


def test_scans_shape_times_and_exact_beam_geometry():
    w = adsb.load_traffic()
    radar = SurveillanceRadar(period=PERIOD, clutter_rate=5.0)
    scans = radar.scans(w, np.random.default_rng(1), t_start=100.0, t_end=400.0)
    assert len(scans) == math.ceil(300.0 / PERIOD) == 63
    assert all(isinstance(s, Scan) for s in scans)
    for j, s in enumerate(scans):
        assert s.time == 100.0 + j * PERIOD
        m = s.times.shape[0]
        assert s.z.shape == (m, 2) and s.origin.shape == (m,) and s.origin.dtype.kind == "i"
        assert np.all(np.diff(s.times) >= 0) and np.all(s.times >= s.time) and np.all(s.times < s.time + PERIOD)
        assert np.all(np.abs(s.z[:, 1]) <= np.pi)
        # aircraft: the beam, clockwise from north at s.time, points at the TRUE position at the
        # detection time. The fixed point contracts by v / (r 2 pi / T) < 250 / (6000 * 1.309) = 0.032
        # (nearest aircraft 6 km), so 10 iterations leave < 0.032^10 * 4.8 s; 1e-6 s is the tolerance
        a = s.origin >= 0
        present, xy, _ = w.states_at(s.origin[a], s.times[a])
        assert present.all()
        np.testing.assert_allclose(s.times[a], s.time + PERIOD * compass_azimuth(xy) / (2 * np.pi), rtol=0, atol=1e-6)
        # clutter: placed noise-free at its bearing, so its time follows from the bearing (round-off)
        c = ~a
        az = np.mod(np.pi / 2 - s.z[c, 1], 2 * np.pi)
        np.testing.assert_allclose(s.times[c], s.time + PERIOD * az / (2 * np.pi), rtol=0, atol=1e-9)
        # coverage: every aircraft plot comes from an aircraft in the annulus at its detection time
        r = np.hypot(*xy.T)
        assert np.all((r >= radar.min_range) & (r <= radar.max_range))
        assert np.all((s.z[c, 0] >= radar.min_range) & (s.z[c, 0] <= radar.max_range))
        # each aircraft at most once per scan
        assert len(set(s.origin[a].tolist())) == int(a.sum())
    # tens of aircraft per scan (25 on average in coverage, times P_D = 0.9)
    n_det = np.mean([np.count_nonzero(s.origin >= 0) for s in scans])
    assert 15 < n_det < 35
    ids, xy = radar.truth_at_scan(w, scans[3])
    assert np.all(radar.in_coverage(xy)) and set(ids.tolist()) <= set(range(len(w.ids)))
    ids2, _ = truth_at_scan(w, scans[3], radar)
    np.testing.assert_array_equal(ids, ids2)
    assert truth_at_scan(w, scans[3])[0].size >= ids.size


def test_default_scans_span_the_window_and_are_reproducible():
    w = adsb.load_traffic()
    radar = SurveillanceRadar()
    a = radar.scans(w, np.random.default_rng(7))
    b = radar.scans(w, np.random.default_rng(7))
    assert len(a) == 249 and a[0].time == 0.0 and a[-1].time + PERIOD <= w.t1
    for s, t in zip(a, b):
        np.testing.assert_array_equal(s.z, t.z)
        np.testing.assert_array_equal(s.origin, t.origin)


def test_clutter_count_is_poisson_and_uniform_over_the_annulus():
    lam, n = 8.0, 3000
    radar = SurveillanceRadar(period=1.0, clutter_rate=lam, min_range=5e3, max_range=50e3)
    scans = radar.scans(_still(np.zeros((0, 2)), duration=n + 1.0), np.random.default_rng(11), t_start=0.0,
                        t_end=float(n))
    counts = np.array([s.z.shape[0] for s in scans])
    assert counts.size == n and np.all(np.concatenate([s.origin for s in scans]) == -1)
    # mean: N(lam, lam/n) for a Poisson count; |mean - lam| < 5 sd has probability 6e-7 of failing
    assert abs(counts.mean() - lam) < 5 * math.sqrt(lam / n)
    # dispersion: sum (c - cbar)^2 / cbar ~ chi2(n - 1) for Poisson counts; outside [ppf(1e-6), isf(1e-6)]
    # fails with probability 2e-6, while a Binomial or overdispersed count would shift it by ~n
    disp = np.sum((counts - counts.mean()) ** 2) / counts.mean()
    assert stats.chi2.ppf(1e-6, n - 1) < disp < stats.chi2.isf(1e-6, n - 1)
    # P(count = 0) = exp(-lam): the number of empty scans is Binomial(n, e^-8 = 3.4e-4), mean 1.0;
    # and the histogram up to 16 against the Poisson pmf by a chi-square test (cells with
    # expected count >= 5 pooled), p > 1e-6
    edges = np.arange(2, 16)
    obs = np.array([np.sum(counts <= 2)] + [np.sum(counts == k) for k in edges[1:]] + [np.sum(counts >= 16)])
    p = np.array([stats.poisson.cdf(2, lam)] + [stats.poisson.pmf(k, lam) for k in edges[1:]]
                 + [stats.poisson.sf(15, lam)])
    assert np.all(n * p >= 5) and abs(p.sum() - 1) < 1e-12
    chi = np.sum((obs - n * p) ** 2 / (n * p))
    assert chi < stats.chi2.isf(1e-6, len(p) - 1)
    # uniform over the annulus: r^2 uniform on [rmin^2, rmax^2] and compass azimuth uniform on
    # [0, 2 pi), so the fraction in the inner half of the area and in the east half are each
    # Binomial(N, 1/2); |fraction - 1/2| < 5 sd = 2.5 / sqrt(N) fails with probability 6e-7 each
    z = np.concatenate([s.z for s in scans])
    big_n = z.shape[0]
    inner = np.mean(z[:, 0] ** 2 < 0.5 * (5e3**2 + 50e3**2))
    east = np.mean(np.cos(z[:, 1]) > 0)
    assert abs(inner - 0.5) < 2.5 / math.sqrt(big_n) and abs(east - 0.5) < 2.5 / math.sqrt(big_n)
    assert z[:, 0].min() >= 5e3 and z[:, 0].max() <= 50e3
    # the density form gives the same rate
    dens = SurveillanceRadar(clutter_density=1e-9, min_range=5e3, max_range=50e3)
    assert dens.clutter_rate == pytest.approx(1e-9 * math.pi * (50e3**2 - 5e3**2), rel=1e-14)
    assert radar.clutter_density == pytest.approx(lam / (math.pi * (50e3**2 - 5e3**2)), rel=1e-14)


def _ring(k=40, r=30e3):
    """k still aircraft on a circle of radius r, avoiding north (no crossing of the beam's start)."""
    az = np.linspace(0.2, 2 * np.pi - 0.2, k)
    return np.column_stack([r * np.sin(az), r * np.cos(az)])


def test_detection_fraction_is_P_D():
    pts = _ring()
    radar = SurveillanceRadar(period=PERIOD, P_D=0.7, clutter_rate=0.0)
    scans = radar.scans(_still(pts), np.random.default_rng(5), t_start=0.0, t_end=1500.0)
    detected = sum(s.origin.size for s in scans)
    trials = len(scans) * len(pts)
    # detections ~ Binomial(trials, 0.7); 5 sd: failure probability 6e-7
    assert abs(detected / trials - 0.7) < 5 * math.sqrt(0.7 * 0.3 / trials)
    # P_D = 1: every aircraft in every scan, each once
    full = SurveillanceRadar(period=PERIOD, P_D=1.0, clutter_rate=0.0).scans(_still(pts), np.random.default_rng(0),
                                                                           t_start=0.0, t_end=100.0)
    assert all(sorted(s.origin.tolist()) == list(range(len(pts))) for s in full)


def test_plot_noise_has_the_stated_covariance():
    pts = _ring(k=30, r=40e3)
    sig = (60.0, math.radians(0.2))
    radar = SurveillanceRadar(period=PERIOD, sigmas=sig, P_D=1.0, clutter_rate=0.0)
    scans = radar.scans(_still(pts), np.random.default_rng(9), t_start=0.0, t_end=1000.0)
    o = np.concatenate([s.origin for s in scans])
    z = np.concatenate([s.z for s in scans])
    truth = np.column_stack([np.hypot(*pts[o].T), np.arctan2(pts[o, 1], pts[o, 0])])
    e = np.column_stack([z[:, 0] - truth[:, 0], wrap_angle(z[:, 1] - truth[:, 1])]) / np.array(sig)
    n = e.shape[0]
    # standardised errors are iid N(0, 1): their sum of squares ~ chi2(2n); the mean of each
    # component N(0, 1/n), |mean| < 5/sqrt(n); the sample correlation ~ N(0, 1/n), |rho| < 5/sqrt(n)
    ss = np.sum(e**2)
    assert stats.chi2.ppf(1e-6, 2 * n) < ss < stats.chi2.isf(1e-6, 2 * n)
    for c in range(2):
        assert stats.chi2.ppf(1e-6, n) < np.sum(e[:, c] ** 2) < stats.chi2.isf(1e-6, n)
    assert np.all(np.abs(e.mean(axis=0)) < 5 / math.sqrt(n))
    assert abs(np.mean(e[:, 0] * e[:, 1])) < 5 / math.sqrt(n)
    assert isinstance(radar.measurement_model, RangeBearing) and radar.measurement_model.sigmas == sig
    np.testing.assert_array_equal(radar.measurement_model.R, np.diag(np.square(sig)))


def test_coverage_is_respected():
    pts = np.array([[0.0, -1e3], [3e3, 0.0], [-20e3, -20e3], [0.0, -99e3], [-101e3, 0.0], [150e3, 1e3]])
    radar = SurveillanceRadar(period=PERIOD, P_D=1.0, clutter_rate=0.0, min_range=2e3, max_range=100e3)
    scans = radar.scans(_still(pts), np.random.default_rng(2), t_start=0.0, t_end=200.0)
    assert all(sorted(s.origin.tolist()) == [1, 2, 3] for s in scans)
    ids, xy = radar.truth_at_scan(_still(pts), scans[0])
    assert ids.tolist() == [1, 2, 3]


def test_shifted_traffic_scans():
    big = adsb.load_traffic().shifted(150, seed=2)
    scans = SurveillanceRadar().scans(big, np.random.default_rng(3), t_start=600.0, t_end=650.0)
    assert len(scans) == 11 and max(s.origin.max() for s in scans) >= 61
    assert np.mean([np.count_nonzero(s.origin >= 0) for s in scans]) > 40


@pytest.mark.parametrize("kwargs, name", [
    ({"period": 0.0}, "period"), ({"period": float("nan")}, "period"), ({"P_D": 0.0}, "P_D"),
    ({"P_D": 1.5}, "P_D"), ({"sigmas": (50.0,)}, "sigmas"), ({"sigmas": (50.0, 10.0)}, "sigmas"),
    ({"clutter_rate": -1.0}, "clutter_rate"), ({"clutter_density": -1e-9}, "clutter_density"),
    ({"clutter_rate": 1.0, "clutter_density": 1e-9}, "clutter_rate or clutter_density"),
    ({"max_range": -5.0}, "max_range"), ({"min_range": 200e3}, "min_range"), ({"min_range": -1.0}, "min_range"),
])
def test_bad_arguments_name_themselves(kwargs, name):
    with pytest.raises(ValueError, match=name):
        SurveillanceRadar(**kwargs)


def test_bad_scan_arguments():
    w = adsb.load_traffic()
    radar = SurveillanceRadar()
    with pytest.raises(TypeError, match="rng"):
        radar.scans(w, 0)
    with pytest.raises(TypeError, match="window"):
        radar.scans(np.zeros(3), np.random.default_rng(0))
    with pytest.raises(ValueError, match="t_end"):
        radar.scans(w, np.random.default_rng(0), t_start=10.0, t_end=5.0)
    with pytest.raises(ValueError, match="t_start"):
        radar.scans(w, np.random.default_rng(0), t_start=float("inf"))
