r"""Motion models for tracking: constant velocity, constant acceleration, Singer, the
coordinated turn with known or estimated turn rate, and 3-D turns (:class:`Turn3D`,
:class:`Turn3DAngles`, chapter 6).

Every model gives the transition ``F(dt)``, the process noise ``Q(dt)``, the transition
function ``f(x, dt)``, its Jacobian ``jacobian(x, dt)`` and the position-measurement matrix
``H``. The matrices are derived in :mod:`kftrack.symbolic` and generated once per process.

One argument order: a method that needs the state takes ``(x, dt)`` (``f``, ``jacobian``, the
state-dependent ``F(x, dt)`` of :class:`CoordinatedTurn` and :class:`Turn3DAngles`); a linear
model's ``F(dt)`` and ``Q(dt)`` take the interval alone. A model whose process noise depends on
the state says so with the class attribute ``state_dependent_noise = True``; its ``Q`` is then
``Q(x, dt)`` (:class:`Turn3DAngles`). Every other model has ``state_dependent_noise = False``
and ``Q(dt)``; :class:`kftrack.imm.EKFMode` and :class:`kftrack.imm.UKFMode` read the attribute.

Conventions
-----------
* State order is interleaved by axis: ``[x, vx, y, vy, z, vz]``, ``[x, vx, ax, y, vy, ay]``;
  the turn rate ``omega`` (rad/s, counter-clockwise positive) comes last.
* Shapes: ``x`` is ``(..., n)``; ``dt`` (s) is a scalar or an array broadcasting with the batch
  axes; ``F``, ``Q``, ``jacobian`` return ``(..., n, n)``.
* ``dt`` may be negative in ``F``, ``f`` and ``jacobian`` (``F(-dt)`` is the inverse of
  ``F(dt)``: retrodiction); ``Q(dt)`` needs ``dt >= 0``, since the noise of a backward step
  is not ``Q(|dt|)``.
* Noise parameters say what they are. ``q`` is a **continuous-time power spectral density**
  (continuous white noise, e.g. m²/s³ for white acceleration); ``sigma2`` is a **discrete
  variance** of a noise held constant over each interval (e.g. m²/s⁴). Each model takes
  exactly one of the two.
* Singular points have series branches: the turn models at :math:`\omega T \to 0`
  (exact at :math:`\omega = 0`), Singer at :math:`\alpha T \to 0` (tends to constant acceleration).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import ClassVar

import numpy as np
import sympy as sp

from . import symbolic as sym
from .discretize import van_loan
from ._validate import as_float_array, as_vector, check_finite

__all__ = [
    "ConstantVelocity", "ConstantAcceleration", "Singer", "KnownTurn", "CoordinatedTurn",
    "CoordinatedTurnPolar", "van_loan", "singer_acceleration_variance", "turn_state_to_polar",
    "turn_state_from_polar", "TURN_SERIES_THRESHOLD", "SINGER_SERIES_THRESHOLD",
    "Turn3D", "turn3d_A", "Turn3DAngles", "turn3d_angles_A", "ANGLES_STATE",
]

#: ``|omega*dt|`` below which the turn models use their Taylor series (order 20 in omega).
TURN_SERIES_THRESHOLD = 0.5
#: ``|alpha*dt|`` below which Singer uses its Taylor series (order 24 in alpha).
SINGER_SERIES_THRESHOLD = 1.0
_TURN_SERIES = (sym.omega, sym.omega * sym.T, TURN_SERIES_THRESHOLD, 20)
_SINGER_SERIES = (sym.alpha, sym.alpha * sym.T, SINGER_SERIES_THRESHOLD, 24)


# --------------------------------------------------------------------------------------------
# generated functions, derived once per process
# --------------------------------------------------------------------------------------------
@lru_cache(maxsize=None)
def _kinematic(order: int) -> dict:
    A = sym.kinematic_A(order)
    G = sym.white_noise_gain(order + 1, [order])
    Gam = sym.kinematic_discrete_gain(order)
    args = [sym.T]
    return {
        "F": sym.GeneratedFunction(args, sym.transition_matrix(A)),
        "Qc": sym.GeneratedFunction(args, sym.continuous_white_noise(A, G, sp.Matrix([[1]]))),
        "Qd": sym.GeneratedFunction(args, sym.discrete_white_noise(Gam, 1)),
    }


@lru_cache(maxsize=None)
def _singer() -> dict:
    A = sym.singer_A()
    G = sym.white_noise_gain(3, [2])
    args = [sym.T, sym.alpha]
    return {
        "F": sym.GeneratedFunction(args, sym.transition_matrix(A), _SINGER_SERIES),
        "Qc": sym.GeneratedFunction(args, sym.continuous_white_noise(A, G, sp.Matrix([[1]])), _SINGER_SERIES),
    }


@lru_cache(maxsize=None)
def _known_turn() -> dict:
    A = sym.turn_A()
    G = sym.white_noise_gain(4, [1, 3])
    args = [sym.T, sym.omega]
    return {
        "F": sym.GeneratedFunction(args, sym.transition_matrix(A), _TURN_SERIES),
        "Qc": sym.GeneratedFunction(args, sym.continuous_white_noise(A, G, sp.eye(2)), _TURN_SERIES),
    }


@lru_cache(maxsize=None)
def _coordinated_turn(ndim: int) -> dict:
    s, f = sym.coordinated_turn_transition(ndim)
    args = [*s, sym.T]
    return {
        "f": sym.GeneratedFunction(args, f, _TURN_SERIES),
        "J": sym.GeneratedFunction(args, sym.jacobian(f, s), _TURN_SERIES),
    }


@lru_cache(maxsize=None)
def _polar_turn() -> dict:
    s, f = sym.polar_turn_transition()
    args = [*s, sym.T]
    return {
        "f": sym.GeneratedFunction(args, f, _TURN_SERIES),
        "J": sym.GeneratedFunction(args, sym.jacobian(f, s), _TURN_SERIES),
    }


# --------------------------------------------------------------------------------------------
# input checks and block assembly
# --------------------------------------------------------------------------------------------
def _dt(dt, nonnegative: bool = False, what: str = "") -> np.ndarray:
    arr = check_finite(as_float_array(dt, "dt"), "dt")
    if nonnegative and np.any(arr < 0):
        raise ValueError(f"dt must be >= 0{what}, got min(dt) = {arr.min():.6g}")
    return arr


def _nonneg(value, name: str, count: int) -> tuple[float, ...]:
    arr = check_finite(as_float_array(value, name), name)
    if arr.ndim == 0:
        arr = np.full(count, float(arr))
    if arr.shape != (count,):
        raise ValueError(f"{name} must be a scalar or have shape ({count},), got shape {arr.shape}")
    if np.any(arr < 0):
        raise ValueError(f"{name} must be >= 0, got {arr.tolist()}")
    return tuple(float(v) for v in arr)


def _ndim(ndim, allowed: tuple[int, ...]) -> int:
    if isinstance(ndim, bool) or not isinstance(ndim, (int, np.integer)) or ndim not in allowed:
        raise ValueError(f"ndim must be one of {allowed}, got {ndim!r}")
    return int(ndim)


def _one_of(q, sigma2, q_name: str = "q", sigma2_name: str = "sigma2") -> str:
    if (q is None) == (sigma2 is None):
        raise ValueError(
            f"give exactly one noise parameter: {q_name} (continuous-time spectral density) or "
            f"{sigma2_name} (discrete variance); got {q_name}={q!r}, {sigma2_name}={sigma2!r}"
        )
    return "continuous" if q is not None else "discrete"


def _block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    """Block-diagonal stack of ``(..., k_i, k_i)`` blocks with broadcast batch axes."""
    batch = np.broadcast_shapes(*(b.shape[:-2] for b in blocks))
    n = sum(b.shape[-1] for b in blocks)
    out = np.zeros(batch + (n, n))
    i = 0
    for b in blocks:
        k = b.shape[-1]
        out[..., i:i + k, i:i + k] = b
        i += k
    return out


def _apply(F: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.einsum("...ij,...j->...i", F, x)


def _check_batch(x: np.ndarray, dt_shape: tuple[int, ...]) -> None:
    """The batch axes of ``x`` ``(..., n)`` and the shape of ``dt`` must broadcast."""
    try:
        np.broadcast_shapes(x.shape[:-1], dt_shape)
    except ValueError:
        raise ValueError(f"dt must be a scalar or broadcast with the batch axes of x: got dt of shape "
                         f"{dt_shape} and x of shape {x.shape}") from None


def _position_selector(n: int, positions: tuple[int, ...]) -> np.ndarray:
    H = np.zeros((len(positions), n))
    H[np.arange(len(positions)), positions] = 1.0
    return H


# --------------------------------------------------------------------------------------------
# linear kinematic models
# --------------------------------------------------------------------------------------------
class _LinearModel:
    """Shared behaviour of the linear models: ``f(x, dt) = F(dt) x`` and ``jacobian = F``."""

    #: ``Q(dt)`` does not depend on the state (read by :mod:`kftrack.imm`).
    state_dependent_noise: ClassVar[bool] = False

    ndim: int
    _k: int  # states per axis

    @property
    def n(self) -> int:
        """State dimension."""
        return self.ndim * self._k

    @property
    def H(self) -> np.ndarray:
        """Position-measurement matrix, shape ``(ndim, n)``."""
        return _position_selector(self.n, tuple(range(0, self.n, self._k)))

    def f(self, x, dt) -> np.ndarray:
        """Transition function ``F(dt) x``; ``x`` ``(..., n)`` -> ``(..., n)``."""
        x = as_vector(x, "x", self.n)
        F = self.F(dt)
        _check_batch(x, F.shape[:-2])
        return _apply(F, x)

    def jacobian(self, x, dt) -> np.ndarray:
        """Jacobian of ``f``: ``F(dt)`` broadcast to the batch of ``x``, ``(..., n, n)``."""
        x = as_vector(x, "x", self.n)
        F = self.F(dt)
        _check_batch(x, F.shape[:-2])
        return np.broadcast_to(F, np.broadcast_shapes(F.shape[:-2], x.shape[:-1]) + F.shape[-2:]).copy()


@dataclass(frozen=True)
class _Kinematic(_LinearModel):
    ndim: int = 1
    q: float | tuple | None = None
    sigma2: float | tuple | None = None
    noise: str = field(init=False)
    _order = 1

    def __post_init__(self):
        object.__setattr__(self, "ndim", _ndim(self.ndim, (1, 2, 3)))
        noise = _one_of(self.q, self.sigma2)
        object.__setattr__(self, "noise", noise)
        name = "q" if noise == "continuous" else "sigma2"
        object.__setattr__(self, name, _nonneg(getattr(self, name), name, self.ndim))

    @property
    def _k(self) -> int:
        return self._order + 1

    def F(self, dt) -> np.ndarray:
        """Transition matrix, ``(..., n, n)``: per axis ``F[i, j] = dt**(j-i) / (j-i)!``."""
        Fa = _kinematic(self._order)["F"](_dt(dt))
        return _block_diag([Fa] * self.ndim)

    def Q(self, dt) -> np.ndarray:
        """Process noise, ``(..., n, n)``, by the model's noise convention (see the class)."""
        d = _dt(dt, nonnegative=True, what=" for the process noise Q(dt)")
        if self.noise == "continuous":
            Qa = _kinematic(self._order)["Qc"](d)
            return _block_diag([qi * Qa for qi in self.q])
        Qa = _kinematic(self._order)["Qd"](d)
        return _block_diag([si * Qa for si in self.sigma2])


