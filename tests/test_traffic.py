"""kftrack.adsb.load_traffic: the bundled window of many aircraft loads with exact counts, every
row is kept or counted, positions are the ENU of the fixes, interpolation is exact at the reports
and linear between them, gaps are respected, shifted() makes N trajectories; bad input names itself."""
from __future__ import annotations

import gzip

import numpy as np
import pytest

from kftrack import adsb, datasets

HEADER = ",".join(adsb.TRAFFIC_COLUMNS)


def _rows():
    text = gzip.decompress(datasets.data_path(adsb.TRAFFIC_FILE).read_bytes()).decode()
    lines = [line for line in text.splitlines() if line and not line.startswith("#")]
    assert lines[0] == HEADER
    return [line.split(",") for line in lines[1:]]


def test_bundled_window_counts():
    w = adsb.load_traffic()
    rows = _rows()
    assert len(rows) == 34871 and len({r[0] for r in rows}) == 63
    # every row is kept or skipped under a reason
    assert w.t.size + sum(w.skipped.values()) == len(rows)
    assert w.skipped == {"position held from the previous report": 2542, "missing ground speed or track": 293}
    assert len(w.ids) == 61 and len(w.callsigns) == 61 and not w.synthetic
    assert (w.t0, w.t1, w.start_unix, w.site) == (0.0, 1200.0, 1633615201.0, adsb.RADAR_SITE)
    assert w.t.min() >= 0 and w.t.max() < 1200 and np.all(np.isfinite(w.xy)) and np.all(np.isfinite(w.v))
    # tens of aircraft at once all through the window
    counts = [len(w.truth_at(t)[0]) for t in np.arange(0.0, 1200.0, 30.0)]
    assert min(counts) >= 20 and max(counts) <= 40
    assert adsb.load_traffic() is w  # cached, read-only
    with pytest.raises(ValueError):
        w.xy[0, 0] = 1.0


def test_positions_are_the_enu_of_the_fixes_and_kept_rows_are_not_held():
    w = adsb.load_traffic()
    rows = _rows()
    kept = {}
    last = {}
    for r in rows:   # the loader's rule, restated: skip a missing speed/track, then a held position
        if r[6] == "nan" or r[7] == "nan":
            continue
        if last.get(r[0]) == (r[3], r[4]):
            continue
        last[r[0]] = (r[3], r[4])
        kept.setdefault(r[0], []).append(r)
    for i in (0, 17, 40):
        mine = kept[w.ids[i]]
        lat = np.array([float(r[3]) for r in mine])
        lon = np.array([float(r[4]) for r in mine])
        enu, _ = adsb.to_enu(lat, lon, origin=adsb.RADAR_SITE)
        sel = w.aircraft == i
        np.testing.assert_array_equal(w.t[sel], np.array([float(r[2]) for r in mine]) - w.start_unix)
        np.testing.assert_array_equal(w.xy[sel], enu[:, :2])


def test_interpolation_exact_at_reports_and_linear_between():
    w = adsb.load_traffic()
    k = np.arange(0, w.t.size, 97)
    present, xy, v = w.states_at(w.aircraft[k], w.t[k])
    assert present.all()
    np.testing.assert_array_equal(xy, w.xy[k])          # weight 0: exact, not just close
    np.testing.assert_array_equal(v, w.v[k])
    ids, xy_t, _ = w.truth_at(float(w.t[k[5]]))
    j = int(np.flatnonzero(ids == w.aircraft[k[5]])[0])
    np.testing.assert_array_equal(xy_t[j], w.xy[k[5]])
    # half-way between two consecutive 1 s reports of one aircraft: the mean (to round-off)
    nxt = k[(k + 1 < w.t.size)]
    nxt = nxt[(w.aircraft[nxt + 1] == w.aircraft[nxt]) & (np.diff(w.t)[nxt] <= adsb.MAX_GAP_S)]
    present, xy, _ = w.states_at(w.aircraft[nxt], 0.5 * (w.t[nxt] + w.t[nxt + 1]))
    assert present.all()
    # |xy| < 2e5 m: the mean in floating point differs by a few ulp, 2e5 * 4 * 2.2e-16 < 1e-9 m
    np.testing.assert_allclose(xy, 0.5 * (w.xy[nxt] + w.xy[nxt + 1]), rtol=0, atol=1e-9)


