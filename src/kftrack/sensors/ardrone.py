r"""Parrot AR.Drone 2.0 sensors: units, the altimeter's raw format, outliers, statistics and logs.

Models layer. Everything here comes from the sensor characterisation of seed 004
(Marques, Trindade & Afonso 2018, Sect. 2, Tables 1–3; notes ``004_ardrone.md`` §2):

* **Channels** (:data:`CHANNELS`): ``altitude`` (ultrasonic altimeter), ``acc_x``,
  ``acc_y``, ``acc_z`` (accelerometer, body axes, z down), ``roll_rate``, ``pitch_rate``,
  ``yaw_rate`` (rate gyros).
* **Raw units** (:data:`RAW_UNITS`): accelerations in cm/s², rates in °/s, and the altitude
  as *an int32 number of millimetres whose bits were read as a float32*: 238 mm shows up as
  the denormal 3.3351e-43. :func:`decode_altitude` undoes this exactly (a bit view).
* **Units** are converted to SI in one place, :func:`to_si`: values scale by ``c``,
  variances by ``c**2`` (so (°/s)² to (rad/s)² is the factor (π/180)²).
* **Outliers**: two *stated* rules. :func:`altimeter_valid` is a physical bound (a
  reading outside the sonar's range cannot be an echo); :func:`mad_outliers` is the
  median/MAD modified z-score of Iglewicz & Hoaglin (1993) for channels without one.
* **Logs**: :func:`generate_log` makes seeded synthetic logs of experiments A–C with the
  statistics of the study's tables (:data:`STUDY_TABLES`); :func:`write_logs` saves them
  as ``ardrone_exp{A,B,C}.csv`` in a folder the caller names; :func:`load_log` reads the
  committed ones from ``data/`` back, skipping and counting corrupt records. The study's own logs were never published.

Raw values are kept as float64 arrays; the altitude column holds the float32 value
exactly. Statistics use the unbiased variance (``ddof=1``).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .._validate import as_float_array, check_finite, check_rng
from ..datasets import data_path
from ..gaussians import MomentTest, moment_test

__all__ = [
    "CHANNELS", "RAW_UNITS", "SI_UNITS", "EXPERIMENTS", "STUDY_TABLES", "STUDY_INCLINOMETER_VAR", "STUDY_ALTITUDE_UNIT",
    "ALTITUDE_LSB", "ACCEL_SCALES", "ALTIMETER_MIN_RANGE", "ALTIMETER_MAX_RANGE",
    "SAMPLE_RATE", "SAMPLES", "DEFAULT_SEED", "CORRUPT_PER_FILE",
    "si_scale", "to_si", "study_moments", "decode_altitude", "encode_altitude", "altitude_study_convention",
    "altimeter_valid", "mad_outliers",
    "ChannelStats", "channel_stats", "statistics_table",
    "ChannelModel", "channel_model", "ArdroneLog", "generate_log", "log_csv_text", "write_logs",
    "parse_log_csv", "read_log", "load_log", "log_filename", "model_tests",
]

CHANNELS: tuple[str, ...] = ("altitude", "acc_x", "acc_y", "acc_z", "roll_rate", "pitch_rate", "yaw_rate")
"""Sensor channels, in the column order of the study's tables and of the log files."""

_ACC = ("acc_x", "acc_y", "acc_z")
_GYRO = ("roll_rate", "pitch_rate", "yaw_rate")

RAW_UNITS: dict[str, str] = {"altitude": "float32 bits of int32 mm",
                             **{c: "cm/s^2" for c in _ACC}, **{c: "deg/s" for c in _GYRO}}
"""Raw unit of each channel, as found by the study (Sect. 2.1–2.3)."""

SI_UNITS: dict[str, str] = {"altitude": "m", **{c: "m/s^2" for c in _ACC}, **{c: "rad/s" for c in _GYRO}}
"""SI unit of each channel after :func:`to_si`."""

EXPERIMENTS: dict[str, str] = {
    "A": "at rest on the floor, motors off",
    "B": "on the floor, motors on, held down by hand",
    "C": "hover at 1 m reference height",
}
"""The three characterisation experiments of the study (Sect. 2.1–2.3)."""