@dataclass(frozen=True)
class ConstantVelocity(_Kinematic):
    r"""Nearly constant velocity, state ``[x, vx(, y, vy(, z, vz))]`` (m, m/s).

    Parameters
    ----------
    ndim : 1, 2 or 3 spatial axes.
    q : power spectral density of the continuous white acceleration, **m²/s³** (scalar or one
        per axis). Gives the DCWNA model, per axis
        :math:`Q = q\begin{bmatrix}T^3/3 & T^2/2\\ T^2/2 & T\end{bmatrix}` (full rank).
    sigma2 : variance of the discrete white acceleration held constant over each interval,
        **m²/s⁴**. Gives the DWNA model, :math:`\Gamma = [T^2/2, T]^\top`,
        :math:`Q = \sigma^2 \Gamma\Gamma^\top` (rank 1 per axis).

    Bar-Shalom, Li & Kirubarajan (2001), ch. 6. Give exactly one of ``q``, ``sigma2``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.models import ConstantVelocity
    >>> cv = ConstantVelocity(ndim=1, q=1.0)          # state [x, vx], q in m²/s³
    >>> cv.F(0.5)
    array([[1. , 0.5],
           [0. , 1. ]])
    >>> print(np.round(cv.Q(1.0), 6))                 # q [[T³/3, T²/2], [T²/2, T]] at T = 1
    [[0.333333 0.5     ]
     [0.5      1.      ]]
    >>> ConstantVelocity(ndim=2, sigma2=4.0).Q(np.array([0.5, 1.0, 2.0])).shape   # one Q per interval
    (3, 4, 4)
    """

    _order = 1


