"""Bad input to the data loaders and the particle filters (issue 25; the cases of
``shared/reviews/2026-12-newcomer/bad-input.md`` in ``adsb``, ``sensors.gps``, ``sensors.ardrone``,
``gpstrack`` and ``particle``): each ends as a clear error naming the argument or the file, as a
record skipped and counted by reason, or as the correct result. Corrupted files are made here,
in ``tmp_path``, from copies of the committed ones."""
from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest

from kftrack import adsb, datasets, gpstrack, models, particle
from kftrack.sensors import ardrone, gps

GOOD = "$GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W*6A"


def _fix(sentence: str) -> str:
    """The sentence with its checksum recomputed (so only the field content is wrong)."""
    return sentence[:-3] + "*" + gps.nmea_checksum(sentence[1:-3])


# ------------------------------------------------------------------------------------ ADS-B files
def _corrupt_folder(tmp_path: Path, monkeypatch, name: str, raw: bytes) -> Path:
    """A KFTRACK_DATA folder whose flight ``name`` holds the bytes ``raw``."""
    path = tmp_path / "adsb" / f"{name}.csv.gz"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(raw)
    monkeypatch.setenv("KFTRACK_DATA", str(tmp_path))
    return path


def test_flight_file_that_is_not_gzip_names_the_file(tmp_path, monkeypatch):
    path = _corrupt_folder(tmp_path, monkeypatch, "calibration/munich",
                           b"this is not gzip\n" + ",".join(adsb.COLUMNS).encode() + b"\n")
    with pytest.raises(ValueError, match="not a valid gzip file") as info:
        adsb.load_flight("calibration/munich")
    assert str(path) in str(info.value)


