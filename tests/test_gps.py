"""Tests of kftrack.sensors.gps: NMEA parsing and writing, logs with bad lines, units, geodesy."""
import datetime as dt

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kftrack.sensors import gps

THESIS_RMC = "$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A"


def _with_checksum(body: str) -> str:
    return f"${body}*{gps.nmea_checksum(body)}"


# --- the thesis's example sentence (Fig. 2.2) -------------------------------------------------

def test_thesis_rmc_checksum_is_0x6A():
    body = THESIS_RMC[1:THESIS_RMC.index("*")]
    assert gps.nmea_checksum(body) == "6A"
    xor = 0
    for ch in body:
        xor ^= ord(ch)
    assert xor == 0x6A


def test_thesis_rmc_fields():
    status, f = gps.parse_sentence(THESIS_RMC)
    assert status == "ok"
    assert f["type"] == "RMC" and f["talker"] == "GP"
    assert f["lat"] == pytest.approx(48.1173, abs=5e-5)
    assert f["lon"] == pytest.approx(11.516667, abs=5e-7)
    assert f["speed"] == pytest.approx(11.5236, abs=5e-5)
    assert f["course"] == pytest.approx(np.deg2rad(84.4), abs=1e-12)
    assert f["time"] == 12 * 3600 + 35 * 60 + 19
    assert f["date"] == dt.date(1994, 3, 23)


def test_bytes_with_crlf_parse_like_str():
    assert gps.parse_sentence((THESIS_RMC + "\r\n").encode()) == gps.parse_sentence(THESIS_RMC)


# --- talkers, sentence types, status ----------------------------------------------------------

@pytest.mark.parametrize("talker", ["GP", "GN", "GL", "GA", "GB"])
def test_any_talker_rmc_and_gga(talker):
    rmc = gps.format_rmc(3600.0, -26.2, -52.7, 1.5, 0.5, talker=talker)
    gga = gps.format_gga(3600.0, -26.2, -52.7, 2, talker=talker)
    s1, f1 = gps.parse_sentence(rmc)
    s2, f2 = gps.parse_sentence(gga)
    assert (s1, s2) == ("ok", "ok")
    assert f1["talker"] == f2["talker"] == talker
    assert f2["quality"] == 2 and np.isnan(f2["speed"])


def test_status_v_and_gga_quality_0_are_no_fix():
    assert gps.parse_sentence(gps.format_rmc(10.0, 0, 0, 0, 0, status="V"))[0] == "no_fix"
    assert gps.parse_sentence("$GPRMC,123519,V,,,,,,,230394,,*33")[0] == "no_fix"
    assert gps.parse_sentence(gps.format_gga(10.0, 1.0, 2.0, quality=0))[0] == "no_fix"


def test_empty_course_is_nan_but_fix_kept():
    s, f = gps.parse_sentence(_with_checksum("GPRMC,123519,A,4807.038,N,01131.000,E,0.1,,230394,,"))
    assert s == "ok" and np.isnan(f["course"]) and f["speed"] == pytest.approx(0.1 * gps.KNOT)


def test_southern_western_hemisphere_signs():
    s, f = gps.parse_sentence(gps.format_rmc(0.0, -26.19, -52.68, 1.0, 1.0))
    assert f["lat"] == pytest.approx(-26.19, abs=1e-7) and f["lon"] == pytest.approx(-52.68, abs=1e-7)


@pytest.mark.parametrize("line, reason", [
    (b"\xff\xfe$GPRMC,1", "non_utf8"),
    (THESIS_RMC[:-3], "truncated"),
    (THESIS_RMC[:30], "truncated"),
    (THESIS_RMC[:-1] + "B", "bad_checksum"),
    ("GPRMC,123519,A*6A", "malformed"),
    (_with_checksum("GPRMC,123519,A,48x7.038,N,01131.000,E,022.4,084.4,230394,003.1,W"), "malformed"),
    (_with_checksum("GPRMC,99x519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W"), "malformed"),
    (_with_checksum("GPRMC,123519,A,4807.038,N,01131.000,E,,084.4,230394,003.1,W"), "malformed"),
    (_with_checksum("GPRMC,123519,X,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W"), "malformed"),
    (_with_checksum("G1RMC,123519"), "malformed"),
    (_with_checksum("GPGSV,1,1,00"), "unsupported"),
    ("$GPRMC,123519,V,,,,,,,230394,,*33", "no_fix"),
])
def test_every_skip_reason(line, reason):
    assert gps.parse_sentence(line) == (reason, None)


