"""Where numba keeps the compiled kernels: one stable, per-user directory for every process.

numba's default is ``__pycache__`` beside each module, which it must be able to write even to
*load* from (it probes with a temporary file): an install owned by another user (a system
install, an image built as root and run as a service user) silently falls back to numba's own
user cache, and a read-only one compiles at every start. The ``burrforce`` command therefore
sets ``NUMBA_CACHE_DIR`` before anything imports numba; the hot-loop workers and the spare
inherit it, so ``burrforce compile`` fills the very cache every later ``serve`` loads.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import MutableMapping
from functools import cache
from pathlib import Path

from . import __version__

#: numba's own variable: when the user (or the image) sets it, it wins.
ENV = "NUMBA_CACHE_DIR"


#: The folders of ``burrforce.server`` and ``burrforce.proto``: the kernels and every module
#: they take constants from (message layouts, state indices).
SOURCE_ROOTS = (Path(__file__).resolve().parent, Path(__file__).resolve().parent.parent / "proto")


@cache
def kernels_digest(roots: tuple[Path, ...] = SOURCE_ROOTS) -> str:
    """12 hex digits of SHA-256 over the server's and the protocol's modules (path and text).
    numba keys a cached kernel on its own file's timestamp only, not on the kernels it calls
    from other files nor on the constants it imports (a message layout, a state index): after
    an edit to ``voxels.py`` the cached ``bone_tick`` would silently run the old code. A
    directory per digest makes any source edit start a fresh cache instead (a few ms to hash).
    """
    digest = hashlib.sha256()
    for root in roots:
        for path in sorted(root.rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            digest.update(f"{root.name}/{path.relative_to(root)}".encode() + b"\0"
                          + path.read_bytes() + b"\0")
    return digest.hexdigest()[:12]


def default_cache_dir(environ: MutableMapping[str, str] | None = None) -> Path:
    """``$XDG_CACHE_HOME/burrforce/numba-<version>-<kernels digest>`` (``~/.cache`` when
    XDG_CACHE_HOME is unset or relative, as the XDG spec says). An upgrade or a kernel edit
    gets a directory of its own (see :func:`kernels_digest`); stale ones can simply be
    deleted."""
    environ = os.environ if environ is None else environ
    base = environ.get("XDG_CACHE_HOME", "")
    root = Path(base) if os.path.isabs(base) else Path.home() / ".cache"
    return root / "burrforce" / f"numba-{__version__}-{kernels_digest()}"


def configure(environ: MutableMapping[str, str] | None = None) -> Path:
    """Point numba's cache at ``NUMBA_CACHE_DIR`` if set, else at :func:`default_cache_dir`,
    and return it. Must run before numba is imported (numba reads the variable once); child
    processes inherit it through ``environ``. Does not create the directory: numba does, and
    falls back to its own locations if it cannot."""
    environ = os.environ if environ is None else environ
    if not environ.get(ENV):
        environ[ENV] = str(default_cache_dir(environ))
    return Path(environ[ENV])
