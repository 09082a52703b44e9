r"""The interacting multiple model (IMM) estimator of Blom & Bar-Shalom (1988), with GPB1 and a
clairvoyant (mode-matched) filter as references.

A target switches among ``r`` motion **modes** as a Markov chain with

.. math:: \Pi_{ij} = P\{M_k = j \mid M_{k-1} = i\}, \qquad \textstyle\sum_j \Pi_{ij} = 1

(rows are "from", columns "to"). One IMM cycle (Bar-Shalom, Li & Kirubarajan 2001, §11.6.6):

1. mixing probabilities :math:`\bar c_j = \sum_i \Pi_{ij}\mu_i`,
   :math:`\mu_{i|j} = \Pi_{ij}\mu_i / \bar c_j`;
2. mixing :math:`x^{0j} = \sum_i \mu_{i|j} x^i`,
   :math:`P^{0j} = \sum_i \mu_{i|j}[P^i + (x^i - x^{0j})(x^i - x^{0j})^\top]`;
3. mode-matched prediction from :math:`(x^{0j}, P^{0j})` (:meth:`IMM.predict`, which also sets
   the predicted mode probabilities :math:`\mu = \bar c`) and update (:meth:`IMM.update`),
   giving the likelihoods :math:`\Lambda_j = N(\nu_j; 0, S_j)`;
4. mode probabilities :math:`\mu_j \propto \Lambda_j \bar c_j`, computed in log space with
   log-sum-exp;
5. combination (output only, never fed back)
   :math:`x = \sum_j \mu_j x^j`, :math:`P = \sum_j \mu_j[P^j + (x^j - x)(x^j - x)^\top]`.

A step without a measurement is a :meth:`IMM.predict` alone: the mode probabilities become
:math:`\mu\Pi` and no likelihood is computed (no "update with nothing").

**Modes** follow a small protocol (:class:`Mode`): an attribute ``n`` (state dimension),
``predict(x, P, dt) -> (x, P)`` and ``update(x, P, z) -> u`` with ``u.x``, ``u.P``, ``u.loglik``;
all broadcast over leading batch axes. :class:`KalmanMode` wraps a linear model of
:mod:`kftrack.models`, :class:`EKFMode` (Jacobians) and :class:`UKFMode` (sigma points) a nonlinear
one (e.g. :class:`~kftrack.models.CoordinatedTurn`); a bank may mix the three.

**Modes of different dimension** (constant velocity ``[x, vx, y, vy]`` beside the coordinated
turn ``[x, vx, y, vy, omega]``). Every mode's state is a subset of one *common* state of
dimension ``N``: mode ``i`` holds the common components ``components[i]`` (by default the first
``n_i``, which fits the book's convention of putting ``omega`` last). The rule is **unbiased
mixing** (Yuan, Bar-Shalom et al. 2012): when mixing into mode ``j``, a source mode ``i`` that
lacks some of ``j``'s components is completed with **mode j's own estimate and covariance** of
those components, with zero cross-covariance to ``i``'s components (``i`` carries no information
about them, and the completed covariance stays positive semi-definite). Components that ``j``
lacks are simply dropped (marginalized). Zero padding would instead pull ``omega`` towards 0 and
shrink its variance. The combined output is reported in the common state; there a mode lacking
components is completed in the same way from the combination of the *full* modes (those holding
every component; at least one is required). :func:`imm_smoother` smooths every such bank on the NumPy engine (Kim's
backward pass with the same completion; its JAX engine takes KalmanModes on the common state).

Shapes: ``x`` ``(..., N)``, ``P`` ``(..., N, N)``, ``mu`` ``(..., r)``; time first for sequences.
"""
from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple, Protocol, runtime_checkable

import numpy as np
import scipy.linalg
from array_api_compat import array_namespace

from ._validate import as_float_array, as_matrix, as_vector, broadcast_batch, check_angles, check_covariance
from ._validate import check_finite, check_missing, check_state, is_tracer, stand_in
from .kernels import Update, ekf_predict, ekf_update, kf_predict, kf_update, logsumexp, mixing_log_weights, moment_match
from .kernels import rts_step, ukf_predict, ukf_update
from .kernels import residual, unscented, wrap_state
from .engines import PerDt, check_dtype, check_dts, choose_engine, run_imm_scan, run_imm_smoother_scan
from .engines import run_imm_total_scan, to_engine, use_jax
from .ukf import Points, check_points

__all__ = [
    "Mode", "KalmanMode", "EKFMode", "UKFMode", "IMMState", "IMMResult", "IMM", "GPB1",
    "sojourn_generator", "sojourn_transition", "first_order_transition", "SojournTransition",
    "check_transition", "stationary_distribution", "mix_gaussians", "imm_filter", "clairvoyant_filter",
    "IMMSmootherResult", "imm_smoother", "IMMParams", "imm_loglik", "imm_params",
]

_TOL = 1e-9  # tolerance on sums of probabilities


_PerDt = PerDt  # cache of fn(dt) per distinct interval (kftrack.engines.PerDt)


# --------------------------------------------------------------------------------------------
# modes
# --------------------------------------------------------------------------------------------
@runtime_checkable
class Mode(Protocol):
    """What the IMM needs of a mode-matched filter (all methods broadcast over batch axes).

    Attributes
    ----------
    n : int
        State dimension.

    Methods
    -------
    predict(x, P, dt)
        Time update over ``dt`` seconds; returns ``(x, P)``.
    update(x, P, z)
        Measurement update; returns ``u`` with ``u.x`` ``(..., n)``, ``u.P`` ``(..., n, n)`` and
        ``u.loglik`` ``(...)``, the log-likelihood :math:`\\log N(\\nu; 0, S)` of the innovation.
    predict_linearized(x, P, dt)
        Optional, needed by :func:`imm_smoother` only: ``predict``'s ``(x, P)`` and the
        ``(..., n, n)`` transition matrix the backward pass uses (``F(dt)``, the Jacobian at ``x``,
        or a statistical linearization).
    """

    n: int

    def predict(self, x: np.ndarray, P: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]: ...

    def update(self, x: np.ndarray, P: np.ndarray, z: np.ndarray): ...


def _measurement(model, R, H):
    H = np.asarray(model.H if H is None else H, dtype=float)
    if H.ndim != 2 or H.shape[1] != model.n:
        raise ValueError(f"H must have shape (m, {model.n}) for a model with {model.n} states, got shape {H.shape}")
    R = check_covariance(R, "R", H.shape[0], positive_definite=True)
    return H, R


def _takes_dt_alone(fn) -> bool:
    """Whether ``fn`` can be called as ``fn(dt)`` (a callable whose signature cannot be read is
    given the benefit of the doubt)."""
    if not callable(fn):
        return False
    try:
        inspect.signature(fn).bind(1.0)
    except TypeError:
        return False
    except ValueError:  # no signature (a builtin): cannot tell
        return True
    return True


def _check_linear_model(model) -> None:
    """Refuse, when a :class:`KalmanMode` is built, a model that is not linear in the IMM's sense:
    ``F(dt)`` and ``Q(dt)`` of the interval alone (a nonlinear model such as
    :class:`~kftrack.models.CoordinatedTurn` has ``F(x, dt)``; seed 001's turn has ``Q(x, dt)``)."""
    name = type(model).__name__
    for attr in ("F", "Q"):
        if not _takes_dt_alone(getattr(model, attr, None)):
            raise TypeError(f"model must be a linear model with {attr}(dt) for a KalmanMode, got {name}, whose "
                            f"{attr} cannot be called as {attr}(dt) (a nonlinear model); use EKFMode (Jacobians) "
                            "or UKFMode (sigma points) for it")
    if getattr(model, "state_dependent_noise", False):
        raise TypeError(f"model must have a process noise Q(dt) independent of the state for a KalmanMode, got "
                        f"{name} (state_dependent_noise = True); use EKFMode or UKFMode for it")


class KalmanMode:
    """Linear Kalman-filter mode: ``model.F(dt)``, ``model.Q(dt)`` and a linear measurement.

    Parameters
    ----------
    model : a linear model of :mod:`kftrack.models` (``ConstantVelocity``, ``KnownTurn``, ...):
        anything with ``n``, ``F(dt)``, ``Q(dt)`` and, unless ``H`` is given, ``H``. A nonlinear
        model (``F(x, dt)``, as :class:`~kftrack.models.CoordinatedTurn`, or a state-dependent
        ``Q``) raises ``TypeError``: use :class:`EKFMode` or :class:`UKFMode`.
    R : (m, m) measurement-noise covariance.
    H : (m, n) measurement matrix; default ``model.H`` (the positions).
    """

    def __init__(self, model, R, H=None):
        _check_linear_model(model)
        self.model = model
        self.n = int(model.n)
        self.H, self.R = _measurement(model, R, H)
        self._FQ = _PerDt(lambda dt: (np.asarray(model.F(dt), dtype=float), np.asarray(model.Q(dt), dtype=float)))

    def predict(self, x, P, dt):
        """Kalman time update with ``F(dt)``, ``Q(dt)``."""
        F, Q = self._FQ(dt)
        return kf_predict(x, P, F, Q)

    def predict_linearized(self, x, P, dt):
        """:meth:`predict` and the transition matrix ``F(dt)`` (what :func:`imm_smoother` needs)."""
        F, Q = self._FQ(dt)
        x_pred, P_pred = kf_predict(x, P, F, Q)
        return x_pred, P_pred, F

    def update(self, x, P, z) -> Update:
        """Kalman measurement update (Joseph form); see :func:`kftrack.kalman.update`."""
        return kf_update(x, P, z, self.H, self.R)

    def __repr__(self) -> str:
        return f"KalmanMode({self.model!r})"


class _NonlinearMode:
    """What :class:`EKFMode` and :class:`UKFMode` share: the model, the process noise (fixed or
    state dependent), and a linear (``H``) or nonlinear (``h``) measurement with angle components."""

    def __init__(self, model, R, H=None, h: Callable | None = None, angle_components: Sequence[int] = (),
                 state_dependent_Q: bool | None = None):
        self.model = model
        self.n = int(model.n)
        if state_dependent_Q is None:
            state_dependent_Q = getattr(model, "state_dependent_noise", False)
        if not isinstance(state_dependent_Q, (bool, np.bool_)):
            raise TypeError("state_dependent_Q must be True, False or None (read model.state_dependent_noise), "
                            f"got {state_dependent_Q!r}")
        self.state_dependent_Q = bool(state_dependent_Q)
        if h is not None and not callable(h):  # an (m, n) array: the linear measurement H x
            H, h = h, None
        if h is None:
            self.H, self.R = _measurement(model, R, H)
            self._h = lambda x: (self.H @ x[..., None])[..., 0]
        else:
            self.R = check_covariance(R, "R", positive_definite=True)
            self._h = h
        self._angles = check_angles(angle_components, self.R.shape[-1])

    def _Q(self, x, dt):
        return self.model.Q(x, dt) if self.state_dependent_Q else self.model.Q(dt)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.model!r})"


