"""The distribution maps server/, client/ and proto/ onto burrforce.{server,client,proto}."""

from __future__ import annotations

import importlib
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


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