def test_log_reader_counts_every_reason_and_merges_epochs():
    good_rmc = gps.format_rmc(100.0, -26.2, -52.7, 1.5, 0.25, talker="GN")
    good_gga = gps.format_gga(100.0, -26.2, -52.7, 2, talker="GN")
    lines = [
        good_rmc, good_gga, gps.format_rmc(101.0, -26.2001, -52.7, 1.5, 0.25, talker="GN"),
        b"\xff\x00garbage", good_rmc[:20], good_rmc[:-1] + ("0" if good_rmc[-1] != "0" else "1"),
        "hello world", _with_checksum("GPGSV,1,1,00"), gps.format_rmc(99.0, 0, 0, 0, 0, status="V"),
        "", b"   ",
    ]
    fixes, report = gps.read_nmea_log(lines)
    assert report.counts == {"non_utf8": 1, "truncated": 1, "bad_checksum": 1, "malformed": 1,
                             "no_fix": 1, "unsupported": 1}
    assert report.total == 9 and report.skipped == 6
    assert [n for n, _ in report.lines] == [4, 5, 6, 7, 8, 9]
    np.testing.assert_array_equal(fixes.time, [100.0, 101.0])
    np.testing.assert_array_equal(fixes.quality, [2, 1])  # GGA quality, then RMC mode A
    np.testing.assert_allclose(fixes.speed, 1.5, atol=3e-4)
    np.testing.assert_allclose(fixes.course, 0.25, atol=1e-4)


def test_log_reader_from_path_and_bytes(tmp_path):
    text = (THESIS_RMC + "\r\n" + THESIS_RMC[:-1] + "0\r\n").encode()
    p = tmp_path / "log.nmea"
    p.write_bytes(text)
    for source in (p, str(p), text):
        fixes, report = gps.read_nmea_log(source)
        assert len(fixes.time) == 1 and report.counts["bad_checksum"] == 1


def test_log_reader_day_rollover_from_dates():
    a = gps.format_rmc(86399.0, 1.0, 1.0, 1.0, 0.0, date=dt.date(2018, 12, 31))
    b = gps.format_rmc(0.0, 1.0, 1.0, 1.0, 0.0, date=dt.date(2019, 1, 1))
    fixes, _ = gps.read_nmea_log([a, b])
    np.testing.assert_array_equal(fixes.time, [86399.0, 86400.0])


# --- fuzzing: no line ever escapes the reader, every line is accounted for -----------------------

@settings(max_examples=200, deadline=None)
@given(st.lists(st.binary(max_size=90), max_size=12))
def test_random_bytes_never_raise_and_are_counted(lines):
    fixes, report = gps.read_nmea_log(lines)
    nonblank = [ln for ln in lines if ln.strip()]
    ok = sum(gps.parse_sentence(ln)[0] == "ok" for ln in nonblank)
    assert report.total == len(nonblank)
    assert report.skipped + ok == report.total
    assert len(fixes.time) <= ok


@settings(max_examples=200, deadline=None)
@given(st.lists(st.text(max_size=90), max_size=12))
def test_random_text_never_raises_and_is_counted(lines):
    fixes, report = gps.read_nmea_log(lines)
    nonblank = [ln for ln in lines if ln.strip()]
    ok = sum(gps.parse_sentence(ln)[0] == "ok" for ln in nonblank)
    assert report.total == len(nonblank) and report.skipped + ok == report.total


_CORRUPTION = st.sampled_from(["ok", "truncated", "bad_checksum", "flipped", "non_utf8", "not_a_sentence"])


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(_CORRUPTION, st.integers(0, 10**6), st.binary(max_size=40),
                          st.characters(min_codepoint=33, max_codepoint=126)), max_size=15))
