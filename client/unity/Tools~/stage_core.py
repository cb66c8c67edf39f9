#!/usr/bin/env python3
# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
"""Prepares client/unity as a Unity package (UPM).

Unity imports a package from a git URL or a tarball read-only, so every file and folder in it
needs a committed ``.meta`` file with a GUID that never changes. This script writes them,
deterministically (the GUID is a hash of the path inside the package), and with
``--stage-core`` first copies the core library (client/csharp/Burrforce/*.cs, kept once in
git) into Runtime/Core/, where the Burrforce.Core assembly definition picks it up. The copies
are git-ignored; the release step runs this before packing.

    python3 "client/unity/Tools~/stage_core.py" --stage-core   # before packing or local use
    python3 "client/unity/Tools~/stage_core.py" --check        # every asset has its .meta
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1]
CORE_SOURCE = PACKAGE.parent / "csharp" / "Burrforce"
CORE_TARGET = PACKAGE / "Runtime" / "Core"
NAME = "com.burrforce.haptics"

_TAIL = "  externalObjects: {}\n  userData: \n  assetBundleName: \n  assetBundleVariant: \n"
IMPORTERS = {
    ".cs": "MonoImporter:\n  externalObjects: {}\n  serializedVersion: 2\n  defaultReferences: []\n"
           "  executionOrder: 0\n  icon: {instanceID: 0}\n  userData: \n  assetBundleName: \n"
           "  assetBundleVariant: \n",
    ".asmdef": "AssemblyDefinitionImporter:\n" + _TAIL,
    ".md": "TextScriptImporter:\n" + _TAIL,
    ".json": "PackageManifestImporter:\n" + _TAIL,
}


def guid(relative: str) -> str:
    """A stable GUID for a path inside the package (32 hex digits, as Unity writes them)."""
    return hashlib.md5(f"{NAME}/{relative}".encode()).hexdigest()


def meta_text(path: Path) -> str:
    relative = path.relative_to(PACKAGE).as_posix()
    head = f"fileFormatVersion: 2\nguid: {guid(relative)}\n"
    if path.is_dir():
        return head + "folderAsset: yes\nDefaultImporter:\n" + _TAIL
    importer = IMPORTERS.get(path.suffix, "DefaultImporter:\n" + _TAIL)
    return head + importer


def assets() -> list[Path]:
    """What Unity imports: everything except hidden files, *~ folders and .meta files."""
    out = []
    for p in sorted(PACKAGE.rglob("*")):
        parts = p.relative_to(PACKAGE).parts
        if any(x.startswith(".") or x.endswith("~") for x in parts) or p.suffix == ".meta":
            continue
        out.append(p)
    return out


def stage_core() -> int:
    files = sorted(CORE_SOURCE.glob("*.cs"))
    for f in files:
        shutil.copy2(f, CORE_TARGET / f.name)
    return len(files)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stage-core", action="store_true",
                        help="copy client/csharp/Burrforce/*.cs into Runtime/Core/ first")
    parser.add_argument("--check", action="store_true",
                        help="only check that every asset has its .meta; exit 1 if not")
    args = parser.parse_args()
    if args.check:
        bad = [str(p) for p in assets()
               if not p.with_name(p.name + ".meta").is_file()
               or p.with_name(p.name + ".meta").read_text() != meta_text(p)]
        for b in bad:
            print(f"missing or stale .meta: {b}", file=sys.stderr)
        return 1 if bad else 0
    if args.stage_core:
        print(f"staged {stage_core()} core files into {CORE_TARGET}")
    written = 0
    for p in assets():
        meta = p.with_name(p.name + ".meta")
        text = meta_text(p)
        if not meta.is_file() or meta.read_text() != text:
            meta.write_text(text)
            written += 1
    print(f"{written} .meta files written")
    return 0


if __name__ == "__main__":
    sys.exit(main())
