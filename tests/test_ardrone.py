"""Tests of kftrack.sensors.ardrone: units, the altimeter format, outliers, logs and files."""
import numpy as np
import pytest
from scipy import stats

from kftrack.datasets import data_path
from kftrack.sensors import ardrone as ad

FAMILY_ALPHA = 0.05


# --------------------------------------------------------------------------- units

def test_gyro_variance_conversions_of_the_study():
    """Notes §9 claim 3: (pi/180)^2 = 3.0462e-4; 2.3018 -> 7.0117e-4, 2.7550 -> 8.3922e-4, 1.5478 -> 4.7149e-4."""
    assert abs(ad.to_si(1.0, "roll_rate", variance=True) - 3.0462e-4) < 0.5e-8
    for raw, want in [(2.3018, 7.0117e-4), (2.7550, 8.3922e-4), (1.5478, 4.7149e-4)]:
        assert abs(ad.to_si(raw, "pitch_rate", variance=True) - want) < 0.5e-8


def test_accelerometer_conversions():
    """Cov[hdd_m] = 39.3808 (cm/s^2)^2 = 3.93808e-3 (m/s^2)^2; -977.2680 cm/s^2 = -9.77268 m/s^2."""
    assert np.isclose(ad.to_si(39.3808, "acc_z", variance=True), 3.93808e-3, rtol=1e-14)
    assert np.isclose(ad.to_si(-977.2680, "acc_z"), -9.77268, rtol=1e-14)
    assert ad.to_si(-977.2680, "acc_z", accel_unit="mg") == -977.2680 * 9.80665e-3
    assert np.isclose(ad.to_si(90.0, "yaw_rate"), np.pi / 2)


def test_altitude_decoding_of_the_study_values():
    """Notes §9 claim 5: 3.3351e-43 -> 238 mm, 2.8278e-43 -> 202 mm, 1.4024e-42 -> 1001 mm."""
    got = ad.decode_altitude([3.3351e-43, 2.8278e-43, 1.4024e-42])
    np.testing.assert_array_equal(np.rint(got * 1000).astype(int), [238, 202, 1001])
    assert np.float32(3.3351e-43).view(np.int32) == 238


def test_altitude_decode_is_exact_and_inverts_encode():
    mm = np.arange(0, 20_001)
    raw = ad.encode_altitude(mm / 1000.0)
    assert raw.dtype == np.float32
    np.testing.assert_array_equal(ad.decode_altitude(raw), mm / 1000.0)
    # decoding is a bit view; for denormals it equals multiplying by 2^149 (exact)
    np.testing.assert_array_equal(ad.decode_altitude(raw), raw.astype(float) * 2.0 ** 149 / 1000)
    # the SI scale of to_si agrees, so variances convert consistently
    np.testing.assert_allclose(ad.to_si(raw.astype(float), "altitude"), mm / 1000.0, rtol=1e-15)


def test_study_altitude_convention_versus_decoding():
    """Cov[h_m] = 4.7262e-89 / (1.4024e-42)^2 = 2.4031e-5 m^2 (the study), 2.4069e-5 by decoding."""
    assert ad.altitude_study_convention(1.4024e-42) == pytest.approx(1.0, rel=1e-15)
    assert abs(4.7262e-89 / ad.STUDY_ALTITUDE_UNIT ** 2 - 2.4031e-5) < 0.5e-9
    assert abs(ad.to_si(4.7262e-89, "altitude", variance=True) - 2.4069e-5) < 0.5e-9


def test_study_moments_in_si():
    c = ad.study_moments("C")
    assert abs(c["pitch_rate"][1] - 8.3922e-4) < 0.5e-8
    assert abs(c["altitude"][0] - 1.0008) < 0.5e-4 and abs(c["altitude"][1] - 2.4069e-5) < 0.5e-9
    assert c["acc_z"] == (ad.to_si(-975.2683, "acc_z"), ad.to_si(39.3808, "acc_z", variance=True))
    assert ad.study_moments("A", units="raw") == ad.STUDY_TABLES["A"]


# --------------------------------------------------------------------------- outliers

def test_altimeter_valid_range():
    h = np.array([0.0, 0.199, 0.2, 0.238, 1.0, 6.0, 6.01, np.nan])
    np.testing.assert_array_equal(ad.altimeter_valid(h), [0, 0, 1, 1, 1, 1, 0, 0])