def test_velocity_agrees_with_the_motion_of_the_fixes():
    # central difference over 20 s (reports k-10 .. k+10, all 1 s apart) against the recorded ground
    # velocity at k. Its error: position rounding 2 * 0.56 m / 20 s = 0.06 m/s; the chord of a 3 deg/s
    # turn at 250 m/s, v (w 10 s)^2 / 6 = 250 * 0.52^2 / 6 = 11.4 m/s; a position's age (0..1 s) at either
    # end changes the difference by up to 250 m/s * 1 s / 20 s = 12.5 m/s; a velocity up to 1 s old in
    # that turn is off by 250 * 0.052 = 13 m/s. So the median (mostly straight flight) must be below
    # 2 m/s and every one below 11.4 + 12.5 + 13 + 0.1 < 40 m/s; a swapped axis or a wrong sign would
    # give errors of the order of the speed (100-250 m/s).
    w = adsb.load_traffic()
    k = np.arange(10, w.t.size - 10)
    ok = (w.aircraft[k - 10] == w.aircraft[k + 10]) & (w.t[k + 10] - w.t[k - 10] == 20.0)
    k = k[ok]
    fd = (w.xy[k + 10] - w.xy[k - 10]) / 20.0
    err = np.linalg.norm(fd - w.v[k], axis=1)
    assert k.size > 10000
    assert np.median(err) < 2.0 and err.max() < 40.0


def _write(path, lines):
    with gzip.open(path, "wt") as fh:
        fh.write("\n".join(lines) + "\n")


def test_user_file_skips_counts_and_gaps(tmp_path):
    path = tmp_path / "mine.csv.gz"
    _write(path, ["# window unix [1000, 1100) s", HEADER,
                  "aaa,AB1,1000,48.9,2.5,3000,100,90,0",
                  "aaa,AB1,1001,48.9,2.5,3000,100,90,0",          # held position
                  "aaa,AB1,1001,48.9,2.5014,3000,100,90,0",
                  "aaa,AB1,1001,48.9,2.5028,3000,100,90,0",       # same time again: skipped
                  "aaa,AB1,1002,48.9,2.5028,3000,nan,90,0",       # missing ground speed
                  "aaa,AB1,1030,48.9,2.6,3000,100,90,0",          # after a 29 s gap
                  "aaa,AB1,1031,48.9,2.6014,3000,100,90,0",
                  "bbb,,1050,48.8,2.4,3000,200,0,0",
                  "bbb,,1055,48.81,2.4,3000,200,0,0",             # 5 s later: interpolated
                  "bbb,,1200,48.82,2.4,3000,200,0,0",             # outside the window
                  ",XX,1060,48.8,2.4,3000,200,0,0",               # no icao24
                  "ccc,,1060,95.0,2.4,3000,200,0,0",              # latitude out of range
                  "ccc,,1061,48.8,2.4"])                          # too few fields
    w = adsb.load_traffic(path)
    assert w.skipped == {"position held from the previous report": 1,
                         "time not after the aircraft's previous report": 1, "missing ground speed or track": 1,
                         "time outside the window": 1, "missing icao24": 1, "latitude outside [-90, 90]": 1,
                         "wrong number of fields (expected 9)": 1}
    assert w.ids == ["aaa", "bbb"] and w.callsigns == ["AB1", ""] and (w.t0, w.t1, w.start_unix) == (0, 100, 1000)
    assert w.t.size == 6
    ids, xy, v = w.truth_at(15.0)        # aaa in its 29 s gap: absent; bbb not yet
    assert ids.size == 0
    ids, xy, v = w.truth_at(52.5)        # bbb half-way between its reports 5 s apart
    assert ids.tolist() == [1]
    np.testing.assert_allclose(xy[0], 0.5 * (w.xy[w.aircraft == 1][0] + w.xy[w.aircraft == 1][1]), atol=1e-9)
    # 200 m/s due north at 48.8 N 2.4 E, 0.07 deg west of the site: the meridians converge toward the
    # pole, so local north there leans east in the site's frame by about 0.07 * sin(48.85 deg) =
    # 0.053 deg: east 200 * 9.2e-4 = +0.18 m/s, north 200 * cos(0.053 deg) = 199.99991 m/s
    assert abs(v[0, 1] - 200.0) < 1e-3 and 0.15 < v[0, 0] < 0.22
    assert w.truth_at(0.5)[0].tolist() == [0]   # aaa between 0 and 1 s (same-time duplicate skipped)