class EKFMode(_NonlinearMode):
    r"""Extended-Kalman-filter mode: ``model.f(x, dt)``, ``model.jacobian(x, dt)``, ``model.Q(dt)``
    (or ``model.Q(x, dt)``, see ``state_dependent_Q``).

    Parameters
    ----------
    model : e.g. :class:`kftrack.models.CoordinatedTurn` (state ``[x, vx, y, vy, omega]``).
    R : (m, m) measurement-noise covariance.
    H : (m, n) linear measurement matrix (default ``model.H``), used unless ``h`` is given.
    h, H_jac : nonlinear measurement function ``(..., n) -> (..., m)`` and its Jacobian.
    angle_components : indices of ``z`` that are angles (innovation wrapped), with ``h``.
    state_dependent_Q : whether the process noise depends on the state, called as
        ``model.Q(x, dt)`` at the estimate being predicted (the mixed estimate in the IMM), as
        seed 001's :meth:`kftrack.models.Turn3DAngles.Q`
        :math:`\Gamma(\hat x)\Sigma\Gamma(\hat x)^\top`. Default ``None``: the model's class
        attribute ``state_dependent_noise`` (True: ``Q(x, dt)``; absent or False: ``Q(dt)``).
    """

    def __init__(self, model, R, H=None, h: Callable | None = None, H_jac: Callable | None = None,
                 angle_components: Sequence[int] = (), state_dependent_Q: bool | None = None):
        if h is not None and not callable(h):
            if H_jac is not None:
                raise ValueError("H_jac must be None when h is an (m, n) matrix (the linear measurement H x "
                                 f"has Jacobian H), got {type(H_jac).__name__}")
        elif (h is None) != (H_jac is None):
            raise ValueError("h and H_jac go together: give both (nonlinear measurement) or neither")
        super().__init__(model, R, H, h, angle_components, state_dependent_Q)
        self._H_jac = (lambda x: self.H) if H_jac is None else H_jac

    def predict(self, x, P, dt):
        """EKF time update; see :func:`kftrack.ekf.ekf_predict`."""
        return ekf_predict(x, P, lambda s: self.model.f(s, dt), lambda s: self.model.jacobian(s, dt),
                            self._Q(x, dt))

    def predict_linearized(self, x, P, dt):
        """:meth:`predict` and the Jacobian :math:`F = \\partial f/\\partial x` at ``x`` it used
        (what :func:`imm_smoother` needs: the extended RTS step)."""
        F = self.model.jacobian(x, dt)
        x_pred, P_pred = ekf_predict(x, P, lambda s: self.model.f(s, dt), lambda s: F, self._Q(x, dt))
        return x_pred, P_pred, F

    def update(self, x, P, z) -> Update:
        """EKF measurement update; see :func:`kftrack.ekf.ekf_update`."""
        return ekf_update(x, P, z, self._h, self._H_jac, self.R, self._angles)


class UKFMode(_NonlinearMode):
    r"""Unscented-Kalman-filter mode: the unscented transform of ``model.f(x, dt)`` plus
    ``model.Q(dt)`` (or ``model.Q(x, dt)`` at the mean, as in :class:`EKFMode`), and the unscented
    measurement update; no Jacobians. ``model.f`` and ``h`` must broadcast over a stack of sigma
    points ``(..., 2n+1, n)``.

    Parameters
    ----------
    model : e.g. :class:`kftrack.models.CoordinatedTurn`; needs ``n``, ``f(x, dt)``, ``Q``.
    R : (m, m) measurement-noise covariance.
    H : (m, n) linear measurement matrix (default ``model.H``), used unless ``h`` is given.
    h : nonlinear measurement function ``(..., n) -> (..., m)``.
    points : sigma-point scheme (default :class:`kftrack.ukf.MerweScaledSigmaPoints`).
    angle_components : indices of ``z`` that are angles (circular mean, wrapped innovation).
    state_angles : indices of the state that are angles (e.g. a heading).
    state_dependent_Q : as in :class:`EKFMode`.
    """

    def __init__(self, model, R, H=None, h: Callable | None = None, points: Points | None = None,
                 angle_components: Sequence[int] = (), state_angles: Sequence[int] = (),
                 state_dependent_Q: bool | None = None):
        super().__init__(model, R, H, h, angle_components, state_dependent_Q)
        self.points = check_points(points)
        self._state_angles = check_angles(state_angles, self.n, "state_angles")

    def predict(self, x, P, dt):
        """UKF time update; see :func:`kftrack.ukf.ukf_predict`."""
        return ukf_predict(x, P, lambda s: self.model.f(s, dt), self._Q(x, dt), self.points, self._state_angles)

    def predict_linearized(self, x, P, dt):
        r""":meth:`predict` and the statistical linearization of ``f`` over the sigma points,
        :math:`F = C^\top P^{+}` with the cross-covariance :math:`C = \sum_i W^c_i
        (\mathcal X_i - x)(f(\mathcal X_i) - x^-)^\top` (what :func:`imm_smoother` needs). With it
        the RTS gain :math:`P F^\top (P^-)^{-1} = C (P^-)^{-1}` is the unscented RTS smoother's
        (Särkkä 2008): no Jacobian of the model is needed."""
        x_pred, P_pred = self.predict(x, P, dt)
        _, _, C, _ = unscented(lambda s: self.model.f(s, dt), x, P, self.points, self._state_angles,
                               self._state_angles)
        F = np.swapaxes(np.linalg.pinv(P, hermitian=True) @ C, -1, -2)  # C^T P^+ (P symmetric)
        return x_pred, P_pred, F

    def update(self, x, P, z) -> Update:
        """UKF measurement update; see :func:`kftrack.ukf.ukf_update`."""
        return ukf_update(x, P, z, self._h, self.R, self.points, self._state_angles, self._angles)


# --------------------------------------------------------------------------------------------
# Markov transition matrices
# --------------------------------------------------------------------------------------------
def check_transition(Pi, r: int | None = None, name: str = "transition") -> np.ndarray:
    """Validate a Markov matrix ``Pi[i, j] = P(j at k | i at k-1)``: ``(r, r)``, finite,
    entries in [0, 1], rows summing to one (to 1e-9). Returns it as a float array."""
    Pi = check_finite(as_float_array(Pi, name), name)
    if Pi.ndim != 2 or Pi.shape[0] != Pi.shape[1] or (r is not None and Pi.shape[0] != r):
        want = f"({r}, {r}) for {r} modes" if r is not None else "(r, r)"
        raise ValueError(f"{name} must be a square Markov matrix of shape {want}, got shape {Pi.shape}")
    if np.any(Pi < 0):
        raise ValueError(f"{name} must have non-negative entries (probabilities), got min {Pi.min():.6g}")
    rows = Pi.sum(axis=1)
    if np.any(np.abs(rows - 1.0) > _TOL):
        raise ValueError(f"{name} rows must sum to 1 (Pi[i, j] = P(j | i)), got row sums {rows.tolist()}")
    return Pi


def _check_probability(mu, r: int, name: str) -> np.ndarray:
    mu = as_vector(mu, name, r)
    if np.any(mu < 0):
        raise ValueError(f"{name} must be a probability vector (entries >= 0), got min {mu.min():.6g}")
    s = mu.sum(-1)
    if np.any(np.abs(s - 1.0) > _TOL):
        raise ValueError(f"{name} must sum to 1 over its last axis, got sum {np.ravel(s)[0]:.12g}")
    return mu


def _check_tau(tau) -> np.ndarray:
    tau = check_finite(as_float_array(tau, "tau"), "tau")
    if tau.ndim != 1 or tau.size < 2:
        raise ValueError(f"tau must be a vector of r >= 2 mean sojourn times (s), got shape {tau.shape}")
    if np.any(tau <= 0):
        raise ValueError(f"tau must be > 0 (mean sojourn times, s), got {tau.tolist()}")
    return tau


def sojourn_generator(tau, switch=None) -> np.ndarray:
    r"""Generator :math:`\Lambda` of a continuous-time mode chain from mean sojourn times.

    :math:`\Lambda_{ii} = -1/\tau_i` and :math:`\Lambda_{ij} = S_{ij}/\tau_i` for :math:`j \ne i`:
    the mode ``i`` lasts an exponential time of mean :math:`\tau_i`, then jumps to ``j`` with
    probability :math:`S_{ij}`. Rows of :math:`\Lambda` sum to zero.

    Parameters
    ----------
    tau : (r,) mean sojourn times (s), > 0.
    switch : (r, r) jump probabilities, zero diagonal, rows summing to 1; default: uniform
        over the other modes.
    """
    tau = _check_tau(tau)
    r = tau.size
    if switch is None:
        S = (np.ones((r, r)) - np.eye(r)) / (r - 1)
    else:
        S = check_transition(switch, r, "switch")
        if np.any(np.diag(S) != 0):
            raise ValueError(f"switch must have a zero diagonal (where a jump goes), got diagonal {np.diag(S).tolist()}")
    return S / tau[:, None] - np.diag(1.0 / tau)


def sojourn_transition(tau, dt: float, switch=None) -> np.ndarray:
    r"""Markov matrix over an interval ``dt`` from mean sojourn times: :math:`\Pi(dt) = e^{\Lambda dt}`
    (:func:`sojourn_generator`), valid for any, also irregular, ``dt`` (s, >= 0), with
    :math:`\Pi(dt_1 + dt_2) = \Pi(dt_1)\Pi(dt_2)`."""
    d = float(check_finite(as_float_array(dt, "dt"), "dt"))
    if d < 0:
        raise ValueError(f"dt must be >= 0, got {d}")
    Pi = scipy.linalg.expm(sojourn_generator(tau, switch) * d)
    Pi = np.clip(Pi, 0.0, None)
    return Pi / Pi.sum(axis=1, keepdims=True)


def first_order_transition(tau, dt: float) -> np.ndarray:
    r"""The common first-order approximation :math:`\Pi_{ii} = 1 - dt/\tau_i` (off-diagonal shared
    uniformly), as in seed 001's eq. (43); valid only for :math:`dt \ll \tau_i` (requires
    ``dt <= min(tau)``). Compare with :func:`sojourn_transition`."""
    tau = _check_tau(tau)
    d = float(check_finite(as_float_array(dt, "dt"), "dt"))
    if not 0 <= d <= tau.min():
        raise ValueError(f"dt must lie in [0, min(tau)] = [0, {tau.min():g}] for the first-order rule, got {d}")
    return np.eye(tau.size) + sojourn_generator(tau) * d


class SojournTransition:
    """Callable ``dt -> Pi(dt)`` from mean sojourn times (see :func:`sojourn_transition`); pass it
    as the IMM's ``transition`` for a switching rate that is right for any sampling interval."""

    def __init__(self, tau, switch=None):
        self.tau = _check_tau(tau)
        self.generator = sojourn_generator(self.tau, switch)
        self.switch = switch

    @property
    def r(self) -> int:
        """Number of modes."""
        return self.tau.size

    def __call__(self, dt: float) -> np.ndarray:
        return sojourn_transition(self.tau, dt, self.switch)

    def __repr__(self) -> str:
        return f"SojournTransition(tau={self.tau.tolist()})"


def stationary_distribution(Pi) -> np.ndarray:
    r"""Stationary mode probabilities :math:`\pi = \pi\Pi`, :math:`\sum\pi = 1` (left eigenvector
    for eigenvalue 1; unique for an irreducible chain)."""
    Pi = check_transition(Pi, name="Pi")
    r = Pi.shape[0]
    A = np.vstack([Pi.T - np.eye(r), np.ones((1, r))])
    b = np.zeros(r + 1)
    b[-1] = 1.0
    return np.linalg.lstsq(A, b, rcond=None)[0]