STUDY_TABLES: dict[str, dict[str, tuple[float, float]]] = {
    "A": {"altitude": (3.3351e-43, 0.0), "acc_x": (13.5774, 13.7353), "acc_y": (4.6363, 8.5353),
          "acc_z": (-977.2680, 10.2827), "roll_rate": (0.0402, 0.0022), "pitch_rate": (0.0345, 0.0016),
          "yaw_rate": (0.0023, 0.0017)},
    "B": {"altitude": (2.8278e-43, 1.5176e-86), "acc_x": (-5.3464, 1.3244e3), "acc_y": (16.4132, 1.6847e3),
          "acc_z": (-964.4989, 140.2430), "roll_rate": (0.0561, 44.1893), "pitch_rate": (0.1133, 69.0449),
          "yaw_rate": (-0.0677, 131.2013)},
    "C": {"altitude": (1.4024e-42, 4.7262e-89), "acc_x": (15.2959, 18.5751), "acc_y": (1.7955, 20.6842),
          "acc_z": (-975.2683, 39.3808), "roll_rate": (0.0329, 2.3018), "pitch_rate": (0.0214, 2.7550),
          "yaw_rate": (0.3205, 1.5478)},
}
"""The study's Tables 1–3 as printed: ``STUDY_TABLES[experiment][channel] = (mean, variance)``
in raw units (the tables' "Covariância" row is the variance of each channel)."""

STUDY_INCLINOMETER_VAR: dict[str, float] = {"pitch": 1.9932e-5, "roll": 2.4310e-5}
"""The study's measured variances (rad², hover, experiment C) of the accelerometer-derived
("inclinometer") pitch and roll angles, Sect. 2.4 (notes 004 §2). Its filters inflate them
by a tuning factor of 10⁴ (chapters 3 and 14)."""

STUDY_ALTITUDE_UNIT = 1.4024e-42
"""The study's altitude divisor (raw value per metre): the mean raw reading of the 1 m hover."""

ALTITUDE_LSB = 2.0 ** -149
"""Spacing of float32 denormals: one raw altitude step, i.e. one millimetre."""

ACCEL_SCALES: dict[str, float] = {"cm/s^2": 0.01, "mg": 9.80665e-3}
"""Metres per second squared per raw accelerometer unit: cm/s² (the study) or milli-g (the SDK)."""

ALTIMETER_MIN_RANGE = 0.20
"""Shortest height the sonar measures (m), the course's figure quoted by the study."""

ALTIMETER_MAX_RANGE = 6.0
"""Longest height the sonar measures (m), the manufacturer's figure for the AR.Drone 2.0."""

SAMPLE_RATE = 100.0
"""Sample rate of the synthetic logs (Hz). The study does not state its rate."""

SAMPLES = 1500
"""Records per synthetic log (15 s at :data:`SAMPLE_RATE`)."""

DEFAULT_SEED = 2018
"""Seed of the committed logs in ``data/``."""

CORRUPT_PER_FILE = 3
"""Corrupt records written into each log file: a truncated line, a non-numeric field, a NaN."""

_DEG = np.pi / 180.0


def _check_channel(channel: str) -> str:
    if channel not in CHANNELS:
        raise ValueError(f"channel must be one of {CHANNELS}, got {channel!r}")
    return channel


def _check_experiment(experiment: str) -> str:
    if experiment not in EXPERIMENTS:
        raise ValueError(f"experiment must be one of {tuple(EXPERIMENTS)}, got {experiment!r}")
    return experiment


# --------------------------------------------------------------------------- units

def si_scale(channel: str, accel_unit: str = "cm/s^2") -> float:
    r"""SI units per raw unit of ``channel``: ``si = raw * si_scale(channel)``.

    * accelerations: 0.01 (cm/s² to m/s²), or 9.80665e-3 with ``accel_unit="mg"``;
    * rates: :math:`\pi/180` (°/s to rad/s);
    * altitude: :math:`2^{149}/1000` (one float32 denormal step is one millimetre); for a
      single reading prefer the exact :func:`decode_altitude`.
    """
    _check_channel(channel)
    if accel_unit not in ACCEL_SCALES:
        raise ValueError(f"accel_unit must be one of {tuple(ACCEL_SCALES)}, got {accel_unit!r}")
    if channel == "altitude":
        return 1.0 / (ALTITUDE_LSB * 1000.0)
    if channel in _ACC:
        return ACCEL_SCALES[accel_unit]
    return _DEG


