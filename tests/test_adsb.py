"""kftrack.adsb: the committed ADS-B files equal a fresh extraction from the traffic 2.13 wheel;
the loader skips and counts bad rows by reason; the ENU conversion round-trips and measures
distances right; bad arguments name themselves."""
from __future__ import annotations

import builtins
import gzip
import math
import re
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from kftrack import adsb, datasets

ROOT = Path(__file__).resolve().parents[1]
EXTRACT = ROOT / "data" / "adsb" / "extract.py"
WHEEL = "traffic-2.13-py3-none-any.whl"


@pytest.fixture(scope="session")
def traffic_wheel(tmp_path_factory) -> Path:
    """traffic 2.13 from PyPI (``pip download``), once per session; a failure fails the test."""
    folder = tmp_path_factory.mktemp("traffic-wheel")
    cmd = [sys.executable, "-m", "pip", "download", "traffic==2.13", "--no-deps", "--only-binary", ":all:",
           "--disable-pip-version-check", "-q", "-d", str(folder)]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    wheel = folder / WHEEL
    if res.returncode != 0 or not wheel.is_file():
        pytest.fail(f"cannot check data/adsb against its source: '{' '.join(cmd)}' failed "
                    f"(exit {res.returncode}); PyPI must be reachable.\n{res.stderr}", pytrace=False)
    return wheel


def _committed() -> list[str]:
    return sorted(p.relative_to(ROOT / "data" / "adsb").as_posix()
                  for p in (ROOT / "data" / "adsb").glob("*/*.csv.gz"))


