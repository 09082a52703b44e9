"""The site builds with warnings as errors from the stored (nbval-validated) outputs.

Runs after the unit tests and nbval (see the Makefile). Nothing executes during the build
(``execute_notebooks: off``), so the site shows exactly what the tests proved.
"""
from __future__ import annotations

from pathlib import Path

from sitepages import toc_files as _toc_files


def test_every_toc_page_is_built(built_site: Path) -> None:
    for name in _toc_files():
        assert (built_site / f"{name}.html").is_file(), f"{name}.html missing from the site"


def test_every_chapter_is_executed_and_shows_figures(built_site: Path) -> None:
    chapters = [f for f in _toc_files() if f.startswith("notebooks/")]
    assert chapters, "the table of contents lists no chapter"
    for name in chapters:
        html = (built_site / f"{name}.html").read_text(encoding="utf-8")
        assert "cell_output" in html, f"{name}: no stored outputs on the page"
        assert "<img" in html, f"{name}: no figure on the page"


def test_exercises_and_bibliography_render(built_site: Path) -> None:
    bib = (built_site / "book" / "bibliography.html").read_text(encoding="utf-8")
    assert "Bar-Shalom" in bib
    for name in [f for f in _toc_files() if f.startswith("notebooks/")]:
        html = (built_site / f"{name}.html").read_text(encoding="utf-8")
        assert "exercise" in html, f"{name}: no exercise block"


def test_mathematics_is_served_by_the_site_itself(built_site: Path) -> None:
    """MathJax comes from _static/ (book/_ext/offline_mathjax.py), not a CDN: the site renders
    its equations offline."""
    bundle = built_site / "_static" / "mathjax" / "tex-mml-chtml.js"
    assert bundle.is_file() and bundle.stat().st_size > 500_000
    fonts = list((built_site / "_static" / "mathjax" / "output" / "chtml" / "fonts" / "woff-v2").glob("*.woff"))
    assert len(fonts) > 10
    for name in _toc_files():
        html = (built_site / f"{name}.html").read_text(encoding="utf-8")
        assert "cdn.jsdelivr.net/npm/mathjax" not in html, f"{name}: MathJax still loaded from a CDN"
        if "\\(" in html or "\\[" in html:
            assert "_static/mathjax/tex-mml-chtml.js" in html, f"{name}: equations but no local MathJax"