def to_si(value, channel: str, *, variance: bool = False, accel_unit: str = "cm/s^2") -> np.ndarray:
    r"""Convert raw values (or, with ``variance=True``, raw variances) of ``channel`` to SI.

    A value (a reading, a mean or a standard deviation) scales by :math:`c` =
    :func:`si_scale`; a variance by :math:`c^2`. For the gyros
    :math:`c^2 = (\pi/180)^2 = 3.0462\times10^{-4}`, so 2.3018 (°/s)² is
    7.0117e-4 (rad/s)²; for the accelerometers :math:`c^2 = 10^{-4}`.
    """
    arr = check_finite(as_float_array(value, "value"), "value")
    c = si_scale(channel, accel_unit)
    if variance:
        if np.any(arr < 0):
            raise ValueError(f"value must be a non-negative variance when variance=True, got min {arr.min()!r}")
        return arr * c * c
    return arr * c


def study_moments(experiment: str, units: str = "si", accel_unit: str = "cm/s^2") -> dict[str, tuple[float, float]]:
    """The study's table for ``experiment`` as ``{channel: (mean, variance)}``.

    With ``units="si"`` (default) means are in m, m/s², rad/s and variances in their
    squares, converted by :func:`to_si` (the altitude by exact decoding, so the hover's
    ``Cov[h_m]`` is 2.4069e-5 m², not the study's 2.4031e-5). ``units="raw"`` returns
    :data:`STUDY_TABLES` unchanged. These are the measurement-noise variances a filter
    of the drone would use (experiment C: in flight).
    """
    _check_experiment(experiment)
    if units not in ("raw", "si"):
        raise ValueError(f"units must be 'raw' or 'si', got {units!r}")
    table = STUDY_TABLES[experiment]
    if units == "raw":
        return dict(table)
    return {c: (float(to_si(m, c, accel_unit=accel_unit)), float(to_si(v, c, variance=True, accel_unit=accel_unit)))
            for c, (m, v) in table.items()}


def decode_altitude(raw) -> np.ndarray:
    """Height in metres from raw altimeter values: the float32's bits are an int32 of mm.

    ``float32(3.3351e-43).view(int32) == 238``, so 3.3351e-43 decodes to 0.238 m, exactly
    (no division by a calibration constant; compare :func:`altitude_study_convention`).

    Raises ``ValueError`` (naming ``raw``) for values that are not finite, negative, or
    not float32 denormals (their bits would not be a plausible millimetre count).
    """
    arr = check_finite(as_float_array(raw, "raw"), "raw")
    f32 = arr.astype(np.float32)
    if np.any(f32 < 0) or np.any(f32 >= np.finfo(np.float32).smallest_normal):
        bad = arr[(f32 < 0) | (f32 >= np.finfo(np.float32).smallest_normal)].flat[0]
        raise ValueError(f"raw must hold non-negative float32 denormals (int32 mm read as float32), got {bad!r}")
    return f32.view(np.int32).astype(float) / 1000.0


def encode_altitude(height_m) -> np.ndarray:
    """Inverse of :func:`decode_altitude`: heights in metres to raw float32 values
    (rounded to the millimetre, then the int32 bits read as float32)."""
    h = check_finite(as_float_array(height_m, "height_m"), "height_m")
    if np.any(h < 0) or np.any(h >= 8388.608):
        raise ValueError(f"height_m must lie in [0, 8388.608) m, got range [{h.min()!r}, {h.max()!r}]")
    return np.rint(h * 1000.0).astype(np.int32).view(np.float32)


def altitude_study_convention(raw) -> np.ndarray:
    """Height in metres by the study's rule: raw divided by :data:`STUDY_ALTITUDE_UNIT`,
    the mean raw value of the 1 m hover. It equals :func:`decode_altitude` times
    ``1000 * ALTITUDE_LSB / STUDY_ALTITUDE_UNIT`` (= 0.99922): a calibration that assumes
    the hover sat at exactly 1 m."""
    return check_finite(as_float_array(raw, "raw"), "raw") / STUDY_ALTITUDE_UNIT


# --------------------------------------------------------------------------- outliers