def test_shifted_makes_n_trajectories():
    w = adsb.load_traffic()
    small = w.shifted(10, seed=3)
    assert len(small.ids) == 10 and not small.synthetic and set(small.ids) <= set(w.ids)
    i = small.ids[4]
    np.testing.assert_array_equal(small.xy[small.aircraft == 4], w.xy[w.aircraft == w.ids.index(i)])
    for n in (62, 200):
        big = w.shifted(n, seed=1)
        assert len(big.ids) == n and big.synthetic and len(set(big.ids)) == n
        assert big.ids[:61] == w.ids
    big = w.shifted(200, seed=1)
    again = w.shifted(200, seed=np.random.default_rng(1))
    np.testing.assert_array_equal(big.xy, again.xy)
    # a copy is its original rotated about the site and shifted in time: same ranges, speeds, time steps
    c = big.ids.index(w.ids[0] + "+1")
    orig, copy = w.aircraft == 0, big.aircraft == c
    np.testing.assert_allclose(np.hypot(*big.xy[copy].T), np.hypot(*w.xy[orig].T), rtol=1e-12)
    np.testing.assert_allclose(np.hypot(*big.v[copy].T), np.hypot(*w.v[orig].T), rtol=1e-12)
    np.testing.assert_allclose(np.diff(big.t[copy]), np.diff(w.t[orig]), atol=1e-9)
    # every copy's recorded span overlaps the window by at least 60 s
    for a in range(61, 200):
        ts = big.t[big.aircraft == a]
        assert ts.max() >= 60.0 and ts.min() <= 1200.0 - 60.0 and min(ts.max(), 1200.0) - max(ts.min(), 0.0) >= 60.0
    # more aircraft at once than recorded
    assert np.mean([len(big.truth_at(t)[0]) for t in (300.0, 600.0, 900.0)]) > 60


def test_bad_input_names_the_argument(tmp_path):
    with pytest.raises(TypeError, match="path"):
        adsb.load_traffic(123)
    with pytest.raises(FileNotFoundError, match="path"):
        adsb.load_traffic(tmp_path / "none.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,lat_deg,lon_deg\n1,2,3\n")
    with pytest.raises(ValueError, match="header"):
        adsb.load_traffic(bad)
    notgz = tmp_path / "notgz.csv.gz"
    notgz.write_bytes(b"icao24,callsign\n")
    with pytest.raises(ValueError, match="gzip"):
        adsb.load_traffic(notgz)
    cut = tmp_path / "cut.csv.gz"
    cut.write_bytes(datasets.data_path(adsb.TRAFFIC_FILE).read_bytes()[:20000])
    with pytest.raises(ValueError, match="truncated or corrupt"):
        adsb.load_traffic(cut)
    w = adsb.load_traffic()
    with pytest.raises(ValueError, match="t"):
        w.truth_at(float("nan"))
    for n in (0, 2.5, True):
        with pytest.raises(ValueError, match="n_aircraft"):
            w.shifted(n)
    common = dict(t1=10.0, start_unix=0.0, site=adsb.RADAR_SITE, skipped={})
    with pytest.raises(ValueError, match="aircraft must index ids"):
        adsb.TrafficWindow(["a"], [""], [0, 1], [0.0, 1.0], np.zeros((2, 2)), np.zeros((2, 2)), **common)
    with pytest.raises(ValueError, match=r"xy and v shape \(K, 2\)"):
        adsb.TrafficWindow(["a"], [""], [0, 0], [0.0, 1.0], np.zeros((2, 3)), np.zeros((2, 2)), **common)
    with pytest.raises(ValueError, match="finite"):
        adsb.TrafficWindow(["a"], [""], [0], [np.nan], np.zeros((1, 2)), np.zeros((1, 2)), **common)
