"""The built site in a real browser: headless Chromium, offline, every page.

The site is served on 127.0.0.1 by a local HTTP server that this module starts and stops.
Playwright's Python package drives Debian's ``chromium`` (``/usr/bin/chromium``; Playwright
never downloads a browser here). Every request that would leave 127.0.0.1 is recorded and
refused, so a page that needs the network fails. For every page of the table of contents:
no console error, no page error, no request off the machine, every ``<img>`` decoded,
MathJax has typeset every formula. Then: the search page finds "Joseph", an exercise's
solution stays hidden until its toggle is clicked, the API reference documents
``kftrack.kalman.update``. Screenshots of three pages go to ``_build/screenshots/``.
"""
from __future__ import annotations

import http.server
import shutil
from pathlib import Path
from urllib.parse import urlparse

import pytest

from sitepages import ROOT, serve, toc_files

CHROMIUM = Path("/usr/bin/chromium")
SHOTS = ROOT / "_build" / "screenshots"
# Flags for a sandboxed root session on a closed network (no background connections, no GPU).
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage"]

if not CHROMIUM.is_file():
    pytest.skip("Chromium is not installed: `apt-get install -y chromium` (Debian's package; .ci/run installs it)",
                allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is pinned in requirements.txt: make venv")


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:  # keep pytest's output clean
        pass


@pytest.fixture(scope="module")
def site_url(built_site: Path):
    with serve(built_site, _QuietHandler) as url:
        yield url


@pytest.fixture(scope="module")
def browser():
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=ARGS)
        try:
            yield b
        finally:
            b.close()


class _Page:
    """A page opened offline, with what it logged and what it tried to fetch."""

    def __init__(self, browser, url: str):
        self.errors: list[str] = []
        self.outside: list[str] = []
        self.context = browser.new_context(viewport={"width": 1280, "height": 900})
        self.page = self.context.new_page()
        self.page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        self.page.on("pageerror", lambda e: self.errors.append(f"page error: {e}"))
        self.page.on("response", lambda r: self.errors.append(f"HTTP {r.status}: {r.url}") if r.status >= 400 else None)
        self.context.route("**/*", self._route)
        self.page.goto(url, wait_until="load")

    def _route(self, route) -> None:
        url = route.request.url
        host = urlparse(url).hostname
        if url.startswith(("data:", "blob:", "about:")) or host == "127.0.0.1":
            route.continue_()
        else:
            self.outside.append(url)
            route.abort()

    def close(self) -> None:
        self.context.close()


def _wait_for_mathjax(page) -> None:
    page.wait_for_function("() => !window.MathJax || (window.MathJax.startup && window.MathJax.startup.promise)")
    page.evaluate("() => window.MathJax && window.MathJax.startup.promise")


def _check_page(browser, url: str, name: str) -> list[str]:
    p = _Page(browser, url)
    problems = []
    try:
        page = p.page
        _wait_for_mathjax(page)
        # Images below the fold may be lazy: make every image load, then check it decoded.
        page.evaluate("() => document.querySelectorAll('img').forEach(i => { i.loading = 'eager'; })")
        page.wait_for_function("() => [...document.images].every(i => i.complete)", timeout=20_000)
        broken = page.evaluate("() => [...document.images].filter(i => !(i.naturalWidth > 0)).map(i => i.src)")
        problems += [f"image not loaded: {src}" for src in broken]
        math = page.evaluate("""() => {
            const main = document.querySelector('main') || document.body;
            const typeset = document.querySelectorAll('mjx-container').length;
            const raw = [...main.querySelectorAll('.math, span.math, div.math')]
                .filter(e => !e.querySelector('mjx-container')).length;
            const text = main.innerText;
            return {typeset, raw, dollars: text.includes('$$'), paren: text.includes('\\\\(')};
        }""")
        if math["raw"]:
            problems.append(f"{math['raw']} formula(s) left untypeset by MathJax")
        if math["dollars"] or math["paren"]:
            problems.append("raw TeX delimiters ($$ or \\() left in the page text")
        problems += [f"console error: {e}" for e in p.errors]
        problems += [f"request leaving 127.0.0.1: {u}" for u in p.outside]
    finally:
        p.close()
    return [f"{name}: {x}" for x in problems]


def test_every_page_is_clean_offline(browser, site_url: str) -> None:
    problems = []
    for name in toc_files() + ["genindex"]:
        problems += _check_page(browser, f"{site_url}/{name}.html", name)
    assert not problems, "\n".join(problems)


def test_pages_with_mathematics_are_typeset(browser, site_url: str) -> None:
    p = _Page(browser, f"{site_url}/notebooks/02-kalman-filter-from-scratch.html")
    try:
        _wait_for_mathjax(p.page)
        assert p.page.locator("mjx-container").count() > 10
    finally:
        p.close()


def test_search_finds_joseph(browser, site_url: str) -> None:
    p = _Page(browser, f"{site_url}/search.html?q=Joseph")
    try:
        p.page.wait_for_selector("#search-results ul.search li", timeout=30_000)
        hits = p.page.locator("#search-results ul.search li").count()
        assert hits > 0
        assert not p.outside and not p.errors, (p.outside, p.errors)
    finally:
        p.close()


def test_solution_is_hidden_until_its_toggle_is_clicked(browser, site_url: str) -> None:
    p = _Page(browser, f"{site_url}/notebooks/02-kalman-filter-from-scratch.html")
    try:
        solution = p.page.locator("div.solution.dropdown").first
        solution.scroll_into_view_if_needed()
        body = solution.locator("> :not(.admonition-title):not(button)").first
        assert not body.is_visible(), "the solution is visible before its toggle is clicked"
        solution.locator("button.toggle-button, .admonition-title").first.click()
        body.wait_for(state="visible", timeout=5_000)
        assert body.is_visible()
    finally:
        p.close()


def test_api_reference_documents_kalman_update(browser, site_url: str) -> None:
    p = _Page(browser, f"{site_url}/book/api/kftrack.kalman.html")
    try:
        entry = p.page.locator("dt#kftrack\\.kalman\\.update")
        assert entry.count() == 1 and "update" in entry.inner_text()
    finally:
        p.close()


def test_screenshots_for_a_person(browser, site_url: str) -> None:
    if SHOTS.exists():
        shutil.rmtree(SHOTS)
    SHOTS.mkdir(parents=True)
    for name in ("book/intro", "notebooks/04-continuous-to-discrete", "book/api/kftrack.kalman"):
        p = _Page(browser, f"{site_url}/{name}.html")
        try:
            _wait_for_mathjax(p.page)
            out = SHOTS / (name.replace("/", "_") + ".png")
            p.page.screenshot(path=str(out), full_page=False)
            assert out.stat().st_size > 10_000
        finally:
            p.close()