def test_truncated_gzip_stream_names_the_file_and_returns_no_partial_flight(tmp_path, monkeypatch):
    raw = datasets.data_path("adsb/gliders/cevennes.csv.gz").read_bytes()
    path = _corrupt_folder(tmp_path, monkeypatch, "gliders/cevennes", raw[: len(raw) // 2])
    with pytest.raises(ValueError, match="truncated gzip stream") as info:
        adsb.load_flight("gliders/cevennes")
    assert str(path) in str(info.value)
    # a user's truncated file: the same error, naming the user's path
    user = tmp_path / "mine.csv.gz"
    user.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match="truncated gzip stream") as info:
        adsb.load_flight(user)
    assert str(user) in str(info.value)


def test_corrupt_deflate_data_names_the_file(tmp_path, monkeypatch):
    raw = bytearray(datasets.data_path("adsb/calibration/toulouse.csv.gz").read_bytes())
    raw[len(raw) // 2: len(raw) // 2 + 64] = bytes(64)  # 64 zero bytes inside the deflate stream
    path = _corrupt_folder(tmp_path, monkeypatch, "calibration/toulouse", bytes(raw))
    with pytest.raises(ValueError, match="gzip") as info:
        adsb.load_flight("calibration/toulouse")
    assert str(path) in str(info.value)


def test_empty_altitude_cell_keeps_the_position_with_nan_altitude(tmp_path):
    path = tmp_path / "one.csv"
    path.write_text("\n".join([",".join(adsb.COLUMNS), "1600000006,43.6,1.4,,100,90,0",
                               "1600000007,43.7,1.5,1000,,,", ",43.8,1.6,1000,100,90,0",
                               "1600000009,,1.7,1000,100,90,0"]) + "\n")
    f = adsb.load_flight(path)
    np.testing.assert_array_equal(f.t_s, [1600000006.0, 1600000007.0])
    np.testing.assert_array_equal(f.lat_deg, [43.6, 43.7])
    assert np.isnan(f.alt_m[0]) and f.groundspeed_mps[0] == 100.0 and f.alt_m[1] == 1000.0
    assert np.isnan(f.groundspeed_mps[1]) and np.isnan(f.track_deg[1]) and np.isnan(f.vertical_rate_mps[1])
    # time, latitude and longitude are required: an empty one skips the row, counted by reason
    assert f.skipped == {"missing time, latitude or longitude": 2}


@pytest.mark.parametrize("kind", ["csv", "csv.gz", "str"])
def test_a_users_file_loads_through_load_flight_like_the_bundled_one(tmp_path, kind):
    bundled = adsb.load_flight("noisy/noisy_spoofing")
    text = gzip.decompress(datasets.data_path("adsb/noisy/noisy_spoofing.csv.gz").read_bytes())
    if kind == "csv.gz":
        path = tmp_path / "flight.csv.gz"
        path.write_bytes(gzip.compress(text))
    else:
        path = tmp_path / "flight.csv"
        path.write_bytes(text)
    mine = adsb.load_flight(str(path) if kind == "str" else path)
    assert mine.name == str(path) and mine.skipped == bundled.skipped
    for column in adsb.COLUMNS:
        np.testing.assert_array_equal(getattr(mine, column), getattr(bundled, column), err_msg=column)


def test_load_flight_argument_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="name: no flight file"):
        adsb.load_flight(tmp_path / "absent.csv")
    with pytest.raises(ValueError, match=r"name must be a flight file ending in \.csv or \.csv\.gz"):
        adsb.load_flight(tmp_path / "flight.json")
    with pytest.raises(ValueError, match=r"name must be one of the ADS-B flights.*\.csv\.gz file"):
        adsb.load_flight("calibration/atlantis")
    with pytest.raises(TypeError, match="name must be a flight name"):
        adsb.load_flight(None)
    plain = tmp_path / "text.csv.gz"  # named .gz but not compressed
    plain.write_text(",".join(adsb.COLUMNS) + "\n")
    with pytest.raises(ValueError, match="not a valid gzip file"):
        adsb.load_flight(plain)


# ------------------------------------------------------------------------------------ NMEA
BAD_NMEA = {
    "longitude minutes 75": _fix(GOOD.replace("01131.000", "01175.000")),
    "latitude minutes 60": _fix(GOOD.replace("4807.038", "4860.000")),
    "hemisphere Q": _fix(GOOD.replace(",N,", ",Q,")),
    "hemisphere missing": _fix(GOOD.replace(",N,", ",,")),
    "longitude hemisphere N": _fix(GOOD.replace(",E,", ",N,")),
    "negative speed": _fix(GOOD.replace("022.4", "-5.0")),
    "signed latitude field": _fix(GOOD.replace("4807.038", "-4807.038")),
    "31 February": _fix(GOOD.replace("230394", "310294")),
    "GGA hemisphere s": _fix(gps.format_gga(100.0, -26.2, -52.7).replace(",S,", ",s,")),
    "GGA longitude minutes 61": _fix(gps.format_gga(100.0, -26.2, -52.7).replace("05242.00000", "05261.00000")),
}


@pytest.mark.parametrize("case", sorted(BAD_NMEA))
def test_nmea_field_that_cannot_be_a_reading_is_malformed_under_a_valid_checksum(case):
    line = BAD_NMEA[case]
    assert line[-2:] == gps.nmea_checksum(line[1:-3])  # the checksum is right: only the content is wrong
    assert gps.parse_sentence(line) == ("malformed", None)


def test_read_nmea_log_counts_the_bad_fields_and_keeps_the_good_fix():
    fixes, report = gps.read_nmea_log([GOOD] + [BAD_NMEA[c] for c in sorted(BAD_NMEA)])
    assert report.counts["malformed"] == len(BAD_NMEA) and report.skipped == len(BAD_NMEA)
    assert len(fixes.time) == 1 and fixes.lat[0] == pytest.approx(48 + 7.038 / 60, abs=1e-12)


def test_nmea_edge_values_that_are_readings_stay_ok():
    for line in (_fix(GOOD.replace("4807.038", "4859.999")),      # 59.999 minutes
                 _fix(GOOD.replace("022.4", "000.0")),             # standing still
                 _fix(GOOD.replace("230394", "290200")),           # 29 February 2000
                 _fix(GOOD.replace(",N,", ",S,").replace(",E,", ",W,"))):
        status, fields = gps.parse_sentence(line)
        assert status == "ok", line
    assert gps.parse_sentence(_fix(GOOD.replace("230394", "")))[1]["date"] is None  # no date: not an error
    status, fields = gps.parse_sentence(gps.format_gga(100.0, -26.2, -52.7))
    assert status == "ok" and fields["lat"] == pytest.approx(-26.2, abs=1e-9)


def test_read_nmea_log_given_a_sentence_str_says_to_pass_a_path_or_a_list(tmp_path):
    for text in (GOOD, GOOD + "\r\n" + GOOD):
        with pytest.raises(ValueError, match=r"source must be a path.*list of sentences"):
            gps.read_nmea_log(text)
    with pytest.raises(FileNotFoundError):  # a str is a path
        gps.read_nmea_log(str(tmp_path / "absent.nmea"))
    fixes, report = gps.read_nmea_log([GOOD])
    assert len(fixes.time) == 1 and report.skipped == 0
    assert np.array_equal(gps.read_nmea_log(GOOD.encode())[0].lat, fixes.lat)


# ------------------------------------------------------------------------------------ writers
def test_log_writers_need_an_explicit_folder(tmp_path):
    with pytest.raises(TypeError, match="directory"):
        ardrone.write_logs()
    with pytest.raises(TypeError, match="directory must be the folder"):
        ardrone.write_logs(None)
    with pytest.raises(TypeError, match="directory"):
        gpstrack.write_track_logs()
    with pytest.raises(TypeError, match="directory must be the folder"):
        gpstrack.write_track_logs(None)
    paths = ardrone.write_logs(tmp_path / "new" / "folder")
    assert [p.name for p in paths] == ["ardrone_expA.csv", "ardrone_expB.csv", "ardrone_expC.csv"]
    assert all(p.parent == tmp_path / "new" / "folder" for p in paths)


# ------------------------------------------------------------------------------------ particle filters
CV = models.ConstantVelocity(ndim=2, q=1.0)
F, Q, H = CV.F(1.0), CV.Q(1.0), CV.H
X0, P0, R = np.zeros(4), 10 * np.eye(4), 4 * np.eye(2)
ZS = np.cumsum(np.ones((20, 2)), 0)


def h_lin(s):
    return s[..., [0, 2]]


def f_lin(s):
    return s @ F.T


def f_nan(s):
    """The reviewer's f: NaN for every particle with x > 5 (first met after a few steps)."""
    return s @ F.T + np.where(s[..., :1] > 5, np.nan, 0.0)


def test_bootstrap_initial_size_below_n_is_refused():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match=r"initial_size must be at least N = 200.*got 10"):
        particle.bootstrap_filter(ZS, X0, P0, f_lin, Q, h_lin, R, 200, rng, initial_size=10)
    # initial_size = N is the default behaviour, bit for bit
    a = particle.bootstrap_filter(ZS, X0, P0, f_lin, Q, h_lin, R, 50, np.random.default_rng(1), initial_size=50)
    b = particle.bootstrap_filter(ZS, X0, P0, f_lin, Q, h_lin, R, 50, np.random.default_rng(1))
    np.testing.assert_array_equal(a.x, b.x)


