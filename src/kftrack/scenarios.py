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
"""
from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping, NamedTuple

import numpy as np

from ._validate import as_float_array, check_finite

__all__ = [
    "Scenario", "Printed", "printed", "CarRadarStudy", "RobotStudy", "COSTA2023_CAR",
    "COSTA2023_ROBOT", "car_radar", "robot_truth", "robot",
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


def _positive(value, name: str) -> float:
    v = float(check_finite(as_float_array(value, name), name))
    if not v > 0:
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return v


def _count(value, name: str, allow_none: bool = False) -> int | None:
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer{' or None' if allow_none else ''}, got {value!r}")
    return int(value)


def _noisy(rng: np.random.Generator, clean: np.ndarray, sigma: float, runs: int | None) -> np.ndarray:
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
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
    """
    n_steps = _count(n_steps, "n_steps")
    runs = _count(runs, "runs", allow_none=True)
    sigma, dt = _positive(sigma, "sigma"), _positive(dt, "dt")
    x1 = COSTA2023_CAR.z[1] if start is None else float(check_finite(as_float_array(start, "start"), "start"))
    v = COSTA2023_CAR.speed if speed is None else float(check_finite(as_float_array(speed, "speed"), "speed"))
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
    sigma, dt = _positive(sigma, "sigma"), _positive(dt, "dt")
    t = dt * np.arange(1, n_steps + 1)
    truth = robot_truth(t)
    z = _noisy(rng, truth[:, [0, 3]], sigma, runs)
    return Scenario(t, _batch(truth, runs), z)
