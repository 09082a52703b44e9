"""Tests of kftrack.plotting and kftrack.datasets: geometry of ellipses, style independent of
the working directory, plots that draw what they are given."""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest
from scipy import stats

from kftrack import datasets, plotting


def test_ellipse_points_lie_on_the_mahalanobis_contour():
    mean, cov = np.array([1.0, -2.0]), np.array([[4.0, 1.5], [1.5, 1.0]])
    for kwargs, r2 in [({}, 4.0), ({"nsigma": 3.0}, 9.0), ({"confidence": 0.95}, stats.chi2.ppf(0.95, 2))]:
        pts = plotting.ellipse_points(mean, cov, **kwargs)
        d = pts - mean
        m2 = np.einsum("ki,ij,kj->k", d, np.linalg.inv(cov), d)
        np.testing.assert_allclose(m2, r2, rtol=1e-10)


def test_ellipse_of_singular_covariance_is_a_segment():
    pts = plotting.ellipse_points([0.0, 0.0], np.diag([1.0, 0.0]))
    np.testing.assert_allclose(pts[:, 1], 0.0, atol=1e-15)
    # 100 samples of the angle: the extreme point is missed by at most 1 - cos(pi / 99)
    assert 2.0 * np.cos(np.pi / 99) <= np.abs(pts[:, 0]).max() <= 2.0


def test_ellipse_bad_input():
    with pytest.raises(ValueError, match="cov must be symmetric"):
        plotting.ellipse_points([0, 0], [[1.0, 1.0], [0.0, 1.0]])
    with pytest.raises(ValueError, match="mean must have shape"):
        plotting.ellipse_points([0, 0, 0], np.eye(2))
    with pytest.raises(ValueError, match="nsigma or confidence, not both"):
        plotting.ellipse_points([0, 0], np.eye(2), nsigma=1, confidence=0.5)


def test_book_style_loads_from_any_working_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    plotting.use_book_style()
    assert plt.rcParams["figure.dpi"] == 80
    assert plt.rcParams["axes.spines.top"] is False


def test_plot_track_draws_truth_measurements_estimates_and_ellipses():
    T = 20
    t = np.linspace(0, 1, T)
    truth = np.stack([t, t**2], axis=1)
    cov = np.broadcast_to(0.01 * np.eye(2), (T, 2, 2))
    fig, ax = plt.subplots()
    plotting.plot_track(ax, truth, truth + 0.1, truth, cov, every=5)
    assert len(ax.lines) == 3 + 4
    line = plotting.plot_band(ax, t, t, 0.1 * np.ones(T), label="band")
    assert line.get_label() == "band"
    plt.close(fig)


def test_data_path(tmp_path, monkeypatch):
    monkeypatch.setenv("KFTRACK_DATA", str(tmp_path))
    (tmp_path / "a.csv").write_text("x\n")
    assert datasets.data_path("a.csv") == tmp_path / "a.csv"
    with pytest.raises(FileNotFoundError, match="'missing.csv' not found"):
        datasets.data_path("missing.csv")


def test_animation_html_loads_nothing_from_the_network() -> None:
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation

    from kftrack.plotting import animation_html

    fig, ax = plt.subplots(figsize=(2, 2), dpi=30)
    (line,) = ax.plot([0, 1], [0, 1])
    anim = FuncAnimation(fig, lambda i: line.set_ydata([0, i]) or (line,), frames=2)
    page = animation_html(anim, default_mode="once")
    plt.close(fig)
    assert "<script" in page and "font-awesome" not in page and 'class="fa ' not in page
    assert "\u25b6" in page  # the play button, as a glyph
