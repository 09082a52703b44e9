"""Issue 28: benchmarks/multitarget.py (kftrack against Stone Soup on radar scans of real traffic)
regenerates the committed data/multitarget/benchmark.json: its quick figures, its structure, and
the summary figures follow from the stored per-run values."""
from __future__ import annotations

import datetime
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("multitarget_bench", ROOT / "benchmarks" / "multitarget.py")
    mod = importlib.util.module_from_spec(spec)
    old, sys.dont_write_bytecode = sys.dont_write_bytecode, True
    try:
        spec.loader.exec_module(mod)
    finally:
        sys.dont_write_bytecode = old
    return mod


@pytest.fixture(scope="module")
def bench():
    return _bench()


@pytest.fixture(scope="module")
def stored():
    return json.loads((ROOT / "data" / "multitarget" / "benchmark.json").read_text())


# ---------------------------------------------------------------- the peer's models are kftrack's
def test_stonesoup_models_equal_kftrack_models(bench):
    # Same F, Q (continuous white-acceleration PSD q per axis) and h, with the measurement order
    # swapped; closed forms of O(1e4) numbers: agreement to 1e-9 relative.
    from stonesoup.types.state import State

    from kftrack.models import ConstantVelocity
    from kftrack.sensors.radar import RangeBearing

    radar = RangeBearing(sigmas=(50.0, np.deg2rad(0.1)))
    trans, meas = bench.stonesoup_models(radar, q=5.0)
    cv = ConstantVelocity(ndim=2, q=5.0)
    for dt in (0.7, 4.8, 30.0):
        td = datetime.timedelta(seconds=dt)
        np.testing.assert_allclose(trans.matrix(time_interval=td), cv.F(dt), rtol=1e-12, atol=0)
        np.testing.assert_allclose(trans.covar(time_interval=td), cv.Q(dt), rtol=1e-12, atol=0)
    np.testing.assert_allclose(np.asarray(meas.covar(), float), np.diag(np.square(radar.sigmas))[::-1, ::-1])
    x = np.array([-30e3, 120.0, 4e3, -80.0])   # west of the radar: bearing near pi
    z_ss = np.asarray(meas.function(State(x.reshape(4, 1))), float).ravel()
    np.testing.assert_allclose(z_ss[::-1], radar.h(x), rtol=1e-12)


def test_detections_carry_their_own_times(bench):
    from kftrack.sensors.surveillance import Scan
    from kftrack.sensors.radar import RangeBearing

    _, meas = bench.stonesoup_models(RangeBearing(sigmas=(50.0, 0.002)), q=1.0)
    scan = Scan(10.0, np.array([10.5, 12.25]), np.array([[20e3, 0.3], [40e3, -3.0]]), np.array([0, -1]))
    dets = bench.stonesoup_detections(scan, meas)
    assert [bench._seconds(d.timestamp) for d in dets] == [10.5, 12.25]
    assert [float(d.state_vector[1, 0]) for d in dets] == [20e3, 40e3]      # (bearing, range) order
    np.testing.assert_allclose([d.metadata["txyr"][1] for d in dets], [20e3 * np.cos(0.3), 40e3 * np.cos(-3.0)])


# ---------------------------------------------------------------- the committed file
def test_quick_figures_reproduce(bench, stored):
    # The reduced run (two paired runs of a few scans, all three methods, and the aligned runs) is
    # deterministic: seeded scans, no timing in it. Same code, same numbers: GOSPA sums over a few
    # dozen targets of O(1e3) m, so round-off of another BLAS stays below 1e-6 relative.
    window, radar, cfg = bench.setup()
    got = json.loads(json.dumps(bench.quick_figures(window, radar, cfg), default=float))
    want = stored["quick"]
    assert got["mode"] == want["mode"]

    def close(a, b, path):
        if isinstance(b, dict):
            assert set(a) == set(b), path
            for k in b:
                close(a[k], b[k], f"{path}/{k}")
        elif isinstance(b, list):
            assert len(a) == len(b), path
            for i, (x, y) in enumerate(zip(a, b)):
                close(x, y, f"{path}[{i}]")
        elif isinstance(b, float):
            assert a == pytest.approx(b, rel=1e-6, abs=1e-6), path
        else:
            assert a == b, path

    close(got, want, "quick")


