"""The book's figures: matplotlib style, covariance ellipses and track plots.

Presentation layer: imports numerics from below, never the other way round. The style
file ships inside the package, so it works from any working directory.
"""
from __future__ import annotations

from importlib import resources

import numpy as np
from scipy import stats

from ._validate import as_vector, check_covariance

__all__ = ["use_book_style", "ellipse_points", "covariance_ellipse", "plot_track", "plot_tracks", "plot_band", "plot_chi2_band"]


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

    Examples
    --------
    >>> import numpy as np
    >>> from kftrack.plotting import ellipse_points
    >>> pts = ellipse_points([0.0, 0.0], np.diag([4.0, 1.0]), nsigma=1.0, num=5)   # semi-axes 2 and 1
    >>> pts.shape, np.round(np.abs(pts).max(axis=0), 6).tolist()
    ((5, 2), [2.0, 1.0])
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
    """Draw the covariance ellipse of a 2-D Gaussian on ``ax``; returns the line.

    Examples
    --------
    >>> import numpy as np
    >>> from matplotlib.figure import Figure
    >>> from kftrack.plotting import covariance_ellipse
    >>> ax = Figure().add_subplot()                   # no window: draw on a figure in memory
    >>> line = covariance_ellipse(ax, [0.0, 0.0], np.diag([4.0, 1.0]), confidence=0.95)
    >>> line.get_xydata().shape
    (100, 2)
    """
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