# --------------------------------------------------------------------------------------------
# Gaussian mixtures and mixing across dimensions
# --------------------------------------------------------------------------------------------
def mix_gaussians(weights, means, covs) -> tuple[np.ndarray, np.ndarray]:
    r"""Moment-matched single Gaussian of a mixture:
    :math:`\bar x = \sum_i w_i x_i`, :math:`\bar P = \sum_i w_i [P_i + (x_i - \bar x)(x_i - \bar x)^\top]`.

    Parameters
    ----------
    weights : (..., r) probabilities summing to one.
    means : (r, ..., n) component means; ``covs`` (r, ..., n, n) their covariances.
    """
    means = as_vector(means, "means")
    if means.ndim < 2:
        raise ValueError(f"means must have shape (r, ..., n), got shape {means.shape}")
    r, n = means.shape[0], means.shape[-1]
    w = _check_probability(weights, r, "weights")
    covs = check_covariance(covs, "covs", n)
    if covs.shape[0] != r:
        raise ValueError(f"covs must have shape (r, ..., n, n) with r = {r}, got shape {covs.shape}")
    return moment_match(w, means, covs)


def _embedding(src: tuple[int, ...], dst: tuple[int, ...]):
    """Index maps to express a state on components ``src`` in the components ``dst``."""
    pos = {c: a for a, c in enumerate(src)}
    shared_dst = np.array([b for b, c in enumerate(dst) if c in pos], dtype=int)
    shared_src = np.array([pos[c] for c in dst if c in pos], dtype=int)
    missing_dst = np.array([b for b, c in enumerate(dst) if c not in pos], dtype=int)
    return shared_src, shared_dst, missing_dst, tuple(src) == tuple(dst)


def _complete(x, P, emb, fill_x, fill_P):
    """Express ``(x, P)`` in the destination components; missing ones from ``(fill_x, fill_P)``
    with zero cross-covariance (unbiased mixing)."""
    s_src, s_dst, miss, same = emb
    if same:
        return x, P
    batch = np.broadcast_shapes(x.shape[:-1], fill_x.shape[:-1])
    n = fill_x.shape[-1]
    xo = np.array(np.broadcast_to(fill_x, batch + (n,)))
    Po = np.zeros(batch + (n, n))
    xo[..., s_dst] = x[..., s_src]
    Po[..., s_dst[:, None], s_dst] = P[..., s_src[:, None], s_src]
    if miss.size:
        Po[..., miss[:, None], miss] = fill_P[..., miss[:, None], miss]
    return xo, Po


# --------------------------------------------------------------------------------------------
# the estimator
# --------------------------------------------------------------------------------------------
class IMMState(NamedTuple):
    """Immutable state of a multiple-model estimator (batch axes ``...``).

    Attributes
    ----------
    x : (..., N) combined mean in the common state.
    P : (..., N, N) combined covariance.
    mu : (..., r) mode probabilities (after :meth:`IMM.predict`: the predicted ones, :math:`\\bar c`).
    log_mu : (..., r) their logarithms (the recursion runs on these).
    xs : tuple of r arrays (..., n_i), the mode-matched means.
    Ps : tuple of r arrays (..., n_i, n_i), the mode-matched covariances.
    loglik : (..., r) mode log-likelihoods of the last update; NaN after a prediction.
    """

    x: np.ndarray
    P: np.ndarray
    mu: np.ndarray
    log_mu: np.ndarray
    xs: tuple
    Ps: tuple
    loglik: np.ndarray


class IMM:
    r"""Interacting multiple model estimator (Blom & Bar-Shalom 1988).

    Parameters
    ----------
    modes : sequence of r mode filters following :class:`Mode` (:class:`KalmanMode`,
        :class:`EKFMode`, :class:`UKFMode`, in any combination).
    transition : the Markov matrix ``Pi[i, j] = P(mode j at k | mode i at k-1)`` (rows sum to
        1), either a fixed ``(r, r)`` array (used per step, whatever ``dt``) or a callable
        ``dt -> Pi`` such as :class:`SojournTransition` (right for any ``dt``).
    mu0 : (r,) or (..., r) initial mode probabilities.
    components : optional, for modes of different dimension: ``components[i]`` lists the
        indices of the common state held by mode ``i`` (default: the first ``n_i``). See the
        module docstring for the mixing rule.

    Use ``s = imm.initialize(x0, P0)``, then ``s = imm.update(s, z)`` and
    ``s = imm.predict(s, dt)``; a step with no measurement is a predict alone.
    """

    def __init__(self, modes: Sequence, transition, mu0, components: Sequence[Sequence[int]] | None = None):
        modes = tuple(modes)
        if not modes:
            raise ValueError("modes must be a non-empty sequence of mode filters, got none")
        for i, m in enumerate(modes):
            if not isinstance(m, Mode):
                raise TypeError(f"modes[{i}] must have n, predict(x, P, dt) and update(x, P, z), "
                                f"got {type(m).__name__}")
        self.modes = modes
        r = len(modes)
        dims = [int(m.n) for m in modes]
        if components is None:
            comps = [tuple(range(d)) for d in dims]
        else:
            comps = [tuple(int(c) for c in cs) for cs in components]
            if len(comps) != r:
                raise ValueError(f"components must list one index tuple per mode ({r}), got {len(comps)}")
            for i, (cs, d) in enumerate(zip(comps, dims)):
                if len(cs) != d or len(set(cs)) != d or min(cs) < 0:
                    raise ValueError(f"components[{i}] must hold {d} distinct indices >= 0 (mode {i} has "
                                     f"{d} states), got {cs}")
        self.components = tuple(comps)
        universe = sorted(set().union(*comps))
        if universe != list(range(len(universe))):
            raise ValueError(f"components must together cover 0..N-1 without gaps, got {sorted(universe)}")
        self.N = len(universe)
        full = tuple(i for i, cs in enumerate(comps) if len(cs) == self.N)
        if not full:
            raise ValueError("modes must include at least one mode holding every state component "
                             f"(dimension {self.N}); got dimensions {dims}")
        self._full = full
        common = tuple(range(self.N))
        self._emb = [[_embedding(comps[i], comps[j]) for j in range(r)] for i in range(r)]
        self._to_common = [_embedding(comps[i], common) for i in range(r)]
        if callable(transition) and not isinstance(transition, np.ndarray):
            check_transition(transition(1.0), r)
            self._transition = _PerDt(lambda dt: check_transition(transition(dt), r))
        else:
            Pi = check_transition(transition, r)
            self._transition = lambda dt: Pi
        self.mu0 = _check_probability(mu0, r, "mu0")

    @property
    def r(self) -> int:
        """Number of modes."""
        return len(self.modes)

    def transition(self, dt: float) -> np.ndarray:
        """The Markov matrix used for a step of ``dt`` seconds, ``(r, r)``."""
        return self._transition(dt)

    # ---- building blocks ------------------------------------------------------------------
    def _combine(self, log_mu, xs, Ps):
        mu = np.exp(log_mu)
        # the full modes in the common order (a full mode may hold the components permuted)
        common = {k: _complete(xs[k], Ps[k], self._to_common[k], xs[k], Ps[k]) for k in self._full}
        if len(self._full) == 1:
            fx, fP = common[self._full[0]]
        else:
            w = mu[..., self._full]
            w = w / w.sum(-1, keepdims=True)
            fx, fP = moment_match(w, np.stack([common[k][0] for k in self._full]),
                                  np.stack([common[k][1] for k in self._full]))
        full = [_complete(xs[i], Ps[i], self._to_common[i], fx, fP) for i in range(self.r)]
        x, P = moment_match(mu, np.stack([a for a, _ in full]), np.stack([b for _, b in full]))
        return mu, x, P

    def _state(self, log_mu, xs, Ps, loglik) -> IMMState:
        # a measurement with batch axes may meet a state without them; a linear update leaves P
        # unbatched: give every field the common batch shape
        batch = np.broadcast_shapes(log_mu.shape[:-1], *(a.shape[:-1] for a in xs), *(b.shape[:-2] for b in Ps))
        xs = [np.broadcast_to(a, batch + a.shape[-1:]) for a in xs]
        Ps = [np.broadcast_to(b, batch + b.shape[-2:]) for b in Ps]
        log_mu = np.broadcast_to(log_mu, batch + log_mu.shape[-1:])
        loglik = np.broadcast_to(loglik, batch + loglik.shape[-1:])
        mu, x, P = self._combine(log_mu, xs, Ps)
        return IMMState(x, P, mu, log_mu, tuple(xs), tuple(Ps), loglik)

    def _mixing_log_weights(self, log_mu, Pi):
        """``log mu_{i|j}`` (..., r_i, r_j) and ``log cbar_j`` (..., r_j); see :func:`kftrack.kernels.mixing_log_weights`."""
        return mixing_log_weights(log_mu, Pi)

    def _mix(self, w, xs, Ps):
        """Mixed initial conditions per destination mode; ``w`` (..., r_i, r_j)."""
        out_x, out_P = [], []
        for j in range(self.r):
            parts = [_complete(xs[i], Ps[i], self._emb[i][j], xs[j], Ps[j]) for i in range(self.r)]
            x0, P0 = moment_match(w[..., :, j], np.stack([a for a, _ in parts]), np.stack([b for _, b in parts]))
            out_x.append(x0)
            out_P.append(P0)
        return out_x, out_P

    def _mixing_weights(self, log_mu, Pi):
        logw, log_cbar = self._mixing_log_weights(log_mu, Pi)
        return array_namespace(logw).exp(logw), log_cbar

    # ---- public API -----------------------------------------------------------------------
    def from_modes(self, xs, Ps, mu) -> IMMState:
        r"""An :class:`IMMState` built from per-mode estimates, with every field consistent: the
        combined ``x``, ``P`` (moment matching, :func:`mix_gaussians`; modes of lower dimension
        completed as in the module docstring), ``mu``, ``log_mu = log(mu)`` and ``loglik`` NaN
        (no update yet). Use it instead of ``state._replace(xs=...)``, which leaves ``x``, ``P``,
        ``mu`` stale.

        Parameters
        ----------
        xs : sequence of r arrays ``(..., n_i)``, the mode-matched means (mode ``i`` holds the
            common components ``components[i]``).
        Ps : sequence of r arrays ``(..., n_i, n_i)``, their covariances.
        mu : (r,) or (..., r) mode probabilities, summing to one.
        """
        r = self.r
        try:
            xs, Ps = list(xs), list(Ps)
        except TypeError:
            raise TypeError(f"xs and Ps must be sequences of {r} per-mode arrays, got {type(xs).__name__} "
                            f"and {type(Ps).__name__}") from None
        if len(xs) != r or len(Ps) != r:
            raise ValueError(f"xs and Ps must hold one estimate per mode ({r} modes), got {len(xs)} and {len(Ps)}")
        xs = [as_vector(a, f"xs[{i}]", len(c)) for i, (a, c) in enumerate(zip(xs, self.components))]
        Ps = [check_covariance(b, f"Ps[{i}]", len(c), origin=f"mode {i} holds {len(c)} components")
              for i, (b, c) in enumerate(zip(Ps, self.components))]
        mu = _check_probability(mu, r, "mu")
        shapes = {"mu": mu.shape[:-1]}
        shapes.update({f"xs[{i}]": a.shape[:-1] for i, a in enumerate(xs)})
        shapes.update({f"Ps[{i}]": b.shape[:-2] for i, b in enumerate(Ps)})
        batch = broadcast_batch(shapes)
        with np.errstate(divide="ignore"):
            log_mu = np.broadcast_to(np.log(mu), batch + (r,)).copy()
        xs = [np.broadcast_to(a, batch + a.shape[-1:]).copy() for a in xs]
        Ps = [np.broadcast_to(b, batch + b.shape[-2:]).copy() for b in Ps]
        return self._state(log_mu, xs, Ps, np.full(batch + (r,), np.nan))

    def initialize(self, x0, P0, mu0=None) -> IMMState:
        """Initial state: every mode starts from ``(x0, P0)`` restricted to its components.

        Parameters
        ----------
        x0 : (..., N) mean in the common state; ``P0`` (..., N, N).
        mu0 : optional (..., r) mode probabilities (default: the constructor's ``mu0``).
        """
        x0 = as_vector(x0, "x0", self.N)
        P0 = check_covariance(P0, "P0", self.N)
        mu = self.mu0 if mu0 is None else _check_probability(mu0, self.r, "mu0")
        batch = broadcast_batch({"x0": x0.shape[:-1], "P0": P0.shape[:-2], "mu0": mu.shape[:-1]})
        xs, Ps = [], []
        for cs in self.components:
            idx = np.array(cs)
            xs.append(np.broadcast_to(x0[..., idx], batch + (idx.size,)).copy())
            Ps.append(np.broadcast_to(P0[..., idx[:, None], idx], batch + (idx.size, idx.size)).copy())
        with np.errstate(divide="ignore"):
            log_mu = np.broadcast_to(np.log(mu), batch + (self.r,)).copy()
        return self._state(log_mu, xs, Ps, np.full(batch + (self.r,), np.nan))

    def predict(self, state: IMMState, dt: float) -> IMMState:
        """Mixing (steps 1–2) and mode-matched prediction over ``dt``; ``mu`` becomes the
        predicted :math:`\\bar c = \\mu\\Pi(dt)`. Alone, it is a step without a measurement."""
        w, log_cbar = self._mixing_weights(state.log_mu, self.transition(dt))
        x0, P0 = self._mix(w, state.xs, state.Ps)
        pred = [m.predict(a, b, dt) for m, a, b in zip(self.modes, x0, P0)]
        return self._state(log_cbar, [p[0] for p in pred], [p[1] for p in pred],
                           np.full(log_cbar.shape, np.nan))

    def update(self, state: IMMState, z) -> IMMState:
        """Mode-matched updates with ``z`` (..., m) and the mode-probability update
        :math:`\\mu_j \\propto \\Lambda_j \\bar c_j` (log-sum-exp), then the combination."""
        z = as_vector(z, "z")
        _check_measurement_size(self.modes, z, "z")
        broadcast_batch({"state.x": state.x.shape[:-1], "z": z.shape[:-1]})
        return self._update(state, z)

    def _update(self, state: IMMState, z) -> IMMState:
        ups = [m.update(a, b, z) for m, a, b in zip(self.modes, state.xs, state.Ps)]
        loglik = np.stack([np.asarray(u.loglik, dtype=float) for u in ups], axis=-1)
        joint = state.log_mu + loglik
        log_mu = joint - logsumexp(joint, axis=-1, keepdims=True)
        return self._state(log_mu, [u.x for u in ups], [u.P for u in ups], loglik)