def test_mad_rule_finds_gross_outliers_and_few_false_alarms():
    rng = np.random.default_rng(10)
    trials, n = 200, 1000
    false = 0
    for _ in range(trials):
        x = rng.standard_normal(n)
        false += ad.mad_outliers(x).sum()
    # the docstring's claim: about P(|N(0,1)| > 3.5) = 4.65e-4 per sample (with n = 1000 the
    # MAD is estimated to a few percent, which moves this rate far less than the bounds)
    p = 2 * stats.norm.sf(3.5)
    lo, hi = stats.binom.ppf([0.0005, 0.9995], trials * n, p)
    assert lo <= false <= hi
    x = rng.standard_normal(500)
    x[[3, 50, 400]] = [40.0, -25.0, 12.0]
    assert set(np.flatnonzero(ad.mad_outliers(x))) >= {3, 50, 400}


def test_mad_rule_with_zero_mad_and_constant_sample():
    assert not ad.mad_outliers(np.full(10, 238.0)).any()
    x = np.full(100, 238.0)
    x[:10] = 0.0  # MAD = 0: falls back to the mean absolute deviation
    np.testing.assert_array_equal(np.flatnonzero(ad.mad_outliers(x)), np.arange(10))


def test_three_sigma_rule_masks_the_dropouts_but_mad_and_range_do_not():
    log = ad.load_log("B")
    h = log.si("altitude")
    dropouts = h == 0
    assert dropouts.sum() == round(ad.channel_model("B", "altitude").dropout_fraction * ad.SAMPLES)
    naive = np.abs(h - h.mean()) > 3 * h.std(ddof=1)
    assert not naive[dropouts].any()          # mean +- 3 std is inflated by the dropouts
    np.testing.assert_array_equal(~ad.altimeter_valid(h), dropouts)
    np.testing.assert_array_equal(ad.mad_outliers(h), dropouts)


# --------------------------------------------------------------------------- models and logs

def test_channel_models_reproduce_the_table_moments():
    for e in ad.EXPERIMENTS:
        for c in ad.CHANNELS:
            m = ad.channel_model(e, c)
            mean, var = ad.STUDY_TABLES[e][c]
            if c != "altitude":
                assert (m.mean, m.var) == (mean, var)
                continue
            f, lsb = m.dropout_fraction, ad.ALTITUDE_LSB
            total_mean = (1 - f) * m.mean
            total_var = (1 - f) * (m.var + m.mean ** 2) - total_mean ** 2
            assert abs(total_mean * lsb - mean) <= 0.5e-47 if e == "A" else np.isclose(total_mean * lsb, mean, rtol=1e-12)
            assert np.isclose(total_var * lsb ** 2, var, rtol=1e-9, atol=0)  # (1-f)(v+m^2)-m^2 cancels
    b = ad.channel_model("B", "altitude")
    assert round(b.mean, 1) == 240.0 and round(100 * b.dropout_fraction, 1) == 15.9


def test_committed_logs_equal_a_fresh_generation():
    for e in ad.EXPERIMENTS:
        assert data_path(ad.log_filename(e)).read_text(encoding="utf-8") == ad.log_csv_text(e, ad.DEFAULT_SEED)


def test_loader_skips_and_counts_corrupt_records():
    for e in ad.EXPERIMENTS:
        log = ad.load_log(e)
        assert log.n_corrupt == ad.CORRUPT_PER_FILE == len(log.corrupt_lines)
        assert log.raw.shape == (ad.SAMPLES, len(ad.CHANNELS)) and log.t.shape == (ad.SAMPLES,)
        lines = data_path(ad.log_filename(e)).read_text().splitlines()
        bad = [lines[k - 1] for k in log.corrupt_lines]
        assert sum(len(b.split(",")) != 8 for b in bad) == 1
        assert sum("ERR" in b for b in bad) == 1 and sum("nan" in b for b in bad) == 1


def test_parser_counts_every_kind_of_corrupt_record():
    head = "# comment\nt,altitude_raw,acc_x,acc_y,acc_z,roll_rate,pitch_rate,yaw_rate\n"
    good = "0.00,3.335e-43,1,2,3,4,5,6\n"
    text = head + good + "0.01,3.335e-43,1\n" + "0.02,x,1,2,3,4,5,6\n" + "0.03,inf,1,2,3,4,5,6\n" \
        + "0.04,-1e-43,1,2,3,4,5,6\n" + "0.05,1.0,1,2,3,4,5,6\n" + "\n" + good
    log = ad.parse_log_csv(text, "A")
    assert log.raw.shape == (2, 7) and log.n_corrupt == 6 and log.corrupt_lines == (4, 5, 6, 7, 8, 9)
    assert log.si("altitude")[0] == 0.238