def test_stored_structure_and_summaries(bench, stored):
    for key in ("settings", "radar", "gospa", "quick", "runs", "timeline", "comparison", "aligned", "pregate",
                "initiation_training", "scaling", "jpda_12x12", "provenance"):
        assert key in stored, key
    prov = stored["provenance"]
    assert prov["stonesoup"] == __import__("stonesoup").__version__
    for k in ("date_utc", "kftrack", "numpy", "load_average_before", "load_average_after", "cpus"):
        assert k in prov
    # the comparison follows from the stored per-run values (same function)
    again = json.loads(json.dumps(bench.compare(stored["runs"]), default=float))
    for m, v in stored["comparison"].items():
        for k, w in v.items():
            if isinstance(w, float):
                assert again[m][k] == pytest.approx(w, rel=1e-9), (m, k)
            else:
                assert again[m][k] == w, (m, k)
    # the fitted exponent follows from the stored rows
    rows = stored["scaling"]["rows"]
    lx = np.log([r["N"] for r in rows])
    for m, b in stored["scaling"]["exponent"].items():
        assert np.polyfit(lx, np.log([r[m] for r in rows]), 1)[0] == pytest.approx(b, rel=1e-9)
    # the pre-gate changed no track state (it only drops pairs the gate would reject)
    for m, v in stored["pregate"].items():
        assert v["max_state_difference"] == 0.0, m
    # the committed table is the one the stored figures give
    assert bench.markdown(stored) == (ROOT / "benchmarks" / "multitarget.md").read_text()


# ---------------------------------------------------------------- command line and the pre-gate's audit
def test_arguments_are_parsed_before_anything_runs(bench, stored, capsys):
    # --help and an unknown argument stop in argparse (SystemExit) before any computation or file write
    with pytest.raises(SystemExit) as e:
        bench.main(["--help"])
    assert e.value.code == 0 and "--gnn-runs" in capsys.readouterr().out
    for bad in (["--bogus"], ["--runs", "1"], ["--gnn-runs", "x"]):
        with pytest.raises(SystemExit) as e:
            bench.main(bad)
        assert e.value.code == 2, bad
    # the stored provenance is the command that reproduces the committed file (from the parsed arguments)
    mode = stored["mode"]
    args = bench.parse_args(["--runs", str(mode["runs"]), "--gnn-runs", str(mode["gnn_runs"]),
                             "--phd-runs", str(mode["phd_runs"])])
    assert stored["provenance"]["command"] == bench._command(args)
    assert bench.parse_args([]).out == bench.OUT_JSON


def test_pregate_audit_statistic_is_stonesoups_gate_distance(bench):
    # The audit's d^2 of a dropped pair equals the squared Mahalanobis distance Stone Soup's
    # DistanceHypothesiser compares with its gate (EKF prediction to the detection's time, closed-form
    # Jacobian): the same closed forms, agreement to 1e-9 relative.
    from stonesoup.measures import SquaredMahalanobis
    from stonesoup.types.state import GaussianState

    from kftrack.sensors.radar import RangeBearing

    sensor = RangeBearing(sigmas=(50.0, np.deg2rad(0.1)), sensor=(1000.0, -2000.0))
    cfg = dict(sensor=sensor, q=5.0, P_G=0.99, exact_jacobian=True)
    _, meas, predictor, updater = bench._ss_components(cfg)
    x = np.array([30e3, 150.0, 20e3, -60.0])
    P = np.diag([400.0 ** 2, 20.0 ** 2, 300.0 ** 2, 15.0 ** 2])
    P[0, 2] = P[2, 0] = 0.3 * 400.0 * 300.0
    state = GaussianState(x.reshape(4, 1), P, timestamp=bench._stamp(100.0))
    scan = __import__("kftrack.sensors.surveillance", fromlist=["Scan"]).Scan(
        101.0, np.array([101.3, 102.1]), np.array([[37e3, 0.61], [36.1e3, 0.66]]), np.array([-1, -1]))
    dets = bench.stonesoup_detections(scan, meas)
    want = []
    for d in dets:
        mp = updater.predict_measurement(predictor.predict(state, timestamp=d.timestamp), measurement_model=meas)
        want.append(float(SquaredMahalanobis()(mp, d)))
    pg = bench._wrap(None, cfg, True)
    for d, w in zip(dets, want):
        bench.reset_pregate_audit()
        meta = np.array([d.metadata["txyr"]])
        pg.audit(x, P, meta, meta[:, 0] - 100.0)
        assert bench.PREGATE_AUDIT["dropped"] == 1
        assert bench.PREGATE_AUDIT["min_d2_over_gate"] * pg.gate == pytest.approx(w, rel=1e-9)
        assert bench.PREGATE_AUDIT["dropped_inside_gate"] == int(w <= pg.gate)
    assert min(want) < pg.gate < max(want)      # one pair inside the gate, one outside: both branches
    bench.reset_pregate_audit()


