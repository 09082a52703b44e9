"""kftrack: the package behind the course-book *Kalman filtering for tracking*.

Every module is reachable from the package, ``import kftrack; kftrack.kalman.kalman_filter(...)``,
and is imported on first use (PEP 562): ``import kftrack`` itself imports none of them, so none of
JAX, SymPy or matplotlib. SymPy comes with :mod:`~kftrack.symbolic`, :mod:`~kftrack.models`,
:mod:`~kftrack.frenet`, :mod:`~kftrack.slam`, :mod:`~kftrack.sensors.radar` and the modules that
import them (:mod:`~kftrack.scenarios`, :mod:`~kftrack.multitarget`); matplotlib only inside the functions of
:mod:`~kftrack.plotting`; JAX only when a filter is given JAX arrays. JAX is optional (the
``[jax]`` extra, ``pip install ".[jax]"``): without it every function runs on NumPy arrays.

The modules by layer, lowest first. A module imports only from its own layer and the layers
below it, with one exception: :mod:`~kftrack.sensors.ardrone` finds its log files with
:mod:`~kftrack.datasets`. ``kftrack._validate`` (private: the input checks shared by the public
functions) sits below them all.

Numerics: pure functions and small immutable results.

- :mod:`kftrack.kalman` -- the linear Kalman filter: predict, update, ``kalman_filter``, ``rts_smoother``, ``KalmanStepper``.
- :mod:`kftrack.ekf` -- the extended Kalman filter, with angle-aware residuals.
- :mod:`kftrack.ukf` -- the unscented transform and the unscented Kalman filter.
- :mod:`kftrack.imm` -- interacting multiple models (IMM, GPB1, clairvoyant filter) and Kim's IMM smoother.
- :mod:`kftrack.particle` -- particle filters: bootstrap, optimal proposal, jump-Markov.
- :mod:`kftrack.resampling` -- resampling schemes for particle filters (multinomial, stratified, systematic, residual).
- :mod:`kftrack.steady` -- steady-state gains (Riccati equations), alpha-beta filters and the frequency view.
- :mod:`kftrack.discretize` -- continuous to discrete: Van Loan's method.
- :mod:`kftrack.gaussians` -- Gaussian densities, products, the 1-D update and sample-moment checks.
- :mod:`kftrack.metrics` -- RMSE, NEES, NIS, ANEES, chi-square bounds and the PCRLB.
- :mod:`kftrack.adaptive` -- NIS-based manoeuvre detection and process-noise adaptation.
- :mod:`kftrack.tuning` -- noise parameters by maximum likelihood (innovation log-likelihood and its gradient).
- :mod:`kftrack.association` -- gates, nearest neighbour, PDAF, IMM-PDAF, GNN, JPDA and the GOSPA/OSPA metrics.
- :mod:`kftrack.phd` -- the Gaussian-mixture PHD filter: birth, pruning, merging, state extraction.
- :mod:`kftrack.trackeval` -- GOSPA over time and track-level metrics: breaks, switches, false and missed tracks.
- :mod:`kftrack.trackmanagement` -- track initiation, M-of-N confirmation, track score and lost tracks.
- :mod:`kftrack.scanmatch` -- planar rigid transforms and ICP scan matching.
- :mod:`kftrack.montecarlo` -- Monte Carlo comparison of several filters on one scenario.
- :mod:`kftrack.compare` -- a paired comparison of two methods with its interval and verdict.
- :mod:`kftrack.kernels` -- the unchecked predict/update/mixing kernels (array API), one home for the equations.
- :mod:`kftrack.engines` -- the two time-loop drivers: a Python loop for NumPy, ``jax.lax.scan`` for JAX.
- :mod:`kftrack.parallel` -- the linear Kalman filter and RTS smoother parallel in time (prefix scans, JAX).
- ``kftrack.results`` -- the result types of the whole-sequence filters and smoothers.

Models: what moves and what is measured.

- :mod:`kftrack.models` -- constant velocity, constant acceleration, Singer, known and coordinated turns, 3-D turns.
- :mod:`kftrack.symbolic` -- SymPy derivations of the motion models and the code generated from them.
- :mod:`kftrack.frenet` -- curves in space: the Frenet-Serret frame, curvature, torsion, a trajectory simulator.
- ``kftrack.sensors`` -- sensor models and sensor data, one module per sensor family:
- :mod:`kftrack.sensors.radar` -- radar measurements: 2-D range-bearing, 3-D range-azimuth-elevation.
- :mod:`kftrack.sensors.lidar` -- a floor plan of walls and a simulated 2-D LIDAR (ray casting).
- :mod:`kftrack.sensors.gps` -- NMEA 0183 sentences and logs, and the geodesy from fixes to metres.
- :mod:`kftrack.sensors.ardrone` -- the Parrot AR.Drone's sensors: units, altimeter format, statistics, logs.
- :mod:`kftrack.sensors.surveillance` -- a simulated rotating surveillance radar over recorded traffic: scans of plots.
- :mod:`kftrack.clutter` -- what a sensor reports each scan: detections with probability ``P_D`` and Poisson clutter.
- :mod:`kftrack.attitude` -- drone pitch, roll and height from an IMU and an altimeter.
- :mod:`kftrack.gpsfusion` -- fusing GPS receivers: the speed-heading model, stacked and weighted fusion.
- :mod:`kftrack.slam` -- robot localization and EKF-SLAM in the plane.
- :mod:`kftrack.multitarget` -- many targets in clutter: GNN, cluster JPDA or GM-PHD on a radar's scans, with track initiation, confirmation and deletion.

Worlds: seeded scenarios and recorded data.

- :mod:`kftrack.scenarios` -- seeded worlds that return a true trajectory and its measurements.
- :mod:`kftrack.datasets` -- where the data files are, wherever the package is installed (used by every loader).
- :mod:`kftrack.gpstrack` -- the athletics-track world of chapter 13 and its NMEA logs.
- :mod:`kftrack.adsb` -- recorded ADS-B flights and the geodetic-to-local conversion.
- :mod:`kftrack.aircraft` -- tracking recorded aircraft (chapter 18): the causal one-step-prediction recipe.
- :mod:`kftrack.flighttuning` -- baselines for recorded flights tuned on the training flights only (chapter 18).
- :mod:`kftrack.flightscore` -- every tracking method scored on the same rows of recorded flights, with block-bootstrap ratios.

Presentation: figures and tables.

- :mod:`kftrack.plotting` -- the book's matplotlib style, covariance ellipses and track plots.
- :mod:`kftrack.tables` -- tables that show as HTML on the page and as aligned text elsewhere.
"""
from __future__ import annotations