def altimeter_valid(height_m, min_range: float = ALTIMETER_MIN_RANGE,
                    max_range: float = ALTIMETER_MAX_RANGE) -> np.ndarray:
    """Physical-bound rule: a height reading is valid iff ``min_range <= h <= max_range``.

    The sonar cannot return an echo closer than its minimum range or farther than its
    maximum, so a reading outside the range (e.g. the 0 of a dropout) is not a
    measurement, whatever the rest of the sample looks like. Returns a boolean mask,
    ``True`` = valid. Readings at the clamp value (0.238 m at rest) are kept: they are
    what the sensor says, and deciding what they mean is modelling, not cleaning.
    """
    h = as_float_array(height_m, "height_m")
    if not 0.0 <= min_range < max_range:
        raise ValueError(f"min_range and max_range must satisfy 0 <= min_range < max_range, "
                         f"got {min_range!r}, {max_range!r}")
    return np.isfinite(h) & (h >= min_range) & (h <= max_range)


def mad_outliers(x, threshold: float = 3.5) -> np.ndarray:
    r"""Median/MAD rule (modified z-score, Iglewicz & Hoaglin 1993): ``True`` = outlier.

    .. math:: M_i = \frac{0.6745\,(x_i - \operatorname{median} x)}{\operatorname{MAD}},
              \qquad \text{outlier} \iff |M_i| > \text{threshold}

    with :math:`\operatorname{MAD} = \operatorname{median}|x_i - \operatorname{median} x|`;
    0.6745 makes :math:`M` a standard normal for Gaussian data, and 3.5 flags about 5 in
    10 000 clean Gaussian samples. Median and MAD are not dragged by the outliers they are
    meant to find, unlike mean ± 3 std. If MAD is 0 (more than half the sample equal),
    the mean absolute deviation times 1.2533 is used; a constant sample has no outliers.

    Parameters
    ----------
    x : (n,) finite values.
    threshold : positive cut on the modified z-score.
    """
    x = check_finite(as_float_array(x, "x"), "x")
    if x.ndim != 1 or x.size == 0:
        raise ValueError(f"x must have shape (n,) with n >= 1, got shape {x.shape}")
    if not threshold > 0:
        raise ValueError(f"threshold must be positive, got {threshold!r}")
    dev = x - np.median(x)
    mad = np.median(np.abs(dev))
    if mad > 0:
        z = 0.6745 * dev / mad
    else:
        mean_ad = np.mean(np.abs(dev))
        if mean_ad == 0:
            return np.zeros(x.shape, dtype=bool)
        z = dev / (1.2533 * mean_ad)
    return np.abs(z) > threshold


# --------------------------------------------------------------------------- statistics

class ChannelStats(NamedTuple):
    """Sample statistics of one channel: count, mean, variance (ddof=1), standard deviation."""

    n: int
    mean: float
    var: float
    std: float


def channel_stats(values) -> ChannelStats:
    """:class:`ChannelStats` of a 1-D sample (NaNs are not allowed: remove them first)."""
    x = check_finite(as_float_array(values, "values"), "values")
    if x.ndim != 1 or x.size < 2:
        raise ValueError(f"values must have shape (n,) with n >= 2, got shape {x.shape}")
    var = float(np.var(x, ddof=1))
    return ChannelStats(int(x.size), float(np.mean(x)), var, float(np.sqrt(var)))


# --------------------------------------------------------------------------- logs

@dataclass(frozen=True)
class ArdroneLog:
    """A sensor log: time first.

    Attributes
    ----------
    experiment : "A", "B" or "C" (see :data:`EXPERIMENTS`).
    t : (T,) time stamps, s.
    raw : (T, 7) raw readings in the order of :data:`CHANNELS`, raw units.
    n_corrupt : number of corrupt records skipped when the log was read.
    corrupt_lines : their 1-based line numbers in the file.
    """

    experiment: str
    t: np.ndarray
    raw: np.ndarray
    n_corrupt: int = 0
    corrupt_lines: tuple[int, ...] = field(default=())

    def channel(self, name: str) -> np.ndarray:
        """Raw readings ``(T,)`` of channel ``name``."""
        return self.raw[:, CHANNELS.index(_check_channel(name))]

    def si(self, name: str, accel_unit: str = "cm/s^2") -> np.ndarray:
        """Readings ``(T,)`` of channel ``name`` in SI units (altitude decoded exactly)."""
        if name == "altitude":
            return decode_altitude(self.channel(name))
        return to_si(self.channel(name), name, accel_unit=accel_unit)


