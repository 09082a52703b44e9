"""Locate the book's data files, wherever the package is installed and whatever the working
directory.

The files live in the repository's ``data/`` folder (their provenance is in
``data/README.md``); a wheel built from the repository (``pip install .``) ships a copy of
them inside the package as ``kftrack/data``. :func:`data_dir` looks, in order, in

1. ``$KFTRACK_DATA``, if set (an explicit choice of folder always wins);
2. ``kftrack/data`` next to this module (an installed wheel);
3. ``<repository>/data`` (a source checkout or an editable install).
"""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["data_dir", "data_path", "data_files", "load_script"]

_PACKAGE_DATA = Path(__file__).resolve().parent / "data"
_SOURCE_DATA = Path(__file__).resolve().parents[2] / "data"


def data_dir() -> Path:
    """The data folder: ``$KFTRACK_DATA`` if set, else the installed package's ``kftrack/data``,
    else the source tree's ``<repository>/data``. Raises ``FileNotFoundError`` (naming the
    places looked in) if none exists."""
    env = os.environ.get("KFTRACK_DATA")
    if env:
        return Path(env)
    for folder in (_PACKAGE_DATA, _SOURCE_DATA):
        if folder.is_dir():
            return folder
    raise FileNotFoundError(f"no kftrack data folder: looked in $KFTRACK_DATA (unset), {_PACKAGE_DATA} "
                            f"(installed package) and {_SOURCE_DATA} (source tree); set KFTRACK_DATA")


def data_path(name: str) -> Path:
    """Path of the data file ``name`` inside :func:`data_dir`; raises if it is missing.

    Examples
    --------
    >>> from kftrack.datasets import data_files, data_path
    >>> data_path("adsb/calibration/toulouse.csv.gz").name   # wherever the package is installed
    'toulouse.csv.gz'
    >>> "gps_track" in {name.split("/")[0] for name in data_files()}
    True
    """
    folder = data_dir()
    path = folder / name
    if not path.exists():
        raise FileNotFoundError(f"data file {name!r} not found in {folder} (see data/README.md)")
    return path


def data_files() -> list[str]:
    """Names (relative paths, ``/``-separated) of every data file in :func:`data_dir`, sorted;
    ``README.md`` (the provenance) excluded."""
    folder = data_dir()
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                  if p.is_file() and p.name != "README.md" and "__pycache__" not in p.parts)


def load_script(name: str):
    """A regeneration script shipped under ``data/`` (e.g. ``"adsb/baseline.py"``), imported as a
    module without writing bytecode into the data folder."""
    import importlib.util
    import sys

    path = data_path(name)
    spec = importlib.util.spec_from_file_location(Path(name).stem, path)
    mod = importlib.util.module_from_spec(spec)
    old, sys.dont_write_bytecode = sys.dont_write_bytecode, True  # no __pycache__ inside data/
    try:
        spec.loader.exec_module(mod)
    finally:
        sys.dont_write_bytecode = old
    return mod
