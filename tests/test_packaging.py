"""The distribution maps server/, client/ and proto/ onto burrforce.{server,client,proto}
(pyproject.toml alone, no setup.py), ships the live view's vendored files with their licences
and the protocol's documents, and holds no test harness."""

from __future__ import annotations

import importlib
import json
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]

#: What only the tests and the project's own measurements use: never in the wheel. The USB
#: emulation, the podman, container and Chromium harnesses, the browser part of the latency
#: page, the callgrind and GIL probes (where they were before they left the package, and where
#: they are now), and the checkout's own packages.
FORBIDDEN = ("burrforce/server/devices/emulation/", "burrforce/server/bench/podman.py",
             "burrforce/server/bench/container.py", "burrforce/server/bench/chromium.py",
             "burrforce/server/bench/latency_page.py", "burrforce/server/bench/tick_profile.py",
             "burrforce/server/bench/gil_probe.py", "support/", "benchmarks/", "tests/")
#: An import of the checkout's harness from the package would fail in an install.
HARNESS_IMPORT = re.compile(r"^\s*(from|import)\s+(support|benchmarks|tests)\b", re.M)


@pytest.mark.parametrize("name", ["burrforce.server", "burrforce.client", "burrforce.proto",
                                  "burrforce.server.model", "burrforce.server.bench"])
def test_namespace_imports(name):
    importlib.import_module(name)


def test_non_editable_wheel_has_the_namespace_layout(tmp_path):
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps",
                    "-q", "-w", str(tmp_path), str(ROOT)], check=True, capture_output=True)
    wheel = next(tmp_path.glob("burrforce-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    for expected in ("burrforce/server/__init__.py", "burrforce/server/model/kernels.py",
                     "burrforce/server/cli/__init__.py", "burrforce/client/__init__.py",
                     "burrforce/proto/__init__.py"):
        assert expected in names
    assert not any(n.startswith(("server/", "client/", "proto/", "tests/")) for n in names)
    # No test harness, no emulation (by path, and by what the shipped modules import).
    harness = sorted(n for n in names if n.startswith(FORBIDDEN) or "/emulation/" in n)
    assert harness == []
    with zipfile.ZipFile(wheel) as archive:
        importing = sorted(n for n in names if n.endswith(".py")
                           and HARNESS_IMPORT.search(archive.read(n).decode()))
    assert importing == []
    assert "burrforce/server/bench/runner.py" in names  # the user's benches stay
    # The files the packages read at run time: the live view (page, lock, the vendored
    # three.js and uPlot with their licences) and the protocol's documents and vectors.
    ui = "burrforce/server/ui/"
    lock = json.loads((ROOT / "server" / "ui" / "vendor.lock.json").read_text())
    vendored = {f"{ui}vendor/{e['to']}" for pkg in lock["packages"] for e in pkg["files"]}
    assert {f"{ui}vendor/three/LICENSE", f"{ui}vendor/uplot/LICENSE"} <= vendored
    assert vendored | {f"{ui}vendor/README.md", f"{ui}vendor.lock.json", f"{ui}index.html",
                       f"{ui}static/app.js", f"{ui}static/style.css"} <= names
    assert sorted(n for n in names if n.startswith(f"{ui}vendor/")) \
        == sorted(vendored | {f"{ui}vendor/README.md"})
    assert {"burrforce/proto/SPEC.md", "burrforce/proto/MESH.md",
            "burrforce/proto/vectors/vectors.json"} <= names
    # Installed on its own (dependencies from this environment), it imports and runs.
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target",
                    str(target), str(wheel)], check=True, capture_output=True)
    code = ("import burrforce.server.model as m, burrforce.client, burrforce.proto;"
            f"assert str(m.__file__).startswith({str(target)!r});"
            "print(m.CuttingModel().evaluate((0,0,1.5),(0,0,1),(3,0,0),60000).force_N)")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, env={"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr


def test_pyproject_names_every_package_and_no_setup_py():
    """setuptools cannot find packages under a prefix, so pyproject lists them: the list must
    be exactly the folders of server/, client/ and proto/ that hold an __init__.py."""
    assert not (ROOT / "setup.py").exists()
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert config["package-dir"] == {f"burrforce.{top}": top
                                     for top in ("server", "client", "proto")}
    found = {"burrforce." + init.parent.relative_to(ROOT).as_posix().replace("/", ".")
             for top in ("server", "client", "proto")
             for init in (ROOT / top).rglob("__init__.py")
             if "__pycache__" not in init.parts}
    assert sorted(config["packages"]) == sorted(found)