class GPB1(IMM):
    r"""First-order generalized pseudo-Bayesian estimator (Ackerson & Fu 1970; Bar-Shalom et al.
    2001, §11.6.5): every mode starts each cycle from the **same** Gaussian, the combination of
    all modes, :math:`x^{0j} = \sum_i \mu_i x^i` (mixing weights :math:`\mu_i` instead of
    :math:`\mu_{i|j}`). Same API and conventions as :class:`IMM`; a reference that the IMM
    should beat at the same cost."""

    def _mixing_weights(self, log_mu, Pi):
        _, log_cbar = self._mixing_log_weights(log_mu, Pi)
        xp = array_namespace(log_mu)
        mu = xp.exp(log_mu)
        return xp.broadcast_to(mu[..., :, None], mu.shape + (self.r,)), log_cbar


# --------------------------------------------------------------------------------------------
# whole sequences
# --------------------------------------------------------------------------------------------
class IMMResult(NamedTuple):
    """A filtered sequence, time first (``T`` steps): combined posterior ``x`` (T, ..., N),
    ``P`` (T, ..., N, N), mode probabilities ``mu`` (T, ..., r), mode log-likelihoods
    ``loglik`` (T, ..., r) (NaN without a measurement), and the combined prior ``x_prior``,
    ``P_prior`` and predicted mode probabilities ``mu_prior`` of each step.

    ``xs``, ``Ps``: the mode-matched posteriors, tuples of r arrays (T, ..., n_i) and
    (T, ..., n_i, n_i) (what :func:`imm_smoother` needs); ``None`` if not recorded."""

    x_prior: np.ndarray
    P_prior: np.ndarray
    mu_prior: np.ndarray
    x: np.ndarray
    P: np.ndarray
    mu: np.ndarray
    loglik: np.ndarray
    xs: tuple | None = None
    Ps: tuple | None = None


def _keep_where(gone, old: IMMState, new: IMMState) -> IMMState:
    """``old`` where ``gone`` (batch mask), ``new`` elsewhere, field by field."""
    def sel(a, b, extra):
        return np.where(gone.reshape(gone.shape + (1,) * extra), a, b)

    return IMMState(sel(old.x, new.x, 1), sel(old.P, new.P, 2), sel(old.mu, new.mu, 1),
                    sel(old.log_mu, new.log_mu, 1), tuple(sel(a, b, 1) for a, b in zip(old.xs, new.xs)),
                    tuple(sel(a, b, 2) for a, b in zip(old.Ps, new.Ps)), sel(old.loglik, new.loglik, 1))


def _check_zs(zs) -> tuple[np.ndarray, np.ndarray]:
    """Measurements ``(T, ..., m)``; returns them and the mask ``(T, ...)`` of missing rows."""
    zs = as_vector(zs, "zs", allow_nan=True)
    if zs.ndim < 2:
        raise ValueError(f"zs must have shape (T, ..., m) with time first, got shape {zs.shape}")
    gone = np.isnan(zs).all(-1)
    if not np.isfinite(zs[~gone]).all():
        raise ValueError("zs rows must be finite, or all NaN for a missing measurement; got inf or a partly NaN row")
    return zs, gone


def _check_measurement_size(modes, z: np.ndarray, name: str) -> None:
    """Raise ``ValueError`` naming ``name`` if the last axis of ``z`` is not the size of the
    measurement of every mode that exposes its ``R``."""
    for i, mode in enumerate(modes):
        R = getattr(mode, "R", None)
        if R is not None and np.shape(R)[-1] != z.shape[-1]:
            raise ValueError(f"{name} must have shape (..., {np.shape(R)[-1]}), the measurement size of modes[{i}] "
                             f"(its R), got shape {z.shape}")


_dts = check_dts  # intervals (T,) after each step (kftrack.engines.check_dts)


def imm_filter(estimator: IMM, zs, x0, P0, dt=None, mu0=None, *, times=None, progress: bool = False,
               dtype=None) -> IMMResult:
    """Run an :class:`IMM` (or :class:`GPB1`) over a measurement sequence: at each step update
    with ``zs[k]`` (skipped, not faked, when the row is NaN), then predict over ``dt[k]``.

    Parameters
    ----------
    estimator : an :class:`IMM` or :class:`GPB1`.
    zs : (T, ..., m) measurements, time first; rows of NaN mark missing measurements.
    x0, P0 : (..., N), (..., N, N) prior of step 0, in the common state.
    dt : interval (s) after each step: a scalar, ``(T,)`` (``dt[k]`` from step ``k`` to ``k + 1``,
        the last one unused) or ``(T - 1,)`` (``np.diff(t)`` of the timestamps).
    mu0 : optional initial mode probabilities (default: the estimator's).
    times : None, or instead of ``dt`` the timestamps ``(T,)`` (s, non-decreasing) of the
        measurements: ``dt = np.diff(times)``. ``dt`` and ``times`` exclude each other.
    progress : show a progress bar (tqdm) over the time steps, for long Monte Carlo runs
        (NumPy engine only).
    dtype : None or ``"float64"`` (default), or ``"float32"`` (explicit, about nine decimal
        digits lost); see :func:`kftrack.kalman.kalman_filter`.

    Returns
    -------
    IMMResult
        NumPy arrays, or JAX arrays when any of ``zs``, ``x0``, ``P0``, ``mu0`` is a JAX array:
        then the JAX engine (:func:`kftrack.engines.run_imm_scan`) runs the same kernels under
        ``jax.lax.scan``. It takes banks of :class:`KalmanMode` that all hold the whole common
        state (per-mode ``F(dt_k)``, ``Q(dt_k)`` and ``Pi(dt_k)`` are evaluated in NumPy once per
        distinct interval); concrete arrays (values are checked here).

    Raises
    ------
    ValueError
        On the NumPy engine, if the run breaks down (a singular matrix, or a non-finite estimate
        from finite input): naming ``zs`` when its scale explains it (entries so large that float64
        resolves them more coarsely than the measurement noise, or that their squares overflow,
        beyond about 1.3e154), otherwise naming the step. The JAX engine does not check: NaN or inf
        propagate to the outputs.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.imm import IMM, KalmanMode, imm_filter
    >>> from kftrack.models import ConstantVelocity
    >>> R = np.eye(1)
    >>> bank = IMM([KalmanMode(ConstantVelocity(ndim=1, q=0.01), R),     # quiet
    ...             KalmanMode(ConstantVelocity(ndim=1, q=10.0), R)],    # agile
    ...            transition=[[0.95, 0.05], [0.05, 0.95]], mu0=[0.5, 0.5])
    >>> zs = np.array([[0.0], [1.0], [2.1], [2.9], [np.nan], [8.0], [12.5], [17.0]])   # speeds up; one missing
    >>> out = imm_filter(bank, zs, np.zeros(2), 10 * np.eye(2), dt=1.0)
    >>> out.x.shape, out.mu.shape                    # combined state [x, vx], mode probabilities
    ((8, 2), (8, 2))
    >>> bool(out.mu[3, 1] < 0.5 < out.mu[-1, 1])     # the agile mode takes over after the speed-up
    True
    """
    jax_engine, dtype = choose_engine(zs, x0, P0, mu0, dtype=dtype)
    zs, row_missing = _check_zs(zs)
    _check_measurement_size(estimator.modes, zs, "zs")
    T = zs.shape[0]
    dts = _dts(dt, T, times)
    N, r = estimator.N, estimator.r
    x0 = as_vector(x0, "x0", N)
    P0 = check_covariance(P0, "P0", N)
    mu0 = estimator.mu0 if mu0 is None else _check_probability(mu0, r, "mu0")
    batch = broadcast_batch({"zs[k]": zs.shape[1:-1], "x0": x0.shape[:-1], "P0": P0.shape[:-2], "mu0": mu0.shape[:-1]})
    if jax_engine:
        return _imm_filter_jax(estimator, zs, row_missing, x0, P0, mu0, dts, batch, dtype)
    if dtype != np.float64:
        zs, x0, P0 = zs.astype(dtype), x0.astype(dtype), P0.astype(dtype)
    s = estimator.initialize(np.broadcast_to(x0, batch + (N,)), np.broadcast_to(P0, batch + (N, N)),
                             np.broadcast_to(mu0, batch + (r,)))
    out = {k: np.empty((T,) + batch + shp) for k, shp in
           (("x_prior", (N,)), ("P_prior", (N, N)), ("mu_prior", (r,)), ("x", (N,)), ("P", (N, N)), ("mu", (r,)),
            ("loglik", (r,)))}
    out_xs = tuple(np.empty((T,) + batch + (len(c),)) for c in estimator.components)  # per-mode posteriors
    out_Ps = tuple(np.empty((T,) + batch + (len(c), len(c))) for c in estimator.components)
    steps = range(T)
    if progress:
        from tqdm.auto import tqdm  # only when asked for

        steps = tqdm(steps, desc=type(estimator).__name__, unit="step")
    k = 0
    try:
        for k in steps:
            out["x_prior"][k], out["P_prior"][k], out["mu_prior"][k] = s.x, s.P, s.mu
            gone = np.broadcast_to(row_missing[k], batch)
            if not gone.all():
                new = estimator._update(s, np.where(gone[..., None], 0.0, zs[k]))
                s = _keep_where(gone, s, new) if gone.any() else new
            out["x"][k], out["P"][k], out["mu"][k], out["loglik"][k] = s.x, s.P, s.mu, s.loglik
            for i in range(r):
                out_xs[i][k], out_Ps[i][k] = s.xs[i], s.Ps[i]
            if k < T - 1:
                s = estimator.predict(s, dts[k])
    except np.linalg.LinAlgError:
        _check_scale(estimator, zs, row_missing, k, "a singular matrix")
        raise
    bad = ~np.isfinite(out["x"]).all(-1) | ~np.isfinite(out["P"]).all((-2, -1)) | np.isnan(out["mu"]).any(-1)
    if bad.any():  # finite input must give finite estimates (mu may hold 0, never NaN)
        k = int(np.argwhere(bad)[0][0])
        _check_scale(estimator, zs, row_missing, k, "a non-finite estimate")
        raise ValueError(f"imm_filter produced a non-finite estimate at step {k} from finite zs, x0, P0: a mode's "
                         "model or measurement function (f, h, a Jacobian, Q) returned NaN or inf there, or x0, "
                         "P0, R are too large to square in floating point")
    return IMMResult(**out, xs=out_xs, Ps=out_Ps)