@dataclass(frozen=True)
class ConstantAcceleration(_Kinematic):
    r"""Nearly constant acceleration, state ``[x, vx, ax(, y, vy, ay(, z, vz, az))]``.

    Parameters
    ----------
    ndim : 1, 2 or 3 spatial axes.
    q : power spectral density of the continuous white jerk, **m²/s⁵**. Gives the continuous
        Wiener-process acceleration model,
        :math:`Q = q[[T^5/20, T^4/8, T^3/6], [T^4/8, T^3/3, T^2/2], [T^3/6, T^2/2, T]]`.
    sigma2 : variance of the acceleration increment over one interval, **m²/s⁴**. Gives the
        discrete Wiener-process acceleration model, :math:`\Gamma = [T^2/2, T, 1]^\top` (rank 1).

    Bar-Shalom, Li & Kirubarajan (2001), ch. 6. Give exactly one of ``q``, ``sigma2``.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.models import ConstantAcceleration
    >>> ca = ConstantAcceleration(ndim=1, q=1.0)      # state [x, vx, ax], q in m²/s⁵
    >>> ca.F(2.0)
    array([[1., 2., 2.],
           [0., 1., 2.],
           [0., 0., 1.]])
    >>> print(np.round(120 * ca.Q(1.0), 6))           # q [[T⁵/20, T⁴/8, T³/6], ...] times 120
    [[  6.  15.  20.]
     [ 15.  40.  60.]
     [ 20.  60. 120.]]
    """

    _order = 2


@dataclass(frozen=True)
class Singer(_LinearModel):
    r"""Singer (1970) manoeuvre model, state ``[x, vx, ax(, y, vy, ay(, z, vz, az))]``.

    The acceleration is a first-order Markov process, :math:`\dot a = -\alpha a + w`,
    :math:`\alpha = 1/\tau`, with :math:`w` continuous white noise.

    Parameters
    ----------
    tau : manoeuvre time constant :math:`\tau_m` (s), ``> 0``; ``np.inf`` gives constant
        acceleration exactly.
    ndim : 1, 2 or 3 spatial axes.
    q : power spectral density of :math:`w`, **m²/s⁵** (continuous).
    sigma2_a : alternatively, Singer's stationary variance of the target acceleration
        :math:`\sigma_m^2` (**m²/s⁴**), giving :math:`q = 2\alpha\sigma_m^2`. This is a
        parameter of the continuous model, not a discrete noise variance.

    ``F`` and ``Q`` are the exact exponential and noise integral (Singer 1970; Li & Jilkov 2003),
    with a Taylor branch for :math:`|\alpha T| < 1`, so that ``alpha -> 0`` tends to
    :class:`ConstantAcceleration` with spectral density ``q`` without cancellation.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.models import ConstantAcceleration, Singer
    >>> print(np.round(Singer(tau=10.0, q=1.0).F(1.0), 6))   # the acceleration decays as exp(-T/tau)
    [[1.       1.       0.483742]
     [0.       1.       0.951626]
     [0.       0.       0.904837]]
    >>> ca, s = ConstantAcceleration(q=1.0), Singer(tau=np.inf, q=1.0)   # tau -> inf: constant acceleration
    >>> bool(np.allclose(s.F(1.0), ca.F(1.0), rtol=1e-12) and np.allclose(s.Q(1.0), ca.Q(1.0), rtol=1e-12))
    True
    """

    tau: float = 1.0
    ndim: int = 1
    q: float | tuple | None = None
    sigma2_a: float | tuple | None = None
    _k = 3

    def __post_init__(self):
        object.__setattr__(self, "ndim", _ndim(self.ndim, (1, 2, 3)))
        tau_ = as_float_array(self.tau, "tau")
        if tau_.ndim != 0:
            raise ValueError(f"tau must be a scalar time constant (s), got shape {tau_.shape}")
        tau_ = float(tau_)
        if not tau_ > 0 or np.isnan(tau_):
            raise ValueError(f"tau must be > 0 (s; np.inf for constant acceleration), got {self.tau!r}")
        object.__setattr__(self, "tau", tau_)
        noise = _one_of(self.q, self.sigma2_a, "q", "sigma2_a")
        if noise == "continuous":
            object.__setattr__(self, "q", _nonneg(self.q, "q", self.ndim))
        else:
            s2 = _nonneg(self.sigma2_a, "sigma2_a", self.ndim)
            object.__setattr__(self, "sigma2_a", s2)
            object.__setattr__(self, "q", tuple(2.0 * v / self.tau for v in s2))

    @property
    def alpha(self) -> float:
        """Manoeuvre correlation rate :math:`\\alpha = 1/\\tau` (1/s)."""
        return 0.0 if np.isinf(self.tau) else 1.0 / self.tau

    def F(self, dt) -> np.ndarray:
        """Transition matrix, ``(..., n, n)``."""
        Fa = _singer()["F"](_dt(dt), self.alpha)
        return _block_diag([Fa] * self.ndim)

    def Q(self, dt) -> np.ndarray:
        """Exact continuous-white-noise process noise, ``(..., n, n)``."""
        Qa = _singer()["Qc"](_dt(dt, nonnegative=True, what=" for the process noise Q(dt)"), self.alpha)
        return _block_diag([qi * Qa for qi in self.q])


