"""Every chapter runs in the reader's browser: JupyterLite + Pyodide, offline, in Chromium.

The built site (``_build/html``, with ``lite/`` built by ``book/_ext/lite.py``) is served on
127.0.0.1; Debian's Chromium (through Playwright, which never downloads a browser) opens a
chapter in the JupyterLite notebook interface, runs all cells with the interface's "Run All"
command, and checks that every code cell ran (has an execution count) without an error output.
Every request that would leave 127.0.0.1 is recorded and refused, and Chromium resolves no
other host at all. In a chapter with widgets (04, 06), a slider renders (screenshot in
``_build/screenshots/``) and dragging it changes the figure. In ``make test``: :data:`DEFAULT`.
``make lite-check`` runs every chapter that has a Lite copy (KFTRACK_LITE_CHAPTERS=all) and
prints the time of each and what it downloaded into an empty browser cache.

The hash check of the Pyodide files is tested without a browser: a tampered copy fails.
"""
from __future__ import annotations

import hashlib
import http.server
import json
import os
import sys
import threading
import time
from pathlib import Path
from urllib.parse import urlparse

import pytest

from sitepages import ROOT, serve

sys.path.insert(0, str(ROOT / "book" / "_ext"))
import lite  # noqa: E402  (the build extension under test)

CHROMIUM = Path("/usr/bin/chromium")
SHOTS = ROOT / "_build" / "screenshots"
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
        "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1"]  # no other host resolves at all
# In `make test`: an early chapter with widgets (04: the screenshot and the slider drag), the IMM chapter
# (10) and the clutter chapter (17). With 01 they took 525 s together at load average ~7 on 2 cores
# (DEVELOPERS.md); the unit tests and nbval run on both cores (pytest-xdist) to leave room for them.
# `make lite-check` runs every chapter.
DEFAULT = ("04", "10", "17")
# Hang guards, not performance claims (times are in DEVELOPERS.md): on a 2-core machine shared
# with a load average of ~15, the kernel took up to 270 s to start and a chapter up to 400 s.
KERNEL_TIMEOUT_MS = 600_000
RUN_TIMEOUT_MS = 900_000


# --- the hash check (no browser) -------------------------------------------------------------

def _fake_lock(tmp_path: Path) -> tuple[dict, Path]:
    src = tmp_path / "src"
    src.mkdir()
    files = {"numpy": b"numpy bytes", "scipy": b"scipy bytes"}
    pkgs = {}
    for name, data in files.items():
        (src / f"{name}.whl").write_bytes(data)
        pkgs[name] = {"name": name, "file_name": f"{name}.whl", "sha256": hashlib.sha256(data).hexdigest(),
                      "depends": ["numpy"] if name == "scipy" else []}
    return {"info": {"version": "0.27.7"}, "packages": pkgs}, src


def test_copy_verified_copies_files_that_match_the_lock(tmp_path: Path) -> None:
    lock, src = _fake_lock(tmp_path)
    n = lite.copy_verified(lock, ["numpy", "scipy"], src, tmp_path / "out")
    assert n == len(b"numpy bytes") + len(b"scipy bytes")
    assert (tmp_path / "out" / "scipy.whl").read_bytes() == b"scipy bytes"


def test_a_tampered_pyodide_file_fails_the_build(tmp_path: Path) -> None:
    lock, src = _fake_lock(tmp_path)
    (src / "scipy.whl").write_bytes(b"scipy bytes, tampered")
    with pytest.raises(lite.LockMismatch, match=r"scipy\.whl: sha256 .* does not match the official pyodide-lock"):
        lite.copy_verified(lock, ["numpy", "scipy"], src, tmp_path / "out")
    assert not (tmp_path / "out" / "scipy.whl").exists()


def test_the_real_lock_and_the_shipped_closure() -> None:
    """The npm lock is Pyodide 0.27.7's; the shipped set holds the chapters' packages and none
    of the large unused ones."""
    lock = json.loads((lite.PYODIDE_NPM / "pyodide-lock.json").read_text())
    assert lock["info"]["version"] == "0.27.7"
    names = lite.package_closure(lock, lite.PYODIDE_ROOTS)
    assert {"numpy", "scipy", "matplotlib", "openblas", "ipython"} <= set(names)
    assert not {"pandas", "pyarrow", "scikit-learn"} & set(names)
    served = lite.served_lock(lock, names)
    assert set(served["packages"]) == set(names) and served["info"] == lock["info"]


def test_chapter_19_is_left_out_for_jax_and_the_rest_is_not() -> None:
    reasons = {nb.stem[:2]: lite.unavailable_reason(nb) for nb in lite.chapters()}
    assert "JAX" in (reasons.get("19") or "")
    assert [k for k, v in reasons.items() if v] == ["19"]


