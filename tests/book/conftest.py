"""The built site, shared by the build test and the browser test (built once per session)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from sitepages import HTML, ROOT


@pytest.fixture(scope="session")
def built_site() -> Path:
    """Build the site with -W -n. A developer re-running only the browser checks on a site they
    have just built may set KFTRACK_SITE_BUILT=1 to skip the build (make test never does)."""
    if os.environ.get("KFTRACK_SITE_BUILT") == "1" and (HTML / "index.html").is_file():
        return HTML
    exe = Path(sys.executable).with_name("jupyter-book")
    proc = subprocess.run([str(exe), "build", str(ROOT), "-W", "-n", "--keep-going"],
                          capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        reports = "\n".join(p.read_text() for p in (HTML / "reports").rglob("*.log")) if (HTML / "reports").exists() else ""
        pytest.fail(f"jupyter-book build failed (exit {proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}\n{reports}")
    return HTML