def singer_acceleration_variance(a_max: float, p_max: float, p_0: float) -> float:
    r"""Singer's (1970) acceleration variance from the expected manoeuvre,
    :math:`\sigma_m^2 = \frac{A_{max}^2}{3}(1 + 4P_{max} - P_0)` (m²/s⁴): the target accelerates at
    :math:`\pm A_{max}` with probability ``p_max`` each, not at all with ``p_0``, and uniformly
    in between otherwise.

    Examples
    --------
    >>> from kftrack.models import singer_acceleration_variance
    >>> singer_acceleration_variance(30.0, 0.1, 0.5)   # A_max = 30 m/s², P_max = 0.1, P_0 = 0.5
    270.0
    """
    a = float(check_finite(as_float_array(a_max, "a_max"), "a_max"))
    pm, p0 = float(as_float_array(p_max, "p_max")), float(as_float_array(p_0, "p_0"))
    if not (0 <= pm and 0 <= p0 and 2 * pm + p0 <= 1):
        raise ValueError(f"p_max and p_0 must be probabilities with 2*p_max + p_0 <= 1, got p_max={p_max!r}, p_0={p_0!r}")
    return a * a / 3.0 * (1.0 + 4.0 * pm - p0)


# --------------------------------------------------------------------------------------------
# turns
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class KnownTurn(_LinearModel):
    r"""Coordinated turn at a known, constant rate :math:`\omega` (linear model).

    State ``[x, vx, y, vy]`` (2-D) or ``[x, vx, y, vy, z, vz]`` (3-D: the turn is in the
    horizontal plane, the vertical axis moves at nearly constant velocity). Counter-clockwise
    positive (rad/s).

    .. math::

        F(T) = \begin{bmatrix} 1 & \frac{\sin\omega T}{\omega} & 0 & -\frac{1-\cos\omega T}{\omega}\\
        0 & \cos\omega T & 0 & -\sin\omega T\\ 0 & \frac{1-\cos\omega T}{\omega} & 1 &
        \frac{\sin\omega T}{\omega}\\ 0 & \sin\omega T & 0 & \cos\omega T\end{bmatrix}

    Parameters
    ----------
    omega : turn rate (rad/s); ``0`` gives constant velocity exactly.
    ndim : 2 or 3.
    q : spectral density of the continuous white acceleration in each axis, **m²/s³**. ``Q`` is
        then the **exact** noise integral of the turning model (it couples the axes:
        :math:`Q_{14} = -Q_{23} = q(\omega T - \sin\omega T)/\omega^2`), not the axis-decoupled
        constant-velocity approximation.
    sigma2 : variance of the discrete white acceleration per axis, **m²/s⁴** (direct-discrete,
        :math:`\Gamma = \mathrm{blockdiag}([T^2/2, T]^\top)`; Li & Jilkov 2003).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.models import KnownTurn
    >>> turn = KnownTurn(omega=np.pi / 2, q=0.0)      # a quarter turn per second, state [x, vx, y, vy]
    >>> print(np.round(turn.f(np.array([0.0, 1.0, 0.0, 0.0]), 1.0), 6) + 0.0)   # heading +x -> +y
    [0.63662 0.      0.63662 1.     ]
    >>> bool(np.allclose(KnownTurn(omega=0.0, q=1.0).F(2.0), np.kron(np.eye(2), [[1.0, 2.0], [0.0, 1.0]]), rtol=1e-12))   # omega = 0: constant velocity
    True
    """

    omega: float = 0.0
    ndim: int = 2
    q: float | None = None
    sigma2: float | None = None
    noise: str = field(init=False)
    _k = 2

    def __post_init__(self):
        object.__setattr__(self, "ndim", _ndim(self.ndim, (2, 3)))
        arr = check_finite(as_float_array(self.omega, "omega"), "omega")
        if arr.ndim != 0:
            raise ValueError(f"omega must be a scalar turn rate (rad/s), got shape {arr.shape}")
        object.__setattr__(self, "omega", float(arr))
        noise = _one_of(self.q, self.sigma2)
        object.__setattr__(self, "noise", noise)
        name = "q" if noise == "continuous" else "sigma2"
        object.__setattr__(self, name, _nonneg(getattr(self, name), name, 1)[0])

    def F(self, dt) -> np.ndarray:
        """Transition matrix, ``(..., n, n)``; exact at ``omega = 0`` (series branch)."""
        d = _dt(dt)
        Fh = _known_turn()["F"](d, self.omega)
        return Fh if self.ndim == 2 else _block_diag([Fh, _kinematic(1)["F"](d)])

    def Q(self, dt) -> np.ndarray:
        """Process noise, ``(..., n, n)``: exact continuous white noise (``q``) or direct discrete (``sigma2``)."""
        d = _dt(dt, nonnegative=True, what=" for the process noise Q(dt)")
        if self.noise == "continuous":
            Qh = self.q * _known_turn()["Qc"](d, self.omega)
            return Qh if self.ndim == 2 else _block_diag([Qh, self.q * _kinematic(1)["Qc"](d)])
        Qa = self.sigma2 * _kinematic(1)["Qd"](d)
        return _block_diag([Qa] * self.ndim)


