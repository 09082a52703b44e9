"""Serve MathJax from the site itself, so the book's mathematics renders without a network.

Sphinx loads MathJax from a CDN by default; a reader offline (an exam room, a copied
``_build/html``) would see raw ``\\(...\\)``. This extension takes MathJax 3 from the pinned
PyPI package ``django-static-mathjax`` (import name ``mathjax``, static files only, no
Django needed), points ``mathjax_path`` at ``_static/mathjax/tex-mml-chtml.js`` and copies
that bundle with its fonts and TeX extensions (about 2 MB, not the whole 35 MB package)
into the built site.
"""
from __future__ import annotations

import shutil
from importlib import resources
from pathlib import Path

BUNDLE = "tex-mml-chtml.js"
PARTS = (BUNDLE, "output/chtml/fonts/woff-v2", "input/tex/extensions")


def _source() -> Path:
    es5 = Path(str(resources.files("mathjax"))) / "static" / "mathjax" / "es5"
    if not (es5 / BUNDLE).is_file():
        raise FileNotFoundError(f"MathJax bundle not found at {es5 / BUNDLE}: is django-static-mathjax installed?")
    return es5


def _use_local(app, config) -> None:
    _source()  # fail early, before a build that would ship a site with raw TeX
    config.mathjax_path = f"mathjax/{BUNDLE}"  # relative: under _static/


def _copy(app, exception) -> None:
    if exception is not None or app.builder.format != "html":
        return
    src, dst = _source(), Path(app.outdir) / "_static" / "mathjax"
    for part in PARTS:
        if (src / part).is_dir():
            shutil.copytree(src / part, dst / part, dirs_exist_ok=True)
        else:
            (dst / part).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / part, dst / part)


def setup(app):
    app.connect("config-inited", _use_local)
    app.connect("build-finished", _copy)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