def _check_scale(estimator: IMM, zs, row_missing, k: int, what: str) -> None:
    """Where the NumPy engine broke down at step ``k`` (``what``), raise a ``ValueError`` naming
    ``zs`` if its scale explains it: numbers of size :math:`|z|` are resolved only to
    :math:`|z|\\,\\varepsilon`; once that is coarser than the measurement noise (the smallest std of
    the modes' ``R``) the covariances lose rank in round-off, and beyond :math:`\\sqrt{\\max}`
    (1.3e154 in float64) the squared innovations overflow."""
    seen = zs[~row_missing]
    scale = float(np.abs(seen).max()) if seen.size else 0.0
    info = np.finfo(zs.dtype)
    stds = [np.sqrt(np.linalg.eigvalsh(m.R).min()) for m in estimator.modes if getattr(m, "R", None) is not None]
    noise = float(min(stds)) if stds else 0.0
    if scale * float(info.eps) > noise or scale > 1e-3 * np.sqrt(float(info.max)):
        raise ValueError(f"zs has entries up to {scale:.3g} in magnitude, too large for {zs.dtype} arithmetic: "
                         f"numbers of that size are resolved only to {scale * float(info.eps):.2g}, coarser than the "
                         f"measurement noise (std {noise:.3g} from R), and squares overflow above "
                         f"{np.sqrt(float(info.max)):.2g}; the filter met {what} at step {k}. Rescale the units or "
                         "subtract a reference point from zs and x0")


def _imm_filter_jax(estimator: IMM, zs, row_missing, x0, P0, mu0, dts, batch, dtype) -> IMMResult:
    """The JAX engine of :func:`imm_filter` (arguments already checked)."""
    modes, N, r = estimator.modes, estimator.N, estimator.r
    Fs, Qs, Pis = _linear_bank(estimator, dts, "imm_filter")
    H = np.stack([m.H for m in modes])
    R = np.stack([m.R for m in modes])
    with np.errstate(divide="ignore"):
        log_mu0 = np.log(np.broadcast_to(mu0, batch + (r,)))
    xs0 = np.broadcast_to(x0, (r,) + batch + (N,))
    Ps0 = np.broadcast_to(P0, (r,) + batch + (N, N))
    gone = np.broadcast_to(row_missing, (zs.shape[0],) + batch)
    args = [to_engine(a, True, dtype) for a in (zs, gone, log_mu0, xs0, Ps0, Pis, Fs, Qs, H, R)]
    return IMMResult(*run_imm_scan(*args, batch=batch, mixing_weights=estimator._mixing_weights))