@dataclass(frozen=True)
class CoordinatedTurn:
    r"""Nearly coordinated turn with the turn rate in the state (nonlinear; for the EKF).

    State ``[x, vx, y, vy, omega]`` (2-D) or ``[x, vx, y, vy, z, vz, omega]`` (3-D, constant
    velocity vertically); m, m/s, rad/s, counter-clockwise positive.
    ``f(x, dt)`` applies :class:`KnownTurn`'s ``F`` with the state's own :math:`\omega`; its
    Jacobian has the :math:`\omega` column (Bar-Shalom et al. 2001, §11.7), which tends
    to :math:`[-T^2 v_y/2, -T v_y, T^2 v_x/2, T v_x]` as :math:`\omega \to 0` (series branch).

    Parameters
    ----------
    ndim : 2 or 3.
    sigma2, sigma2_omega : direct-discrete "nearly coordinated turn" noise (Bar-Shalom et al.
        2001, §11.7): variances of the discrete white linear acceleration per axis
        (**m²/s⁴**) and of the turn-rate acceleration (**rad²/s⁴**), with
        :math:`\Gamma = [[T^2/2,0,0],[T,0,0],[0,T^2/2,0],[0,T,0],[0,0,T]]`.
    q, q_omega : continuous white noise instead: spectral densities of the linear acceleration
        (**m²/s³**) and of the turn-rate derivative (**rad²/s³**). ``Q`` is then
        :math:`\mathrm{blockdiag}(q\,Q_{CV}, \dots, q_\omega T)`, the continuous-white-noise
        ``Q`` of the model linearized at :math:`\omega = 0` (for the exact ``Q`` at a given
        :math:`\omega` see :class:`KnownTurn`).

    Give either (``sigma2``, ``sigma2_omega``) or (``q``, ``q_omega``).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.models import CoordinatedTurn
    >>> ct = CoordinatedTurn(ndim=2, sigma2=1.0, sigma2_omega=0.01)   # state [x, vx, y, vy, omega]
    >>> x = np.array([0.0, 10.0, 0.0, 0.0, 0.1])                    # 10 m/s along +x, turning 0.1 rad/s
    >>> print(np.round(ct.f(x, 1.0), 6))
    [9.983342 9.950042 0.499583 0.998334 0.1     ]
    >>> ct.jacobian(x, 1.0).shape, ct.Q(1.0).shape
    ((5, 5), (5, 5))
    """

    #: ``Q(dt)`` does not depend on the state (read by :mod:`kftrack.imm`).
    state_dependent_noise: ClassVar[bool] = False

    ndim: int = 2
    q: float | None = None
    q_omega: float | None = None
    sigma2: float | None = None
    sigma2_omega: float | None = None
    noise: str = field(init=False)

    def __post_init__(self):
        object.__setattr__(self, "ndim", _ndim(self.ndim, (2, 3)))
        noise = _one_of(self.q, self.sigma2)
        _one_of(self.q_omega, self.sigma2_omega, "q_omega", "sigma2_omega")
        if (self.q_omega is None) != (noise == "discrete"):
            raise ValueError("q_omega goes with q (continuous), sigma2_omega with sigma2 (discrete); "
                             f"got q={self.q!r}, q_omega={self.q_omega!r}, sigma2={self.sigma2!r}, "
                             f"sigma2_omega={self.sigma2_omega!r}")
        object.__setattr__(self, "noise", noise)
        for name in (("q", "q_omega") if noise == "continuous" else ("sigma2", "sigma2_omega")):
            object.__setattr__(self, name, _nonneg(getattr(self, name), name, 1)[0])

    @property
    def n(self) -> int:
        """State dimension (5 or 7)."""
        return 2 * self.ndim + 1

    @property
    def H(self) -> np.ndarray:
        """Position-measurement matrix, ``(ndim, n)``."""
        return _position_selector(self.n, tuple(range(0, 2 * self.ndim, 2)))

    def _call(self, key: str, x, dt) -> np.ndarray:
        x = as_vector(x, "x", self.n)
        d = _dt(dt)
        _check_batch(x, d.shape)
        return _coordinated_turn(self.ndim)[key](*np.moveaxis(x, -1, 0), d)

    def f(self, x, dt) -> np.ndarray:
        """Transition function, ``(..., n) -> (..., n)``; exact at ``omega = 0``."""
        return self._call("f", x, dt)[..., 0]

    def jacobian(self, x, dt) -> np.ndarray:
        """Jacobian ``df/dx`` at ``x``, ``(..., n, n)``, including the ``omega`` column."""
        return self._call("J", x, dt)

    def F(self, x, dt) -> np.ndarray:
        """State-dependent transition matrix with ``f(x, dt) = F(x, dt) @ x`` (the ``omega`` of
        ``x``; the ``omega`` column is ``[0, ..., 0, 1]``), ``(..., n, n)``."""
        J = self.jacobian(x, dt)
        J[..., :-1, -1] = 0.0
        return J

    def Q(self, dt) -> np.ndarray:
        """Process noise, ``(..., n, n)`` (see the class for the two conventions)."""
        d = _dt(dt, nonnegative=True, what=" for the process noise Q(dt)")
        if self.noise == "continuous":
            Qa = self.q * _kinematic(1)["Qc"](d)
            return _block_diag([Qa] * self.ndim + [self.q_omega * d[..., None, None]])
        Qa = self.sigma2 * _kinematic(1)["Qd"](d)
        return _block_diag([Qa] * self.ndim + [self.sigma2_omega * (d * d)[..., None, None]])


@dataclass(frozen=True)
class CoordinatedTurnPolar:
    r"""The same coordinated turn in polar-velocity form, state ``[x, y, v, chi, omega]``
    (m, m, m/s, rad, rad/s; heading :math:`\chi` from +x, counter-clockwise):

    .. math::

        x^+ = x + \tfrac{2v}{\omega}\sin\tfrac{\omega T}{2}\cos\!\left(\chi + \tfrac{\omega T}{2}\right),\;
        y^+ = y + \tfrac{2v}{\omega}\sin\tfrac{\omega T}{2}\sin\!\left(\chi + \tfrac{\omega T}{2}\right),\;
        v^+ = v,\; \chi^+ = \chi + \omega T,\; \omega^+ = \omega .

    Only the motion (``f``, ``jacobian``, ``H``); convert states with :func:`turn_state_to_polar`.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.models import CoordinatedTurnPolar, turn_state_from_polar
    >>> s = np.array([0.0, 0.0, 10.0, 0.0, np.pi / 20])   # [x, y, v, chi, omega]: 10 m/s along +x, turning left
    >>> print(np.round(CoordinatedTurnPolar().f(s, 10.0), 6) + 0.0)   # a quarter turn of radius v / omega
    [63.661977 63.661977 10.        1.570796  0.15708 ]
    >>> print(np.round(turn_state_from_polar(s), 6) + 0.0)            # the same state as [x, vx, y, vy, omega]
    [ 0.      10.       0.       0.       0.15708]
    """

    #: ``Q(dt)`` does not depend on the state (read by :mod:`kftrack.imm`).
    state_dependent_noise: ClassVar[bool] = False

    n: int = field(default=5, init=False)

    @property
    def H(self) -> np.ndarray:
        """Position-measurement matrix, ``(2, 5)``."""
        return _position_selector(5, (0, 1))

    def _call(self, key: str, x, dt) -> np.ndarray:
        x = as_vector(x, "x", 5)
        d = _dt(dt)
        _check_batch(x, d.shape)
        return _polar_turn()[key](*np.moveaxis(x, -1, 0), d)

    def f(self, x, dt) -> np.ndarray:
        """Transition function, ``(..., 5) -> (..., 5)``; exact at ``omega = 0``."""
        return self._call("f", x, dt)[..., 0]

    def jacobian(self, x, dt) -> np.ndarray:
        """Jacobian ``df/dx``, ``(..., 5, 5)``."""
        return self._call("J", x, dt)


