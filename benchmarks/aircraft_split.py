"""Chapter 18 judged out of sample (issue 26): tune on the training flights, score on the test flights.

1. **Train** (:func:`train`): load the training flights (``kftrack.adsb.TRAINING_FLIGHTS``, the
   seven chapter flights) and only those; tune the constant-velocity baseline on them
   (``kftrack.flighttuning.tune_baselines``: q, r by maximum likelihood, by an RMSE scan over all
   of them and by the scan per category) and name the reference baseline, the tuning with the
   lowest geometric-mean one-step RMSE on the training flights. The recipe's constants (``kftrack.aircraft``) were chosen on the same seven
   flights (its docstring, "Provenance of the constants"); nothing here changes them.
2. **Judge** (:func:`judge`): score every method on the same rows (``kftrack.aircraft.scored_rows``)
   of every flight of a set, ratios to the reference with moving-block bootstrap intervals
   (``kftrack.flightscore.evaluate``, seed 26).

Methods: the recipe; the CV filter tuned the three ways; the chapter's untuned CV
(``kftrack.aircraft.cv_predictions``: discrete sigma^2 = 0.05, R = 25 m^2, every row); the untuned
filterpy IMM of issue 15 (cached, ``data/adsb/baseline/``).

Run: ``python benchmarks/aircraft_split.py`` (about two minutes on one core); writes
``data/adsb/aircraft_split.json`` (read by chapter 18; checked by ``tests/test_aircraft_split.py``)
and ``benchmarks/aircraft_split.md`` (training table labelled as such, test table, per-category
summary, wins and losses, timings).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from kftrack import adsb
from kftrack import aircraft as A
from kftrack import flighttuning as T
from kftrack.compare import compare_runs
from kftrack.datasets import load_script
from kftrack.flightscore import category_summary, evaluate, intervals, wins_losses

HERE = Path(__file__).resolve().parent
SEED = 26


def _baseline_module():
    return load_script("adsb/baseline.py")


def train(load=None) -> T.CvTuning:
    """Tune the baselines on the training flights, read with ``load`` (default ``adsb.load_flight``)."""
    load = adsb.load_flight if load is None else load
    return T.tune_baselines([load(n) for n in adsb.TRAINING_FLIGHTS])


def methods_of(tuning: T.CvTuning, filterpy_cache: bool = True) -> dict:
    """The methods, each ``flight -> (lat_pred_deg, lon_pred_deg)``."""
    def cv(method):
        return lambda f: T.cv_tuned_predictions(f.t_s, f.lat_deg, f.lon_deg, *T.cv_params_for(tuning, method, f.name))

    out = {"recipe": lambda f: A.one_step_predictions(f.t_s, f.lat_deg, f.lon_deg)}
    out.update({m: cv(m) for m in tuning.score})
    out["CV (chapter, untuned)"] = lambda f: A.cv_predictions(f.t_s, f.lat_deg, f.lon_deg)
    if filterpy_cache:
        base = _baseline_module()
        out["filterpy IMM (untuned)"] = lambda f: base.read_cache(f.name)[1:]
    return out


def judge(tuning: T.CvTuning, names, load=None, filterpy_cache: bool = True):
    load = adsb.load_flight if load is None else load
    return evaluate([load(n) for n in names], methods_of(tuning, filterpy_cache), tuning.reference, seed=SEED)


def as_dict(scores) -> dict:
    per = []
    for i, f in enumerate(scores.flights):
        per.append({"flight": f, "category": scores.categories[i], "n_rows": int(scores.n_rows[i]),
                    "block": int(scores.block[i]),
                    "methods": {m: {"rmse_m": round(float(scores.rmse[i, j]), 2),
                                    "median_m": round(float(scores.median[i, j]), 2),
                                    "ratio": round(float(scores.ratio[i, j]), 4),
                                    "ci": [round(float(v), 4) for v in scores.ci[i, j]]}
                                for j, m in enumerate(scores.methods)}})
    summ = category_summary(scores)
    j = scores.methods.index("recipe")
    sens = {}
    for block in (50, 300):       # the reviewer's blocks: do the recipe's verdicts depend on the block?
        ci = intervals(scores, block)[:, j]
        sens[str(block)] = [int(np.sum(ci[:, 1] < 1.0)), int(np.sum(ci[:, 0] > 1.0))]
    return {"reference": scores.reference, "seed": scores.seed, "n_boot": scores.n_boot, "level": scores.level,
            "flights": per,
            "categories": {c: {m: {k: (round(v, 4) if isinstance(v, float) else v) for k, v in d.items()}
                               for m, d in s.items()} for c, s in summ.items()},
            "wins_losses": {m: list(wins_losses(scores, m)) for m in scores.methods if m != scores.reference},
            "recipe_wins_losses_fixed_block": sens}


def markdown(title: str, scores) -> str:
    ms = scores.methods
    lines = [f"### {title}", "",
             f"One-step RMSE / median error (m) on the scored rows; ratio = RMSE / RMSE of the reference "
             f"({scores.reference}) with its {scores.level:.0%} moving-block bootstrap interval "
             f"({scores.n_boot} replicates, seed {scores.seed}; block in rows).", "",
             "| flight | rows | block | " + " | ".join(ms) + " |",
             "|---|---:|---:|" + "---:|" * len(ms)]
    for i, f in enumerate(scores.flights):
        cells = []
        for j, m in enumerate(ms):
            c = f"{scores.rmse[i, j]:.0f} / {scores.median[i, j]:.0f}"
            if m != scores.reference:
                c += f" ({scores.ratio[i, j]:.2f}, {scores.ci[i, j, 0]:.2f}–{scores.ci[i, j, 1]:.2f})"
            cells.append(c)
        lines.append(f"| {f} | {scores.n_rows[i]} | {scores.block[i]} | " + " | ".join(cells) + " |")
    lines += ["", "| category | flights | " + " | ".join(f"{m}: median ratio, wins/losses" for m in ms
                                                   if m != scores.reference) + " |",
              "|---|---:|" + "---|" * (len(ms) - 1)]
    for c, s in category_summary(scores).items():
        n = next(iter(s.values()))["n"]
        lines.append(f"| {c} | {n} | " + " | ".join(f"{s[m]['median_ratio']:.2f}, {s[m]['wins']}/{s[m]['losses']}"
                                                 for m in ms if m != scores.reference) + " |")
    return "\n".join(lines) + "\n"


def spike_undo_effect(tuning, load=None) -> list:
    """Recipe RMSE with and without its spike-undo rule on every training and test flight where the
    rule can act (the stream repeats a position exactly), on the scored rows."""
    load = adsb.load_flight if load is None else load
    out = []
    for name in adsb.TRAINING_FLIGHTS + adsb.TEST_FLIGHTS:
        f = load(name)
        if not np.any((f.lat_deg[1:] == f.lat_deg[:-1]) & (f.lon_deg[1:] == f.lon_deg[:-1])):
            continue
        m = A.scored_rows(f.t_s, f.lat_deg, f.lon_deg)
        rm = []
        for undo in (True, False):
            res = A.track_flight(f.t_s, f.lat_deg, f.lon_deg, spike_undo=undo)
            rm.append(float(np.sqrt(np.mean(np.sum((res.enu_pred[m] - res.enu[m]) ** 2, axis=1)))))
        out.append({"flight": name, "split": adsb.split_of(name), "rmse_m": round(rm[0], 2),
                    "rmse_m_without": round(rm[1], 2)})
    return out


def main() -> int:
    t0 = time.perf_counter()
    tuning = train()
    t1 = time.perf_counter()
    train_scores = judge(tuning, adsb.TRAINING_FLIGHTS)
    t2 = time.perf_counter()
    test_scores = judge(tuning, adsb.TEST_FLIGHTS)
    t3 = time.perf_counter()
    undo = spike_undo_effect(tuning)
    t4 = time.perf_counter()
    j_rec, j_ref = test_scores.methods.index("recipe"), test_scores.methods.index(test_scores.reference)
    across = compare_runs(test_scores.rmse[:, j_rec], test_scores.rmse[:, j_ref], scale="log_ratio")
    out = {"tuning": {"cv_ml": {"q": tuning.ml[0], "r": tuning.ml[1], "mean_loglik": tuning.ml_loglik},
                      "cv_scan": {"q": tuning.scan[0], "r": tuning.scan[1]},
                      "cv_scan_by_category": {c: {"q": q, "r": r} for c, (q, r) in tuning.by_category.items()},
                      "training_geo_mean_rmse_m": tuning.score, "reference": tuning.reference,
                      "tuned_on": list(tuning.flights)},
           "training": as_dict(train_scores), "test": as_dict(test_scores),
           "test_recipe_vs_reference_across_flights": across.sentence("recipe", tuning.reference, "RMSE"),
           "spike_undo_effect": undo,
           "seconds": {"tuning": round(t1 - t0, 1), "training_scores": round(t2 - t1, 1),
                       "test_scores": round(t3 - t2, 1), "spike_undo": round(t4 - t3, 1)}}
    (HERE.parent / "data" / "adsb" / "aircraft_split.json").write_text(json.dumps(out, indent=1) + "\n")
    md = ["# Chapter 18 out of sample (benchmarks/aircraft_split.py)", "",
          f"Reference baseline: {tuning.reference} (training geometric-mean RMSE "
          + ", ".join(f"{k} {v:.1f} m" for k, v in tuning.score.items()) + "); "
          f"CV (ML) q = {tuning.ml[0]:.3g} m²/s³, r = {tuning.ml[1]:.4g} m²; "
          f"CV (scan) q = {tuning.scan[0]:.3g} m²/s³, r = {tuning.scan[1]:.3g} m²; per category "
          + ", ".join(f"{c} q = {q:.3g}, r = {r:.3g}" for c, (q, r) in tuning.by_category.items()) + ".", "",
          markdown("Training flights (in-sample: the recipe's constants were chosen on them)", train_scores),
          markdown("Test flights (out of sample)", test_scores),
          "Across the test flights: " + out["test_recipe_vs_reference_across_flights"], "",
          "Spike-undo rule (designed on belevingsvlucht), recipe RMSE with / without it on the flights where it "
          "can act: " + "; ".join(f"{u['flight']} ({u['split']}) {u['rmse_m']:.2f} / {u['rmse_m_without']:.2f} m"
                                  for u in undo), "",
          f"Time: tuning {t1 - t0:.0f} s, training scores {t2 - t1:.0f} s, test scores {t3 - t2:.0f} s."]
    (HERE / "aircraft_split.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