def test_generated_logs_fit_their_models_within_bounds():
    """Every non-constant channel of every committed log passes the t and chi-square tests
    against its model, at a Bonferroni-corrected level (family-wise 95 %)."""
    logs = [ad.load_log(e) for e in ad.EXPERIMENTS]
    tests = [r for log in logs for r in ad.model_tests(log).values() if r is not None]
    confidence = 1 - FAMILY_ALPHA / (2 * len(tests))
    for log in logs:
        for name, r in ad.model_tests(log, confidence).items():
            if r is None:
                model = ad.channel_model(log.experiment, name)
                assert np.all(ad.decode_altitude(log.channel(name)) * 1000 == model.mean)
            else:
                assert r.mean_ok and r.var_ok, (log.experiment, name, r)


def test_statistics_table_raw_and_si_agree():
    log = ad.load_log("C")
    raw = ad.statistics_table(log)
    si = ad.statistics_table(log, units="si")
    for c in ad.CHANNELS:
        assert np.isclose(si[c].var, ad.to_si(raw[c].var, c, variance=True), rtol=1e-9)
        assert np.isclose(si[c].mean, ad.to_si(raw[c].mean, c), rtol=1e-9)
        assert np.isclose(si[c].std ** 2, si[c].var)
    a = ad.statistics_table(ad.load_log("A"))
    assert a["altitude"].var == 0.0 and abs(a["altitude"].mean - 3.3351e-43) <= 0.5e-47


def test_outlier_options_of_the_statistics_table():
    log = ad.load_log("B")
    full = ad.statistics_table(log)
    rng_clean = ad.statistics_table(log, outliers="range")
    mad_clean = ad.statistics_table(log, outliers="mad")
    n_drop = full["altitude"].n - rng_clean["altitude"].n
    assert n_drop == np.sum(log.channel("altitude") == 0)
    assert rng_clean["acc_x"] == full["acc_x"]           # the range rule touches the altitude only
    assert mad_clean["altitude"].n == rng_clean["altitude"].n


def test_generation_is_deterministic_and_seed_dependent():
    a = ad.generate_log("C", np.random.default_rng(1), n=50)
    b = ad.generate_log("C", np.random.default_rng(1), n=50)
    c = ad.generate_log("C", np.random.default_rng(2), n=50)
    np.testing.assert_array_equal(a.raw, b.raw)
    assert not np.array_equal(a.raw, c.raw)


def test_write_logs_roundtrip(tmp_path):
    paths = ad.write_logs(tmp_path, seed=7)
    assert [p.name for p in paths] == ["ardrone_expA.csv", "ardrone_expB.csv", "ardrone_expC.csv"]
    log = ad.read_log(paths[2], "C")
    again = ad.generate_log("C", np.random.default_rng([7, 2]))
    np.testing.assert_array_equal(log.raw, again.raw)
    np.testing.assert_array_equal(log.t, again.t)


# --------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("call, name", [
    (lambda: ad.to_si(1.0, "speed"), "channel"),
    (lambda: ad.to_si(1.0, "acc_x", accel_unit="g"), "accel_unit"),
    (lambda: ad.to_si(-1.0, "acc_x", variance=True), "value"),
    (lambda: ad.decode_altitude(-1e-43), "raw"),
    (lambda: ad.decode_altitude(1.0), "raw"),
    (lambda: ad.decode_altitude(np.nan), "raw"),
    (lambda: ad.encode_altitude(-0.1), "height_m"),
    (lambda: ad.altimeter_valid([1.0], min_range=2.0, max_range=1.0), "min_range"),
    (lambda: ad.mad_outliers([1.0, np.inf]), "x"),
    (lambda: ad.mad_outliers([1.0, 2.0], threshold=0), "threshold"),
    (lambda: ad.channel_stats([1.0]), "values"),
    (lambda: ad.channel_model("D", "acc_x"), "experiment"),
    (lambda: ad.study_moments("C", units="imperial"), "units"),
    (lambda: ad.generate_log("A", np.random.default_rng(0), n=1), "n"),
    (lambda: ad.statistics_table(ad.load_log("A"), units="cgs"), "units"),
    (lambda: ad.statistics_table(ad.load_log("A"), outliers="iqr"), "outliers"),
    (lambda: ad.parse_log_csv("a,b\n1,2\n", "A"), "header"),
    (lambda: ad.parse_log_csv("# only a comment\n", "A"), "header"),
])
def test_bad_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()


def test_rng_must_be_a_generator():
    with pytest.raises(TypeError, match="rng"):
        ad.generate_log("A", 42)
