r"""Scenarios: seeded worlds that produce a true trajectory and its measurements.

Worlds layer: imports numerics and models from below, never plotting. Every simulated
scenario is a function that takes ``rng: np.random.Generator`` and returns a
:class:`Scenario` ``(t, truth, z)`` with **time first**:

* ``t``: ``(T,)`` times in seconds;
* ``truth``: ``(T, ..., n)`` true states, state order interleaved by axis (``[x, vx]``,
  ``[x, vx, ax, y, vy, ay]``, ...), SI units;
* ``z``: ``(T, ..., m)`` measurements.

With ``runs=N`` the batch axis holds ``N`` independent Monte Carlo runs (``(T, N, ...)``), so
one call of :func:`kftrack.kalman.kalman_filter` filters them all.

The module also keeps the **printed record of the source studies**: their parameters, the
measurements they print and the numbers they report, transcribed once here, with
:func:`printed` turning a printed number into a value and the tolerance its printed digits
allow (half a unit in the last digit).

Seed 003 (Costa 2023, *Monitoramento e predição de sistemas autônomos*, §2.2.3 and §2.3.2):

* :data:`COSTA2023_CAR`, :func:`car_radar`: a car receding from a radar, 1-D, measured every
  second (a random-walk Kalman filter in the study);
* :data:`COSTA2023_ROBOT`, :func:`robot_truth`, :func:`robot`: a robot in the plane on
  :math:`x_n = 15 + 5n`, :math:`y = 2^{x/30}` (our reconstruction of the study's path), with
  direct position fixes.

Chapter 6 (curves in space): :class:`ManoeuvreScenario` tracks with manoeuvre labels, built
with :func:`kftrack.frenet.simulate`: seed 000's drone scenarios (:func:`drone_scenario`),
seed 001's zig-zag in a tilted plane (:func:`tilted_zigzag`), :func:`climbing_helix`,
:func:`torsion_manoeuvre`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping, NamedTuple

import numpy as np

from . import frenet as _fr
from . import slam as _slam
from ._validate import as_float_array, check_finite, check_rng, finite_scalar, positive_scalar
from .ekf import wrap_angle as _wrap_angle

__all__ = [
    "Scenario", "Printed", "printed", "CarRadarStudy", "RobotStudy", "COSTA2023_CAR",
    "COSTA2023_ROBOT", "car_radar", "robot_truth", "robot",
    "ManoeuvreScenario", "DroneScenario", "MARTINS2018_SCENARIOS", "drone_scenario", "tilted_zigzag",
    "climbing_helix", "torsion_manoeuvre",
    "floor_plan", "drive", "apartment_loop", "ring_landmarks", "SlamScenario", "slam_loop",
]


class Scenario(NamedTuple):
    """A simulated world, time first.

    Attributes
    ----------
    t : (T,) sample times (s).
    truth : (T, ..., n) true states (interleaved order, SI units).
    z : (T, ..., m) measurements.
    """

    t: np.ndarray
    truth: np.ndarray
    z: np.ndarray


# --------------------------------------------------------------------------------------------
# printed numbers of the source studies
# --------------------------------------------------------------------------------------------
class Printed(NamedTuple):
    """A number (or array) as a study printed it.

    Attributes
    ----------
    value : the printed value; NaN where the study printed nothing.
    tol : half a unit in the last printed digit (``"0.9412"`` -> ``5e-5``); NaN where missing.
    """

    value: np.ndarray
    tol: np.ndarray

    def agrees(self, computed) -> np.ndarray:
        """True where ``|computed - value| <= tol`` (and where nothing was printed)."""
        computed = np.asarray(computed, dtype=float)
        if computed.shape != self.value.shape:
            raise ValueError(f"computed must have the printed shape {self.value.shape}, got shape {computed.shape}")
        ok = np.abs(computed - self.value) <= self.tol * (1.0 + 1e-9)
        return ok | np.isnan(self.value)


def _one_printed(text: str) -> tuple[float, float]:
    if not isinstance(text, str):
        raise TypeError(f"printed numbers must be given as text, got {type(text).__name__} {text!r}")
    s = text.strip()
    if s == "":
        return np.nan, np.nan
    try:
        value = float(s)
    except ValueError:
        raise ValueError(f"printed number must look like '12.34' (dot decimal), got {text!r}") from None
    mantissa = s.lower().split("e")[0]
    decimals = len(mantissa.split(".")[1]) if "." in mantissa else 0
    exponent = int(s.lower().split("e")[1]) if "e" in s.lower() else 0
    return value, 0.5 * 10.0 ** (exponent - decimals)


def printed(text) -> Printed:
    """Parse a printed number, or a nested list of them, into a :class:`Printed`.

    ``""`` marks an entry the study left blank. The tolerance is half a unit in the last
    printed digit: ``printed("0.941")`` has ``tol = 5e-4``; ``printed("12.9")`` has ``0.05``.
    """
    arr = np.asarray(text, dtype=object)
    pairs = [_one_printed(s) for s in arr.ravel()]
    value = np.array([p[0] for p in pairs], dtype=float).reshape(arr.shape)
    tol = np.array([p[1] for p in pairs], dtype=float).reshape(arr.shape)
    return Printed(value, tol)


def _frozen(obj):
    """Read-only copy: dicts become mapping proxies, lists become tuples, recursively."""
    if isinstance(obj, dict):
        return MappingProxyType({k: _frozen(v) for k, v in obj.items()})
    if isinstance(obj, (list, tuple)):
        return tuple(_frozen(v) for v in obj)
    return obj


# --------------------------------------------------------------------------------------------
# seed 003: the car and the radar (Costa 2023, §2.2.3)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CarRadarStudy:
    """The 1-D worked example of Costa (2023, §2.2.3), as printed.

    A random-walk (position-only) Kalman filter: ``x_{n+1,n} = x_{n,n}``,
    ``p_{n+1,n} = p_{n,n} + q``. Steps 4 to 11 are not printed.

    Attributes
    ----------
    dt : sampling interval (s).
    x0, p0 : initial estimate (m) and its variance (m²), :math:`\\hat x_{0,0}`, :math:`p_{0,0}`.
    q : process-noise **variance** per step (m²); the study calls it an "uncertainty from 0 to 1".
    r : measurement **variance** (m², so sigma = 0.1 m); the study calls it "1 % error".
    z : printed measurements (m) by step ``n``.
    printed : printed texts: ``p_1_0``, ``x_12_11`` and, by step, ``K``, ``x_post``
        (:math:`\\hat x_{n,n}`), ``p_post``, ``x_pred`` (:math:`\\hat x_{n+1,n}`), ``p_pred``.
    """

    dt: float = 1.0
    x0: float = 10.0
    p0: float = 10_000.0
    q: float = 0.15
    r: float = 0.01
    z: Mapping[int, float] = field(default_factory=lambda: _frozen(
        {1: 49.732, 2: 59.781, 3: 68.545, 12: 161.131}))
    printed: Mapping[str, object] = field(default_factory=lambda: _frozen({
        "p_1_0": "10000.15",
        "x_12_11": "150.170",
        "K": {1: "0.999999", 2: "0.9412", 3: "0.941", 12: "0.941"},
        "x_post": {1: "49.732", 2: "59.190", 3: "67.993", 12: "160.484"},
        "p_post": {1: "0.01", 2: "0.0094", 3: "0.0094", 12: "0.0094"},
        "x_pred": {1: "49.732", 2: "59.190", 3: "67.993", 12: "160.484"},
        "p_pred": {1: "0.16", 2: "0.1594", 3: "0.1594", 12: "0.1594"},
    }))

    @property
    def speed(self) -> float:
        """Mean speed implied by the first and last printed measurements (m/s), about 10.13."""
        return (self.z[12] - self.z[1]) / (11 * self.dt)


#: The printed record of Costa (2023), §2.2.3.
COSTA2023_CAR = CarRadarStudy()


def _count(value, name: str, allow_none: bool = False) -> int | None:
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer{' or None' if allow_none else ''}, got {value!r}")
    return int(value)


def _noisy(rng: np.random.Generator, clean: np.ndarray, sigma: float, runs: int | None) -> np.ndarray:
    check_rng(rng)
    shape = clean.shape[:1] + (() if runs is None else (runs,)) + clean.shape[1:]
    noise = sigma * rng.standard_normal(shape)
    return (clean if runs is None else clean[:, None]) + noise


def _batch(truth: np.ndarray, runs: int | None) -> np.ndarray:
    if runs is None:
        return truth
    return np.repeat(truth[:, None], runs, axis=1)


def car_radar(rng: np.random.Generator, n_steps: int = 30, *, sigma: float = 0.1,
              start: float | None = None, speed: float | None = None, dt: float = 1.0,
              runs: int | None = None) -> Scenario:
    """A car receding from a radar at constant speed, range measured with Gaussian noise.

    Our reconstruction of Costa (2023, §2.2.3): by default the car is at the first printed
    measurement (49.732 m) at step 1 and keeps the mean speed of the printed measurements
    (:attr:`CarRadarStudy.speed`, about 10.13 m/s); the noise is the study's ``r = 0.01 m²``.

    Parameters
    ----------
    rng : random generator.
    n_steps : number of measurements ``T``, at ``t = dt, 2 dt, ..., T dt``.
    sigma : standard deviation of the range noise (m).
    start, speed : position (m) at the first step and speed (m/s); default from the study.
    dt : sampling interval (s).
    runs : if given, that many independent noise realisations on a batch axis.

    Returns
    -------
    Scenario
        ``t`` ``(T,)``; ``truth`` ``(T[, runs], 2)`` as ``[x, vx]``; ``z`` ``(T[, runs], 1)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.scenarios import car_radar
    >>> sc = car_radar(np.random.default_rng(0), n_steps=30)      # t, truth [x, vx], z (range)
    >>> sc.t.shape, sc.truth.shape, sc.z.shape
    ((30,), (30, 2), (30, 1))
    >>> car_radar(np.random.default_rng(0), runs=100).z.shape     # 100 noise runs on a batch axis
    (30, 100, 1)
    """
    n_steps = _count(n_steps, "n_steps")
    runs = _count(runs, "runs", allow_none=True)
    sigma, dt = positive_scalar(sigma, "sigma"), positive_scalar(dt, "dt")
    x1 = COSTA2023_CAR.z[1] if start is None else finite_scalar(start, "start")
    v = COSTA2023_CAR.speed if speed is None else finite_scalar(speed, "speed")
    t = dt * np.arange(1, n_steps + 1)
    truth = np.stack([x1 + v * (t - t[0]), np.full(n_steps, v)], axis=-1)
    z = _noisy(rng, truth[:, :1], sigma, runs)
    return Scenario(t, _batch(truth, runs), z)


# --------------------------------------------------------------------------------------------
# seed 003: the robot in the plane (Costa 2023, §2.3.2)
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RobotStudy:
    """The 2-D constant-acceleration worked example of Costa (2023, §2.3.2), as printed.

    State order ``[x, vx, ax, y, vy, ay]`` (the only order that reproduces the printed
    numbers; it is also the book's interleaved order). ``F`` and ``Q`` are the discrete
    Wiener-process acceleration model with ``sigma2 = sigma_a**2``, ``H`` picks ``x`` and ``y``.

    Attributes
    ----------
    dt : sampling interval (s).
    sigma_a : standard deviation of the acceleration increment per step (m/s²) that reproduces
        the printed numbers; ``sigma_a_stated_later`` is the 0.2 m/s² of a later sentence.
    sigma_m : measurement standard deviation the filter assumes (m); ``R = sigma_m² I``.
    p0 : initial variance of every state, ``P_{0,0} = p0 I``; the initial state is zero.
    z : printed measurements ``(x, y)`` (m) by step.
    printed : printed texts of ``P_1_0``, ``K_1``, ``w_1_1``, ``P_1_1``, ``w_2_1``, ``P_2_1``,
        ``K_2``, ``w_2_2``, ``P_2_2``, ``w_3_2``, ``P_3_2``, ``K_35``, ``w_35_35``, ``P_35_35``,
        ``w_36_35``, ``P_36_35``, as the full printed vectors and matrices (``""`` = blank).
    """

    dt: float = 1.0
    sigma_a: float = 0.1
    sigma_a_stated_later: float = 0.2
    sigma_m: float = 3.0
    p0: float = 500.0
    z: Mapping[int, tuple[float, float]] = field(default_factory=lambda: _frozen(
        {1: (19.5, 2.08), 2: (25.24, 1.92), 35: (189.02, 80.72)}))
    printed: Mapping[str, object] = field(default_factory=lambda: _frozen(_ROBOT_PRINTED))


def _blk(a: list[list[str]], b: list[list[str]] | None = None) -> list[list[str]]:
    """A 6x6 printed matrix from its printed x block ``a`` and y block ``b`` (zeros elsewhere)."""
    b = a if b is None else b
    z3 = ["0"] * 3
    return [row + z3 for row in a] + [z3 + row for row in b]


def _with(matrix: list[list[str]], entries: dict[tuple[int, int], str]) -> list[list[str]]:
    """A printed matrix with some entries replaced (stray or blank entries of the print)."""
    out = [list(row) for row in matrix]
    for (i, j), text in entries.items():
        out[i][j] = text
    return out


def _gain(col: list[str]) -> list[list[str]]:
    return [[c, "0"] for c in col] + [["0", c] for c in col]


_ROBOT_PRINTED = {
    "P_1_0": _blk([["1125.0025", "750.005", "250.005"], ["750.005", "1000.01", "500.01"],
                   ["250.005", "500.01", "500.01"]]),
    "K_1": _gain(["0.9921", "0.6614", "0.2205"]),
    "w_1_1": ["19.35", "12.9", "4.3", "2.06", "1.38", "0.46"],
    "P_1_1": _blk([["8.93", "5.95", "1.98"], ["5.95", "503.97", "334.66"], ["1.98", "334.66", "444.89"]]),
    "w_2_1": ["34.39", "17.2", "4.3", "3.67", "1.83", "0.46"],
    "P_2_1": _blk([["972.68", "1236.35", "559.1"], ["1236.35", "1618.2", "779.57"], ["559.1", "779.57", "444.9"]],
                  [["972.68", "1236.36", "559.1"], ["1236.35", "1618.2", "779.57"], ["559.1", "779.57", "444.9"]]),
    "K_2": _gain(["0.9908", "1.2594", "0.5695"]),
    "w_2_2": ["25.32", "5.67", "-0.91", "1.94", "-0.37", "-0.54"],
    "P_2_2": _blk([["8.92", "11.33", "5.13"], ["11.33", "61.1", "75.42"], ["5.13", "75.42", "126.48"]]),
    "w_3_2": ["30.54", "4.76", "-0.91", "1.3", "-0.9", "-0.54"],
    "P_3_2": _with(_blk([["204.86", "253.94", "143.79"], ["253.94", "338.43", "201.91"],
                         ["143.79", "201.91", "126.49"]]),
                   {(3, 0): "0.01", (3, 1): "0.01", (4, 0): "0.01", (4, 1): "0.01"}),  # stray entries
    "K_35": _gain(["0.4747", "0.1515", "0.0242"]),
    "w_35_35": ["189.55", "4.76", "-0.04", "79.19", "8.07", "0.56"],
    "P_35_35": _blk([["4.27", "1.36", "0.22"], ["1.36", "0.74", "0.17"], ["0.22", "0.17", "0.05"]],
                    [["4.27", "1.37", "0.22"], ["1.36", "0.74", "0.17"], ["0.22", "0.16", "0.05"]]),
    "w_36_35": ["194.29", "4.72", "-0.04", "87.55", "8.64", "0.56"],
    "P_36_35": _with(_blk([["8.13", "2.59", "0.410"], ["2.59", "1.13", "0.230"], ["0.41", "0.23", "0.060"]],
                          [["8.14", "2.6", "0.42"], ["2.59", "1.13", "0.23"], ["0.41", "0.23", "0.06"]]),
                     {(0, 5): "", (1, 5): "", (2, 5): ""}),  # the last column of the x rows is blank
}

#: The printed record of Costa (2023), §2.3.2.
COSTA2023_ROBOT = RobotStudy()

_LN2_30 = np.log(2.0) / 30.0


def robot_truth(t) -> np.ndarray:
    r"""True state of the robot of Costa (2023, §2.3.2) at times ``t`` (s): our reconstruction.

    The path is :math:`x(t) = 15 + 5t`, :math:`y = 2^{x/30}`, so :math:`v_x = 5`,
    :math:`a_x = 0`, :math:`v_y = 5 \ln 2/30\; y`, :math:`a_y = (5 \ln 2/30)^2\, y`.
    It matches the three printed measurements to about 1 m and the printed estimate
    :math:`\hat w_{35,35}` to about 0.5 m.

    Parameters
    ----------
    t : (...) times (s); step ``n`` of the study is ``t = n``.

    Returns
    -------
    (..., 6) states ``[x, vx, ax, y, vy, ay]`` (m, m/s, m/s²).
    """
    t = check_finite(as_float_array(t, "t"), "t")
    x = 15.0 + 5.0 * t
    y = 2.0 ** (x / 30.0)
    rate = 5.0 * _LN2_30
    return np.stack([x, np.full_like(x, 5.0), np.zeros_like(x), y, rate * y, rate**2 * y], axis=-1)


def robot(rng: np.random.Generator, n_steps: int = 35, *, sigma: float = 3.0, dt: float = 1.0,
          runs: int | None = None) -> Scenario:
    """The robot of :func:`robot_truth` with position fixes ``z = (x, y) + N(0, sigma² I)``.

    Parameters
    ----------
    rng : random generator.
    n_steps : number of fixes ``T`` at ``t = dt, ..., T dt`` (the study shows steps 1 to 35).
    sigma : measurement standard deviation (m); the study states 3 m, its printed
        measurements suggest about 0.5 m (see chapter 2).
    dt : sampling interval (s).
    runs : if given, that many independent noise realisations on a batch axis.

    Returns
    -------
    Scenario
        ``t`` ``(T,)``; ``truth`` ``(T[, runs], 6)``; ``z`` ``(T[, runs], 2)``.
    """
    n_steps = _count(n_steps, "n_steps")
    runs = _count(runs, "runs", allow_none=True)
    sigma, dt = positive_scalar(sigma, "sigma"), positive_scalar(dt, "dt")
    t = dt * np.arange(1, n_steps + 1)
    truth = robot_truth(t)
    z = _noisy(rng, truth[:, [0, 3]], sigma, runs)
    return Scenario(t, _batch(truth, runs), z)


# --------------------------------------------------------------------------------------------
# curves in space (chapter 6): seed 000's drone scenarios, seed 001's tilted zig-zag, and more
# --------------------------------------------------------------------------------------------


class ManoeuvreScenario(NamedTuple):
    """A 3-D trajectory with its manoeuvre labels, time first.

    Attributes
    ----------
    t : (T,) sample times (s).
    truth : (T, 6) true states ``[x, vx, y, vy, z, vz]`` (m, m/s).
    z : (T, 3) position measurements (m), truth plus white Gaussian noise of std ``sigma``.
    label : (T,) int, 0 on a straight segment, 1 while turning (non-zero curvature).
    track : the full :class:`kftrack.frenet.FrenetTrack` (frame, acceleration, kappa, tau).
    """

    t: np.ndarray
    truth: np.ndarray
    z: np.ndarray
    label: np.ndarray
    track: "_fr.FrenetTrack"


def _manoeuvre(rng: np.random.Generator, track, sigma: float) -> ManoeuvreScenario:
    check_rng(rng)
    s = finite_scalar(sigma, "sigma")
    if s < 0:
        raise ValueError(f"sigma must be >= 0 (m), got {sigma!r}")
    truth = np.stack([track.r[:, 0], track.v[:, 0], track.r[:, 1], track.v[:, 1],
                      track.r[:, 2], track.v[:, 2]], axis=-1)
    z = track.r + s * rng.standard_normal(track.r.shape)
    return ManoeuvreScenario(track.t, truth, z, track.turning.astype(int), track)


@dataclass(frozen=True)
class DroneScenario:
    """One of study 000's filtering scenarios (Martins, Naruto & Danner 2018, tables 3–5).

    Attributes
    ----------
    r0, v0 : initial position (m) and velocity (m/s) of the simulator (tables 3–5).
    ds : arc-length step (m); the sampling interval is ``ds / |v0|`` (the study gives no T).
    sigma : measurement noise std (m).
    radii, lengths : segments as :func:`kftrack.frenet.segments_from_radii` takes them
        (R = 0 straight, negative R a right turn). Scenario I is as printed; II and III are
        **our reconstructions** (the study shows them only in figures), see ``assumption``.
    assumption : what we had to choose.
    """

    r0: tuple
    v0: tuple
    ds: float
    sigma: float
    radii: tuple
    lengths: tuple
    assumption: str

    @property
    def dt(self) -> float:
        """Implied sampling interval ``ds / |v0|`` (s)."""
        return self.ds / float(np.linalg.norm(self.v0))

    @property
    def segments(self) -> list:
        """The segments, :class:`kftrack.frenet.Segment`."""
        return _fr.segments_from_radii(self.radii, self.lengths)


#: Study 000's three filtering scenarios, keyed "I", "II", "III".
MARTINS2018_SCENARIOS = MappingProxyType({
    "I": DroneScenario((1.0, 1.0, 0.0), (1.0, 0.8, 0.0), 0.5, 0.5, (0.0,), (100.0,),
                       "as printed: a 100 m straight line, 200 steps of ds = 0.5 m"),
    "II": DroneScenario((44.0, 71.7, 0.0), (-1.0, 2.0, 0.0), 1.0, 2.0,
                        (0.0, 30.0, 0.0, -30.0, 0.0), (50.0, 15 * np.pi, 50.0, 15 * np.pi, 50.0),
                        "reconstructed: 50 m straight (the KF error rises near sample 50), a 90° left "
                        "turn of radius 30 m, 50 m straight, a 90° right turn, 50 m straight"),
    "III": DroneScenario((0.0, 0.7, 10.0), (2.0, 1.0, 0.0), 6.0, 5.0,
                         (0.0, -30.0, 0.0, 30.0, 0.0, -30.0, 0.0),
                         (360.0, 15 * np.pi, 240.0, 15 * np.pi, 180.0, 15 * np.pi, 240.0),
                         "reconstructed: 360 m straight (the IMM starts switching near sample 60), "
                         "then three 90° city-block turns of radius 30 m (right, left, right) "
                         "between straight streets, at a constant 10 m altitude"),
})


def drone_scenario(rng: np.random.Generator, name: str, *, sigma: float | None = None) -> ManoeuvreScenario:
    """Study 000's scenario ``"I"``, ``"II"`` or ``"III"`` (:data:`MARTINS2018_SCENARIOS`),
    simulated exactly (:func:`kftrack.frenet.simulate`), with position noise of the study's
    ``sigma`` (0.5, 2, 5 m) unless given.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.scenarios import drone_scenario
    >>> sc = drone_scenario(np.random.default_rng(0), "II")   # straight, left turn, straight, right turn, straight
    >>> sc.t.shape, sc.truth.shape, sc.z.shape               # truth [x, vx, y, vy, z, vz], z positions
    ((245,), (245, 6), (245, 3))
    >>> np.bincount(sc.label)                                 # samples on straight legs, in turns
    array([150,  95])
    """
    if name not in MARTINS2018_SCENARIOS:
        raise ValueError(f"name must be one of {tuple(MARTINS2018_SCENARIOS)}, got {name!r}")
    sc = MARTINS2018_SCENARIOS[name]
    track = _fr.simulate(sc.segments, sc.dt, sc.r0, sc.v0)
    return _manoeuvre(rng, track, sc.sigma if sigma is None else sigma)


def _tilted_up(v0: np.ndarray, tilt: float) -> np.ndarray:
    """Binormal of a plane through the level velocity ``v0``, tilted by ``tilt`` (rad) so that a
    left turn climbs."""
    t0 = v0 / np.linalg.norm(v0)
    left = np.cross([0.0, 0.0, 1.0], t0)
    left /= np.linalg.norm(left)
    return np.cos(tilt) * np.array([0.0, 0.0, 1.0]) - np.sin(tilt) * left


def tilted_zigzag(rng: np.random.Generator, *, sigma: float = 75.0, tilt_deg: float = 30.0,
                  speed: float = 250.0, dt: float = 4.0, omega: float = 0.05,
                  turn_deg: float = 45.0, leg: float = 60.0) -> ManoeuvreScenario:
    r"""Seed 001's zig-zag (Agner Júnior et al. 2019, §4): seven segments, straight–turn–...–
    straight, in a plane tilted ``tilt_deg`` from horizontal, at ``speed`` m/s sampled every
    ``dt`` s. The paper gives none of the geometry; **our choices**: the truth starts at the
    paper's initial estimate (−30 km, −30 km, 600 m; level, heading 38.31° from +x), straight
    legs of ``leg`` seconds, turns at ``omega`` rad/s of +``turn_deg``, −2·``turn_deg``,
    +``turn_deg`` (so the first turn climbs and the last leg is level again), and the tilt
    axis along the initial velocity. Every turn is planar (zero torsion). Measurements are
    Cartesian positions with std ``sigma`` (m), not the paper's polar radar."""
    speed, dt, omega = positive_scalar(speed, "speed"), positive_scalar(dt, "dt"), positive_scalar(omega, "omega")
    turn_deg, leg = positive_scalar(turn_deg, "turn_deg"), positive_scalar(leg, "leg")
    tilt_deg = finite_scalar(tilt_deg, "tilt_deg")
    v0 = speed * np.array([np.cos(np.arctan2(154.98, 196.16)), np.sin(np.arctan2(154.98, 196.16)), 0.0])
    kappa = omega / speed
    arc = np.deg2rad(turn_deg) / kappa
    L = leg * speed
    segs = [_fr.Segment(L), _fr.Segment(arc, kappa), _fr.Segment(L), _fr.Segment(2 * arc, -kappa),
            _fr.Segment(L), _fr.Segment(arc, kappa), _fr.Segment(L)]
    track = _fr.simulate(segs, dt, (-30000.0, -30000.0, 600.0), v0, up=_tilted_up(v0, np.deg2rad(tilt_deg)))
    return _manoeuvre(rng, track, sigma)


def climbing_helix(rng: np.random.Generator, *, sigma: float = 10.0, speed: float = 100.0,
                   rate: float = 0.05, climb_deg: float = 10.0, dt: float = 1.0,
                   lead_in: float = 20.0, duration: float = 180.0) -> ManoeuvreScenario:
    r"""A straight climb of ``lead_in`` s, then a climbing turn at ``rate`` rad/s about the
    vertical (counter-clockwise from above) for ``duration`` s: a circular helix of radius
    :math:`R = v\cos\gamma/\Omega`, curvature :math:`\cos^2\gamma/R` and torsion
    :math:`\sin\gamma\cos\gamma/R` (:math:`\gamma` = ``climb_deg``). A negative ``rate``
    turns clockwise (a left-handed helix, negative torsion)."""
    speed, dt = positive_scalar(speed, "speed"), positive_scalar(dt, "dt")
    lead_in, duration = positive_scalar(lead_in, "lead_in"), positive_scalar(duration, "duration")
    rate = finite_scalar(rate, "rate")
    climb_deg = finite_scalar(climb_deg, "climb_deg")
    if rate == 0 or not abs(climb_deg) < 90:
        raise ValueError(f"rate must be non-zero (rad/s) and |climb_deg| < 90, got rate={rate!r}, climb_deg={climb_deg!r}")
    g = np.deg2rad(climb_deg)
    R = speed * np.cos(g) / rate
    segs = [_fr.Segment(speed * lead_in), _fr.Segment(speed * duration, np.cos(g) ** 2 / R, np.sin(g) * np.cos(g) / R)]
    v0 = speed * np.array([np.cos(g), 0.0, np.sin(g)])
    return _manoeuvre(rng, _fr.simulate(segs, dt, (0.0, 0.0, 500.0), v0), sigma)


def torsion_manoeuvre(rng: np.random.Generator, *, sigma: float = 10.0, dt: float = 1.0) -> ManoeuvreScenario:
    """A 3-D manoeuvre with torsion and speed changes, from 60 m/s: straight (600 m);
    accelerating climbing turn (κ = 1/500, τ = 1/800 per m, +1 m/s²; 800 m); decelerating
    straight (−1 m/s², 400 m); descending right turn with negative torsion (κ = −1/400,
    τ = −1/600; 900 m); straight (500 m)."""
    segs = [_fr.Segment(600.0), _fr.Segment(800.0, 1 / 500, 1 / 800, 1.0), _fr.Segment(400.0, accel=-1.0),
            _fr.Segment(900.0, -1 / 400, -1 / 600), _fr.Segment(500.0)]
    return _manoeuvre(rng, _fr.simulate(segs, dt, (0.0, 0.0, 300.0), (60.0, 0.0, 0.0)), sigma)


# --------------------------------------------------------------------------------------------
# Chapter 15 (seed 003's missing simulation chapter): a floor plan, robot paths, landmark maps.
# Our reconstruction: the study names no environment, path or noise level.
# --------------------------------------------------------------------------------------------


def floor_plan() -> np.ndarray:
    """A 12 m × 8 m apartment seen from above (seed 003 §2.3.3): outer walls, a partition
    (4–8 m at y = 5.5 m), a square pillar (9–9.6 m, 3–3.6 m) and a counter (1–3 m at y = 6.5 m).
    Returns walls ``(W, 2, 2)`` in metres."""
    segs = [((0, 0), (12, 0)), ((12, 0), (12, 8)), ((12, 8), (0, 8)), ((0, 8), (0, 0)),
            ((4, 5.5), (8, 5.5)),
            ((9, 3), (9.6, 3)), ((9.6, 3), (9.6, 3.6)), ((9.6, 3.6), (9, 3.6)), ((9, 3.6), (9, 3)),
            ((1, 6.5), (3, 6.5))]
    return np.array(segs, dtype=float)


def drive(segments, dt: float, start) -> tuple[np.ndarray, np.ndarray]:
    r"""Drive the noise-free unicycle (:class:`kftrack.slam.Unicycle`) through ``segments`` of
    ``(duration_s, v, omega)``; ``start`` is the pose ``(x, y, heading)``.

    Returns ``(poses (T, 3), controls (T, 2))`` with ``poses[k + 1] = f(poses[k], controls[k])``;
    the last control row repeats the one before (unused by a filter)."""
    dt = positive_scalar(dt, "dt")
    u = []
    for seg in segments:
        duration, v, w = (float(s) for s in seg)
        u += [(v, w)] * int(round(duration / dt))
    if not u:
        raise ValueError("segments must drive for at least one step")
    u = np.array(u + [u[-1]])
    model = _slam.Unicycle(0.0, 0.0)
    poses = np.empty((len(u), 3))
    poses[0] = check_finite(as_float_array(start, "start"), "start")
    for k in range(len(u) - 1):
        poses[k + 1] = model.f(poses[k], u[k], dt)
    return poses, u


def apartment_loop(dt: float = 0.5, speed: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """A rectangular loop through :func:`floor_plan`: from (2, 1.5) heading east, 8 m × 3 m,
    turning 90° left in place (2 s per turn) at each corner. Returns ``(poses, controls)``."""
    turn = (2.0, 0.0, np.pi / 4)
    segs = [(8.0 / speed, speed, 0.0), turn, (3.0 / speed, speed, 0.0), turn,
            (8.0 / speed, speed, 0.0), turn, (3.0 / speed, speed, 0.0), turn]
    return drive(segs, dt, (2.0, 1.5, 0.0))


def ring_landmarks(rng: np.random.Generator, count: int = 12, radius: float = 6.0,
                   spread: float = 2.5) -> np.ndarray:
    """``count`` point landmarks ``(count, 2)`` around a circle of ``radius``: evenly spaced in
    angle with a uniform jitter of ±1/4 spacing, alternately inside and outside the circle by
    ``spread`` ± 0.5 m."""
    check_rng(rng)
    count = _count(count, "count")
    radius, spread = positive_scalar(radius, "radius"), positive_scalar(spread, "spread")
    ang = 2 * np.pi * (np.arange(count) + rng.uniform(-0.25, 0.25, count)) / count
    rad = radius + spread * np.where(np.arange(count) % 2, 1.0, -1.0) + rng.uniform(-0.5, 0.5, count)
    return np.stack([rad * np.cos(ang), rad * np.sin(ang)], -1)


class SlamScenario(NamedTuple):
    """A robot among point landmarks, time first.

    Attributes
    ----------
    t : (T,) times (s).
    truth : (T, 3) true poses ``[x, y, heading]``.
    controls : (T, 2) true ``[v, omega]`` applied after each step.
    odometry : (T, ..., 2) measured ``[v, omega]`` (white noise; runs on the middle axis).
    landmarks : (L, 2) true landmark positions.
    observations : list of T pairs ``(ids (M_k,), z (M_k, ..., 2))``: range and bearing of the
        landmarks within ``max_range``; the visible set depends on the true path only, so it is
        the same in every run.
    """

    t: np.ndarray
    truth: np.ndarray
    controls: np.ndarray
    odometry: np.ndarray
    landmarks: np.ndarray
    observations: list


def slam_loop(rng: np.random.Generator, landmarks, *, loops: float = 1.0, runs: int | None = None,
              dt: float = 0.25, speed: float = 1.0, radius: float = 6.0, sigma_v: float = 0.05,
              sigma_omega: float = np.deg2rad(3.0), sigma_range: float = 0.1,
              sigma_bearing: float = np.deg2rad(2.0), max_range: float = 4.0) -> SlamScenario:
    r"""The robot drives ``loops`` times counter-clockwise around a circle of ``radius`` (from
    ``(radius, 0)`` heading north) at ``speed``; odometry and range–bearing observations of
    ``landmarks`` closer than ``max_range`` carry white Gaussian noise of the given standard
    deviations (m/s, rad/s, m, rad). ``runs=N`` draws N independent noise realisations on the
    same true path."""
    check_rng(rng)
    for name, val in (("sigma_v", sigma_v), ("sigma_omega", sigma_omega), ("sigma_range", sigma_range),
                      ("sigma_bearing", sigma_bearing)):
        if not (np.isfinite(val) and val >= 0):
            raise ValueError(f"{name} must be a non-negative standard deviation, got {val!r}")
    if not max_range > 0:
        raise ValueError(f"max_range must be a positive distance (m), got {max_range!r}")
    lm = check_finite(as_float_array(landmarks, "landmarks"), "landmarks")
    if lm.ndim != 2 or lm.shape[1] != 2:
        raise ValueError(f"landmarks must have shape (L, 2), got shape {lm.shape}")
    loops, radius, speed = positive_scalar(loops, "loops"), positive_scalar(radius, "radius"), positive_scalar(speed, "speed")
    runs = _count(runs, "runs", allow_none=True)
    duration = loops * 2 * np.pi * radius / speed
    truth, u = drive([(duration, speed, speed / radius)], dt, (radius, 0.0, np.pi / 2))
    size = (len(u),) + (() if runs is None else (runs,)) + (2,)
    odo = u.reshape((len(u),) + (1,) * (runs is not None) + (2,)) + rng.standard_normal(size) * [sigma_v, sigma_omega]
    obs = []
    for k, pose in enumerate(truth):
        z = _slam.observe(np.broadcast_to(pose, lm.shape[:-1] + (3,)), lm)
        ids = np.flatnonzero(z[:, 0] < max_range)
        zk = z[ids].reshape((len(ids),) + (1,) * (runs is not None) + (2,))
        zk = zk + rng.standard_normal((len(ids),) + size[1:]) * [sigma_range, sigma_bearing]
        zk[..., 1] = _wrap_angle(zk[..., 1])
        obs.append((ids, zk))
    return SlamScenario(dt * np.arange(len(u)), truth, u, odo, lm, obs)
