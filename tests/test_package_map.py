"""The map of the package: ``kftrack.<module>`` works after ``import kftrack`` (PEP 562, imported
on first use), the package docstring names every module by layer, importing a module pulls in
JAX, SymPy or matplotlib only where the docstring says so, the package runs without JAX, and the
version has one source.

The import checks run in fresh interpreters (subprocesses): this test process has imported
matplotlib (conftest) and much of kftrack already.
"""
from __future__ import annotations

import importlib
import inspect
import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

import kftrack
from test_imports import import_graph

ROOT = Path(__file__).resolve().parents[1]
PKG = Path(kftrack.__file__).resolve().parent
LAYERS = ("Numerics", "Models", "Worlds", "Presentation")


def _module_files() -> set[str]:
    """Dotted names of every module file under src/kftrack (packages by their __init__.py)."""
    out = set()
    for path in PKG.rglob("*.py"):
        parts = path.relative_to(PKG).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out.add(".".join(("kftrack",) + parts))
    return out


def _docstring_layers() -> dict[str, str]:
    """``{module: layer}`` from the bullet lines ``- :mod:`kftrack.x` -- ...`` under each layer
    heading of the package docstring."""
    layers, layer = {}, None
    for line in kftrack.__doc__.splitlines():
        head = re.match(r"(\w+): ", line)
        if head and head.group(1) in LAYERS:
            layer = head.group(1)
        bullet = re.match(r"- (?::mod:`|``)(kftrack[\w.]*)(?:`|``) -- \S", line)
        if bullet:
            assert layer is not None, f"module listed before any layer heading: {line}"
            assert bullet.group(1) not in layers, f"module listed twice: {bullet.group(1)}"
            layers[bullet.group(1)] = layer
    return layers


def _run(code: str) -> str:
    """Run ``code`` in a fresh interpreter (working directory: the repository); its stdout."""
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    return res.stdout


def test_docstring_lists_every_module_by_layer():
    layers = _docstring_layers()
    files = _module_files()
    private = {m for m in files if m.rpartition(".")[2].startswith("_")}
    assert private == {"kftrack._validate"}
    # every module file is listed in one layer, and every listed name is a module file
    assert set(layers) == files - private - {"kftrack"}
    assert set(layers.values()) == set(LAYERS)
    assert "kftrack._validate" in kftrack.__doc__  # the private module is named too, outside the layers
    # every name the docstring mentions anywhere exists: a module, or an attribute of one
    for name in set(re.findall(r"kftrack(?:\.\w+)+", kftrack.__doc__)):
        parts = name.split(".")
        k = max(i for i in range(1, len(parts) + 1) if ".".join(parts[:i]) in files)
        assert k >= 2, f"the package docstring names {name}, which is no module of kftrack"
        obj = importlib.import_module(".".join(parts[:k]))
        for attr in parts[k:]:
            assert hasattr(obj, attr), f"the package docstring names {name}, which does not exist"
            obj = getattr(obj, attr)


def test_layers_import_only_downwards():
    # "A module imports only from its own layer and the layers below it, with one exception:
    # sensors.ardrone finds its log files with datasets"; _validate sits below them all.
    layers = _docstring_layers()
    rank = {m: LAYERS.index(layer) for m, layer in layers.items()}
    rank["kftrack._validate"] = -1
    graph = import_graph(PKG)
    up = sorted((m, d) for m, deps in graph.items() if m in rank for d in deps
                if d in rank and rank[d] > rank[m])
    assert up == [("kftrack.sensors.ardrone", "kftrack.datasets")]
    assert graph["kftrack._validate"] == set()


def test_every_module_is_an_attribute_of_its_package():
    files = sorted(_module_files() - {"kftrack", "kftrack._validate"})
    top = {m.split(".")[1] for m in files}
    assert set(kftrack.__all__) == top
    assert set(kftrack.sensors.__all__) == {m.split(".")[2] for m in files if m.startswith("kftrack.sensors.")}
    assert top <= set(dir(kftrack)) and set(kftrack.sensors.__all__) <= set(dir(kftrack.sensors))
    # in a fresh interpreter: only `import kftrack`, then attribute access down to every module
    out = json.loads(_run(
        "import json, kftrack\n"
        f"names = {files!r}\n"
        "got = {}\n"
        "for name in names:\n"
        "    obj = kftrack\n"
        "    for part in name.split('.')[1:]:\n"
        "        obj = getattr(obj, part)\n"
        "    got[name] = obj.__name__\n"
        "try:\n"
        "    kftrack.no_such_module\n"
        "    got['missing'] = 'no error'\n"
        "except AttributeError as e:\n"
        "    got['missing'] = str(e)\n"
        "print(json.dumps(got))\n"))
    assert out.pop("missing") == "module 'kftrack' has no attribute 'no_such_module'"
    assert out == {m: m for m in files}