def statistics_table(log: ArdroneLog, *, units: str = "raw", outliers: str | None = None,
                     accel_unit: str = "cm/s^2") -> dict[str, ChannelStats]:
    """Mean, variance and standard deviation of every channel of ``log``.

    Parameters
    ----------
    log : the log.
    units : ``"raw"`` (the study's units; comparable with :data:`STUDY_TABLES`) or ``"si"``.
    outliers : ``None`` (use every record, as the study's tables do), ``"range"`` (drop
        altitude readings outside the sonar's range, :func:`altimeter_valid`; other
        channels untouched) or ``"mad"`` (drop :func:`mad_outliers` in every channel).
    accel_unit : raw accelerometer unit for ``units="si"``.

    Returns
    -------
    dict mapping each channel name to its :class:`ChannelStats`.
    """
    if units not in ("raw", "si"):
        raise ValueError(f"units must be 'raw' or 'si', got {units!r}")
    if outliers not in (None, "range", "mad"):
        raise ValueError(f"outliers must be None, 'range' or 'mad', got {outliers!r}")
    table = {}
    for name in CHANNELS:
        raw_altitude = units == "raw" and name == "altitude"
        # raw altitudes are denormals: work in LSB steps (an exact power-of-two scaling)
        x = log.channel(name) / ALTITUDE_LSB if raw_altitude else (
            log.si(name, accel_unit) if units == "si" else log.channel(name))
        if outliers == "range" and name == "altitude":
            x = x[altimeter_valid(log.si("altitude"))]
        elif outliers == "mad":
            x = x[~mad_outliers(x)]
        st = channel_stats(x)
        if raw_altitude:
            st = ChannelStats(st.n, st.mean * ALTITUDE_LSB, st.var * ALTITUDE_LSB ** 2, st.std * ALTITUDE_LSB)
        table[name] = st
    return table


class ChannelModel(NamedTuple):
    """How :func:`generate_log` draws one channel (log units: altitude in mm, others raw).

    Valid readings are ``N(mean, var)`` rounded to ``quantum`` (0 = not rounded; the
    Gaussian's variance is reduced by ``quantum**2 / 12`` so that the rounded readings
    have variance ``var``, Sheppard's correction). A fraction ``dropout_fraction`` of the
    records are dropouts reading 0, in runs. ``var = 0`` is a constant channel.
    """

    mean: float
    var: float
    dropout_fraction: float
    quantum: float


def channel_model(experiment: str, channel: str) -> ChannelModel:
    r"""The generator's model of ``channel`` in ``experiment``, derived from :data:`STUDY_TABLES`.

    Every channel is Gaussian with the table's mean and variance, except the altitude:
    integer millimetres (``table / ALTITUDE_LSB``), constant at rest (A, 238 mm). In B
    the drone stays on the floor and the sonar drops out to 0 now and then; the study's
    Table 2 keeps the dropouts. Give the valid readings the sonar noise of the hover
    (C, :math:`\sigma_v^2` = 24.07 mm²); then the table's mean :math:`\bar h` and variance
    :math:`s^2` of the whole sample fix the valid mean :math:`\mu_v` and the dropout
    fraction :math:`f`:

    .. math::

        \bar h = (1-f)\mu_v, \qquad s^2 = (1-f)(\sigma_v^2 + \mu_v^2) - \bar h^2
        \;\Rightarrow\;
        \mu_v^2 - c\,\mu_v + \sigma_v^2 = 0, \quad c = \frac{s^2 + \bar h^2}{\bar h},

    the larger root: :math:`\mu_v` = 240.0 mm and :math:`f` = 15.9 %.
    """
    _check_experiment(experiment)
    _check_channel(channel)
    mean, var = STUDY_TABLES[experiment][channel]
    if channel != "altitude":
        return ChannelModel(mean, var, 0.0, 0.0)
    mean_mm, var_mm = mean / ALTITUDE_LSB, var / ALTITUDE_LSB ** 2
    if var_mm == 0.0:
        return ChannelModel(float(np.rint(mean_mm)), 0.0, 0.0, 1.0)
    if experiment == "B":
        var_valid = STUDY_TABLES["C"]["altitude"][1] / ALTITUDE_LSB ** 2
        c = (var_mm + mean_mm ** 2) / mean_mm
        mean_valid = 0.5 * (c + np.sqrt(c * c - 4.0 * var_valid))
        return ChannelModel(float(mean_valid), var_valid, float(1.0 - mean_mm / mean_valid), 1.0)
    return ChannelModel(mean_mm, var_mm, 0.0, 1.0)


