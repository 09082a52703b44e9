"""The page's scripts: local copies instead of CDNs, and each script once.

* **Widgets.** A chapter with ipywidgets embeds the widget state; myst-nb then loads
  ``require.js`` and the Jupyter widgets HTML manager (``embed-amd.js``) from public CDNs.
  This extension serves both from ``_static/`` instead, taken from the npm packages pinned in
  ``book/_js/package.json`` (installed by ``make`` with ``npm ci``), so a page with widgets
  renders them offline. The manager bundles ``@jupyter-widgets/base`` and ``controls``; the
  book uses no third-party widget, so no module is ever fetched from a CDN.
* **Thebe.** ``sphinx-thebe`` adds its inline configuration script on every build pass;
  a page that carries it twice logs ``Identifier 'THEBE_JS_URL' has already been
  declared``. Duplicate inline scripts are dropped from each page.
"""
from __future__ import annotations

import shutil
from pathlib import Path

JS = Path(__file__).resolve().parents[1] / "_js" / "node_modules"
REQUIRE = JS / "requirejs" / "require.js"
MANAGER = JS / "@jupyter-widgets" / "html-manager" / "dist"



def _check() -> None:
    for path in (REQUIRE, MANAGER / "embed-amd.js"):
        if not path.is_file():
            raise FileNotFoundError(f"{path} not found: run `make venv` (npm ci in book/_js) first")


def _use_local(app, config) -> None:
    _check()  # fail early, before a build that would ship pages loading scripts from a CDN
    config.nb_ipywidgets_js = {
        "require.js": {},
        # A module the manager does not bundle would be looked up here (none is: base and controls).
        "jupyter-widgets/embed-amd.js": {"data-jupyter-widgets-cdn": "../_static/jupyter-widgets/"},
    }


def _dedupe(app, builder) -> None:
    """Sphinx 7.4 re-adds the registry's inline scripts as ``_JavaScript('')`` while the copies
    added earlier are ``_JavaScript(None)``, so each inline script would appear twice; drop
    the early copies just before the builder re-adds them."""
    js_files = getattr(builder, "_js_files", None)
    if js_files is None:
        return
    inline = [{k: v for k, v in attrs.items() if k != "priority"} for name, attrs in app.registry.js_files if not name]
    js_files[:] = [js for js in js_files if not (js.filename is None and js.attributes in inline)]


def _copy(app, exception) -> None:
    if exception is not None or app.builder.format != "html":
        return
    static = Path(app.outdir) / "_static"
    shutil.copy2(REQUIRE, static / "require.js")
    (static / "jupyter-widgets").mkdir(parents=True, exist_ok=True)
    shutil.copy2(MANAGER / "embed-amd.js", static / "jupyter-widgets" / "embed-amd.js")
    # The bundle's style sheets resolve their Font Awesome fonts against the module path that
    # require.js gives it, "@jupyter-widgets/html-manager/dist/" relative to the page, before any
    # setting can move it: serve the fonts there, beside each page that embeds widgets.
    fonts = [p for p in MANAGER.iterdir() if p.suffix in (".woff", ".woff2", ".ttf", ".eot", ".svg")]
    folders = {page.parent for page in Path(app.outdir).rglob("*.html")
               if "jupyter-widgets/embed-amd.js" in page.read_text(encoding="utf-8", errors="ignore")}
    for folder in folders:
        dst = folder / "@jupyter-widgets" / "html-manager" / "dist"
        dst.mkdir(parents=True, exist_ok=True)
        for path in fonts:
            shutil.copy2(path, dst / path.name)


def setup(app):
    app.connect("config-inited", _use_local)
    app.connect("write-started", _dedupe)
    app.connect("build-finished", _copy)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