# --------------------------------------------------------------------------------------------
# a pure entry point for jax.jit, jax.vmap and jax.grad
# --------------------------------------------------------------------------------------------
def _linear_bank(estimator: IMM, dts, what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arrays of the JAX engines (``what``: :func:`imm_filter`, :func:`imm_smoother`) for a bank
    of :class:`KalmanMode` that all hold the whole common state: ``Fs``, ``Qs`` (T, r, N, N) and
    ``Pis`` (T, r, r) at the intervals ``dts`` (T,), each distinct interval evaluated once (cached);
    any other bank raises ``TypeError``."""
    modes, N = estimator.modes, estimator.N
    if not all(isinstance(m, KalmanMode) for m in modes) or any(c != tuple(range(N)) for c in estimator.components):
        raise TypeError(f"estimator: the JAX engine of {what} runs banks of KalmanMode that all hold the whole "
                        f"common state (N = {N}); got modes {[type(m).__name__ for m in modes]} with components "
                        f"{estimator.components}. Pass NumPy arrays to use the NumPy engine")
    FQ = [[m._FQ(d) for m in modes] for d in dts]
    Fs = np.stack([np.stack([f for f, _ in row]) for row in FQ])
    Qs = np.stack([np.stack([q for _, q in row]) for row in FQ])
    if Fs.shape[2:] != (N, N) or Qs.shape[2:] != (N, N):
        raise ValueError(f"estimator: the JAX engine needs each mode's F(dt), Q(dt) of shape ({N}, {N}), "
                         f"got {Fs.shape[2:]} and {Qs.shape[2:]}")
    return Fs, Qs, np.stack([estimator.transition(d) for d in dts])


class IMMParams(NamedTuple):
    r"""The parameters of a linear IMM (full-state :class:`KalmanMode` bank, constant sampling
    interval) as arrays, for :func:`imm_loglik`: one pytree, so ``jax.grad`` and ``jax.vmap``
    over any of them are natural.

    Attributes
    ----------
    F, Q : (r, n, n) transition matrix and process-noise covariance of each mode (per step).
    H : (r, m, n) per mode, or (m, n) shared.
    R : (r, m, m) per mode, or (m, m) shared.
    logits : (r, r) Markov matrix by rows, :math:`\Pi_{ij} = e^{L_{ij}} / \sum_l e^{L_{il}}`
        (any real ``L`` gives a stochastic matrix, so a gradient step stays on the simplex;
        ``-inf`` is a zero probability).
    log_mu0 : (r,) initial mode probabilities, :math:`\mu_{0,j} \propto e^{\lambda_j}` (the logs
        of probabilities are left unchanged; finite for a finite gradient).
    """

    F: np.ndarray
    Q: np.ndarray
    H: np.ndarray
    R: np.ndarray
    logits: np.ndarray
    log_mu0: np.ndarray


def _check_imm_params(params, n: int, m: int | None, n_from: str = "x0", m_from: str = "zs") -> int:
    """Shapes of :class:`IMMParams` (values too when concrete; abstract values are checked
    through :func:`kftrack._validate.stand_in`), ``n`` and ``m`` coming from the arguments named
    ``n_from``, ``m_from`` (``m`` None: any); returns ``r``."""
    if not isinstance(params, IMMParams):
        raise TypeError(f"params must be an IMMParams, got {type(params).__name__}")
    logits = as_float_array(stand_in(params.logits, "matrix"), "params.logits")
    if logits.ndim != 2 or logits.shape[0] != logits.shape[1] or logits.shape[0] == 0:
        raise ValueError(f"params.logits must have shape (r, r) (one row of the Markov matrix per mode), got shape "
                         f"{logits.shape}")
    r = logits.shape[0]
    log_mu0 = as_float_array(stand_in(params.log_mu0, "vector"), "params.log_mu0")
    if log_mu0.shape != (r,):
        raise ValueError(f"params.log_mu0 must have shape ({r},) (r = {r} from params.logits), got shape "
                         f"{log_mu0.shape}")
    for name, a in (("params.logits", logits), ("params.log_mu0", log_mu0)):
        if np.isnan(a).any() or np.isposinf(a).any() or np.isneginf(a).all(-1).any():
            raise ValueError(f"{name} must be real logits (no NaN or +inf, not all -inf in a row), got shape "
                             f"{a.shape} with such values")
    origin = f"r = {r} from params.logits, n = {n} from {n_from}"
    F = as_matrix(stand_in(params.F, "matrix"), "params.F", n, n, origin=origin)
    Q = check_covariance(stand_in(params.Q, "cov"), "params.Q", n, origin=origin)
    H = as_matrix(stand_in(params.H, "matrix"), "params.H", m, n,
                  origin=("" if m is None else f"m = {m} from {m_from}, ") + f"n = {n} from {n_from}")
    R = check_covariance(stand_in(params.R, "cov"), "params.R", H.shape[-2], positive_definite=True,
                         origin=f"m = {H.shape[-2]} from {m_from}")
    for name, a, shared in (("F", F, False), ("Q", Q, False), ("H", H, True), ("R", R, True)):
        if a.shape[:-2] != (r,) and not (shared and a.ndim == 2):
            alt = f" or {a.shape[-2:]} (shared by the modes)" if shared else ""
            raise ValueError(f"params.{name} must have shape ({r}, {a.shape[-2]}, {a.shape[-1]}) (one per mode, "
                             f"r = {r} from params.logits){alt}, got shape {a.shape}")
    return r


def _imm_mixing_weights(log_mu, Pi):
    """The IMM's mixing weights ``mu_{i|j}`` and ``log cbar_j`` (:meth:`IMM._mixing_weights`)."""
    logw, log_cbar = mixing_log_weights(log_mu, Pi)
    return array_namespace(logw).exp(logw), log_cbar


def imm_loglik(params: IMMParams, zs, x0, P0, *, missing=None, dtype=None, sequence: bool = True) -> tuple:
    r"""The IMM filter of a linear mode bank as a pure function of its parameters, for
    ``jax.jit``, ``jax.vmap`` and ``jax.grad``: the same cycle as :func:`imm_filter` on the JAX
    engine (:func:`kftrack.engines.run_imm_scan`), from arrays alone, and its log-likelihood

    .. math:: \ell = \sum_{k\ \text{measured}} \log \sum_j \bar c_{k,j}\, \Lambda_{k,j},
              \qquad \Lambda_{k,j} = N(\nu_{k,j}; 0, S_{k,j}),

    :math:`\bar c_{k,j}` the predicted mode probabilities (``mu_prior``) and
    :math:`\Lambda_{k,j}` the mode likelihoods (``loglik``) of step ``k``: the log density of
    the measurements under the IMM's Gaussian-mixture predictions.

    Parameters
    ----------
    params : :class:`IMMParams` (r modes; shapes checked, values too when concrete).
    zs : (T, ..., m) measurements, time first; NaN rows are missing.
    x0, P0 : (..., n), (..., n, n) prior of step 0 (every mode starts from it).
    missing : None (the NaN rows of ``zs``, found inside the trace when ``zs`` is abstract),
        ``False`` (none missing) or a concrete boolean ``(T,)``/``(T, ...)`` mask, as in
        :func:`kftrack.kalman.kalman_filter`.
    dtype : None or ``"float64"`` (needs ``jax_enable_x64``), or ``"float32"``.
    sequence : True (default): also return the filtered sequence. False: only ``ell``, from a
        loop that stores nothing per step (:func:`kftrack.engines.run_imm_total_scan`): what
        ``jax.grad`` should differentiate (its reverse pass then carries the IMM's state alone, not
        the stored sequence and its cotangents).

    Returns
    -------
    (ell, IMMResult or None)
        ``ell`` (...) the log-likelihood of each run, and the filtered sequence (JAX arrays;
        None with ``sequence=False``): ``jax.grad(imm_loglik, has_aux=True)`` differentiates
        ``ell`` (sum it first when runs are batched). :func:`imm_params` builds ``params`` from an
        :class:`IMM` of :class:`KalmanMode`.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.imm import IMMParams, imm_loglik
    >>> F = np.stack([np.eye(2) + np.eye(2, k=1)] * 2)             # two constant-velocity modes
    >>> Q = np.stack([0.01 * np.eye(2), 1.0 * np.eye(2)])          # quiet and manoeuvring
    >>> p = IMMParams(F, Q, np.array([[1.0, 0.0]]), np.eye(1), np.log([[0.9, 0.1], [0.1, 0.9]]), np.zeros(2))
    >>> zs = np.arange(10.0)[:, None]                                # (T, m) = (10, 1)
    >>> ell, res = imm_loglik(p, zs, np.zeros(2), 10 * np.eye(2), dtype="float32")
    >>> res.mu.shape, bool(np.isfinite(ell))
    ((10, 2), True)

    ``jax.grad(lambda p: imm_loglik(p, zs, x0, P0, sequence=False)[0])(p)`` is an :class:`IMMParams` of
    gradients (``.logits`` ``(2, 2)``: :math:`\partial\ell/\partial L`); ``tests/test_compose_imm.py``
    checks it against central differences.
    """
    import jax  # the entry point is JAX's

    jnp = jax.numpy
    dtype = check_dtype(dtype, True)
    zs_c, pattern = check_missing(zs, missing)
    x0_c, P0_c, n = check_state(stand_in(x0, "vector"), stand_in(P0, "cov"), ("x0", "P0"))
    T, m = zs_c.shape[0], zs_c.shape[-1]
    r = _check_imm_params(params, n, m)
    batch = broadcast_batch({"zs[k]": zs_c.shape[1:-1], "x0": x0_c.shape[:-1], "P0": P0_c.shape[:-2]})
    zs = to_engine(zs if is_tracer(zs) else zs_c, True, dtype)
    gone = (jnp.isnan(zs).all(-1) if pattern is None else jnp.asarray(pattern))
    gone = jnp.broadcast_to(gone.reshape((T,) + (1,) * (1 + len(batch) - gone.ndim) + gone.shape[1:]), (T,) + batch)
    zs = jnp.where(gone[..., None], jnp.zeros((), zs.dtype), zs)  # no NaN enters the arithmetic (nor its gradient)
    F, Q, H, R, logits, log_mu0, x0, P0 = (to_engine(a, True, dtype) for a in
                                           (*params[:4], params.logits, params.log_mu0, x0, P0))
    log_Pi = jax.nn.log_softmax(logits, axis=-1)
    log_mu0 = jax.nn.log_softmax(log_mu0)
    if not isinstance(sequence, (bool, np.bool_)):
        raise TypeError(f"sequence must be True or False, got {sequence!r}")
    args = (zs, gone, jnp.broadcast_to(log_mu0, batch + (r,)), jnp.broadcast_to(x0, (r,) + batch + (n,)),
            jnp.broadcast_to(P0, (r,) + batch + (n, n)), jnp.broadcast_to(jnp.exp(log_Pi), (T, r, r)),
            jnp.broadcast_to(F, (T, r, n, n)), jnp.broadcast_to(Q, (T, r, n, n)), jnp.broadcast_to(H, (r, m, n)),
            jnp.broadcast_to(R, (r, m, m)))
    if not sequence:
        return run_imm_total_scan(*args, batch=batch, mixing_weights=_imm_mixing_weights), None
    res = IMMResult(*run_imm_scan(*args, batch=batch, mixing_weights=_imm_mixing_weights))
    g = gone[..., None]
    step = logsumexp(jnp.log(res.mu_prior) + jnp.where(g, jnp.zeros((), dtype), res.loglik), axis=-1)
    return jnp.sum(jnp.where(gone, jnp.zeros((), dtype), step), axis=0), res


def imm_params(estimator: IMM, dt: float) -> IMMParams:
    """:class:`IMMParams` of an :class:`IMM` of full-state :class:`KalmanMode` at a constant
    sampling interval ``dt`` (s): ``F(dt)``, ``Q(dt)``, ``H``, ``R`` of each mode, ``logits =
    log Pi(dt)`` and ``log_mu0 = log mu0`` (``-inf`` for a zero probability), NumPy arrays."""
    if not isinstance(estimator, IMM) or isinstance(estimator, GPB1):
        raise TypeError(f"estimator must be an IMM (imm_loglik runs the IMM's mixing), got "
                        f"{type(estimator).__name__}")
    modes, N = estimator.modes, estimator.N
    if not all(isinstance(m, KalmanMode) for m in modes) or any(c != tuple(range(N)) for c in estimator.components):
        raise TypeError(f"estimator must be a bank of KalmanMode that all hold the whole state (N = {N}), got "
                        f"modes {[type(m).__name__ for m in modes]} with components {estimator.components}")
    d = float(check_finite(as_float_array(dt, "dt"), "dt")) if np.ndim(dt) == 0 else None
    if d is None or d < 0:
        got = f"shape {np.shape(dt)}" if d is None else f"{d:g}"
        raise ValueError(f"dt must be a scalar interval >= 0 (s), got {got}")
    FQ = [m._FQ(d) for m in modes]
    with np.errstate(divide="ignore"):
        return IMMParams(np.stack([f for f, _ in FQ]), np.stack([q for _, q in FQ]), np.stack([m.H for m in modes]),
                         np.stack([m.R for m in modes]), np.log(estimator.transition(d)), np.log(estimator.mu0))


def clairvoyant_filter(modes: Sequence, mode_sequence, zs, x0, P0, dt) -> tuple[np.ndarray, np.ndarray]:
    """Model-matched reference filter that is **told the true mode** at every step: it predicts
    with mode ``mode_sequence[k]`` from step ``k`` to ``k + 1``. A lower bound on what any
    multiple-model estimator can achieve with these modes.

    Parameters
    ----------
    modes : r mode filters of the **same** state dimension ``n`` and the same measurement model
        (the updates use ``modes[0].update``).
    mode_sequence : (T,) or (T, ...) integer mode index in force from step k to k + 1 (the last
        row is unused); batch axes select a different sequence per run.
    zs : (T, ..., m) measurements (NaN rows: missing); ``x0``, ``P0`` prior of step 0.
    dt : interval (s), scalar or (T,).

    Returns
    -------
    x, P : (T, ..., n), (T, ..., n, n) posterior estimates.
    """
    modes = tuple(modes)
    dims = {int(m.n) for m in modes}
    if len(dims) != 1:
        raise ValueError(f"modes must all have the same state dimension, got {sorted(dims)}")
    zs, row_missing = _check_zs(zs)
    _check_measurement_size(modes[:1], zs, "zs")  # the updates use modes[0]
    T = zs.shape[0]
    dts = _dts(dt, T)
    seq = np.asarray(mode_sequence)
    if seq.shape[:1] != (T,) or not np.issubdtype(seq.dtype, np.integer) or seq.min() < 0 or seq.max() >= len(modes):
        raise ValueError(f"mode_sequence must be integers in [0, {len(modes) - 1}] with time first, length {T}; "
                         f"got shape {seq.shape}, dtype {seq.dtype}")
    n = dims.pop()
    x0 = as_vector(x0, "x0", n)
    P0 = check_covariance(P0, "P0", n)
    batch = broadcast_batch({"zs[k]": zs.shape[1:-1], "mode_sequence[k]": seq.shape[1:], "x0": x0.shape[:-1],
                    "P0": P0.shape[:-2]})
    x = np.broadcast_to(x0, batch + (n,)).copy()
    P = np.broadcast_to(P0, batch + (n, n)).copy()
    out_x, out_P = np.empty((T,) + batch + (n,)), np.empty((T,) + batch + (n, n))
    for k in range(T):
        gone = np.broadcast_to(row_missing[k], batch)
        if not gone.all():
            u = modes[0].update(x, P, np.where(gone[..., None], 0.0, zs[k]))
            x = np.where(gone[..., None], x, u.x)
            P = np.where(gone[..., None, None], P, u.P)
        out_x[k], out_P[k] = x, P
        if k < T - 1:
            sk = np.broadcast_to(seq[k], batch)
            nx, nP = np.empty_like(x), np.empty_like(P)
            for i in np.unique(sk):
                xi, Pi_ = modes[i].predict(x, P, dts[k])
                sel = sk == i
                nx = np.where(sel[..., None], xi, nx)
                nP = np.where(sel[..., None, None], Pi_, nP)
            x, P = nx, nP
    return out_x, out_P


# --------------------------------------------------------------------------------------------
# fixed-interval smoothing
# --------------------------------------------------------------------------------------------
class IMMSmootherResult(NamedTuple):
    """A fixed-interval smoothed sequence (:func:`imm_smoother`), time first: combined means
    ``x`` (T, ..., N) and covariances ``P`` (T, ..., N, N) in the common state, smoothed mode
    probabilities ``mu`` (T, ..., r) :math:`P\\{M_k = j \\mid Z^T\\}`, and the mode-conditioned
    smoothed means ``xs`` and covariances ``Ps`` (tuples of r arrays (T, ..., n_i),
    (T, ..., n_i, n_i), each on its mode's components). NumPy arrays, or JAX arrays from the
    smoother's JAX engine (a pytree: it passes through ``jax.jit`` and ``jax.vmap``)."""

    x: np.ndarray
    P: np.ndarray
    mu: np.ndarray
    xs: tuple
    Ps: tuple


def _check_smoother_estimator(estimator) -> None:
    """Validate :func:`imm_smoother`'s estimator (an :class:`IMM` whose modes have ``predict_linearized``)."""
    if not isinstance(estimator, IMM) or isinstance(estimator, GPB1):
        raise TypeError("estimator must be an IMM (not GPB1: its mode posteriors all start from the combined "
                        "estimate, which the smoother's pairwise predictions do not model) or an IMMParams, got "
                        f"{type(estimator).__name__}")
    for i, m in enumerate(estimator.modes):
        if not callable(getattr(m, "predict_linearized", None)):
            raise TypeError(f"estimator.modes[{i}] must be a KalmanMode, EKFMode or UKFMode, or have "
                            "predict_linearized(x, P, dt) (the backward pass needs the mode's transition matrix "
                            f"at the filtered state), got {type(m).__name__} without it")


def _check_smoother_result(result, r: int, components: tuple, N: int) -> tuple[int, tuple]:
    """Validate :func:`imm_smoother`'s result for ``r`` modes on ``components`` of an ``N``-state:
    shapes always, the values of ``mu`` when concrete (not inside a JAX trace); returns
    ``(T, batch)``."""
    if not isinstance(result, IMMResult):
        raise TypeError(f"result must be an IMMResult from imm_filter, got {type(result).__name__}")
    if result.xs is None or result.Ps is None or len(result.xs) != r or len(result.Ps) != r:
        raise ValueError(f"result must carry the per-mode posteriors xs, Ps of {r} modes (an IMMResult from "
                         "imm_filter with this estimator), got "
                         f"{None if result.xs is None else len(result.xs)} and "
                         f"{None if result.Ps is None else len(result.Ps)}")
    shape = tuple(np.shape(result.mu))
    if len(shape) < 2 or shape[-1] != r:
        raise ValueError(f"result.mu must have shape (T, ..., {r}), got shape {shape}")
    T, batch = shape[0], shape[1:-1]
    if not is_tracer(result.mu):  # inside a trace the values are not known: shapes alone
        mu = np.asarray(result.mu)
        bad = ~np.isfinite(mu) | (mu < 0)
        if bad.any():
            k = int(np.argwhere(bad)[0][0])
            raise ValueError(f"result.mu must hold finite mode probabilities >= 0, got NaN, inf or a negative "
                             f"value at step {k} (shape {mu.shape}); the smoother needs the filter's own result")
        tol = max(_TOL, 8 * r * np.finfo(mu.dtype if mu.dtype.kind == "f" else float).eps)  # float32 results too
        off = np.abs(mu.sum(-1) - 1.0)
        if np.any(off > tol):
            raise ValueError(f"result.mu must sum to 1 over its last axis (mode probabilities), got a sum off by "
                             f"{off.max():.3g} (shape {mu.shape})")
    for i, c in enumerate(components):
        n = len(c)
        if np.shape(result.xs[i]) != (T,) + batch + (n,) or np.shape(result.Ps[i]) != (T,) + batch + (n, n):
            raise ValueError(f"result.xs[{i}], result.Ps[{i}] must have shapes {(T,) + batch + (n,)} and "
                             f"{(T,) + batch + (n, n)}, got {np.shape(result.xs[i])} and {np.shape(result.Ps[i])}")
    for name, shape in (("x", (N,)), ("P", (N, N))):
        if np.shape(getattr(result, name)) != (T,) + batch + shape:
            raise ValueError(f"result.{name} must have shape {(T,) + batch + shape}, got "
                             f"{np.shape(getattr(result, name))}")
    return T, batch


def _kim_weights(log_mu, Pi, log_ms_next):
    r"""Kim's backward mode weights of one step, in log space (any array namespace: the NumPy loop
    of :func:`imm_smoother` and its JAX engine :func:`kftrack.engines.run_imm_smoother_scan`).

    From the filtered :math:`\log\mu^i_{k|k}` ``log_mu`` (..., r), the Markov matrix ``Pi`` (r, r)
    of the step after ``k`` and the smoothed :math:`\log\mu^j_{k+1|T}` ``log_ms_next`` (..., r):
    :math:`\mu^{ij}_{k|T} = \mu^{i|j}_k\,\mu^j_{k+1|T}` (:func:`kftrack.kernels.mixing_log_weights`),
    returns the weights :math:`\mu^{ij}_{k|T}/\mu^i_{k|T}` (..., r_i, r_j) of the merge over ``j``
    (all on ``j = i`` for a mode of probability 0) and :math:`\log\mu^i_{k|T}` (..., r), normalized."""
    xp = array_namespace(log_mu, Pi, log_ms_next)
    r = Pi.shape[-1]
    logw, _ = mixing_log_weights(log_mu, Pi)  # log mu^{i|j}_k
    log_joint = logw + log_ms_next[..., None, :]  # log mu^{ij}_{k|T}
    log_mi = logsumexp(log_joint, axis=-1, keepdims=True)  # (..., i, 1)
    with np.errstate(invalid="ignore"):
        log_cond = log_joint - log_mi  # log P(M_{k+1} = j | M_k = i, Z^T)
    zero, minus_inf = xp.asarray(0.0, dtype=log_cond.dtype), xp.asarray(-math.inf, dtype=log_cond.dtype)
    self_weight = xp.where(xp.eye(r, dtype=xp.bool), zero, minus_inf)  # (i, j): all weight on j = i
    log_cond = xp.where(xp.isinf(log_mi) & (log_mi < 0), self_weight, log_cond)  # a mode of probability 0
    log_m = log_mi[..., 0]
    return xp.exp(log_cond), log_m - logsumexp(log_m, axis=-1, keepdims=True)


def _pair_space(ci: tuple, cj: tuple):
    """The state space of the smoother's pair (mode ``i`` at ``k``, mode ``j`` at ``k + 1``): mode
    ``j``'s components ``cj`` followed by those of ``ci`` that ``j`` lacks. Returns the embedding of
    ``ci`` into it, the positions of ``ci`` in it and the number of those extra components."""
    space = tuple(cj) + tuple(c for c in ci if c not in cj)
    pos = {c: a for a, c in enumerate(space)}
    return _embedding(ci, space), np.array([pos[c] for c in ci], dtype=int), len(space) - len(cj)


def _pair_rts(mode, x_i, P_i, x_j, P_j, xs_next, Ps_next, dt, space):
    r"""One RTS step of the pair (i at k, j at k + 1) in the pair space of :func:`_pair_space`.

    Mode ``i``'s posterior ``(x_i, P_i)`` is completed with mode ``j``'s own ``(x_j, P_j)`` at ``k``
    where it lacks ``j``'s components (the filter's unbiased mixing into ``j``); ``j``'s transition
    acts on its components, :math:`F^{ij} = [F_j \; 0]` (the extra components of ``i`` do not enter
    ``j``'s dynamics, they are smoothed through their covariance with the rest); the result is
    returned on ``i``'s components. Angles of a :class:`UKFMode` state: the residual wrapped."""
    emb, back, extra = space
    plain = emb[3] and not extra  # i holds exactly j's components: the plain RTS step
    if plain:
        x_u, P_u = x_i, P_i
        x_a, P_a = x_i, P_i
    else:
        nj = x_j.shape[-1]
        fill_x = np.concatenate([x_j, np.zeros(x_j.shape[:-1] + (extra,))], axis=-1)
        fill_P = np.zeros(P_j.shape[:-2] + (nj + extra, nj + extra))
        fill_P[..., :nj, :nj] = P_j
        x_u, P_u = _complete(x_i, P_i, emb, fill_x, fill_P)
        x_a, P_a = x_u[..., :nj], P_u[..., :nj, :nj]
    x_pred, P_pred, F = mode.predict_linearized(x_a, P_a, dt)
    if extra:
        F = np.concatenate([F, np.zeros(F.shape[:-1] + (extra,))], axis=-1)
    angles = getattr(mode, "_state_angles", ())
    if angles:
        xs_next = x_pred + residual(xs_next, x_pred, angles)
    x_s, P_s, _ = rts_step(x_u, P_u, x_pred, P_pred, xs_next, Ps_next, F)
    if angles:
        x_s = wrap_state(x_s, angles)
    if plain:
        return x_s, P_s
    return x_s[..., back], P_s[..., back[:, None], back]


def imm_smoother(estimator: IMM | IMMParams, result: IMMResult, dt=None, *, times=None) -> IMMSmootherResult:
    r"""Fixed-interval smoother for a Markov-switching linear model over the output of
    :func:`imm_filter`: Kim's backward recursion (Kim 1994; Kim & Nelson 1999, §5.2), run on the
    IMM's mode-matched posteriors :math:`x^i_{k|k}, P^i_{k|k}` and probabilities
    :math:`\mu^i_{k|k}`.

    The mode :math:`M_{k+1} = j` governs the transition from step ``k`` to ``k + 1`` over
    ``dt[k]`` (as in :func:`imm_filter`), with :math:`F_j = F_j(dt_k)`, :math:`Q_j = Q_j(dt_k)`,
    :math:`\Pi = \Pi(dt_k)`. Starting from the filter at ``T - 1``, for ``k = T-2, ..., 0``:

    1. backward mode weights (the IMM's mixing probabilities),
       :math:`\mu^{i|j}_k = \Pi_{ij}\mu^i_{k|k}/\bar c_j`, :math:`\bar c_j = \sum_i \Pi_{ij}\mu^i_{k|k}`;
       joint and marginal smoothed mode probabilities
       :math:`\mu^{ij}_{k|T} = \mu^{i|j}_k\,\mu^j_{k+1|T}`, :math:`\mu^i_{k|T} = \sum_j \mu^{ij}_{k|T}`;
    2. one RTS step per pair (i at k, j at k + 1):
       :math:`P^{ij}_{k+1|k} = F_j P^i_{k|k} F_j^\top + Q_j`,
       :math:`G^{ij} = P^i_{k|k} F_j^\top (P^{ij}_{k+1|k})^{-1}`,

       .. math::

           x^{ij}_{k|T} = x^i_{k|k} + G^{ij}(x^j_{k+1|T} - F_j x^i_{k|k}), \quad
           P^{ij}_{k|T} = P^i_{k|k} + G^{ij}(P^j_{k+1|T} - P^{ij}_{k+1|k})G^{ij\top};

    3. merge over j with weights :math:`\mu^{ij}_{k|T}/\mu^i_{k|T}` into :math:`x^i_{k|T},
       P^i_{k|T}` (moment matching), and combine (output only)
       :math:`x_{k|T} = \sum_i \mu^i_{k|T} x^i_{k|T}`,
       :math:`P_{k|T} = \sum_i \mu^i_{k|T}[P^i_{k|T} + (x^i_{k|T} - x_{k|T})(\cdot)^\top]`.

    Kim's approximation is :math:`P\{M_k = i \mid M_{k+1} = j, Z^T\} \approx
    P\{M_k = i \mid M_{k+1} = j, Z^k\}` plus a Gaussian per mode; with one mode the recursion is
    exactly the RTS smoother (:func:`kftrack.kalman.rts_smoother`). This is not the two-filter
    smoother of Helmick, Blair & Hoffman (1995). Probabilities are handled in log space (a mode
    with zero probability keeps weight zero, no division by zero). Cost: :math:`r^2` RTS steps
    per time step, batched over runs. At ``T - 1`` the output is the filter's, to the last bit.

    **Every mode imm_filter accepts.** :math:`F_j` is the matrix of the mode's
    ``predict_linearized``: ``F(dt)`` for a :class:`KalmanMode`; for an :class:`EKFMode` the
    Jacobian of ``f`` at the pair's starting state :math:`x^i_{k|k}` (the extended RTS step, with
    the EKF's own prediction :math:`f_j(x^i_{k|k})`); for a :class:`UKFMode` the statistical
    linearization over the sigma points, :math:`F_j = C^\top (P^i_{k|k})^{+}`, so that
    :math:`G^{ij} = C (P^{ij}_{k+1|k})^{-1}` is the unscented RTS gain (Särkkä 2008) with the UKF's
    own predicted mean and covariance (no Jacobian needed; state angles: residual wrapped).
    **Modes of different dimension**: the pair step runs on mode ``j``'s components plus those of
    ``i`` that ``j`` lacks; ``i``'s posterior is completed where it lacks ``j``'s components with
    mode ``j``'s own filtered estimate at ``k`` (zero cross-covariance), the unbiased completion of
    the filter's mixing into ``j``; ``j``'s dynamics act on its own components
    (:math:`[F_j\;0]`), and ``i``'s extra components (``omega`` for a turn mode going into CV) are
    smoothed through their covariance with the others. The combined output completes modes of
    lower dimension as the filter's output does. Singular predicted covariances (e.g. after
    ``P0 = 0`` with a rank-deficient ``Q``) are handled by :func:`kftrack.kernels.rts_step`.

    **Limitation.** The collapse to one Gaussian per mode at every step makes the backward pass
    apply, in effect, the probability-weighted mix of the modes' inverse dynamics. With modes that
    one step of data hardly tells apart, frequent switching and small process noise (so the RTS
    gain is close to :math:`F^{-1}` and the data correct little per step), the mean can drift
    over long intervals: in the tests' CV/turn scenario (q = 0.05 m²/s³, 5 m noise) the smoother
    beats the filter with mean sojourn times of 20 s and more, but not with 5 s. Check it on
    the case at hand (tests/test_imm_smoother.py compares with the exact smoother by enumeration
    of the mode sequences).

    **Two engines.** NumPy arrays in ``result`` run the recursion above in a Python loop over
    ``k``, for every bank. JAX arrays (the result of :func:`imm_filter` on JAX input, or of
    :func:`imm_loglik`) run it as one reversed ``jax.lax.scan``
    (:func:`kftrack.engines.run_imm_smoother_scan`: the same kernels, all ``r^2`` pairs in one
    call of :func:`kftrack.kernels.rts_step` per step) and return JAX arrays; it takes the banks
    that :func:`imm_filter`'s JAX engine takes (:class:`KalmanMode` on the whole common state)
    and composes with ``jax.jit``, ``jax.vmap`` and ``jax.grad``: inside a trace the shapes of
    ``result`` are checked, not its values. With an :class:`IMMParams` in place of the estimator
    (the pure entry point, for ``grad`` and ``vmap`` over the parameters), ``F``, ``Q`` and
    :math:`\Pi = \operatorname{softmax}(L)` of ``params`` are those of every step (``H``, ``R``,
    ``log_mu0`` are checked, not used). The JAX engine solves :math:`P^{ij}_{k+1|k}` without
    the NumPy engine's pseudo-inverse branch (inf/NaN for a singular one).

    Parameters
    ----------
    estimator : the :class:`IMM` (not :class:`GPB1`) that produced ``result``; its modes are
        :class:`KalmanMode`, :class:`EKFMode`, :class:`UKFMode` (any mix, any dimensions), or
        modes with ``predict_linearized`` (:class:`Mode`); other modes raise ``TypeError``. Or
        the :class:`IMMParams` given to :func:`imm_loglik` (``F``, ``Q`` (r, n, n), ``logits``
        (r, r): one fixed interval; the JAX engine, whatever the arrays of ``result``).
    result : the :class:`IMMResult` of :func:`imm_filter` with this estimator, or of
        :func:`imm_loglik` with these ``params`` (it carries the per-mode posteriors ``xs``,
        ``Ps``); ``result.mu`` must be finite probabilities (checked when not traced).
    dt : interval (s) after each step, scalar, (T,) or (T - 1,): the same as given to
        :func:`imm_filter`. None with an :class:`IMMParams`.
    times : None, or instead of ``dt`` the timestamps ``(T,)`` (s), as in :func:`imm_filter`.

    Returns
    -------
    IMMSmootherResult
        ``x`` (T, ..., N), ``P`` (T, ..., N, N), ``mu`` (T, ..., r), ``xs``, ``Ps`` (per mode,
        on its components); NumPy or JAX arrays, as ``result`` (JAX with an :class:`IMMParams`).

    References
    ----------
    C.-J. Kim, "Dynamic linear models with Markov-switching", *Journal of Econometrics* 60
    (1994) 1–22. C.-J. Kim and C. R. Nelson, *State-Space Models with Regime Switching*, MIT
    Press 1999, §5.2. S. Särkkä, "Unscented Rauch–Tung–Striebel smoother", *IEEE Transactions
    on Automatic Control* 53 (2008) 845–849.

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.imm import IMM, KalmanMode, imm_filter, imm_smoother
    >>> from kftrack.models import ConstantVelocity
    >>> R = np.eye(1)
    >>> bank = IMM([KalmanMode(ConstantVelocity(ndim=1, q=0.01), R), KalmanMode(ConstantVelocity(ndim=1, q=10.0), R)],
    ...            transition=[[0.95, 0.05], [0.05, 0.95]], mu0=[0.5, 0.5])
    >>> zs = np.array([[0.0], [1.0], [2.1], [2.9], [np.nan], [8.0], [12.5], [17.0]])
    >>> back = imm_smoother(bank, imm_filter(bank, zs, np.zeros(2), 10 * np.eye(2), dt=1.0), dt=1.0)
    >>> back.x.shape, back.mu.shape
    ((8, 2), (8, 2))
    >>> bool(np.allclose(back.mu.sum(-1), 1.0))       # smoothed mode probabilities
    True

    The pure entry point: with ``p = imm_params(bank, 1.0)``,
    ``jax.grad(lambda p: (imm_smoother(p, imm_loglik(p, zs, x0, P0)[1]).x[:, 0] ** 2).sum())(p)``
    is an :class:`IMMParams` of gradients, and ``jax.vmap`` over a mode's ``Q`` smooths for each
    value; ``tests/test_compose_imm.py`` checks both (against central differences and the NumPy
    engine).
    """
    if isinstance(estimator, IMMParams):  # the pure entry point: the JAX engine, one fixed interval
        return _smoother_from_params(estimator, result, dt, times)
    _check_smoother_estimator(estimator)
    r, N, comps = estimator.r, estimator.N, estimator.components
    T, batch = _check_smoother_result(result, r, comps, N)
    dts = _dts(dt, T, times)
    if use_jax(result.mu, result.x, result.P, *result.xs, *result.Ps):
        return _smoother_jax(result, *_linear_bank(estimator, dts, "imm_smoother"))
    common = all(c == tuple(range(N)) for c in comps)  # every mode holds the common state, in order
    with np.errstate(divide="ignore"):
        log_mu_f = np.log(np.asarray(result.mu, dtype=float))
    out_mu = np.empty((T,) + batch + (r,))
    out_xs = tuple(np.empty((T,) + batch + (len(c),)) for c in comps)
    out_Ps = tuple(np.empty((T,) + batch + (len(c), len(c))) for c in comps)
    out_x, out_P = np.empty((T,) + batch + (N,)), np.empty((T,) + batch + (N, N))
    log_ms = log_mu_f[T - 1] - logsumexp(log_mu_f[T - 1], axis=-1, keepdims=True)
    # the filter's per-mode posteriors as NumPy arrays (a JAX result took the JAX engine above)
    f_xs = [np.asarray(a, dtype=float) for a in result.xs]
    f_Ps = [np.asarray(b, dtype=float) for b in result.Ps]
    xs_s = [f_xs[j][T - 1] for j in range(r)]
    Ps_s = [f_Ps[j][T - 1] for j in range(r)]
    spaces = [[_pair_space(comps[i], comps[j]) for j in range(r)] for i in range(r)]
    for k in range(T - 2, -1, -1):
        cond, log_ms = _kim_weights(log_mu_f[k], estimator.transition(dts[k]), log_ms)
        new_xs, new_Ps = [], []
        for i in range(r):
            pairs = [_pair_rts(mode, f_xs[i][k], f_Ps[i][k], f_xs[j][k], f_Ps[j][k], xs_s[j], Ps_s[j], dts[k],
                               spaces[i][j]) for j, mode in enumerate(estimator.modes)]
            a, b = moment_match(cond[..., i, :], np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs]))
            new_xs.append(a)
            new_Ps.append(b)
        xs_s, Ps_s = new_xs, new_Ps
        mu_s = np.exp(log_ms)
        out_mu[k] = mu_s
        for i in range(r):
            out_xs[i][k], out_Ps[i][k] = xs_s[i], Ps_s[i]
        if common:
            out_x[k], out_P[k] = moment_match(mu_s, np.stack(xs_s), np.stack(Ps_s))
        else:  # modes lacking components completed from the full ones, as in the filter's output
            _, out_x[k], out_P[k] = estimator._combine(log_ms, xs_s, Ps_s)
    # at T - 1 the smoother is the filter: its own numbers, to the last bit
    out_mu[T - 1], out_x[T - 1], out_P[T - 1] = (np.asarray(a[T - 1], dtype=float)
                                                  for a in (result.mu, result.x, result.P))
    for i in range(r):
        out_xs[i][T - 1], out_Ps[i][T - 1] = f_xs[i][T - 1], f_Ps[i][T - 1]
    return IMMSmootherResult(out_x, out_P, out_mu, out_xs, out_Ps)