def test_stored_audit_exponent_bounds_and_aligned_phd(bench, stored):
    # every pair the pre-gate dropped in the whole Monte Carlo lies outside the hypothesiser's gate
    au = stored["pregate_audit"]
    assert au["dropped"] > 0 and au["dropped_inside_gate"] == 0 and au["min_d2_over_gate"] > 1.0
    assert au["runs"] == {"gnn": stored["mode"]["gnn_runs"], "jpda": stored["mode"]["runs"],
                          "phd": stored["mode"]["phd_runs"]}
    # the exponent's one-sided bound follows from the stored rows (the function the chapter's numbers come from)
    again = bench.exponent_fit(stored["scaling"]["rows"])
    for m in ("gnn", "jpda"):
        assert again["exponent_upper_one_sided_95"][m] == pytest.approx(
            stored["scaling"]["exponent_upper_one_sided_95"][m], rel=1e-9)
        assert again["exponent_upper_one_sided_95"][m] > again["exponent"][m]
    ap = stored["aligned_phd"]
    for k in ("kftrack_gospa", "stonesoup_gospa", "max_abs_gospa_difference", "max_abs_cardinality_difference",
              "max_state_position_difference_m"):
        assert np.isfinite(ap[k]), k


def test_stored_initiation_training(bench, stored):
    # kftrack's initiation memory: the tracker's default is the value the benchmark uses and stores, chosen
    # on a training split disjoint from the Monte Carlo's scans (other seeds, a later part of the recording)
    import inspect

    from kftrack.compare import compare_runs
    from kftrack.multitarget import MultiTargetTracker

    it = stored["initiation_training"]
    default = inspect.signature(MultiTargetTracker).parameters["candidate_scans"].default
    assert it["used"] == stored["settings"]["candidate_scans"] == bench.SETTINGS["candidate_scans"] == default
    mode = stored["mode"]
    assert it["seed"] != stored["seed"]
    assert it["t_start"] >= mode["t_start"] + mode["n_scans"] * stored["radar"]["period_s"]
    assert {k: it[k] for k in ("t_start", "n_scans", "runs", "seed")} == {k: bench.TRAIN[k] for k in ("t_start", "n_scans",
                                                                                                      "runs", "seed")}
    # the paired ratios follow from the stored per-run values (same function), and the chosen value is the
    # one the training split supports: lower GOSPA than a one-scan memory, equivalent to a three-scan one
    for key, v in it["paired"].items():
        a, b = key.split("/")
        r = compare_runs(np.array(it["gospa"][a]), np.array(it["gospa"][b]), scale="log_ratio", margin=0.02)
        assert r.estimate == pytest.approx(v["ratio"], rel=1e-12) and r.verdict == v["verdict"], key
    assert it["paired"]["2/1"]["verdict"] == "lower" and it["paired"]["3/2"]["verdict"].startswith("equivalent")
