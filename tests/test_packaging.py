"""The distribution maps server/, client/ and proto/ onto burrforce.{server,client,proto}, and
holds no test harness."""

from __future__ import annotations

import importlib
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

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