def test_every_corruption_is_counted_by_its_reason(items):
    """A log of valid RMC lines (talkers GP, GN, GL) with some of them truncated anywhere, given a
    wrong checksum, one body character changed, a non-UTF-8 byte, or no '$': the report counts
    exactly these, at their line numbers, and every intact line becomes a fix."""
    lines, expected = [], []
    for k, (kind, n, noise, char) in enumerate(items):
        line = gps.format_rmc(1000.0 + k, -26.2 + 1e-5 * (n % 97), -52.7, 1.4, (n % 628) / 100,
                              talker=("GP", "GN", "GL")[n % 3])
        if kind == "truncated":
            line = line[: 1 + n % (len(line) - 1)]          # cut anywhere, keeping the '$'
        elif kind == "bad_checksum":
            line = line[:-2] + f"{int(line[-2:], 16) ^ (1 + n % 255):02X}"
        elif kind == "flipped":                            # one body character changed: XOR differs
            i = 1 + n % (len(line) - 4)
            line = line[:i] + (char if char != line[i] else chr(ord(char) % 126 + 1)) + line[i + 1:]
            kind = "bad_checksum"
        elif kind == "non_utf8":
            line = b"\xff" + noise
        elif kind == "not_a_sentence":
            line, kind = "x" + line[1:], "malformed"
        lines.append(line)
        expected.append(kind)
    fixes, report = gps.read_nmea_log(lines)
    bad = [(k + 1, kind) for k, kind in enumerate(expected) if kind != "ok"]
    assert report.lines == bad
    assert report.counts == {r: sum(kind == r for _, kind in bad) for r in gps.SKIP_REASONS}
    assert report.total == len(lines) and len(fixes.time) == expected.count("ok")


# --- writer <-> reader round trip -------------------------------------------------------------

@settings(max_examples=150, deadline=None)
@given(lat=st.floats(-89.9, 89.9), lon=st.floats(-179.9, 179.9), speed=st.floats(0, 50),
       course=st.floats(0, 2 * np.pi - 1e-3), t=st.floats(0, 86399.0), talker=st.sampled_from(["GP", "GN", "GL"]))
def test_writer_reader_round_trip(lat, lon, speed, course, t, talker):
    t = round(t, 2)
    fixes, report = gps.read_nmea_log([gps.format_rmc(t, lat, lon, speed, course, talker=talker),
                                       gps.format_gga(t, lat, lon, 1, talker=talker)])
    assert report.skipped == 0 and len(fixes.time) == 1
    assert fixes.time[0] == pytest.approx(t, abs=6e-3)
    assert fixes.lat[0] == pytest.approx(lat, abs=1e-5 / 60 * 0.51)
    assert fixes.lon[0] == pytest.approx(lon, abs=1e-5 / 60 * 0.51)
    assert fixes.speed[0] == pytest.approx(speed, abs=0.0005 * gps.KNOT + 1e-12)
    d = (fixes.course[0] - course + np.pi) % (2 * np.pi) - np.pi
    assert abs(d) <= np.deg2rad(0.005) + 1e-12


# --- units and heading convention --------------------------------------------------------------

def test_knots_conversion():
    assert gps.KNOT == 1852 / 3600
    assert float(gps.knots_to_mps(1.0)) == pytest.approx(0.514444, abs=5e-7)
    assert float(gps.knots_to_mps(22.4)) == pytest.approx(11.5236, abs=5e-5)
    np.testing.assert_allclose(gps.mps_to_knots(gps.knots_to_mps([0, 3.3, 100])), [0, 3.3, 100], rtol=1e-15)


@pytest.mark.parametrize("course_deg, heading", [(0, np.pi / 2), (90, 0.0), (180, -np.pi / 2), (270, np.pi),
                                                 (45, np.pi / 4), (359, np.deg2rad(91))])
def test_course_to_heading_known(course_deg, heading):
    h = float(gps.course_to_heading(np.deg2rad(course_deg)))
    assert np.isclose(np.cos(h), np.cos(heading)) and np.isclose(np.sin(h), np.sin(heading))
    assert -np.pi < h <= np.pi


@given(st.floats(0, 2 * np.pi - 1e-9))
def test_heading_velocity_identity_and_round_trip(chi):
    h = gps.course_to_heading(chi)
    assert np.allclose([np.cos(h), np.sin(h)], [np.sin(chi), np.cos(chi)], atol=1e-12)
    back = gps.heading_to_course(h)
    assert abs((back - chi + np.pi) % (2 * np.pi) - np.pi) < 1e-12


# --- geodesy ---------------------------------------------------------------------------------------