def test_committed_files_equal_a_fresh_extraction(traffic_wheel, tmp_path):
    out = tmp_path / "adsb"
    # -B: no __pycache__ next to the script (data/ ships as package data)
    res = subprocess.run([sys.executable, "-B", str(EXTRACT), "--wheel", str(traffic_wheel), "--out", str(out)],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    fresh = sorted(p.relative_to(out).as_posix() for p in out.glob("*/*.csv.gz"))
    assert fresh == _committed()
    expected = {f"{n}.csv.gz" for n in adsb.CHAPTER_FLIGHTS + adsb.NOISY_FLIGHTS + adsb.UNSEEN_FLIGHTS}
    expected.add(adsb.TRAFFIC_FILE.removeprefix("adsb/"))  # the traffic window (issue 28)
    assert set(fresh) == expected and len(expected) == 39
    for rel in fresh:
        new, old = (out / rel).read_bytes(), (ROOT / "data" / "adsb" / rel).read_bytes()
        # the text must be identical; the compressed bytes are identical with the same zlib
        assert gzip.decompress(new) == gzip.decompress(old), rel
        # deterministic gzip header: magic, deflate, no flags (no file name), mtime 0
        assert old[:8] == b"\x1f\x8b\x08\x00\x00\x00\x00\x00", rel
    assert not (EXTRACT.parent / "__pycache__").exists()


def test_every_flight_loads_and_keeps_every_good_record():
    for name in adsb.CHAPTER_FLIGHTS + adsb.NOISY_FLIGHTS + adsb.UNSEEN_FLIGHTS:
        f = adsb.load_flight(name)
        text = gzip.decompress(datasets.data_path(f"adsb/{name}.csv.gz").read_bytes()).decode()
        n_rows = sum(1 for line in text.splitlines() if line and not line.startswith("#")) - 1
        assert len(f.t_s) + sum(f.skipped.values()) == n_rows, name
        assert all(len(getattr(f, c)) == len(f.t_s) for c in adsb.COLUMNS)
        assert np.all(np.isfinite(f.t_s)) and np.all(np.abs(f.lat_deg) <= 90) and np.all(np.abs(f.lon_deg) <= 180)
    # the one sample with missing positions (11 records without latitude/longitude)
    assert adsb.load_flight("noisy/noisy_spoofing").skipped == {"non-finite latitude or longitude": 11}


def _write(folder: Path, name: str, lines: list) -> None:
    path = folder / "adsb" / f"{name}.csv.gz"
    path.parent.mkdir(parents=True, exist_ok=True)
    raw = [line if isinstance(line, bytes) else line.encode() for line in lines]
    path.write_bytes(gzip.compress(b"\n".join(raw) + b"\n"))


def test_loader_skips_and_counts_bad_rows_by_reason(tmp_path, monkeypatch):
    monkeypatch.setenv("KFTRACK_DATA", str(tmp_path))
    good = "100.000,45.0,7.0,1000.0,100.0,90.0,0.0"
    _write(tmp_path, "calibration/toulouse", [
        "# a comment", ",".join(adsb.COLUMNS), good,
        "101.000,45.001,7.001",                           # truncated
        "102.000,45.002,ERR,1000.0,100.0,90.0,0.0",       # non-numeric
        "103.000,nan,7.003,1000.0,100.0,90.0,0.0",        # NaN latitude
        "104.000,95.0,7.004,1000.0,100.0,90.0,0.0",       # latitude out of range
        "105.000,45.005,181.0,1000.0,100.0,90.0,0.0",     # longitude out of range
        "nan,45.006,7.006,1000.0,100.0,90.0,0.0",         # no time
        "106.000,45.008,7.008,inf,100.0,90.0,0.0",        # infinite altitude (to_enu would refuse it)
        "107.000,45.009,7.009,1000.0,100.0,-inf,0.0",     # infinite track
        b"108.000,45.01\xff,7.01,1000.0,100.0,90.0,0.0",  # non-UTF-8 byte: non-numeric, no UnicodeError
        "1e400,45.011,7.011,1000.0,100.0,90.0,0.0",       # time overflows to inf
        good,                                             # exact duplicate, kept
        "99.000,45.007,7.007,nan,nan,nan,nan",            # time going back, NaN fields: kept
        "",                                               # blank line: ignored
    ])
    f = adsb.load_flight("calibration/toulouse")
    assert f.skipped == {"wrong number of fields (expected 7)": 1, "non-numeric field": 2,
                         "non-finite latitude or longitude": 1, "latitude outside [-90, 90]": 1,
                         "longitude outside [-180, 180]": 1, "non-finite time": 2,
                         "infinite altitude, speed, track or vertical rate": 2}
    np.testing.assert_array_equal(f.t_s, [100.0, 100.0, 99.0])
    np.testing.assert_array_equal(f.lat_deg, [45.0, 45.0, 45.007])
    assert np.isnan(f.alt_m[2]) and f.name == "calibration/toulouse"
    enu, _ = adsb.to_enu(f.lat_deg, f.lon_deg)       # every kept row is accepted downstream
    assert enu.shape == (3, 3) and np.all(np.isfinite(enu))


def test_loader_file_level_errors(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="name must be one of.*calibration/toulouse"):
        adsb.load_flight("calibration/atlantis")
    with pytest.raises(TypeError, match="name must be a flight name .* or a file path"):
        adsb.load_flight(3)
    monkeypatch.setenv("KFTRACK_DATA", str(tmp_path))
    _write(tmp_path, "calibration/munich", ["t,lat,lon", "1,2,3"])
    with pytest.raises(ValueError, match="header"):
        adsb.load_flight("calibration/munich")


def test_enu_round_trip():
    rng = np.random.default_rng(2014)
    worst = 0.0
    for lat0, lon0 in [(-89.5, -179.9), (-30.0, 20.0), (0.0, 0.0), (45.0, 7.0), (89.5, 120.0)]:
        enu = np.column_stack([rng.uniform(-3e5, 3e5, 500), rng.uniform(-3e5, 3e5, 500),
                               rng.uniform(-500.0, 15000.0, 500)])
        lat, lon, alt = adsb.from_enu(enu, (lat0, lon0, 100.0))
        back, origin = adsb.to_enu(lat, lon, alt, origin=(lat0, lon0, 100.0))
        assert origin == (lat0, lon0, 100.0)
        worst = max(worst, float(np.max(np.abs(back - enu))))
    # round-off bound: ECEF coordinates up to 6.4e6 m, some tens of operations each
    # (rotation, the closed-form inverse of You 2000): 50 * 6.4e6 m * eps = 7.1e-8 m.
    assert worst <= 50 * 6.4e6 * np.finfo(float).eps


def test_horizontal_inverse_lands_on_the_ellipsoid():
    # predictions in east-north mean points at height 0, like the fixes: the inverse returns the
    # point whose to_enu east-north are the given ones, where up = 0 (the tangent plane) is off by
    # about d^3 / 2R^2 (12 m at 100 km)
    rng = np.random.default_rng(18)
    origin = (52.3, 4.7, 0.0)
    en = np.column_stack([rng.uniform(-2e5, 2e5, 300), rng.uniform(-2e5, 2e5, 300)])
    en[5] = np.nan
    lat, lon = adsb.from_enu_horizontal(en, origin)
    back = adsb.to_enu(lat, lon, origin=origin)[0]
    assert np.isnan(lat[5]) and np.isnan(lon[5])
    ok = np.isfinite(en[:, 0])
    assert np.max(np.abs(back[ok, :2] - en[ok])) <= 1e-6                        # the stopping tolerance
    lat0, lon0, _ = adsb.from_enu(np.column_stack([en, np.zeros(len(en))]), origin)
    naive = adsb.to_enu(lat0, lon0, origin=origin)[0]
    d = np.hypot(en[ok, 0], en[ok, 1])
    far = d > 1e5
    # the tangent-plane shortcut really is off by metres far out (so the test above has power)
    assert np.all(np.hypot(*(naive[ok, :2] - en[ok]).T)[far] > 0.2 * d[far] ** 3 / (2 * 6.371e6 ** 2))
    with pytest.raises(ValueError, match="en"):
        adsb.from_enu_horizontal(np.zeros((3, 3)), origin)
    with pytest.raises(ValueError, match="tol_m"):
        adsb.from_enu_horizontal(en, origin, tol_m=0.0)
    with pytest.raises(ValueError, match="en must be finite"):
        adsb.from_enu_horizontal(np.array([[np.inf, 0.0]]), origin)


def test_enu_default_origin_and_nan_rows():
    lat = np.array([np.nan, 45.0, 45.001])
    lon = np.array([7.0, 7.0, 7.0])
    enu, origin = adsb.to_enu(lat, lon)
    assert origin == (45.0, 7.0, 0.0)       # the first finite fix, height 0 without alt_m
    assert np.all(np.isnan(enu[0])) and np.array_equal(enu[1], np.zeros(3))
    enu, origin = adsb.to_enu(lat, lon, alt_m=[100.0, np.nan, 300.0])
    assert origin == (45.001, 7.0, 300.0)


def test_enu_north_distance_equals_the_meridian_arc():
    # 1e-3 degree north of (45 N, 0 E) on the WGS 84 ellipsoid. The meridian arc is
    # s = M(phi_m) dphi with M = a (1 - e2) / (1 - e2 sin^2 phi)^(3/2) at the mid latitude
    # (midpoint rule: error ~ M'' dphi^3 / 24, below 1e-12 m). The tangent-plane north
    # coordinate is the chord's projection, shorter than the arc by about s^3 / (6 R^2) = 6e-9 m.
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    dphi = np.radians(1e-3)
    phi_m = np.radians(45.0) + dphi / 2
    s = a * (1 - e2) / (1 - e2 * np.sin(phi_m) ** 2) ** 1.5 * dphi
    enu, _ = adsb.to_enu([45.0, 45.001], [0.0, 0.0], [0.0, 0.0])
    assert abs(s - 111.13) < 0.01                      # the textbook 111.1 m
    assert abs(enu[1, 1] - s) < 1e-7                   # 6e-9 m chord effect + round-off, with margin
    assert abs(enu[1, 0]) < 1e-9                       # due north: no east component (round-off)
    assert -1.5e-3 < enu[1, 2] < -0.5e-3               # drops below the tangent plane by s^2 / (2 R) = 1e-3 m


@pytest.mark.parametrize("call, arg", [
    (lambda: adsb.to_enu([45.0], [7.0, 8.0]), "lon_deg"),
    (lambda: adsb.to_enu([[45.0]], [[7.0]]), "lat_deg"),
    (lambda: adsb.to_enu([95.0], [7.0]), "lat_deg"),
    (lambda: adsb.to_enu([45.0], [190.0]), "lon_deg"),
    (lambda: adsb.to_enu([45.0], [7.0], [1.0, 2.0]), "alt_m"),
    (lambda: adsb.to_enu([45.0], [7.0], origin=(45.0, 7.0)), "origin"),
    (lambda: adsb.to_enu([45.0], [7.0], origin=(91.0, 7.0, 0.0)), "origin"),
    (lambda: adsb.to_enu([np.nan], [7.0]), "origin"),
    (lambda: adsb.to_enu(None, [7.0]), "lat_deg"),
    (lambda: adsb.from_enu(np.zeros((2, 2)), (45.0, 7.0, 0.0)), "enu"),
    (lambda: adsb.from_enu(np.zeros((2, 3)), None), "origin"),
    (lambda: adsb.from_enu(np.zeros((2, 3)), (45.0, np.nan, 0.0)), "origin"),
])
def test_argument_errors_name_the_argument(call, arg):
    with pytest.raises((ValueError, TypeError), match=arg):
        call()


# ---------------------------------------------------------------- the test-flight guard (issue 26)
def _rows(fl, rows):
    """The record ``fl`` cut to ``rows`` (a slice or index array) in every column."""
    return fl._replace(**{k: getattr(fl, k)[rows] for k in adsb.COLUMNS})


def _nameless(t, lat, lon):
    """A record without a name, as a user may wrap arrays."""
    return SimpleNamespace(t_s=np.asarray(t, float), lat_deg=np.asarray(lat, float),
                           lon_deg=np.asarray(lon, float))


@pytest.fixture(scope="module")
def held_out():
    return {n: adsb.load_flight(n) for n in adsb.TEST_FLIGHTS}


def test_stored_test_flight_tracks_equal_the_files(held_out):
    fresh, stored = adsb._test_flight_tracks(), adsb._TEST_FLIGHT_TRACKS
    assert list(stored) == list(fresh) == list(adsb.TEST_FLIGHTS)
    source = {}                                      # the regeneration's text gives the table back
    exec(adsb._format_tracks(stored), source)
    assert source["_TEST_FLIGHT_TRACKS"] == stored
    for name, (t0, t1, tol, lat, lon) in stored.items():
        f0, f1, ftol, flat, flon = fresh[name]
        assert (t0, t1, len(lat), len(lon)) == (f0, f1, len(flat), len(flon)), name
        # stored rounded to 0.001 deg and up to 0.1 km: round-off (~1e-13) can flip a tie by one unit, no more
        np.testing.assert_allclose(lat, flat, rtol=0, atol=1e-3 + 1e-9, err_msg=name)
        np.testing.assert_allclose(lon, flon, rtol=0, atol=1e-3 + 1e-9, err_msg=name)
        assert abs(tol - ftol) <= 0.1 + 1e-9, name
        # every row of the file lies in the stored span and within the stored tolerance of the stored
        # track, less half the 1 km margin (kept for a flipped 0.001 deg, at most 0.12 km)
        fl = held_out[name]
        assert t0 <= fl.t_s.min() and fl.t_s.max() <= t1, name
        d = adsb._track_distance_km(fl.t_s, fl.lat_deg, fl.lon_deg, adsb._track_times(t0, t1, len(lat)),
                                    np.array(lat), np.array(lon))
        assert d.max() <= tol - 0.5 * adsb._TRACK_MARGIN_KM, name


def test_no_training_or_robustness_row_matches_a_test_flight():
    # Not one row of the 12 other flights lies within a test flight's tolerance of its track at
    # the same time, so no slice of them is refused; the nearest approach and the tolerances are
    # the figures the docstring of refuse_test_flights states.
    nearest = (math.inf, None, None)
    for name in adsb.TRAINING_FLIGHTS + adsb.ROBUSTNESS_FLIGHTS:
        fl = adsb.load_flight(name)
        for test, t0, t1, tol, tt, la, lo in adsb._test_tracks():
            span = (fl.t_s >= t0) & (fl.t_s <= t1)
            if span.any():
                d = adsb._track_distance_km(fl.t_s[span], fl.lat_deg[span], fl.lon_deg[span], tt, la, lo)
                assert not np.any(d <= tol), (name, test, d.min(), tol)
                nearest = min(nearest, (float(d.min()), name, test))
        adsb.refuse_test_flights([fl, _rows(fl, slice(100, 200)), fl._replace(name="mine.csv")])
    tols = [v[2] for v in adsb._TEST_FLIGHT_TRACKS.values()]
    doc = " ".join(adsb.refuse_test_flights.__doc__.split())
    assert nearest[1:] == ("gliders/alpi_italiane", "gliders/alto_adige")
    assert f"stays {nearest[0]:.1f} km from the track of ``gliders/alto_adige``, whose :math:`\\delta` is " \
           f"{adsb._TEST_FLIGHT_TRACKS['gliders/alto_adige'][2]:.1f} km" in doc
    assert f"({min(tols):.1f} to {max(tols):.1f} km)" in doc
    readme = " ".join((ROOT / "data" / "README.md").read_text(encoding="utf-8").split())
    assert f"within its tolerance ({min(tols):.1f} to {max(tols):.1f} km)" in readme
    assert f"every {adsb._TRACK_STEP_S:.0f} s" in readme and f"every {adsb._TRACK_STEP_S:.0f} s" in doc


@pytest.mark.parametrize("name", adsb.TEST_FLIGHTS)
def test_a_test_flight_is_refused_by_its_content(name, held_out):
    fl = held_out[name]
    K = fl.t_s.size
    train = _rows(adsb.load_flight("calibration/toulouse"), slice(0, 300))
    cases = {
        "renamed": (fl._replace(name="renamed.csv"), "name 'renamed.csv'", K),
        "first rows dropped": (fl._replace(name="mine", t_s=fl.t_s[10:], lat_deg=fl.lat_deg[10:],
                                           lon_deg=fl.lon_deg[10:]), "name 'mine'", K - 10),
        "100 rows at the start": (_rows(fl._replace(name="a"), slice(0, 100)), "name 'a'", 100),
        "100 rows in the middle": (_rows(fl._replace(name="b"), slice(K // 2, K // 2 + 100)), "name 'b'", 100),
        "100 rows at the end": (_rows(fl._replace(name="c"), slice(K - 100, K)), "name 'c'", 100),
        "no name": (_nameless(fl.t_s, fl.lat_deg, fl.lon_deg), "no name", K),
        "no name, rounded to 0.001 deg": (_nameless(fl.t_s, np.round(fl.lat_deg, 3), np.round(fl.lon_deg, 3)),
                                          "no name", K),
        "100 rows and 200 rows without a position": (
            _nameless(np.r_[fl.t_s[:100], fl.t_s[:200]], np.r_[fl.lat_deg[:100], np.full(200, np.nan)],
                      np.r_[fl.lon_deg[:100], np.full(200, np.nan)]), "no name", 100),
    }
    for case, (record, label, n) in cases.items():
        expected = (rf"\(kftrack.adsb.TEST_FLIGHTS.*got train\[1\] \({label}: {n} of its {n} finite rows "
                    rf"match {name}\)$")
        try:
            adsb.refuse_test_flights([train, record], argname="train")
        except ValueError as exc:
            assert re.search(expected, str(exc)), (case, str(exc))
        else:
            pytest.fail(f"{name}, {case}: not refused")
    # by name too, as before (and without looking at the rows)
    with pytest.raises(ValueError, match=rf"got flights\[0\] \({name}\)$"):
        adsb.refuse_test_flights([_rows(fl, slice(0, 0))])


def test_the_half_rule_and_flights_elsewhere():
    fl = adsb.load_flight("gliders/luberon")
    t, lat, lon = fl.t_s[:100], fl.lat_deg[:100], fl.lon_deg[:100]
    far_t, far_lat, far_lon = t + 86400.0, lat, lon                  # the same rows one day later
    # at least half of the finite rows: 50 of 100 refused, 49 of 98 refused, 49 of 99 passes
    mixed = _nameless(np.r_[t[:50], far_t[50:]], lat, lon)
    with pytest.raises(ValueError, match="no name: 50 of its 100 finite rows match gliders/luberon"):
        adsb.refuse_test_flights([mixed])
    with pytest.raises(ValueError, match="49 of its 98 finite rows"):
        adsb.refuse_test_flights([_nameless(np.r_[t[:49], far_t[51:]], np.r_[lat[:49], lat[51:]],
                                            np.r_[lon[:49], lon[51:]])])
    adsb.refuse_test_flights([_nameless(np.r_[t[:49], far_t[50:]], np.r_[lat[:49], lat[50:]],
                                        np.r_[lon[:49], lon[50:]])])
    # elsewhere: the same times 1 deg (111 km) north; the same places a day later; a synthetic
    # constant-velocity flight at 45 N 7 E, named or not; an empty record; a record without positions
    adsb.refuse_test_flights([
        fl._replace(name="north.csv", lat_deg=fl.lat_deg + 1.0),
        _nameless(fl.t_s + 86400.0, fl.lat_deg, fl.lon_deg),
        adsb.Flight("synthetic", np.arange(3000) * 5.0 + fl.t_s[0], 45.0 + np.arange(3000) * 1e-4,
                    np.full(3000, 7.0), *(np.full(3000, np.nan),) * 4, {}),
        _nameless(np.arange(3000) * 5.0, 45.0 + np.arange(3000) * 1e-4, np.full(3000, 7.0)),
        _nameless([], [], []),
        _nameless(fl.t_s, np.full(fl.t_s.size, np.nan), fl.lon_deg),
    ])


def test_the_guard_reads_no_file(held_out, monkeypatch):
    # The stored tracks are all it needs: with every way of reading a flight file broken, and the
    # table rebuilt from the constant, a renamed test flight is still refused.
    record = held_out["gliders/sisteron"]._replace(name="mine.csv")

    def no_read(*args, **kwargs):
        raise AssertionError(f"the guard read a file: {args!r}")

    adsb._test_tracks.cache_clear()
    with monkeypatch.context() as m:
        for obj, attr in ((adsb, "load_flight"), (adsb, "data_path"), (gzip, "open"), (builtins, "open")):
            m.setattr(obj, attr, no_read)
        with pytest.raises(ValueError, match="match gliders/sisteron"):
            adsb.refuse_test_flights([record])


def test_the_guard_is_fast(held_out):
    # Budget: 10 ms for a 3000-row flight; best of 20 calls, so that other work on a shared
    # machine does not count (one call takes about 0.5 ms on an idle core).
    matched = held_out["calibration/perth"]._replace(name="mine.csv")      # 3101 rows: refused
    passing = adsb.load_flight("calibration/munich")                            # 3060 rows: passes
    for record, refused in ((matched, True), (passing, False)):
        best = math.inf
        for _ in range(20):
            start = time.perf_counter()
            try:
                adsb.refuse_test_flights([record])
            except ValueError:
                assert refused
            else:
                assert not refused
            best = min(best, time.perf_counter() - start)
        assert best < 0.010, (record.name, best)