def turn_state_to_polar(x) -> np.ndarray:
    """``[x, vx, y, vy, omega]`` -> ``[x, y, v, chi, omega]`` (speed, heading ``chi = atan2(vy, vx)``)."""
    x = as_vector(x, "x", 5)
    return np.stack([x[..., 0], x[..., 2], np.hypot(x[..., 1], x[..., 3]),
                     np.arctan2(x[..., 3], x[..., 1]), x[..., 4]], axis=-1)


def turn_state_from_polar(s) -> np.ndarray:
    """``[x, y, v, chi, omega]`` -> ``[x, vx, y, vy, omega]`` (heading ``chi`` in rad from +x)."""
    s = as_vector(s, "s", 5)
    return np.stack([s[..., 0], s[..., 2] * np.cos(s[..., 3]), s[..., 1],
                     s[..., 2] * np.sin(s[..., 3]), s[..., 4]], axis=-1)


# --------------------------------------------------------------------------------------------
# numerical discretization of any linear model
# --------------------------------------------------------------------------------------------
# --------------------------------------------------------------------------------------------
# 3-D turns (chapter 6)
# --------------------------------------------------------------------------------------------
#: Symbols of seed 001's 8-state model, interleaved, the two rates last.
ANGLES_STATE = sp.Matrix(sp.symbols("x v_x y v_y h v_h omega_chi omega_gamma", real=True))


def turn3d_angles_A(form: str = "paper") -> sp.Matrix:
    r"""Continuous system matrix :math:`A(\mathbf x)` of seed 001's 3-D turn (Agner Júnior et al.
    2019, eq. 24, rebuilt), state ``[x, vx, y, vy, h, vh, omega_chi, omega_gamma]``: constant
    heading rate :math:`\omega_\chi` and flight-path-angle rate :math:`\omega_\gamma`, with
    :math:`\cos\chi = v_x/\rho`, :math:`\sin\chi = v_y/\rho`, :math:`\rho = \sqrt{v_x^2+v_y^2}`.

    ``form="paper"``: the vertical row :math:`\dot v_h = (\omega_\gamma/\sin\chi) v_y` (eq. 17),
    singular for flight along :math:`\pm x`; ``"nonsingular"``:
    :math:`\dot v_h = \omega_\gamma(\cos\chi\,v_x + \sin\chi\,v_y) = \omega_\gamma\rho`, the same on
    the exact motion and regular everywhere except vertical flight.
    """
    if form not in ("paper", "nonsingular"):
        raise ValueError(f"form must be 'paper' or 'nonsingular', got {form!r}")
    x, vx, y, vy, h, vh, wc, wg = ANGLES_STATE
    rho = sp.sqrt(vx**2 + vy**2)
    c, s = vx / rho, vy / rho
    A = sp.zeros(8, 8)
    A[0, 1] = A[2, 3] = A[4, 5] = 1
    A[1, 3], A[1, 5] = -wc, -c * wg
    A[3, 1], A[3, 5] = wc, -s * wg
    if form == "paper":
        A[5, 3] = wg / s
    else:
        A[5, 1], A[5, 3] = c * wg, s * wg
    return A


@lru_cache(maxsize=None)
def _angles_turn(form: str) -> dict:
    X = ANGLES_STATE
    A = turn3d_angles_A(form)
    F = sym.taylor_transition(A, 2)
    f = F * X
    args = [*X, sym.T]
    out = {"F": sym.GeneratedFunction(args, F), "f": sym.GeneratedFunction(args, f),
           "J": sym.GeneratedFunction(args, f.jacobian(X))}
    Bc = sym.white_noise_gain(8, [1, 3, 5, 6, 7])
    out["Gamma"] = sym.GeneratedFunction(args, sp.expand((sp.eye(8) * sym.T + sym.T**2 / 2 * A) * Bc))
    if form == "nonsingular":
        fc = A * X  # the continuous vector field
        fc2 = fc.jacobian(X) * fc
        out["f_taylor_exact"] = sym.GeneratedFunction(args, X + sym.T * fc + sym.T**2 / 2 * fc2)
    return out


def _int_cos_sin(phi, c, dt):
    r""":math:`\int_0^T\cos(\phi + c\tau)d\tau` and the same with sin, stable as :math:`c \to 0`."""
    x = c * dt
    s0 = np.sinc(x / np.pi)
    xs1 = x * 0.5 * np.sinc(x / (2 * np.pi)) ** 2  # (1 - cos x)/x
    return dt * (np.cos(phi) * s0 - np.sin(phi) * xs1), dt * (np.sin(phi) * s0 + np.cos(phi) * xs1)


