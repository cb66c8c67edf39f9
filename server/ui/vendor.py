"""The live view's third-party files (three.js, uPlot): verified in place, refreshed from npm.

The files are committed in ``vendor/`` beside this file, with their licences, so a build needs
no network. ``vendor.lock.json`` is their record: each npm package's version, its tarball's URL
and the registry's sha512 ``integrity``, and the files taken from it (path inside the tarball →
path under ``vendor/``) with their sha256.

At run time only :func:`load_lock` and :func:`check` are used (``ui.vendor_missing``, and
``--check`` on an installation). :func:`fetch` and :func:`relock` are the maintainer's refresh
(``vendor/README.md`` says when and how): a tarball is checked against its integrity before
anything is read from it, each file against its sha256 before anything is written (``fetch``),
and files are written atomically, so a failed or tampered download leaves the folder as it was.

Stdlib only, and runnable from a checkout without installing anything::

    python server/ui/vendor.py --check      # verify vendor/ against the lock; exit 1 if not
    python server/ui/vendor.py              # write what is missing or differs, from npm
    python server/ui/vendor.py --relock     # after editing a version, tarball and integrity
                                            # in the lock: fetch all, record the new sha256s
    python -m burrforce.server.ui.vendor --check   # the same, on an installation

Environment: ``BURRFORCE_NPM_REGISTRY`` replaces https://registry.npmjs.org (a mirror with
npm's layout: Verdaccio, Artifactory, Nexus); CA bundles as urllib finds them
(``SSL_CERT_FILE``, ``SSL_CERT_DIR``), or ``REQUESTS_CA_BUNDLE``/``CURL_CA_BUNDLE`` when set;
proxies from ``HTTPS_PROXY``/``NO_PROXY``.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import hmac
import io
import json
import os
import ssl
import sys
import tarfile
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path, PurePosixPath

LOCK_PATH = Path(__file__).resolve().with_name("vendor.lock.json")
VENDOR_DIR = Path(__file__).resolve().with_name("vendor")

REGISTRY_ENV = "BURRFORCE_NPM_REGISTRY"
DEFAULT_REGISTRY = "https://registry.npmjs.org"

TIMEOUT_S = 30.0
ATTEMPTS = 3
#: Pause before the 2nd and 3rd attempt: a registry's 503 or a dropped connection is often
#: over within seconds.
BACKOFF_S = (1.0, 3.0)
#: Larger than any tarball we lock (three: 5 MB): a misbehaving mirror cannot fill memory.
MAX_TARBALL_BYTES = 64 * 1024 * 1024


class VendorError(RuntimeError):
    """A locked file could not be fetched or verified; the message says which and why."""


def load_lock(lock_path: Path = LOCK_PATH) -> list[dict]:
    """The lock's packages, each checked for the keys and paths ``fetch`` relies on."""
    try:
        lock = json.loads(Path(lock_path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise VendorError(f"cannot read the vendor lock {lock_path}: {exc}") from exc
    packages = lock.get("packages")
    if not isinstance(packages, list) or not packages:
        raise VendorError(f"{lock_path}: no 'packages' list")
    seen: set[str] = set()
    for pkg in packages:
        for key in ("name", "version", "tarball", "integrity", "license", "files"):
            if key not in pkg:
                raise VendorError(f"{lock_path}: package {pkg.get('name', '?')} has no {key!r}")
        if not str(pkg["integrity"]).startswith("sha512-"):
            raise VendorError(f"{lock_path}: {_label(pkg)} integrity is not sha512-...")
        for entry in pkg["files"]:
            _check_member(entry["from"], pkg)
            _safe_relpath(entry["to"], pkg)
            if len(entry.get("sha256", "")) != 64:
                raise VendorError(f"{lock_path}: {_label(pkg)} {entry['to']} has no sha256")
            if entry["to"] in seen:
                raise VendorError(f"{lock_path}: {entry['to']} is locked twice")
            seen.add(entry["to"])
    return packages


def check(target_dir: Path = VENDOR_DIR, lock_path: Path = LOCK_PATH) -> list[str]:
    """The locked files (paths under ``target_dir``) that are absent or differ from the lock."""
    return [entry["to"] for pkg in load_lock(lock_path) for entry in pkg["files"]
            if not _file_matches(Path(target_dir) / entry["to"], entry["sha256"])]


def fetch(target_dir: Path = VENDOR_DIR, lock_path: Path = LOCK_PATH,
          registry: str | None = None, log=print) -> list[str]:
    """Make ``target_dir`` hold the locked files; return the ones written (paths in it).

    Packages whose files all match are not downloaded. Every needed tarball is downloaded and
    verified before the first file is written, so an error leaves ``target_dir`` untouched.
    ``registry`` defaults to ``$BURRFORCE_NPM_REGISTRY``, then to npm's own.
    """
    target_dir = Path(target_dir)
    packages = load_lock(lock_path)
    registry = (registry or os.environ.get(REGISTRY_ENV) or DEFAULT_REGISTRY).rstrip("/")
    contents: dict[str, bytes] = {}
    for pkg in packages:
        stale = [e for e in pkg["files"]
                 if not _file_matches(target_dir / e["to"], e["sha256"])]
        if not stale:
            continue
        url = _tarball_url(pkg, registry)
        log(f"vendor: fetching {_label(pkg)} from {url}")
        tarball = _download(url, pkg)
        _verify_integrity(tarball, pkg, url)
        contents.update(_extract(tarball, stale, pkg, url))
    _write_all(target_dir, contents)
    return sorted(contents)


def relock(target_dir: Path = VENDOR_DIR, lock_path: Path = LOCK_PATH,
           registry: str | None = None, log=print) -> list[str]:
    """Download every locked package, verify its integrity, write its files into
    ``target_dir`` and record their sha256 in the lock; return the files whose sha256 changed.

    For a maintainer moving a package to another release: edit its ``version``, ``tarball``
    and ``integrity`` in the lock first (a new file's ``sha256`` may be 64 zeros). The
    registry's integrity stays the trust anchor; nothing is written unless every tarball
    matches it.
    """
    target_dir = Path(target_dir)
    lock = json.loads(Path(lock_path).read_text(encoding="utf-8"))
    packages = load_lock(lock_path)
    registry = (registry or os.environ.get(REGISTRY_ENV) or DEFAULT_REGISTRY).rstrip("/")
    contents: dict[str, bytes] = {}
    for pkg in packages:
        url = _tarball_url(pkg, registry)
        log(f"vendor: fetching {_label(pkg)} from {url}")
        tarball = _download(url, pkg)
        _verify_integrity(tarball, pkg, url)
        contents.update(_extract(tarball, pkg["files"], pkg, url, check_sha256=False))
    changed = []
    for pkg in packages:
        for entry in pkg["files"]:
            digest = hashlib.sha256(contents[entry["to"]]).hexdigest()
            if digest != entry["sha256"]:
                changed.append(entry["to"])
            entry["sha256"] = digest
    _write_all(target_dir, contents)
    lock["packages"] = packages
    _write_atomically(Path(lock_path),
                      (json.dumps(lock, indent=2, ensure_ascii=False) + "\n").encode("utf-8"))
    return sorted(changed)


def _label(pkg: dict) -> str:
    return f"{pkg.get('name', '?')}@{pkg.get('version', '?')}"


def _check_member(name: str, pkg: dict) -> None:
    # Members are only read by name, never written under their own path; still, a lock that
    # names an odd member is more likely a mistake than intent.
    p = PurePosixPath(name)
    if p.is_absolute() or ".." in p.parts or not name or "\\" in name:
        raise VendorError(f"{_label(pkg)}: odd tarball member {name!r} in the lock")


def _safe_relpath(rel: str, pkg: dict) -> PurePosixPath:
    p = PurePosixPath(rel)
    if not p.parts or p.is_absolute() or ".." in p.parts or "\\" in rel or ":" in rel:
        raise VendorError(f"{_label(pkg)}: target path {rel!r} escapes the vendor folder")
    return p


def _tarball_url(pkg: dict, registry: str) -> str:
    # A mirror keeps npm's layout (<registry>/<name>/-/<name>-<version>.tgz): swap the origin.
    url = pkg["tarball"]
    if url.startswith(DEFAULT_REGISTRY + "/"):
        url = registry + url[len(DEFAULT_REGISTRY):]
    return url


def _ssl_context() -> ssl.SSLContext:
    # The default context reads SSL_CERT_FILE/SSL_CERT_DIR like urllib's; the bundles that pip
    # and requests users set for a TLS-intercepting proxy are added so one setting serves both.
    context = ssl.create_default_context()
    for var in ("REQUESTS_CA_BUNDLE", "CURL_CA_BUNDLE"):
        bundle = os.environ.get(var)
        if bundle:
            try:
                context.load_verify_locations(cafile=bundle)
            except (OSError, ssl.SSLError) as exc:
                raise VendorError(f"{var}={bundle} is not a readable CA bundle: {exc}") from exc
    return context


def _download(url: str, pkg: dict) -> bytes:
    opener = urllib.request.build_opener(urllib.request.HTTPSHandler(context=_ssl_context()))
    request = urllib.request.Request(url, headers={"User-Agent": "burrforce-vendor"})
    last: Exception | None = None
    for attempt in range(ATTEMPTS):
        if attempt:
            time.sleep(BACKOFF_S[min(attempt, len(BACKOFF_S)) - 1])
        try:
            with opener.open(request, timeout=TIMEOUT_S) as response:
                data = response.read(MAX_TARBALL_BYTES + 1)
            if len(data) > MAX_TARBALL_BYTES:
                raise VendorError(f"{url} is larger than {MAX_TARBALL_BYTES} bytes")
            return data
        except urllib.error.HTTPError as exc:
            last = exc
            if 400 <= exc.code < 500 and exc.code not in (408, 429):
                break  # the mirror lacks it; asking again will not help
        except (urllib.error.URLError, OSError) as exc:  # refused, DNS, TLS, timeout, reset
            last = exc
    raise VendorError(
        f"could not fetch {_label(pkg)} from {url}: {last}; set {REGISTRY_ENV} to an npm "
        f"registry mirror this machine can reach (and SSL_CERT_FILE to its CA if needed)")


def _verify_integrity(tarball: bytes, pkg: dict, url: str) -> None:
    expected = pkg["integrity"]
    actual = "sha512-" + base64.b64encode(hashlib.sha512(tarball).digest()).decode("ascii")
    if not hmac.compare_digest(actual, expected):
        raise VendorError(f"{_label(pkg)} from {url} does not match the lock's integrity "
                          f"(got {actual}, locked {expected}); nothing was written")


def _extract(tarball: bytes, entries: list[dict], pkg: dict, url: str,
             check_sha256: bool = True) -> dict[str, bytes]:
    out: dict[str, bytes] = {}
    try:
        with tarfile.open(fileobj=io.BytesIO(tarball), mode="r:gz") as tar:
            for entry in entries:
                try:
                    member = tar.getmember(entry["from"])
                except KeyError:
                    raise VendorError(f"{_label(pkg)} from {url} has no {entry['from']}") \
                        from None
                if not member.isfile():  # a link could point anywhere
                    raise VendorError(f"{_label(pkg)}: {entry['from']} is not a regular file")
                data = tar.extractfile(member).read()
                digest = hashlib.sha256(data).hexdigest()
                if check_sha256 and not hmac.compare_digest(digest, entry["sha256"]):
                    raise VendorError(f"{_label(pkg)}: {entry['from']} has sha256 {digest}, "
                                      f"locked {entry['sha256']}; nothing was written")
                out[entry["to"]] = data
    except (tarfile.TarError, OSError, EOFError) as exc:
        raise VendorError(f"{_label(pkg)} from {url} is not a readable tarball: {exc}") from exc
    return out


def _file_matches(path: Path, sha256: str) -> bool:
    try:
        return hmac.compare_digest(hashlib.sha256(path.read_bytes()).hexdigest(), sha256)
    except OSError:
        return False


def _write_all(target_dir: Path, contents: dict[str, bytes]) -> None:
    root = target_dir.resolve()
    for rel in contents:  # a symlinked folder inside the target could still lead out of it
        if not (target_dir / rel).resolve().is_relative_to(root):
            raise VendorError(f"{target_dir / rel} resolves outside {root}; nothing was written")
    for rel, data in contents.items():
        _write_atomically(target_dir / rel, data)


def _write_atomically(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o644)  # mkstemp's 0600 would keep other users from serving it
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m burrforce.server.ui.vendor",
        description="Verify the live view's third-party files against "
                    f"{LOCK_PATH.name}, or refresh them from npm (maintainers).")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--check", action="store_true",
                      help="only verify the files already there; exit 1 if any differs")
    mode.add_argument("--relock", action="store_true",
                      help="fetch every package again and record the files' sha256 in the "
                           "lock (after editing a version, tarball and integrity in it)")
    parser.add_argument("--target", type=Path, default=VENDOR_DIR,
                        help=f"folder to write into (default: {VENDOR_DIR})")
    parser.add_argument("--lock", type=Path, default=LOCK_PATH, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    try:
        if args.check:
            bad = check(args.target, args.lock)
            for rel in bad:
                print(f"vendor: {args.target / rel} is missing or differs from the lock",
                      file=sys.stderr)
            return 1 if bad else 0
        if args.relock:
            changed = relock(args.target, args.lock)
            print(f"vendor: {len(changed)} file(s) changed, lock rewritten: {args.lock}")
            return 0
        written = fetch(args.target, args.lock)
    except VendorError as exc:
        print(f"vendor: {exc}", file=sys.stderr)
        return 1
    print(f"vendor: {len(written)} file(s) written, all locked files verified in {args.target}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