def test_utm_known_points():
    e, n, zone, letter = gps.geodetic_to_utm(0.0, 3.0)
    assert (zone, letter) == (31, "N") and float(e) == pytest.approx(500000.0, abs=1e-3)
    assert float(n) == pytest.approx(0.0, abs=1e-3)
    e, n, zone, letter = gps.geodetic_to_utm(51.2, 7.5)  # the utm package's documented example
    assert (zone, letter) == (32, "U")
    assert float(e) == pytest.approx(395201.3103811303, abs=1e-3)
    assert float(n) == pytest.approx(5673135.241182375, abs=1e-3)
    e, n, zone, letter = gps.geodetic_to_utm(-26.1966, -52.6897)  # Pato Branco: zone 22 J, south
    assert (zone, letter) == (22, "J") and 3e5 < float(e) < 4e5 and 7.0e6 < float(n) < 7.2e6


def test_enu_against_radii_of_curvature():
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    lat0, lon0 = -26.1966, -52.6897
    phi = np.deg2rad(lat0)
    M = a * (1 - e2) / (1 - e2 * np.sin(phi) ** 2) ** 1.5
    N = a / np.sqrt(1 - e2 * np.sin(phi) ** 2)
    d = np.rad2deg(1e-6)
    e, n, u = gps.geodetic_to_enu(lat0 + d, lon0, lat0, lon0)
    assert float(n) == pytest.approx(M * 1e-6, abs=1e-6) and abs(float(e)) < 1e-6
    e, n, u = gps.geodetic_to_enu(lat0, lon0 + d, lat0, lon0)
    assert float(e) == pytest.approx(N * np.cos(phi) * 1e-6, abs=1e-6)
    assert np.allclose(gps.geodetic_to_enu(lat0, lon0, lat0, lon0), 0.0, atol=1e-9)


def test_round_trips_at_the_millimetre():
    rng = np.random.default_rng(1)
    lat0, lon0 = -26.1966, -52.6897
    east, north = rng.uniform(-200, 200, 50), rng.uniform(-200, 200, 50)
    lat, lon, _ = gps.enu_to_geodetic(east, north, lat0, lon0)
    e2, n2, _ = gps.geodetic_to_enu(lat, lon, lat0, lon0)
    np.testing.assert_allclose(e2, east, atol=1e-3)
    np.testing.assert_allclose(n2, north, atol=1e-3)
    E, N, zone, letter = gps.geodetic_to_utm(lat, lon)
    lat3, lon3 = gps.utm_to_geodetic(E, N, zone, letter)
    e3, n3, _ = gps.geodetic_to_enu(lat3, lon3, lat0, lon0)
    np.testing.assert_allclose(e3, east, atol=1e-3)
    np.testing.assert_allclose(n3, north, atol=1e-3)
    # lane-scale distances agree in ENU and UTM to < 1 mm (claim C3; UTM scale ~0.99994 here)
    d_enu = np.hypot(np.diff(e2), np.diff(n2))
    d_utm = np.hypot(np.diff(E), np.diff(N))
    lane = d_enu < 400
    assert np.all(np.abs(d_utm - d_enu)[lane] / d_enu[lane] * 7.32 < 1e-3)


# --- bad input ---------------------------------------------------------------------------------------

def test_bad_input_messages():
    with pytest.raises(TypeError, match="line"):
        gps.parse_sentence(123)
    with pytest.raises(TypeError, match="source"):
        gps.read_nmea_log(123)
    with pytest.raises(TypeError, match="body"):
        gps.nmea_checksum(b"GPRMC")
    with pytest.raises(ValueError, match="talker"):
        gps.format_rmc(0, 0, 0, 0, 0, talker="G")
    with pytest.raises(ValueError, match="status"):
        gps.format_rmc(0, 0, 0, 0, 0, status="X")
    with pytest.raises(ValueError, match="lat_deg"):
        gps.format_rmc(0, 91, 0, 0, 0)
    with pytest.raises(ValueError, match="lon_deg"):
        gps.format_gga(0, 0, 181)
    with pytest.raises(ValueError, match="quality"):
        gps.format_gga(0, 0, 0, quality=9)
    with pytest.raises(ValueError, match="lat_deg"):
        gps.geodetic_to_enu(100.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="lat0_deg"):
        gps.geodetic_to_enu(10.0, 0.0, 95.0, 0.0)
    with pytest.raises(ValueError, match="zone"):
        gps.utm_to_geodetic(5e5, 0.0, 61, "N")
    with pytest.raises(TypeError, match="knots"):
        gps.knots_to_mps("fast")
    with pytest.raises(TypeError, match="course"):
        gps.course_to_heading(object())