def _smoother_jax(result: IMMResult, Fs, Qs, Pis) -> IMMSmootherResult:
    """The JAX engine of :func:`imm_smoother` (arguments checked): ``Fs``, ``Qs`` (T, r, n, n) and
    ``Pis`` (T, r, r) per step, NumPy or JAX arrays; the result's arrays converted (JAX arrays of
    the result's dtype stay as they are: the last step is the filter's, bit for bit)."""
    conv = lambda a, dtype=_result_dtype(result): to_engine(a, True, dtype)  # noqa: E731
    mu, x, P = conv(result.mu), conv(result.x), conv(result.P)
    xs, Ps = tuple(conv(a) for a in result.xs), tuple(conv(b) for b in result.Ps)
    if x.shape[0] < 2:
        return IMMSmootherResult(x, P, mu, xs, Ps)
    return IMMSmootherResult(*run_imm_smoother_scan(mu, x, P, xs, Ps, conv(Pis), conv(Fs), conv(Qs),
                                                    backward_weights=_kim_weights))


def _result_dtype(result: IMMResult):
    """The dtype of the smoother's JAX engine: the result's if it holds JAX arrays, else float64
    (:func:`kftrack.engines.check_dtype`: needs ``jax_enable_x64``)."""
    return result.x.dtype if use_jax(result.x) else check_dtype(None, True)