def test_import_kftrack_is_lazy():
    out = json.loads(_run(
        "import json, sys\n"
        "heavy = ('jax', 'sympy', 'matplotlib')\n"
        "import kftrack\n"
        "after_import = sorted(m for m in sys.modules if m.startswith('kftrack.') or m in heavy)\n"
        "kftrack.kalman, kftrack.imm, kftrack.ekf, kftrack.ukf, kftrack.metrics, kftrack.sensors.gps\n"
        "print(json.dumps({'after_import': after_import,\n"
        "                  'after_use': sorted(m for m in heavy if m in sys.modules),\n"
        "                  'kalman': 'kftrack.kalman' in sys.modules}))\n"))
    assert out == {"after_import": [], "after_use": [], "kalman": True}


# Which modules need SymPy, JAX or matplotlib to be imported: in one fresh interpreter, each
# package is blocked in turn by a meta path finder, kftrack is dropped from sys.modules and every
# module imported anew; a module that needs the blocked package fails with its ImportError.
_BLOCKED_IMPORTS = r"""
import importlib, json, sys
files = {files!r}

class Block:
    def __init__(self, top):
        self.top = top
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == self.top:
            raise ImportError(f"{{name}} blocked", name=name)

out = {{}}
for top in ("sympy", "jax", "matplotlib"):
    assert top not in sys.modules
    finder = Block(top)
    sys.meta_path.insert(0, finder)
    needs = []
    for name in files:
        for loaded in [m for m in sys.modules if m == "kftrack" or m.startswith("kftrack.")]:
            del sys.modules[loaded]
        try:
            importlib.import_module(name)
        except ImportError as e:
            assert e.name.split(".")[0] == top, e
            needs.append(name)
    sys.meta_path.remove(finder)
    out[top] = needs
print(json.dumps(out))
"""


def test_which_modules_import_sympy_jax_matplotlib():
    files = sorted(_module_files())
    out = json.loads(_run(_BLOCKED_IMPORTS.format(files=files)))
    # the docstring's claim: "SymPy comes with <modules> and the modules that import them (<modules>)"
    claim = re.search(r"SymPy comes with (.*?); matplotlib", kftrack.__doc__, re.S).group(1)
    claimed = {"kftrack." + m for m in re.findall(r":mod:`~kftrack\.([\w.]+)`", claim)}
    assert claimed == {"kftrack.symbolic", "kftrack.models", "kftrack.frenet", "kftrack.slam",
                       "kftrack.sensors.radar", "kftrack.scenarios", "kftrack.multitarget"}
    assert set(out["sympy"]) == claimed
    assert out["jax"] == [] and out["matplotlib"] == []


# Without JAX installed (a meta path finder makes `import jax` and `import jaxlib` fail, as on a
# machine without the [jax] extra), the NumPy filters and smoothers run and give the same bits as
# in this process (same code, same arrays, same machine: the NumPy engine is deterministic).
_NO_JAX = r"""
import json, sys
class NoJax:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("jax", "jaxlib"):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, NoJax())
try:
    import jax
    raise SystemExit("jax imported although blocked")
except ModuleNotFoundError:
    pass
sys.path.insert(0, "tests")
from test_package_map import _example_run
print(json.dumps({k: v.tolist() for k, v in _example_run().items()}))
"""