import importlib

__version__ = "0.2.0"  # the single source: pyproject.toml reads it (tool.setuptools.dynamic)

#: Every public module, imported on first attribute access.
_MODULES = (
    "kalman", "ekf", "ukf", "imm", "particle", "resampling", "steady", "discretize", "gaussians", "metrics",
    "adaptive", "tuning", "association", "phd", "trackeval", "trackmanagement", "multitarget", "scanmatch", "montecarlo", "compare", "kernels",
    "engines", "parallel", "results",
    "models", "symbolic", "frenet", "sensors", "clutter", "attitude", "gpsfusion", "slam",
    "scenarios", "datasets", "gpstrack", "adsb", "aircraft", "flighttuning", "flightscore",
    "plotting", "tables",
)

__all__ = sorted(_MODULES)


def lazy_modules(package: str, names: tuple, namespace: dict):
    """``(__getattr__, __dir__)`` of a package whose submodules ``names`` are imported on first
    use (PEP 562); ``namespace`` is the package's ``globals()``. Used here and by ``kftrack.sensors``."""

    def getattr_(name: str):
        if name in names:
            return importlib.import_module(f"{package}.{name}")
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return getattr_, lambda: sorted(set(namespace) | set(names))


__getattr__, __dir__ = lazy_modules(__name__, _MODULES, globals())
