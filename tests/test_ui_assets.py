"""The live view's third-party files: committed, locked, verified, shipped; refreshed from npm.

The fetches here go to a registry served on 127.0.0.1 (``BURRFORCE_NPM_REGISTRY``), never to
npm's; the wheel build makes none (the files are in the source tree).
"""

from __future__ import annotations

import base64
import hashlib
import http.server
import io
import json
import re
import subprocess
import sys
import tarfile
import threading
import zipfile
from importlib.resources import files
from pathlib import Path, PurePosixPath

import pytest
from hypothesis import given
from hypothesis import strategies as st

from burrforce.server import ui
from burrforce.server.ui import vendor

ROOT = Path(__file__).resolve().parents[1]


def _sri(data: bytes) -> str:
    return "sha512-" + base64.b64encode(hashlib.sha512(data).digest()).decode()


def _tarball(members: dict[str, bytes], links: dict[str, str] | None = None) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
        for name, target in (links or {}).items():
            info = tarfile.TarInfo(name)
            info.type = tarfile.SYMTYPE
            info.linkname = target
            tar.addfile(info)
    return buf.getvalue()


SCRIPT = b"export const answer = 42;\n"
LICENSE = b"MIT License\n"
GOOD = _tarball({"package/dist/fake.js": SCRIPT, "package/LICENSE": LICENSE})


def _lock(path: Path, tarball: bytes, files_: list[dict] | None = None) -> Path:
    files_ = files_ if files_ is not None else [
        {"from": "package/dist/fake.js", "to": "fake/fake.js",
         "sha256": hashlib.sha256(SCRIPT).hexdigest()},
        {"from": "package/LICENSE", "to": "fake/LICENSE",
         "sha256": hashlib.sha256(LICENSE).hexdigest()},
    ]
    path.write_text(json.dumps({"packages": [{
        "name": "fake", "version": "1.0.0", "license": "MIT",
        "tarball": "https://registry.npmjs.org/fake/-/fake-1.0.0.tgz",
        "integrity": _sri(tarball), "files": files_}]}))
    return path


class _Registry:
    """An npm-layout registry on loopback: ``routes`` maps a path to the bytes it serves."""

    def __init__(self):
        self.routes: dict[str, bytes] = {}
        self.requests: list[str] = []
        registry = self

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self):
                registry.requests.append(self.path)
                body = registry.routes.get(self.path)
                self.send_response(200 if body is not None else 404)
                self.send_header("Content-Length", str(len(body or b"")))
                self.end_headers()
                self.wfile.write(body or b"")

            def log_message(self, *args):
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, args=(0.05,),
                                       daemon=True)
        self.thread.start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def registry(monkeypatch):
    r = _Registry()
    monkeypatch.setenv(vendor.REGISTRY_ENV, r.url)
    yield r
    r.close()