def plot_tracks(ax, tracks, truth=None, *, tentative: bool = False, km: bool = True):
    """Draw multi-target tracks over the truth: each track's confirmed part as a coloured line
    (its id at the start), the true paths as thin grey lines.

    Parameters
    ----------
    tracks : :class:`kftrack.multitarget.Tracks` (or any iterable of tracks with ``x`` (k, 4)
        ``[x, vx, y, vy]``, ``confirmed`` (k,) and ``id``).
    truth : optional true paths: a mapping ``{name: (k, 2)}`` or a sequence of ``(k, 2)`` arrays
        of positions in metres.
    tentative : also draw the tentative rows (dotted).
    km : axes in kilometres (default) or metres.
    """
    s = 1e-3 if km else 1.0
    if truth is not None:
        paths = truth.values() if hasattr(truth, "values") else truth
        for k, p in enumerate(paths):
            p = np.asarray(p, dtype=float).reshape(-1, 2)
            ax.plot(s * p[:, 0], s * p[:, 1], color="0.6", lw=0.8, label="truth" if k == 0 else None)
    first = True
    for k, tr in enumerate(tracks):
        x, c = np.asarray(tr.x), np.asarray(tr.confirmed, dtype=bool)
        color = f"C{k % 10}"
        if tentative and (~c).any():
            ax.plot(s * x[~c, 0], s * x[~c, 2], ":", color=color, lw=0.8)
        if c.any():
            ax.plot(s * x[c, 0], s * x[c, 2], color=color, lw=1.2, label="confirmed tracks" if first else None)
            i = int(np.argmax(c))
            ax.annotate(str(tr.id), (s * x[i, 0], s * x[i, 2]), fontsize=7, color=color)
            first = False
    unit = "km" if km else "m"
    ax.set_xlabel(f"east ({unit})")
    ax.set_ylabel(f"north ({unit})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize=8)
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


# --------------------------------------------------------------------------------------------
# robot localization and SLAM (chapter 15)
# --------------------------------------------------------------------------------------------
__all__ += ["plot_walls", "plot_slam_map", "slam_animation", "animation_html"]


def plot_walls(ax, walls, **kwargs):
    """Draw a floor plan ``(W, 2, 2)`` of wall segments (m) on ``ax``."""
    kwargs.setdefault("color", "0.3")
    kwargs.setdefault("lw", 2.0)
    for (x0, y0), (x1, y1) in np.asarray(walls, dtype=float):
        ax.plot([x0, x1], [y0, y1], **kwargs)
    ax.set_aspect("equal", adjustable="datalim")
    return ax


def plot_slam_map(ax, x, P, nsigma: float = 2.0, color: str = "C0", robot: bool = True):
    """Draw an EKF-SLAM estimate ``x`` ``(3 + 2N,)``, ``P``: each landmark with its ``nsigma``
    ellipse and, with ``robot=True``, the robot position, heading tick and ellipse."""
    x, P = np.asarray(x, dtype=float), np.asarray(P, dtype=float)
    artists = []
    for j in range((x.shape[-1] - 3) // 2):
        s = slice(3 + 2 * j, 5 + 2 * j)
        artists.append(covariance_ellipse(ax, x[s], P[s, s], nsigma=nsigma, color=color))
        artists += ax.plot(*x[s], "+", color=color, ms=5)
    if robot:
        artists.append(covariance_ellipse(ax, x[:2], P[:2, :2], nsigma=nsigma, color="C3"))
        artists += ax.plot(x[0], x[1], "o", color="C3", ms=4)
        artists += ax.plot([x[0], x[0] + 0.8 * np.cos(x[2])], [x[1], x[1] + 0.8 * np.sin(x[2])], color="C3")
    return artists


def slam_animation(result, truth, landmarks, frames: int = 16, nsigma: float = 2.0, dpi: int = 50,
                   figsize=(4.0, 4.0)):
    """A small ``matplotlib.animation.FuncAnimation`` of one EKF-SLAM run: the true path and
    landmarks (black), the estimated robot with its ellipse (red) and the map with its ellipses
    (blue), at ``frames`` evenly spaced steps. ``result`` is a :class:`kftrack.slam.SlamResult`
    of one run, ``truth`` ``(T, 3)``, ``landmarks`` ``(L, 2)``. Render with ``to_jshtml()``."""
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation

    steps = np.linspace(0, len(result.x) - 1, int(frames)).round().astype(int)
    fig, ax = plt.subplots(figsize=figsize, dpi=dpi)
    lm = np.asarray(landmarks, dtype=float)
    lo, hi = lm.min(0) - 1.5, lm.max(0) + 1.5
    dynamic: list = []

    def draw(i):
        for a in dynamic:
            a.remove()
        dynamic.clear()
        k = steps[i]
        dynamic.extend(ax.plot(truth[: k + 1, 0], truth[: k + 1, 1], color="k", lw=0.8))
        dynamic.extend(plot_slam_map(ax, result.x[k], result.P[k], nsigma=nsigma))
        ax.set_title(f"step {k}")
        return dynamic

    ax.plot(lm[:, 0], lm[:, 1], "k*", ms=5)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    anim = FuncAnimation(fig, draw, frames=len(steps), interval=400, blit=False)
    plt.close(fig)
    return anim


# matplotlib's JavaScript player draws its buttons with Font Awesome 4 icons, loaded from a
# CDN; the book's pages are offline, so the icons become plain Unicode glyphs instead.
_PLAYER_ICONS = {
    "fa fa-minus": "\u2212", "fa fa-fast-backward": "\u23ee", "fa fa-step-backward": "\u23ea",
    "fa fa-play fa-flip-horizontal": "\u25c0", "fa fa-pause": "\u23f8", "fa fa-play": "\u25b6",
    "fa fa-step-forward": "\u23e9", "fa fa-fast-forward": "\u23ed", "fa fa-plus": "+",
}


def animation_html(anim, **kwargs) -> str:
    """The HTML of a matplotlib animation's JavaScript player, with nothing loaded from the
    network.

    ``anim.to_jshtml(**kwargs)`` links a Font Awesome style sheet on a CDN for its button
    icons; this removes the link and writes each icon as a Unicode glyph, so the player works
    on an offline page.

    Parameters
    ----------
    anim : matplotlib.animation.Animation
    **kwargs
        Passed to ``anim.to_jshtml`` (e.g. ``default_mode="once"``).

    Returns
    -------
    str
        HTML to show with ``IPython.display.HTML``.
    """
    import re

    page = anim.to_jshtml(**kwargs)
    page = re.sub(r'<link rel="stylesheet"\s+href="https?://[^"]*font-awesome[^"]*">', "", page)
    for cls, glyph in _PLAYER_ICONS.items():
        page = page.replace(f'<i class="{cls}"></i>', glyph)
    return page