def test_bootstrap_f_returning_nan_names_f_and_the_step():
    with pytest.raises(ValueError, match=r"^f returned NaN at step \d+ for \d+ of 200 particles"):
        particle.bootstrap_filter(ZS, X0, P0, f_nan, Q, h_lin, R, 200, np.random.default_rng(0))


def test_bootstrap_h_returning_nan_or_inf_names_h_and_the_step():
    with np.errstate(invalid="ignore", divide="ignore"):
        with pytest.raises(ValueError, match=r"^h returned NaN at step 0"):
            particle.bootstrap_filter(ZS, X0, P0, f_lin, Q, lambda s: np.log(s[..., [0, 2]]), R, 200,
                                      np.random.default_rng(0))
        with pytest.raises(ValueError, match=r"^h returned inf at step 3"):
            particle.bootstrap_filter(ZS, X0, P0, f_lin, Q, [h_lin] * 3 + [lambda s: s[..., [0, 2]] / 0.0] * 17,
                                      R, 200, np.random.default_rng(0))


def test_other_particle_filters_check_the_users_functions():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match=r"^f returned NaN at step \d+"):
        particle.optimal_proposal_filter(ZS, X0, P0, f_nan, Q, H, R, 200, rng)

    class NanModel:
        """A user's motion model whose f breaks down for x > 5."""

        def f(self, x, dt):
            return f_nan(x)

        def Q(self, dt):
            return Q

    with pytest.raises(ValueError, match=r"^models\[1\]\.f returned NaN at step \d+"):
        particle.jump_markov_filter(ZS, X0, P0, [CV, NanModel()], np.full((2, 2), 0.5), [0.5, 0.5], h_lin, R, 200,
                                    rng, 1.0)
    with np.errstate(invalid="ignore"):
        with pytest.raises(ValueError, match=r"^h returned NaN at step 0"):
            particle.jump_markov_filter(ZS, X0, P0, [CV], np.eye(1), [1.0], lambda s: np.sqrt(s[..., [0, 2]]), R,
                                        200, rng, 1.0)
        with pytest.raises(ValueError, match=r"^f returned NaN for 5 of 5 particles"):
            particle.propagate(np.full((5, 4), -1.0), np.sqrt, Q, rng)