def _dropout_mask(n: int, n_drop: int, rng: np.random.Generator) -> np.ndarray:
    """Boolean mask with ``n_drop`` True values in runs of 5 to 25 samples."""
    mask = np.zeros(n, dtype=bool)
    if n_drop == 0:
        return mask
    runs = []
    while sum(runs) < n_drop:
        runs.append(int(rng.integers(5, 26)))
    runs[-1] -= sum(runs) - n_drop
    n_valid = n - n_drop
    cuts = np.sort(rng.choice(np.arange(1, n_valid), size=len(runs), replace=False))
    for k, (cut, length) in enumerate(zip(cuts, runs)):
        pos = cut + sum(runs[:k])
        mask[pos:pos + length] = True
    return mask


def _draw_channel(model: ChannelModel, n: int, rng: np.random.Generator) -> np.ndarray:
    if model.var == 0.0:
        return np.full(n, model.mean)
    n_drop = int(round(model.dropout_fraction * n))
    drop = _dropout_mask(n, n_drop, rng)
    sd = np.sqrt(model.var - model.quantum ** 2 / 12.0)
    valid = model.mean + sd * rng.standard_normal(n - n_drop)
    if model.quantum:
        valid = model.quantum * np.rint(valid / model.quantum)
    out = np.zeros(n)
    out[~drop] = valid
    return out


def generate_log(experiment: str, rng: np.random.Generator, n: int = SAMPLES) -> ArdroneLog:
    """A synthetic log of ``experiment`` with ``n`` records at :data:`SAMPLE_RATE`.

    Channels are independent and drawn by :func:`channel_model` (white noise with the
    study's means and variances; the altitude as integer millimetres, stored raw, i.e.
    as float32 bits). Accelerations and rates are rounded to 4 decimals, as the tables.
    """
    _check_experiment(experiment)
    check_rng(rng)
    if int(n) != n or n < 2:
        raise ValueError(f"n must be an integer >= 2, got {n!r}")
    n = int(n)
    cols = []
    for name in CHANNELS:
        x = _draw_channel(channel_model(experiment, name), n, rng)
        if name == "altitude":
            cols.append(encode_altitude(x / 1000.0).astype(float))
        else:
            cols.append(np.round(x, 4))
    t = np.round(np.arange(n) / SAMPLE_RATE, 2)
    return ArdroneLog(experiment, t, np.stack(cols, axis=-1))


def model_tests(log: ArdroneLog, confidence: float = 0.95) -> dict[str, MomentTest | None]:
    """Test each channel of a synthetic ``log`` against its :func:`channel_model`.

    The valid readings (altitude decoded to mm, dropouts removed with
    :func:`altimeter_valid`) are checked with :func:`kftrack.gaussians.moment_test`
    (t for the mean, chi-square for the variance). Constant channels map to ``None``:
    check them for exact equality instead.
    """
    out: dict[str, MomentTest | None] = {}
    for name in CHANNELS:
        model = channel_model(log.experiment, name)
        x = log.channel(name)
        if name == "altitude":
            h = decode_altitude(x)
            x = 1000.0 * h[altimeter_valid(h)] if model.dropout_fraction else 1000.0 * h
        out[name] = None if model.var == 0.0 else moment_test(x, model.mean, model.var, confidence)
    return out


# --------------------------------------------------------------------------- files

_HEADER = "t," + ",".join("altitude_raw" if c == "altitude" else c for c in CHANNELS)


def log_filename(experiment: str) -> str:
    """File name of the committed log of ``experiment`` in ``data/``."""
    return f"ardrone_exp{_check_experiment(experiment)}.csv"


def _format_record(t: float, row: np.ndarray) -> list[str]:
    alt = np.format_float_scientific(np.float32(row[0]), unique=True, trim="-")
    return [f"{t:.2f}", alt] + [f"{v:.4f}" for v in row[1:]]