def test_every_chapter_page_offers_its_lite_copy(built_site: Path) -> None:
    """Each chapter page's launch menu opens its Lite copy, which starts with the setup cell and
    holds no stored output; chapter 19's page says why it has none."""
    seen = 0
    for nb in lite.chapters():
        page = built_site / "notebooks" / f"{nb.stem}.html"
        if not page.is_file():  # a chapter not yet in the table of contents
            continue
        html = page.read_text(encoding="utf-8")
        copy = built_site / "lite" / "files" / nb.name
        if lite.unavailable_reason(nb):
            assert "lite-unavailable" in html and "lite/notebooks/index.html" not in html, nb.name
            assert not copy.exists(), nb.name
            continue
        seen += 1
        assert f'href="../lite/notebooks/index.html?path={nb.name}"' in html, f"{nb.name}: no Run in your browser entry"
        cells = json.loads(copy.read_text(encoding="utf-8"))["cells"]
        assert "piplite.install" in "".join(cells[0]["source"]), f"{nb.name}: no setup cell"
        assert not any(c.get("outputs") for c in cells), f"{nb.name}: the Lite copy keeps stored outputs"
    assert seen >= 18


# --- in the browser ------------------------------------------------------------------------

def _chapters() -> list[str]:
    wanted = os.environ.get("KFTRACK_LITE_CHAPTERS", " ".join(DEFAULT)).split()
    if wanted == ["all"]:
        return [nb.stem[:2] for nb in lite.chapters() if lite.unavailable_reason(nb) is None]
    return wanted


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    """Serves the site; counts the bytes of the bodies it sends (the reader's download)."""
    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, ".wasm": "application/wasm",
                      ".mjs": "text/javascript", ".whl": "application/octet-stream"}
    sent = 0
    files: dict[str, int] = {}  # path -> bytes: what a reader's cache holds after the visit
    lock = threading.Lock()

    def send_header(self, keyword, value) -> None:
        if keyword.lower() == "content-length":
            with _QuietHandler.lock:
                _QuietHandler.sent += int(value)
                _QuietHandler.files[self.path.split("?")[0]] = int(value)
        super().send_header(keyword, value)

    def log_message(self, *args) -> None:
        pass


@pytest.fixture(scope="module")
def site_url(built_site: Path):
    if not (built_site / "lite" / "notebooks" / "index.html").is_file():
        pytest.fail(f"{built_site}/lite was not built (book/_ext/lite.py)")
    with serve(built_site, _QuietHandler) as url:
        yield url


@pytest.fixture(scope="module")
def browser():
    if not CHROMIUM.is_file():
        pytest.skip("Chromium is not installed: `apt-get install -y chromium` (Debian's package; .ci/run installs it)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is pinned in requirements.txt")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=ARGS)
        try:
            yield b
        finally:
            b.close()


class _Lite:
    """One chapter open in the JupyterLite notebook interface, with what left 127.0.0.1."""

    def __init__(self, browser, site_url: str, notebook: str):
        self.outside: list[str] = []
        self.page_errors: list[str] = []
        # A fresh context: empty browser storage, so the chapter is the site's copy.
        self.context = browser.new_context(viewport={"width": 1280, "height": 1000})
        self.context.route("**/*", self._route)
        self.page = self.context.new_page()
        self.page.on("pageerror", lambda e: self.page_errors.append(str(e)))
        self.page.goto(f"{site_url}/lite/notebooks/index.html?path={notebook}", wait_until="load")
        self.page.wait_for_function("""() => {
            const w = window.jupyterapp && window.jupyterapp.shell.currentWidget;
            const k = w && w.sessionContext && w.sessionContext.session && w.sessionContext.session.kernel;
            return k && k.status === 'idle' && w.content.widgets.length > 0;
        }""", timeout=KERNEL_TIMEOUT_MS, polling=500)

    def _route(self, route) -> None:
        url = route.request.url
        if url.startswith(("data:", "blob:", "about:")) or urlparse(url).hostname == "127.0.0.1":
            route.continue_()
        else:
            self.outside.append(url)
            route.abort()

    def run_all(self) -> dict:
        self.page.evaluate("() => window.jupyterapp.commands.execute('notebook:run-all-cells')")
        # Done when the kernel is idle and every code cell has run, or a cell has failed
        # (Run All stops at the first error).
        self.page.wait_for_function("""() => {
            const w = window.jupyterapp.shell.currentWidget;
            const cells = w.content.widgets.filter(c => c.model.type === 'code');
            const failed = cells.some(c => c.model.outputs.toJSON().some(o => o.output_type === 'error'));
            const ran = cells.every(c => c.model.executionCount !== null);
            return w.sessionContext.session.kernel.status === 'idle' && (ran || failed);
        }""", timeout=RUN_TIMEOUT_MS, polling=500)
        return self.page.evaluate("""() => {
            const w = window.jupyterapp.shell.currentWidget;
            const cells = w.content.widgets.filter(c => c.model.type === 'code');
            return {n: cells.length,
                    notrun: cells.map((c, i) => c.model.executionCount === null ? i : -1).filter(i => i >= 0),
                    errors: cells.flatMap((c, i) => c.model.outputs.toJSON().filter(o => o.output_type === 'error')
                                 .map(o => `cell ${i}: ${o.ename}: ${o.evalue}`))};
        }""")

    def close(self) -> None:
        self.context.close()


