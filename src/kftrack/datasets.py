"""Locate the book's data files, independently of the working directory.

The files live in the repository's ``data/`` folder (their provenance is in
``data/README.md``). Set ``KFTRACK_DATA`` to use another folder.
"""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["data_dir", "data_path"]


def data_dir() -> Path:
    """The data folder: ``$KFTRACK_DATA`` if set, else ``<repository>/data``."""
    env = os.environ.get("KFTRACK_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "data"


def data_path(name: str) -> Path:
    """Path of the data file ``name`` inside :func:`data_dir`; raises if it is missing."""
    path = data_dir() / name
    if not path.exists():
        raise FileNotFoundError(f"data file {name!r} not found in {data_dir()} (see data/README.md)")
    return path