@dataclass(frozen=True)
class Turn3DAngles:
    r"""Seed 001's 3-D turn (Agner Júnior et al. 2019, §3): constant speed, heading rate
    :math:`\omega_\chi` and flight-path-angle rate :math:`\omega_\gamma`; the heading
    :math:`\chi = \operatorname{atan2}(v_y, v_x)` and path angle :math:`\gamma` are read from the
    velocity. State ``[x, vx, y, vy, h, vh, omega_chi, omega_gamma]`` (m, m/s, rad/s; ``h``, ``vh``
    are the paper's height and vertical speed, not a heading).

    * :meth:`F`: the paper's eq. (30), :math:`F = I + TA + \tfrac{T^2}{2}A^2` with :math:`\chi`
      and the rates frozen (what the paper calls its Jacobian: the **partial** Jacobian);
    * :meth:`f`: the second-order Taylor transition :math:`F(\mathbf x)\mathbf x` (eq. 28). Its
      one-step error is :math:`O(T^3)` in position but only :math:`O(T^2)` in velocity when both
      rates are non-zero (freezing :math:`\chi` drops :math:`\dot A\mathbf v` from the second
      derivative), :math:`O(T^3)` again when :math:`\omega_\gamma = 0`;
    * :meth:`jacobian`: the **full** Jacobian of :meth:`f`, with the :math:`\partial/\partial\omega`
      columns and the :math:`\partial\chi/\partial v` terms;
    * :meth:`f_taylor_exact`: the true second-order Taylor step
      :math:`\mathbf x + T\mathbf g + \tfrac{T^2}{2}J_g\mathbf g` of the vector field
      :math:`\mathbf g = A\mathbf x` (the paper's :math:`\ddot X = A\dot X` drops :math:`\dot A`),
      one-step error :math:`O(T^3)` in every component;
    * :meth:`f_exact`: the exact motion, :math:`\chi = \chi_0 + \omega_\chi t`,
      :math:`\gamma = \gamma_0 + \omega_\gamma t`, positions integrated in closed form.

    Parameters
    ----------
    form : ``"paper"`` (eq. 17, :math:`1/\sin\chi`, singular along :math:`\pm x`: its methods
        raise ``ValueError`` at :math:`v_y = 0`, i.e. :math:`\chi = 0` or :math:`\pi`, where it
        would return NaN/inf, and grow as :math:`1/\sin\chi` near there) or ``"nonsingular"``
        (see :func:`turn3d_angles_A`).
    sigma2, sigma2_omega : required, keyword only (0.0 for none): the paper's direct-discrete noise (§3.4): variances of the white
        acceleration per axis (**m²/s⁴**, :math:`\sigma_q^2`) and of the rate noise
        (**rad²/s⁴**), :math:`Q = \Gamma\,\mathrm{diag}(\sigma^2,\sigma^2,\sigma^2,
        \sigma_\omega^2,\sigma_\omega^2)\Gamma^\top`, :math:`\Gamma = (IT + \tfrac{T^2}{2}A)B_c`.
    """

    form: str = "nonsingular"
    sigma2: float = field(default=None, kw_only=True)
    sigma2_omega: float = field(default=None, kw_only=True)
    n: int = field(default=8, init=False)
    #: ``Q`` depends on the state: called as ``Q(x, dt)`` (read by :mod:`kftrack.imm`).
    state_dependent_noise: ClassVar[bool] = True

    def __post_init__(self):
        if self.form not in ("paper", "nonsingular"):
            raise ValueError(f"form must be 'paper' or 'nonsingular', got {self.form!r}")
        for name in ("sigma2", "sigma2_omega"):
            if getattr(self, name) is None:
                raise TypeError(f"Turn3DAngles requires {name}= (a discrete variance; pass 0.0 explicitly for no "
                                f"process noise), got sigma2={self.sigma2!r}, sigma2_omega={self.sigma2_omega!r}")
        object.__setattr__(self, "sigma2", _nonneg(self.sigma2, "sigma2", 1)[0])
        object.__setattr__(self, "sigma2_omega", _nonneg(self.sigma2_omega, "sigma2_omega", 1)[0])

    @property
    def H(self) -> np.ndarray:
        """Position-measurement matrix, ``(3, 8)``."""
        return _position_selector(8, (0, 2, 4))

    def _call(self, key: str, x, dt, form: str | None = None) -> np.ndarray:
        x = as_vector(x, "x", 8)
        form = form or self.form
        if form == "paper" and np.any(x[..., 3] == 0):
            k = tuple(int(i) for i in np.argwhere(x[..., 3] == 0)[0])
            chi = np.degrees(np.arctan2(0.0, x[(*k, 1)]))
            raise ValueError(
                f"x{list(k) if k else ''} has v_y = 0, heading chi = {chi:g} deg: the 'paper' form (eq. 17) divides "
                "by sin(chi) = v_y/rho and is singular at chi = 0 and 180 deg (flight along +-x); use "
                "form='nonsingular', the same model on the exact motion and regular there")
        with np.errstate(divide="ignore", invalid="ignore"):
            return _angles_turn(form)[key](*np.moveaxis(x, -1, 0), _dt(dt))

    def F(self, x, dt) -> np.ndarray:
        """The paper's transition / partial Jacobian (eq. 30) at ``x``, ``(..., 8, 8)``."""
        return self._call("F", x, dt)

    def f(self, x, dt) -> np.ndarray:
        """Second-order Taylor transition ``F(x) @ x`` (eq. 28), ``(..., 8)``."""
        return self._call("f", x, dt)[..., 0]

    def jacobian(self, x, dt) -> np.ndarray:
        """Full Jacobian of :meth:`f`, ``(..., 8, 8)``."""
        return self._call("J", x, dt)

    def f_taylor_exact(self, x, dt) -> np.ndarray:
        """Exact second-order Taylor step of the (non-singular) continuous model, ``(..., 8)``."""
        return self._call("f_taylor_exact", x, dt, "nonsingular")[..., 0]

    def Q(self, x, dt) -> np.ndarray:
        """The paper's direct-discrete process noise at ``x`` (eq. 30's Γ, 8×5), ``(..., 8, 8)``.
        State dependent (``state_dependent_noise = True``): called as ``Q(x, dt)``."""
        d = _dt(dt, nonnegative=True, what=" for the process noise Q(dt)")
        G = self._call("Gamma", x, d)
        S = np.diag([self.sigma2] * 3 + [self.sigma2_omega] * 2)
        return G @ S @ np.swapaxes(G, -1, -2)

    @staticmethod
    def state_from_motion(r, v, a) -> np.ndarray:
        r"""The 8-state ``[x, vx, y, vy, h, vh, omega_chi, omega_gamma]`` of a motion with
        position ``r``, velocity ``v`` and acceleration ``a`` (each ``(..., 3)``): the rates are
        the derivatives of :math:`\chi = \operatorname{atan2}(v_y, v_x)` and
        :math:`\gamma = \operatorname{atan2}(v_h, \rho)`, :math:`\rho = \sqrt{v_x^2 + v_y^2}`,

        .. math::

            \omega_\chi = \frac{v_x a_y - v_y a_x}{\rho^2}, \qquad
            \omega_\gamma = \frac{\rho\, a_h - v_h \dot\rho}{\lVert v\rVert^2}, \quad
            \dot\rho = \frac{v_x a_x + v_y a_y}{\rho}.

        Use it for the truth of a filter on :func:`kftrack.scenarios.tilted_zigzag`, whose
        turns in a tilted plane have varying rates. Singular for vertical flight (``rho = 0``).
        """
        r = as_vector(r, "r", 3)
        v = as_vector(v, "v", 3)
        a = as_vector(a, "a", 3)
        vx, vy, vh = np.moveaxis(v, -1, 0)
        ax, ay, ah = np.moveaxis(a, -1, 0)
        rho = np.hypot(vx, vy)
        if np.any(rho == 0):
            raise ValueError("v must have a horizontal component (rho > 0): the heading is undefined in vertical flight")
        w_chi = (vx * ay - vy * ax) / rho**2
        w_gam = (rho * ah - vh * (vx * ax + vy * ay) / rho) / (rho**2 + vh**2)
        shape = np.broadcast_shapes(r.shape, v.shape, a.shape)[:-1]
        parts = [r[..., 0], vx, r[..., 1], vy, r[..., 2], vh, w_chi, w_gam]
        return np.stack([np.broadcast_to(p, shape) for p in parts], axis=-1)

    @staticmethod
    def f_exact(x, dt) -> np.ndarray:
        r"""Exact transition, ``(..., 8)``: speed kept,
        :math:`\mathbf v(t) = v[\cos\chi\cos\gamma, \sin\chi\cos\gamma, \sin\gamma]` with
        :math:`\chi, \gamma` linear in time; the position integrals use
        :math:`\cos\chi\cos\gamma = \tfrac12[\cos(\chi+\gamma) + \cos(\chi-\gamma)]`. No singularity
        (also exact at zero rates)."""
        x = as_vector(x, "x", 8)
        d = _dt(dt)
        vx, vy, vh, wc, wg = x[..., 1], x[..., 3], x[..., 5], x[..., 6], x[..., 7]
        v = np.sqrt(vx**2 + vy**2 + vh**2)
        chi, gam = np.arctan2(vy, vx), np.arctan2(vh, np.hypot(vx, vy))
        cp, sp_ = _int_cos_sin(chi + gam, wc + wg, d)
        cm, sm = _int_cos_sin(chi - gam, wc - wg, d)
        _, sh = _int_cos_sin(gam, wg, d)
        chi1, gam1 = chi + wc * d, gam + wg * d
        out = np.stack([x[..., 0] + 0.5 * v * (cp + cm), v * np.cos(chi1) * np.cos(gam1),
                        x[..., 2] + 0.5 * v * (sp_ + sm), v * np.sin(chi1) * np.cos(gam1),
                        x[..., 4] + v * sh, v * np.sin(gam1),
                        np.broadcast_to(wc, np.shape(chi1)), np.broadcast_to(wg, np.shape(chi1))], axis=-1)
        return out