def _tree(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")) \
        if folder.exists() else []


# --- the real lock and the installed files --------------------------------------------------

def test_lock_is_well_formed():
    packages = vendor.load_lock()
    assert {p["name"] for p in packages} == {"three", "uplot"}
    for pkg in packages:
        name, version = pkg["name"], pkg["version"]
        assert re.fullmatch(r"\d+\.\d+\.\d+", version), "pin a stable release"
        assert pkg["tarball"] == f"https://registry.npmjs.org/{name}/-/{name}-{version}.tgz"
        assert len(base64.b64decode(pkg["integrity"].removeprefix("sha512-"))) == 64
        assert pkg["license"] == "MIT"
        targets = [PurePosixPath(e["to"]) for e in pkg["files"]]
        assert PurePosixPath(name, "LICENSE") in targets, "ship the license beside the files"
        assert all(t.parts[0] == name for t in targets)
        assert all(re.fullmatch(r"[0-9a-f]{64}", e["sha256"]) for e in pkg["files"])


def test_installed_package_holds_every_locked_file():
    installed = files("burrforce.server.ui") / "vendor"
    for pkg in vendor.load_lock():
        for entry in pkg["files"]:
            data = (installed / entry["to"]).read_bytes()
            assert hashlib.sha256(data).hexdigest() == entry["sha256"], entry["to"]
    assert ui.vendor_missing() == []


def test_three_module_imports_only_its_locked_siblings():
    # The page's import map covers 'three' only: every other import must be a locked file.
    three = ui.VENDOR_DIR / "three"
    module = (three / "three.module.js").read_text(encoding="utf-8")
    assert set(re.findall(r"""\bfrom\s*['"]([^'"]+)['"]""", module)) == {"./three.core.js"}
    controls = (three / "OrbitControls.js").read_text(encoding="utf-8")
    assert set(re.findall(r"""^\s*\}?\s*from\s*['"]([^'"]+)['"]""", controls, re.M)) == {"three"}


@pytest.mark.parametrize("how", ["module", "path"])
def test_check_command_passes_on_the_installed_files(how):
    cmd = ["-m", "burrforce.server.ui.vendor"] if how == "module" else \
        [str(ROOT / "server" / "ui" / "vendor.py")]
    r = subprocess.run([sys.executable, *cmd, "--check"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "RuntimeWarning" not in r.stderr


# --- fetching from a registry ----------------------------------------------------------------

def test_fetch_verifies_writes_and_then_stays_offline(registry, tmp_path):
    registry.routes["/fake/-/fake-1.0.0.tgz"] = GOOD
    lock = _lock(tmp_path / "lock.json", GOOD)
    target = tmp_path / "vendor"
    assert vendor.fetch(target, lock, log=lambda _: None) == ["fake/LICENSE", "fake/fake.js"]
    assert (target / "fake" / "fake.js").read_bytes() == SCRIPT
    assert vendor.check(target, lock) == []
    assert _tree(target) == ["fake", "fake/LICENSE", "fake/fake.js"]  # no temporary files left
    # Everything already matches: no request at all, so a rebuild works offline.
    registry.requests.clear()
    assert vendor.fetch(target, lock, log=lambda _: None) == []
    assert registry.requests == []
    # One file edited: fetched again.
    (target / "fake" / "fake.js").write_bytes(b"tampered")
    assert vendor.fetch(target, lock, log=lambda _: None) == ["fake/fake.js"]
    assert vendor.check(target, lock) == []


def test_relock_records_a_new_release_after_checking_its_integrity(registry, tmp_path):
    # The maintainer's refresh: the lock names a new tarball and its integrity, the files'
    # sha256 are still the old release's; relock writes the files and records theirs.
    release = _tarball({"package/dist/fake.js": b"export const answer = 43;\n",
                        "package/LICENSE": LICENSE})
    registry.routes["/fake/-/fake-1.0.0.tgz"] = release
    lock = _lock(tmp_path / "lock.json", release)
    target = tmp_path / "vendor"
    with pytest.raises(vendor.VendorError, match="sha256"):
        vendor.fetch(target, lock, log=lambda _: None)
    assert vendor.relock(target, lock, log=lambda _: None) == ["fake/fake.js"]
    assert vendor.check(target, lock) == []
    assert (target / "fake" / "fake.js").read_bytes() == b"export const answer = 43;\n"
    # The registry's integrity stays the anchor: a tarball that differs from it writes nothing.
    registry.routes["/fake/-/fake-1.0.0.tgz"] = GOOD
    with pytest.raises(vendor.VendorError, match="integrity"):
        vendor.relock(tmp_path / "other", lock, log=lambda _: None)
    assert _tree(tmp_path / "other") == []


def test_tampered_tarball_is_refused_and_nothing_written(registry, tmp_path):
    registry.routes["/fake/-/fake-1.0.0.tgz"] = _tarball(
        {"package/dist/fake.js": b"alert('owned')", "package/LICENSE": LICENSE})
    lock = _lock(tmp_path / "lock.json", GOOD)
    target = tmp_path / "vendor"
    with pytest.raises(vendor.VendorError, match="does not match the lock's integrity"):
        vendor.fetch(target, lock, log=lambda _: None)
    assert _tree(target) == []
    assert vendor.main(["--target", str(target), "--lock", str(lock)]) == 1


def test_file_differing_from_its_sha256_is_refused(registry, tmp_path):
    registry.routes["/fake/-/fake-1.0.0.tgz"] = GOOD
    lock = _lock(tmp_path / "lock.json", GOOD, [
        {"from": "package/LICENSE", "to": "fake/LICENSE",
         "sha256": hashlib.sha256(LICENSE).hexdigest()},
        {"from": "package/dist/fake.js", "to": "fake/fake.js", "sha256": "0" * 64}])
    with pytest.raises(vendor.VendorError, match="sha256"):
        vendor.fetch(tmp_path / "vendor", lock, log=lambda _: None)
    assert _tree(tmp_path / "vendor") == []  # not even the LICENSE, which matched


def test_unreachable_registry_fails_with_advice(registry, tmp_path):
    lock = _lock(tmp_path / "lock.json", GOOD)  # no route: the mirror answers 404
    with pytest.raises(vendor.VendorError) as err:
        vendor.fetch(tmp_path / "vendor", lock, log=lambda _: None)
    message = str(err.value)
    assert "could not fetch fake@1.0.0 from " + registry.url in message
    assert vendor.REGISTRY_ENV in message
    assert registry.requests == ["/fake/-/fake-1.0.0.tgz"]  # a 404 is not retried


@pytest.mark.parametrize("to", ["../escape.js", "/tmp/escape.js", "fake/../../escape.js",
                                "..\\escape.js", "."])
def test_target_path_escaping_the_folder_is_refused(registry, tmp_path, to):
    registry.routes["/fake/-/fake-1.0.0.tgz"] = GOOD
    lock = _lock(tmp_path / "lock.json", GOOD, [
        {"from": "package/dist/fake.js", "to": to, "sha256": hashlib.sha256(SCRIPT).hexdigest()}])
    before = _tree(tmp_path)
    with pytest.raises(vendor.VendorError, match="escapes the vendor folder"):
        vendor.fetch(tmp_path / "out" / "vendor", lock, log=lambda _: None)
    assert _tree(tmp_path) == before
    assert registry.requests == []  # refused from the lock alone


def test_member_path_escaping_the_tarball_is_refused(tmp_path):
    lock = _lock(tmp_path / "lock.json", GOOD, [
        {"from": "package/../../etc/passwd", "to": "fake/x", "sha256": "0" * 64}])
    with pytest.raises(vendor.VendorError, match="odd tarball member"):
        vendor.load_lock(lock)


def test_symlink_member_is_refused(registry, tmp_path):
    tarball = _tarball({"package/LICENSE": LICENSE}, links={"package/dist/fake.js": "/etc/passwd"})
    registry.routes["/fake/-/fake-1.0.0.tgz"] = tarball
    lock = _lock(tmp_path / "lock.json", tarball)
    with pytest.raises(vendor.VendorError, match="not a regular file"):
        vendor.fetch(tmp_path / "vendor", lock, log=lambda _: None)
    assert _tree(tmp_path / "vendor") == []


def test_symlinked_folder_inside_the_target_is_refused(registry, tmp_path):
    registry.routes["/fake/-/fake-1.0.0.tgz"] = GOOD
    lock = _lock(tmp_path / "lock.json", GOOD)
    outside = tmp_path / "outside"
    outside.mkdir()
    target = tmp_path / "vendor"
    target.mkdir()
    (target / "fake").symlink_to(outside, target_is_directory=True)
    with pytest.raises(vendor.VendorError, match="outside"):
        vendor.fetch(target, lock, log=lambda _: None)
    assert _tree(outside) == []


@given(st.lists(st.sampled_from(["..", ".", "a", "b.js", "", "/", "\\", "c:", "~"]),
                min_size=1, max_size=6))
def test_accepted_target_paths_stay_inside(parts):
    rel = "/".join(parts)
    root = Path("/srv/vendor")
    try:
        vendor._safe_relpath(rel, {"name": "x", "version": "1"})
    except vendor.VendorError:
        return
    assert Path(str(root / rel)).resolve().is_relative_to(root)


# --- the wheel -------------------------------------------------------------------------------

def test_wheel_ships_the_lock_and_the_vendor_files(tmp_path):
    # With build isolation: pyproject's SPDX `license` needs setuptools>=77 (the virtualenv's
    # may be older). The files are committed: the build makes no npm request.
    static = ROOT / "server" / "ui" / "static"
    pages = {f"burrforce/server/ui/static/{p.relative_to(static).as_posix()}"
             for p in static.rglob("*") if p.suffix in (".html", ".js", ".css", ".svg")}
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                        str(tmp_path), str(ROOT)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    names = set(zipfile.ZipFile(next(tmp_path.glob("burrforce-*.whl"))).namelist())
    expected = {"burrforce/server/ui/__init__.py", "burrforce/server/ui/vendor.py",
                "burrforce/server/ui/vendor.lock.json"}
    expected |= {f"burrforce/server/ui/vendor/{e['to']}"
                 for pkg in vendor.load_lock() for e in pkg["files"]}
    assert expected <= names
    assert pages <= names  # the page's own files, as they were when the build started
