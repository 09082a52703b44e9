"""Installed as a user would install it: build the wheel (offline, from a copy of the source
tree), install it into a fresh target folder, and import kftrack from there, in a process whose
working directory and ``sys.path`` exclude the source tree and the editable install; every data
file must load, the version of the wheel is ``kftrack.__version__``, and the README's first
example runs there and prints what the README says it prints."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Runs in the installed copy (python -S: no site, so no .pth file puts the editable source on the path).
PROBE = r"""
import json, sys
from pathlib import Path
import kftrack
from kftrack import datasets, gpstrack
from kftrack.sensors import ardrone

out = {"file": kftrack.__file__, "data_dir": str(datasets.data_dir()), "files": datasets.data_files(),
       "path": sys.path}
from importlib import metadata
out["version"] = {"attribute": kftrack.__version__, "metadata": metadata.version("kftrack")}
out["lazy"] = kftrack.kalman.__name__ + " " + kftrack.sensors.radar.__name__
out["ardrone"] = {e: len(ardrone.load_log(e).t) for e in ardrone.EXPERIMENTS}
out["ardrone_path"] = str(datasets.data_path(ardrone.log_filename("A")))
runs, report = gpstrack.load_track_logs()
out["gps_sizes"] = [int(v) for v in __import__("numpy").shape(runs.inner)]
out["sizes"] = {name: datasets.data_path(name).stat().st_size for name in datasets.data_files()}
print(json.dumps(out))
"""


def _site_dirs() -> list[str]:
    """The interpreter's own site-packages (numpy, scipy, ...), without their .pth files."""
    return sorted({sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]})


def _source_version() -> str:
    """``__version__`` as written in the source tree's ``src/kftrack/__init__.py``."""
    text = (ROOT / "src" / "kftrack" / "__init__.py").read_text(encoding="utf-8")
    return re.search(r'^__version__ = "([^"]+)"', text, re.M).group(1)


def readme_example(text: str) -> tuple[str, str]:
    """The README's first example (the ``python`` block after the marker ``README-EXAMPLE``) and
    the output it states (the ``text`` block after ``README-EXAMPLE-OUTPUT``)."""
    code = re.search(r"<!-- README-EXAMPLE:[^>]*-->\n```python\n(.*?)```", text, re.S)
    output = re.search(r"<!-- README-EXAMPLE-OUTPUT -->\n```text\n(.*?)```", text, re.S)
    assert code and output, "README.md must hold the marked example and its output"
    return code.group(1), output.group(1)


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """Build the wheel from a copy of the source, install it into a target folder; returns
    ``(wheel, target, elsewhere, env)`` with ``env`` putting only the target and the
    interpreter's site-packages on the path (run with ``python -S``), ``elsewhere`` an empty
    working directory."""
    tmp_path = tmp_path_factory.mktemp("install")
    src = tmp_path / "src-copy"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    shutil.copytree(ROOT / "src", src / "src", ignore=shutil.ignore_patterns("*.egg-info", "__pycache__"))
    shutil.copytree(ROOT / "data", src / "data")
    wheels, target, elsewhere = tmp_path / "wheels", tmp_path / "site", tmp_path / "elsewhere"
    elsewhere.mkdir()
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    env = {k: v for k, v in os.environ.items() if k not in ("KFTRACK_DATA", "PYTHONPATH")}
    subprocess.run(pip + ["wheel", str(src), "--no-deps", "--no-build-isolation", "--no-index", "-w", str(wheels)],
                   check=True, cwd=tmp_path, env=env, capture_output=True)
    (wheel,) = wheels.glob("kftrack-*.whl")
    subprocess.run(pip + ["install", "--no-deps", "--no-index", "--target", str(target), str(wheel)],
                   check=True, cwd=tmp_path, env=env, capture_output=True)
    env["PYTHONPATH"] = os.pathsep.join([str(target)] + _site_dirs())
    return wheel, target, elsewhere, env


def test_wheel_installs_with_its_data_and_loads_every_dataset(installed):
    wheel, target, elsewhere, env = installed
    res = subprocess.run([sys.executable, "-S", "-c", PROBE], cwd=elsewhere, env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    pkg_dir = target / "kftrack"
    assert Path(out["file"]).resolve().parent == pkg_dir.resolve()  # the installed copy, not the source
    assert not any(str(ROOT / "src") == p or p == str(ROOT) for p in out["path"])
    assert Path(out["data_dir"]).resolve() == (pkg_dir / "data").resolve()
    assert Path(out["ardrone_path"]).resolve().is_relative_to(pkg_dir.resolve())
    # every file of the repository's data/ ships, byte for byte the same size
    repo_files = sorted(p.relative_to(ROOT / "data").as_posix() for p in (ROOT / "data").rglob("*")
                        if p.is_file() and p.name != "README.md")
    assert out["files"] == repo_files
    assert out["sizes"] == {n: (ROOT / "data" / n).stat().st_size for n in repo_files}
    assert all(n > 0 for n in out["ardrone"].values()) and min(out["gps_sizes"]) > 0
    assert (pkg_dir / "data" / "README.md").is_file()  # the provenance ships with the data
    # one version: the wheel's name and metadata are the source's kftrack.__version__
    version = _source_version()
    assert wheel.name.startswith(f"kftrack-{version}-")
    assert out["version"] == {"attribute": version, "metadata": version}
    assert out["lazy"] == "kftrack.kalman kftrack.sensors.radar"  # modules as attributes (PEP 562)


def test_readme_example_runs_in_the_installed_copy(installed):
    _, target, elsewhere, env = installed
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    # every Python block of the README is this one example
    assert len(re.findall(r"^```python$", text, re.M)) == 1
    code, expected = readme_example(text)
    script = elsewhere / "readme_example.py"
    script.write_text(code, encoding="utf-8")
    res = subprocess.run([sys.executable, "-S", str(script)], cwd=elsewhere, env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "from kftrack" in code and "kalman_filter" in code and "imm_smoother" in code
    # the printed RMSEs are rounded to 0.1 m; unrounded they are 4.133, 2.016, 4.012, 2.658 m, each at
    # least 0.008 m from a rounding boundary: a thousand times the largest round-off difference across
    # OpenBLAS kernels that the package allows anywhere (1e-8 relative, on positions below 1 km: 1e-5 m)
    assert res.stdout == expected


# An Examples section that reads the package's data (a loader, a data path, the cached baselines):
# these are the doctests whose result can differ between the source tree and an installed wheel.
_READS_DATA = re.compile(r">>>.*(load_|data_path|data_files|read_cache|TRAINING_FLIGHTS)")


def test_doctests_pass_in_the_installed_copy(installed):
    """The Examples sections that read package data run against the wheel's copy, from another
    directory (every doctest also runs in the source tree in ``make unit``; the data scripts under
    kftrack/data are regeneration tools, not package modules)."""
    _, target, elsewhere, env = installed
    pkg = target / "kftrack"
    modules = sorted(str(f) for f in pkg.rglob("*.py")
                     if pkg / "data" not in f.parents and _READS_DATA.search(f.read_text(encoding="utf-8")))
    names = {Path(m).name for m in modules}
    assert {"datasets.py", "adsb.py", "gpstrack.py", "ardrone.py"} <= names, names
    res = subprocess.run([sys.executable, "-S", "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir",
                          str(elsewhere), "-o", "doctest_optionflags=NORMALIZE_WHITESPACE", "--doctest-modules",
                          *modules], cwd=elsewhere, env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    passed = int(re.search(r"(\d+) passed", res.stdout).group(1))
    assert passed >= len(modules) and "failed" not in res.stdout  # each module's Examples ran, not an empty run