def _example_run() -> dict[str, np.ndarray]:
    """Kalman filter + RTS smoother and IMM filter + smoother on a small 1-D sequence with a
    missing row and irregular intervals."""
    from kftrack import imm, kalman, models

    zs = np.array([[0.0], [1.1], [np.nan], [2.9], [4.2], [6.0], [8.5]])
    dt = np.array([1.0, 0.5, 1.5, 1.0, 1.0, 1.0, 1.0])
    cv, agile = models.ConstantVelocity(ndim=1, q=1.0), models.ConstantVelocity(ndim=1, q=20.0)
    R, x0, P0 = np.eye(1), np.zeros(2), 10.0 * np.eye(2)
    f = kalman.kalman_filter(zs, x0, P0, cv.F, cv.Q, cv.H, R, dt=dt)
    s = kalman.rts_smoother(f, cv.F, dt=dt)
    bank = imm.IMM([imm.KalmanMode(cv, R), imm.KalmanMode(agile, R)], [[0.9, 0.1], [0.1, 0.9]], [0.5, 0.5])
    fi = imm.imm_filter(bank, zs, x0, P0, dt)
    si = imm.imm_smoother(bank, fi, dt)
    return {"kf": f.x, "rts": s.x, "imm": fi.x, "imm_mu": fi.mu, "imm_smooth": si.x}


def test_package_runs_without_jax():
    out = {k: np.array(v) for k, v in json.loads(_run(_NO_JAX)).items()}
    here = _example_run()
    assert out.keys() == here.keys()
    for k in here:
        assert np.all(np.isfinite(here[k]))
        np.testing.assert_array_equal(out[k], here[k], err_msg=k)


def test_version_has_one_source():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    assert "version" not in meta["project"] and "version" in meta["project"]["dynamic"]
    assert meta["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "kftrack.__version__"}
    assert re.fullmatch(r"\d+\.\d+\.\d+", kftrack.__version__)
    # the newest release in the changelog is this version (the wheel's metadata: test_install.py)
    releases = re.findall(r"^## \[(\d+\.\d+\.\d+)\]", (ROOT / "CHANGELOG.md").read_text(encoding="utf-8"), re.M)
    assert releases and releases[0] == kftrack.__version__


def test_readme_map_agrees_with_the_docstring():
    # the README's table "layer | modules" lists the same modules per layer as the docstring
    # (the package kftrack.sensors itself is a folder there, its modules are listed)
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    rows = re.findall(r"^\| (numerics|models|worlds|presentation) \| (.*) \|$", text, re.M)
    readme = {"kftrack." + m: layer.capitalize() for layer, mods in rows for m in re.findall(r"`([\w.]+)`", mods)}
    doc = {m: layer for m, layer in _docstring_layers().items() if m != "kftrack.sensors"}
    assert readme == doc


# The main public functions carry a runnable example (their doctests run with
# ``--doctest-modules src/kftrack``, part of ``make unit``): every filter and smoother, model,
# loader and metric named here has an Examples section with at least one ``>>>`` line.
MAIN_OBJECTS = {
    "kalman": ("predict", "update", "kalman_filter", "rts_smoother", "KalmanStepper"),
    "ekf": ("extended_kalman_filter",),
    "ukf": ("unscented_transform", "unscented_kalman_filter"),
    "imm": ("imm_filter", "imm_smoother"),
    "particle": ("bootstrap_filter",),
    "models": ("ConstantVelocity", "ConstantAcceleration", "Singer", "KnownTurn", "CoordinatedTurn",
               "CoordinatedTurnPolar", "Turn3D"),
    "metrics": ("rmse", "nees", "nis", "anees", "chi2_bounds"),
    "association": ("gnn_assignment", "pdaf_update", "gospa"),
    "adsb": ("load_flight",),
    "sensors.gps": ("parse_sentence", "read_nmea_log"),
    "sensors.ardrone": ("load_log",),
    "gpstrack": ("load_track_logs",),
    "datasets": ("data_path",),
    "steady": ("discrete_gain", "continuous_gain", "alpha_beta_gains"),
    "frenet": ("simulate", "curvature_torsion"),
    "scenarios": ("car_radar", "drone_scenario"),
    "slam": ("ekf_slam",),
    "gpsfusion": ("speed_heading_filter",),
    "tuning": ("fit_noise",),
    "sensors.radar": ("RangeBearing",),
}


@pytest.mark.parametrize("module, name", [(m, n) for m, names in MAIN_OBJECTS.items() for n in names])
def test_main_public_objects_have_examples(module, name):
    obj = getattr(importlib.import_module("kftrack." + module), name)
    doc = inspect.getdoc(obj) or ""
    section = re.search(r"^Examples\n-{8}\n(.*)", doc, re.M | re.S)
    assert section and ">>> " in section.group(1), f"kftrack.{module}.{name} has no Examples section"
