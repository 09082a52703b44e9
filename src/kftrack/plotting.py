"""The book's figures: matplotlib style, covariance ellipses and track plots.

Presentation layer: imports numerics from below, never the other way round. The style
file ships inside the package, so it works from any working directory.
"""
from __future__ import annotations

from importlib import resources

import numpy as np
from scipy import stats

from ._validate import as_vector, check_covariance

__all__ = ["use_book_style", "ellipse_points", "covariance_ellipse", "plot_track", "plot_band", "plot_chi2_band"]


def use_book_style() -> None:
    """Apply the book's matplotlib style (shipped as ``kftrack/styles/book.mplstyle``)."""
    import matplotlib.pyplot as plt

    with resources.as_file(resources.files("kftrack") / "styles" / "book.mplstyle") as path:
        plt.style.use(str(path))


def ellipse_points(mean, cov, nsigma: float | None = None, confidence: float | None = None,
                   num: int = 100) -> np.ndarray:
    r"""Points ``(num, 2)`` on the ellipse :math:`(p-\mu)^\top C^{-1} (p-\mu) = r^2`.

    Give either ``nsigma`` (``r = nsigma``) or ``confidence`` (``r^2 = \chi^2_2(confidence)``,
    the region holding that probability mass); the default is ``nsigma = 2``.
    ``mean`` is ``(2,)``, ``cov`` is ``(2, 2)`` (the position block of a larger covariance).
    """
    mean = as_vector(mean, "mean", 2)
    cov = check_covariance(cov, "cov", 2)
    if nsigma is not None and confidence is not None:
        raise ValueError("give nsigma or confidence, not both")
    if confidence is not None:
        if not 0 < confidence < 1:
            raise ValueError(f"confidence must lie in (0, 1), got {confidence!r}")
        r = np.sqrt(stats.chi2.ppf(confidence, 2))
    else:
        r = 2.0 if nsigma is None else float(nsigma)
    vals, vecs = np.linalg.eigh(cov)
    t = np.linspace(0.0, 2.0 * np.pi, num)
    circle = np.stack([np.cos(t), np.sin(t)], axis=-1)
    return mean + r * (circle * np.sqrt(np.clip(vals, 0.0, None))) @ vecs.T


def covariance_ellipse(ax, mean, cov, nsigma: float | None = None, confidence: float | None = None, **kwargs):
    """Draw the covariance ellipse of a 2-D Gaussian on ``ax``; returns the line."""
    pts = ellipse_points(mean, cov, nsigma=nsigma, confidence=confidence)
    kwargs.setdefault("lw", 1.0)
    (line,) = ax.plot(pts[:, 0], pts[:, 1], **kwargs)
    return line


def plot_track(ax, truth=None, measurements=None, estimates=None, covariances=None, *,
               every: int = 10, nsigma: float = 2.0, labels=("truth", "measurements", "estimate")):
    """Plot a 2-D track: truth (line), measurements (dots), estimates (line) and, when
    ``covariances`` ``(T, 2, 2)`` are given, an ellipse every ``every`` steps.

    Each of ``truth``, ``measurements``, ``estimates`` is ``(T, 2)`` positions in metres.
    """
    if truth is not None:
        truth = np.asarray(truth)
        ax.plot(truth[:, 0], truth[:, 1], color="k", lw=1.0, label=labels[0])
    if measurements is not None:
        z = np.asarray(measurements)
        ax.plot(z[:, 0], z[:, 1], ".", color="C1", ms=3, alpha=0.6, label=labels[1])
    if estimates is not None:
        est = np.asarray(estimates)
        ax.plot(est[:, 0], est[:, 1], color="C0", label=labels[2])
        if covariances is not None:
            cov = np.asarray(covariances)
            for k in range(0, len(est), every):
                covariance_ellipse(ax, est[k], cov[k], nsigma=nsigma, color="C0", alpha=0.5)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend()
    return ax


def plot_band(ax, t, mean, std, nsigma: float = 1.96, label: str | None = None, **kwargs):
    """A line ``mean(t)`` with the band ``mean ± nsigma·std`` shaded; returns the line."""
    t, mean, std = (np.asarray(a, dtype=float) for a in (t, mean, std))
    (line,) = ax.plot(t, mean, label=label, **kwargs)
    ax.fill_between(t, mean - nsigma * std, mean + nsigma * std, color=line.get_color(), alpha=0.2, lw=0)
    return line


def plot_chi2_band(ax, t, mean, bounds, label: str | None = None, **kwargs):
    """A Monte Carlo average of NEES or NIS over time, ``mean(t)``, with its chi-square
    acceptance interval ``bounds = (lower, upper)`` shaded (e.g. from
    :func:`kftrack.metrics.consistency`); returns the line."""
    t, mean = np.asarray(t, dtype=float), np.asarray(mean, dtype=float)
    (line,) = ax.plot(t, mean, label=label, **kwargs)
    ax.axhspan(bounds[0], bounds[1], color="0.5", alpha=0.2, lw=0)
    return line
