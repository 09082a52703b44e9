"""The course apparatus stays complete as the book grows: an API page for every public module,
the dependency figure's chapter list equal to the table of contents, licence and citation."""
from __future__ import annotations

import importlib.util
import pkgutil

import yaml

import kftrack
from sitepages import ROOT, toc_files


def _public_modules() -> list[str]:
    names = [m.name for m in pkgutil.walk_packages(kftrack.__path__, "kftrack.")]
    return sorted(n for n in names if not any(part.startswith("_") for part in n.split("."))
                  and not importlib.util.find_spec(n).submodule_search_locations)  # modules, not packages


def test_every_public_module_has_an_api_page_in_the_toc() -> None:
    pages = set(toc_files())
    missing = [m for m in _public_modules() if f"book/api/{m}" not in pages]
    assert not missing, f"add book/api/<module>.md and a _toc.yml entry for: {missing}"
    for m in _public_modules():
        text = (ROOT / "book" / "api" / f"{m}.md").read_text()
        assert f".. automodule:: {m}" in text and ":members:" in text, m
    index = (ROOT / "book" / "api" / "index.md").read_text()
    unlisted = [m for m in _public_modules() if f"{{doc}}`{m}`" not in index]
    assert not unlisted, f"list these modules in a layer of book/api/index.md: {unlisted}"


def test_dependency_figure_lists_exactly_the_chapters() -> None:
    spec = importlib.util.spec_from_file_location("deps", ROOT / "book" / "figures" / "chapter_dependencies.py")
    deps = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(deps)
    chapters = [f for f in toc_files() if f.startswith("notebooks/")]
    assert sorted(f"notebooks/{stem}" for _, stem, _ in deps.CHAPTERS.values()) == sorted(chapters)
    for k, (_, stem, before) in deps.CHAPTERS.items():
        assert stem.startswith(f"{k:02d}-") and all(b < k for b in before), (k, stem, before)
    assert (ROOT / "book" / "figures" / "chapter-dependencies.png").stat().st_size > 10_000


def test_licence_and_citation() -> None:
    licence = (ROOT / "LICENSE").read_text()
    assert "MIT License" in licence and "CC BY 4.0" in licence
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0" and cff["license"] == "MIT"
    assert cff["preferred-citation"]["license"] == "CC-BY-4.0"
    intro = (ROOT / "book" / "intro.md").read_text()
    assert "CC BY 4.0" in intro and "MIT" in intro