def _turn_rate_scalar(omega) -> float:
    arr = check_finite(as_float_array(omega, "omega"), "omega")
    if arr.ndim != 0:
        raise ValueError(f"omega must be a scalar turn rate (rad/s), got shape {arr.shape}")
    return float(arr)


@lru_cache(maxsize=None)
def _turn3d() -> dict:
    A = turn3d_A()
    G = sym.white_noise_gain(3, [2])
    args = [sym.T, sym.omega]
    return {
        "F": sym.GeneratedFunction(args, sym.transition_matrix(A), _TURN_SERIES),
        "Qc": sym.GeneratedFunction(args, sym.continuous_white_noise(A, G, sp.Matrix([[1]])), _TURN_SERIES),
    }


def turn3d_A() -> sp.Matrix:
    r"""Per-axis system matrix of the 3-D turn, state ``[p, v, a]``:
    :math:`\dot a = -\omega^2 v` (Watson & Blair; Li & Jilkov 2003, §VI)."""
    return sp.Matrix([[0, 1, 0], [0, 0, 1], [0, -sym.omega**2, 0]])


@dataclass(frozen=True)
class Turn3D(_LinearModel):
    r"""3-D constant turn with the turn-rate vector perpendicular to the velocity
    (Li & Jilkov 2003, §VI): per axis :math:`\dot a = -\omega^2 v + w`, the same
    :math:`\omega` (rad/s) for every axis. State ``[x, vx, ax, y, vy, ay(, z, vz, az)]``.

    Per axis (exact; series branch as :math:`\omega T \to 0`, where it tends to constant
    acceleration):

    .. math::

        F = \begin{bmatrix}1 & \frac{\sin\omega T}{\omega} & \frac{1-\cos\omega T}{\omega^2}\\
        0 & \cos\omega T & \frac{\sin\omega T}{\omega}\\ 0 & -\omega\sin\omega T & \cos\omega T\end{bmatrix}

    and ``Q`` the exact continuous-white-jerk integral with spectral density ``q`` (**m²/s⁵**).
    The motion :math:`\dot{\mathbf a} = -\omega^2\mathbf v` is a circle in a fixed plane: exact
    for constant speed and curvature only when the torsion is zero (a planar turn, in any tilted
    plane); on a helix it misses :math:`v^3\kappa\tau\,\mathbf b`
    (:func:`kftrack.frenet.turn_model_residual`).

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.models import Turn3D
    >>> turn = Turn3D(omega=0.1, q=1.0)                # state [x, vx, ax, y, vy, ay, z, vz, az]
    >>> x = np.array([0.0, 10.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])   # 10 m/s, centripetal 1 m/s² to +y
    >>> print(np.round(turn.f(x, 5 * np.pi)[[0, 1, 3, 4]], 6) + 0.0)   # a quarter turn later: x, vx, y, vy
    [100.   0. 100.  10.]
    """

    omega: float = 0.0
    q: float | tuple = 0.0
    ndim: int = 3
    _k = 3

    def __post_init__(self):
        object.__setattr__(self, "ndim", _ndim(self.ndim, (2, 3)))
        object.__setattr__(self, "omega", _turn_rate_scalar(self.omega))
        object.__setattr__(self, "q", _nonneg(self.q, "q", self.ndim))

    def F(self, dt) -> np.ndarray:
        """Transition matrix, ``(..., n, n)``."""
        return _block_diag([_turn3d()["F"](_dt(dt), self.omega)] * self.ndim)

    def Q(self, dt) -> np.ndarray:
        """Exact continuous-white-jerk process noise, ``(..., n, n)``."""
        Qa = _turn3d()["Qc"](_dt(dt, nonnegative=True, what=" for the process noise Q(dt)"), self.omega)
        return _block_diag([qi * Qa for qi in self.q])
