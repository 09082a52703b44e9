"""Installed as a user would install it: build the wheel (offline, from a copy of the source
tree), install it into a fresh target folder, and import kftrack from there, in a process whose
working directory and ``sys.path`` exclude the source tree and the editable install; every data
file must load."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path


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


def test_wheel_installs_with_its_data_and_loads_every_dataset(tmp_path):
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
    res = subprocess.run([sys.executable, "-S", "-c", PROBE], cwd=elsewhere, env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    installed = target / "kftrack"
    assert Path(out["file"]).resolve().parent == installed.resolve()  # the installed copy, not the source
    assert not any(str(ROOT / "src") == p or p == str(ROOT) for p in out["path"])
    assert Path(out["data_dir"]).resolve() == (installed / "data").resolve()
    assert Path(out["ardrone_path"]).resolve().is_relative_to(installed.resolve())
    # every file of the repository's data/ ships, byte for byte the same size
    repo_files = sorted(p.relative_to(ROOT / "data").as_posix() for p in (ROOT / "data").rglob("*")
                        if p.is_file() and p.name != "README.md")
    assert out["files"] == repo_files
    assert out["sizes"] == {n: (ROOT / "data" / n).stat().st_size for n in repo_files}
    assert all(n > 0 for n in out["ardrone"].values()) and min(out["gps_sizes"]) > 0
    assert (installed / "data" / "README.md").is_file()  # the provenance ships with the data
