"""The SDKs' release step (``.ci/release-sdks``): each engine's archive holds what its engine
installs, the shared cores staged in, reproducibly; every SDK source carries its licence."""

from __future__ import annotations

import hashlib
import subprocess
import sys
import tarfile
import time
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CLIENT = ROOT / "client"
SOURCES = ("*.hpp", "*.cpp", "*.h", "*.cs", "*.gd")


def _version() -> str:
    import tomllib

    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]


@pytest.fixture(scope="module")
def release(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("release")
    p = subprocess.run([sys.executable, str(ROOT / ".ci" / "release-sdks"), "--out", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return out


def _zip_names(path: Path) -> set[str]:
    with zipfile.ZipFile(path) as z:
        return set(z.namelist())


def test_each_engine_gets_its_package(release):
    v = _version()
    assert sorted(p.name for p in release.iterdir()) == sorted([
        f"burrforce-cpp-{v}.zip", f"burrforce-unreal-{v}.zip", f"burrforce-csharp-{v}.zip",
        f"com.burrforce.haptics-{v}.tgz", f"burrforce-unity-{v}.zip",
        f"burrforce-godot-{v}.zip"])
    headers = {p.name for p in (CLIENT / "cpp" / "include" / "burrforce").glob("*.hpp")}
    cpp = _zip_names(release / f"burrforce-cpp-{v}.zip")
    assert {f"burrforce-cpp-{v}/include/burrforce/{h}" for h in headers} <= cpp
    assert f"burrforce-cpp-{v}/CMakeLists.txt" in cpp
    unreal = _zip_names(release / f"burrforce-unreal-{v}.zip")
    assert "BurrforceHaptics/BurrforceHaptics.uplugin" in unreal
    assert {f"BurrforceHaptics/Source/ThirdParty/burrforce/include/burrforce/{h}"
            for h in headers} <= unreal
    godot = _zip_names(release / f"burrforce-godot-{v}.zip")
    assert {"addons/burrforce/plugin.cfg", "addons/burrforce/README.md",
            "addons/burrforce/LICENSE"} <= godot
    assert all(n.startswith("addons/burrforce/") for n in godot)


def test_unity_package_has_the_core_and_a_meta_for_every_asset(release):
    v = _version()
    with tarfile.open(release / f"com.burrforce.haptics-{v}.tgz") as t:
        names = set(t.getnames())
    core = {p.name for p in (CLIENT / "csharp" / "Burrforce").glob("*.cs")}
    assert "package/package.json" in names
    assert {f"package/Runtime/Core/{c}" for c in core} <= names
    assets = {n for n in names if not n.endswith(".meta")
              and not any(part.endswith("~") for part in n.split("/"))}
    missing = {a for a in assets if a + ".meta" not in names}
    assert not missing, f"assets without a .meta (Unity ignores them): {sorted(missing)[:5]}"
    folders = {str(Path(n).parent) for n in assets} - {"package"}
    assert all(f + ".meta" in names for f in folders if "~" not in f)


def test_release_is_reproducible(release, tmp_path):
    time.sleep(1.1)  # another second: a timestamp left in any archive shows
    p = subprocess.run([sys.executable, str(ROOT / ".ci" / "release-sdks"), "--out",
                        str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    for a in release.iterdir():
        assert hashlib.sha256(a.read_bytes()).digest() == \
            hashlib.sha256((tmp_path / a.name).read_bytes()).digest(), a.name


def test_every_sdk_source_has_its_licence_header():
    files = [p for folder in ("cpp", "csharp", "unity", "unreal", "godot")
             for pattern in SOURCES for p in (CLIENT / folder).rglob(pattern)
             if "ThirdParty" not in p.parts and p.parent.name != "Core"]
    assert len(files) > 50
    for f in files:
        head = f.read_text().splitlines()[:4]
        assert any("SPDX-License-Identifier: MIT" in x for x in head), f
        assert any("Copyright (c) 2026 the burrforce authors" in x for x in head), f