def _smoother_from_params(params: IMMParams, result: IMMResult, dt, times) -> IMMSmootherResult:
    """:func:`imm_smoother` with an :class:`IMMParams` (one fixed interval): checked, then the JAX engine."""
    if dt is not None or times is not None:
        given = "dt" if dt is not None else "times"
        raise ValueError("dt and times must be None when the first argument is an IMMParams (its F, Q and logits "
                         f"are those of one fixed interval), got {given} of shape "
                         f"{np.shape(dt if dt is not None else times)}")
    if not isinstance(result, IMMResult):
        raise TypeError(f"result must be an IMMResult from imm_loglik or imm_filter, got {type(result).__name__}")
    x_shape = tuple(np.shape(result.x))
    if len(x_shape) < 2:
        raise ValueError(f"result.x must have shape (T, ..., n), got shape {x_shape}")
    n = x_shape[-1]
    r = _check_imm_params(params, n, None, n_from="result.x", m_from="params.H")
    T, _ = _check_smoother_result(result, r, (tuple(range(n)),) * r, n)
    import jax  # IMMParams are JAX's

    jnp = jax.numpy
    F, Q, logits = (to_engine(a, True, _result_dtype(result)) for a in (params.F, params.Q, params.logits))
    Pi = jnp.exp(jax.nn.log_softmax(logits, axis=-1))  # as imm_loglik forms it
    return _smoother_jax(result, jnp.broadcast_to(F, (T,) + F.shape), jnp.broadcast_to(Q, (T,) + Q.shape),
                         jnp.broadcast_to(Pi, (T, r, r)))
