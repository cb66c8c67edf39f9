"""The live view's files: the page (``static/``) and its third-party scripts (``vendor/``).

``vendor/`` is committed with the packages' licences; ``vendor.lock.json`` records their
versions and hashes, and ``vendor.py`` verifies them or refreshes them from npm.
"""

from __future__ import annotations

from pathlib import Path

UI_DIR = Path(__file__).resolve().parent
#: The third-party files, as the lock's ``to`` paths lay them out (``three/three.module.js``).
VENDOR_DIR = UI_DIR / "vendor"
STATIC_DIR = UI_DIR / "static"


def vendor_missing() -> list[str]:
    """The locked files (paths under ``VENDOR_DIR``) that are absent.

    Presence only, no hashing (``vendor.py --check`` hashes): cheap enough to ask per
    request. A tree whose ``vendor/`` was deleted answers all of them.
    """
    # Imported here, not at the top: `python -m burrforce.server.ui.vendor` would otherwise
    # find the module already imported by its package and warn.
    from .vendor import load_lock

    return [entry["to"] for pkg in load_lock() for entry in pkg["files"]
            if not (VENDOR_DIR / entry["to"]).is_file()]