def _notebook(prefix: str) -> str:
    (nb,) = [p for p in lite.chapters() if p.stem.startswith(prefix + "-")]
    return nb.name


def _uses_widgets(notebook: str) -> bool:
    return lite._imports(lite._code(json.loads((lite.NOTEBOOKS / notebook).read_text())), "ipywidgets")


def _move_a_slider(lab: _Lite, chapter: str) -> None:
    """The first interact's slider renders (screenshot) and dragging its handle changes its value
    and then its figure, twice (JupyterLite 0.4 with ipywidgets 8.1.3+ updated an interact only
    once: ipywidgets#3935).

    The handle is dragged with the mouse, as a reader does. Arrow keys on the focused handle do not
    move it in the notebook interface, most likely because its command-mode shortcuts bind
    ArrowLeft/ArrowRight (collapse/expand a heading) for any focused element that is not an
    editor (DEVELOPERS.md)."""
    page = lab.page
    box = page.locator(".widget-interact").first
    box.wait_for(state="attached", timeout=60_000)
    # The notebook is windowed: a cell off screen is display:none. Scroll the notebook to it.
    page.evaluate("""async () => {
        const nb = window.jupyterapp.shell.currentWidget.content;
        const i = nb.widgets.findIndex(c => c.node.querySelector('.widget-interact'));
        nb.activeCellIndex = i;
        await nb.scrollToItem(i, 'center');
    }""")
    box.wait_for(state="visible", timeout=60_000)
    handle = box.locator(".noUi-handle").first
    handle.wait_for(state="visible", timeout=60_000)
    readout = box.locator(".widget-readout").first
    figure = box.locator("img").first
    figure.wait_for(state="visible", timeout=120_000)
    SHOTS.mkdir(parents=True, exist_ok=True)
    shot = SHOTS / f"lite_{chapter}_widget.png"
    box.screenshot(path=str(shot))
    assert shot.stat().st_size > 10_000, "the widget's screenshot is nearly empty"
    for dx in (60, -30):  # two moves: the second must redraw too
        value, src = readout.text_content(), figure.get_attribute("src")
        handle.scroll_into_view_if_needed()
        b = handle.bounding_box()
        x, y = b["x"] + b["width"] / 2, b["y"] + b["height"] / 2
        page.mouse.move(x, y)
        page.mouse.down()
        page.mouse.move(x + dx, y, steps=5)
        page.mouse.up()
        assert readout.text_content() != value, f"dragging the slider by {dx} px did not change its value {value}"
        page.wait_for_function("""(before) => {
            const img = document.querySelector('.widget-interact img');
            return img && img.getAttribute('src') !== before;
        }""", arg=src, timeout=120_000)


@pytest.mark.parametrize("chapter", _chapters())
def test_chapter_runs_in_the_browser(browser, site_url: str, chapter: str) -> None:
    """All cells run without an error, nothing leaves 127.0.0.1; in a widget chapter (04, 06) a
    slider renders and dragging it changes the figure (twice)."""
    notebook = _notebook(chapter)
    _QuietHandler.sent, _QuietHandler.files = 0, {}
    t0 = time.perf_counter()
    lab = _Lite(browser, site_url, notebook)
    try:
        t1 = time.perf_counter()
        result = lab.run_all()
        t2 = time.perf_counter()
        print(f"\nlite chapter {chapter}: {result['n']} code cells, kernel ready {t1 - t0:.0f} s, "
              f"run all {t2 - t1:.0f} s, downloaded {_QuietHandler.sent / 1e6:.1f} MB "
              f"({sum(_QuietHandler.files.values()) / 1e6:.1f} MB in {len(_QuietHandler.files)} distinct files)",
              flush=True)
        assert not result["errors"], "\n".join(result["errors"])
        assert not result["notrun"], f"cells not run: {result['notrun']}"
        if _uses_widgets(notebook):
            _move_a_slider(lab, chapter)
        assert not lab.outside, f"requests leaving 127.0.0.1: {lab.outside}"
    finally:
        lab.close()