def log_csv_text(experiment: str, seed: int = DEFAULT_SEED) -> str:
    """The CSV text of the synthetic log of ``experiment`` generated with ``seed``.

    ``rng = np.random.default_rng([seed, i])`` with ``i`` the experiment's index (0, 1, 2),
    so each file can be regenerated alone. After the :data:`SAMPLES` good records the
    same generator places :data:`CORRUPT_PER_FILE` extra corrupt records at random lines:
    a truncated record, a non-numeric field and a NaN.
    """
    _check_experiment(experiment)
    rng = np.random.default_rng([int(seed), list(EXPERIMENTS).index(experiment)])
    log = generate_log(experiment, rng)
    records = [",".join(_format_record(t, row)) for t, row in zip(log.t, log.raw)]
    where = np.sort(rng.choice(np.arange(1, len(records)), size=CORRUPT_PER_FILE, replace=False))
    bad = []
    for kind, k in enumerate(where):
        fields = _format_record(log.t[k], log.raw[k])
        if kind % 3 == 0:
            bad.append(",".join(fields[:3]))
        elif kind % 3 == 1:
            bad.append(",".join(fields[:4] + ["ERR"] + fields[5:]))
        else:
            bad.append(",".join(fields[:6] + ["nan"] + fields[7:]))
    for k, line in sorted(zip(where, bad), reverse=True):
        records.insert(int(k), line)
    head = [
        f"# kftrack synthetic AR.Drone log, experiment {experiment}: {EXPERIMENTS[experiment]}",
        f"# generator: kftrack.sensors.ardrone.log_csv_text({experiment!r}, seed={int(seed)}); "
        f"{SAMPLES} records at {SAMPLE_RATE:g} Hz plus {CORRUPT_PER_FILE} corrupt ones",
        "# units: t s; altitude_raw int32 mm read as float32; acc_* cm/s^2; *_rate deg/s",
        _HEADER,
    ]
    return "\n".join(head + records) + "\n"


def write_logs(directory: str | os.PathLike, seed: int = DEFAULT_SEED) -> list[Path]:
    """Write ``ardrone_exp{A,B,C}.csv`` (see :func:`log_csv_text`) into ``directory``, created
    if missing. The folder is required, never the installed package's data: the book's files
    are rewritten with ``write_logs("data")`` from the repository's root. Returns the paths."""
    if not isinstance(directory, (str, os.PathLike)):
        raise TypeError(f"directory must be the folder to write into (str or os.PathLike), "
                        f"got {type(directory).__name__}")
    folder = Path(directory)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for experiment in EXPERIMENTS:
        path = folder / log_filename(experiment)
        path.write_text(log_csv_text(experiment, seed), encoding="utf-8")
        paths.append(path)
    return paths


def parse_log_csv(text: str, experiment: str) -> ArdroneLog:
    """Parse the CSV text of a log; corrupt records are skipped and counted.

    Lines starting with ``#`` are comments; the first other line must be the header
    ``t,altitude_raw,acc_x,...``. A record is corrupt if it does not have 8 fields, if a
    field is not a finite number, or if its altitude is not a valid raw value
    (:func:`decode_altitude`). Raises ``ValueError`` if the header is missing or wrong.
    """
    _check_experiment(experiment)
    lines = text.splitlines()
    rows, corrupt = [], []
    header_seen = False
    for number, line in enumerate(lines, start=1):
        if line.startswith("#"):
            continue
        if not header_seen:
            if line.strip() != _HEADER:
                raise ValueError(f"text must start with the header {_HEADER!r}, got {line[:80]!r} at line {number}")
            header_seen = True
            continue
        fields = line.split(",")
        try:
            if len(fields) != len(CHANNELS) + 1:
                raise ValueError
            values = [float(v) for v in fields]
            if not np.all(np.isfinite(values)):
                raise ValueError
            values[1] = float(np.float32(values[1]))  # the raw float32, exactly
            decode_altitude(values[1])
        except ValueError:
            corrupt.append(number)
            continue
        rows.append(values)
    if not header_seen:
        raise ValueError(f"text must contain the header {_HEADER!r}, found none")
    data = np.array(rows, dtype=float).reshape(-1, len(CHANNELS) + 1)
    return ArdroneLog(experiment, data[:, 0], data[:, 1:], len(corrupt), tuple(corrupt))


def read_log(path: str | Path, experiment: str) -> ArdroneLog:
    """Read a log file (see :func:`parse_log_csv`)."""
    return parse_log_csv(Path(path).read_text(encoding="utf-8"), experiment)


def load_log(experiment: str) -> ArdroneLog:
    """Load the committed synthetic log of ``experiment`` ("A", "B" or "C") from ``data/``.

    Examples
    --------
    >>> from kftrack.sensors.ardrone import CHANNELS, load_log
    >>> log = load_log("A")                            # experiment A: at rest, motors off
    >>> log.t.shape, log.raw.shape, len(CHANNELS)      # time first; raw units, one column per channel
    ((1500,), (1500, 7), 7)
    >>> log.n_corrupt                                  # corrupt records skipped and counted
    3
    """
    return read_log(data_path(log_filename(experiment)), experiment)
