"""Where numba keeps the compiled kernels: one stable, per-user directory for every process.

numba's default is ``__pycache__`` beside each module, which it must be able to write even to
*load* from (it probes with a temporary file): an install owned by another user (a system
install, an image built as root and run as a service user) silently falls back to numba's own
user cache, and a read-only one compiles at every start. The ``burrforce`` command therefore
sets ``NUMBA_CACHE_DIR`` before anything imports numba; the hot-loop workers and the spare
inherit it, so ``burrforce compile`` fills the very cache every later ``serve`` loads.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import re
import time
from collections.abc import Callable, Iterator, MutableMapping
from contextlib import contextmanager
from functools import cache
from importlib import metadata
from pathlib import Path

from . import __version__

#: numba's own variable: when the user (or the image) sets it, it wins.
ENV = "NUMBA_CACHE_DIR"


#: The folders of ``burrforce.server`` and ``burrforce.proto`` and their import names.
PACKAGE_ROOTS: tuple[tuple[Path, str], ...] = (
    (Path(__file__).resolve().parent, "burrforce.server"),
    (Path(__file__).resolve().parent.parent / "proto", "burrforce.proto"),
)
#: A module imports one of these at its top level iff numba compiles functions of it (numba
#: itself, or the project's kernel decorators).
KERNEL_IMPORTS = frozenset({"numba", "burrforce.server.hot_kernel"})
#: The packages whose versions change what numba compiles, besides burrforce's own (which
#: names the directory).
COMPILER_DISTRIBUTIONS = ("numba", "llvmlite")


@cache
def kernels_digest(roots: tuple[tuple[Path, str], ...] = PACKAGE_ROOTS) -> str:
    """12 hex digits of SHA-256 over what the compiled kernels are made of: the modules that
    hold kernels, every module they import at their top level (transitively: the constants a
    kernel compiles in, the kernels it calls), and numba's and llvmlite's versions.

    numba keys a cached kernel on its own file's timestamp only, not on the kernels it calls
    from other files nor on the constants it imports (a message layout, a state index): after
    an edit to ``voxels.py`` the cached ``bone_tick`` would silently run the old code. A
    directory per digest makes such an edit start a fresh cache instead; an edit anywhere
    else (a route, a benchmark, a docstring of the command line) keeps it. ``roots`` pairs a
    source folder with its import name. See :func:`kernel_modules`.
    """
    digest = hashlib.sha256()
    for name in COMPILER_DISTRIBUTIONS:
        digest.update(f"{name}=={_version(name)}".encode() + b"\0")
    for name, path in sorted(kernel_modules(roots).items()):
        digest.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:12]


@cache
def _kernel_module_paths(roots: tuple[tuple[Path, str], ...]) -> tuple[Path, ...]:
    """:func:`kernel_modules`' files, in name order, read once a process."""
    return tuple(path for _, path in sorted(kernel_modules(roots).items()))


def kernel_modules(roots: tuple[tuple[Path, str], ...] = PACKAGE_ROOTS) -> dict[str, Path]:
    """The modules :func:`kernels_digest` covers, by import name: those that import numba or
    the kernel decorators at their top level, and the closure of their top-level imports of
    modules under ``roots``.

    Read from the source, nothing imported, and by pattern rather than by parsing (``ast``
    takes seconds for the whole package, and every ``burrforce`` command computes this):
    an import statement that starts a line is a top-level one. Imports inside functions are
    left out (a kernel cannot run them, nor compile in what they bring); so are indented
    ones in a top-level ``try`` or ``if``, which the package keeps for the standard library
    and third parties only. A docstring line that reads like an import only widens the set.
    """
    files = {name: path for root, package in roots for name, path in _modules(root, package)}
    imports = {name: _top_level_imports(name, path, files) for name, path in files.items()}
    pending = [name for name, (_, kernel) in imports.items() if kernel]
    found: dict[str, Path] = {}
    while pending:
        name = pending.pop()
        if name not in found:
            found[name] = files[name]
            pending.extend(imports[name][0])
    return found


def _modules(root: Path, package: str) -> Iterator[tuple[str, Path]]:
    for path in sorted(root.rglob("*.py")):
        if "__pycache__" in path.parts:
            continue
        parts = path.relative_to(root).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join((package, *parts)), path


#: ``from MODULE import NAMES`` (NAMES possibly parenthesized over lines) or ``import
#: MODULES``, at the start of a line.
_IMPORT = re.compile(rb"^(?:from[ \t]+(\.*[\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n#;]*)"
                     rb"|import[ \t]+([^\n#;]+))", re.MULTILINE)
_NAME = re.compile(rb"[\w.]+")


def _top_level_imports(name: str, path: Path,
                       files: dict[str, Path]) -> tuple[set[str], bool]:
    """(the modules under the roots that ``name`` imports at its top level, whether it
    imports a kernel marker)."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    targets: set[str] = set()
    for source, names, plain in _IMPORT.findall(path.read_bytes()):
        if plain:
            targets.update(n.decode() for n in _NAME.findall(plain.split(b" as ")[0])
                           if n != b"as")
            continue
        source = source.decode()
        level = len(source) - len(source.lstrip("."))
        module = source[level:]
        if level:
            base = package[:len(package) - level + 1]
            module = ".".join(base + ([module] if module else []))
        targets.add(module)
        # ``from . import voxels`` imports a module, not a name of the package.
        targets.update(f"{module}.{n.decode()}" for n in _NAME.findall(names))
    kernel = any(t == m or t.startswith(m + ".") for t in targets for m in KERNEL_IMPORTS)
    return {t for t in targets if t in files and t != name}, kernel


def _version(distribution: str) -> str:
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return "none"


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


#: ``burrforce compile`` holds an exclusive lock on this file of the cache while it fills it.
FILL_LOCK = "filling.lock"


def _cpu() -> str:
    # numba keys a cached kernel on the CPU it was compiled for: so does the marker.
    return re.sub(r"[^\w.-]", "_", os.environ.get("NUMBA_CPU_NAME") or "host")


def cache_dir(environ: MutableMapping[str, str] | None = None) -> Path | None:
    """The cache numba uses (``NUMBA_CACHE_DIR``), None before :func:`configure`."""
    value = (os.environ if environ is None else environ).get(ENV)
    return Path(value) if value else None


def sources_stamp(roots: tuple[tuple[Path, str], ...] = PACKAGE_ROOTS) -> str:
    """12 hex digits over where the kernels' modules are and their modification times and
    sizes: what numba itself checks before it loads a cached kernel (it keeps a checkout's
    kernels apart from another checkout's, and treats a source file whose time changed as
    stale). A second clone of the project, or a file checked out again, thus shares the
    directory :func:`default_cache_dir` names (same content, same digest) but not numba's
    kernels in it."""
    digest = hashlib.sha256()
    for path in _kernel_module_paths(roots):
        try:
            st = path.stat()
        except OSError:
            continue
        digest.update(f"{path}\0{st.st_mtime_ns}\0{st.st_size}\0".encode())
    return digest.hexdigest()[:12]


def _marker(directory: Path) -> Path:
    return directory / f"complete-{_cpu()}"


def is_complete(directory: Path | None = None) -> bool:
    """Whether ``burrforce compile`` has filled the cache (``directory``, else
    :func:`cache_dir`) for this CPU and these very source files (:func:`sources_stamp`):
    every kernel the server runs loads from it, none compiles. Until it has, a hot loop
    warms only its sessions' burrs, and ``serve`` compiles what a session needs first."""
    directory = directory if directory is not None else cache_dir()
    if directory is None:
        return False
    try:
        stamps = _marker(directory).read_text().split()
    except (OSError, UnicodeDecodeError):
        return False
    return sources_stamp() in stamps


def mark_complete(directory: Path | None = None) -> None:
    """Note that every kernel is in the cache for these source files (``burrforce compile``,
    at its end). Other checkouts' stamps in the marker are kept: each has its own kernels in
    the same directory."""
    directory = directory if directory is not None else cache_dir()
    if directory is None:
        return
    try:
        directory.mkdir(parents=True, exist_ok=True)
        marker = _marker(directory)
        try:
            stamps = [w for w in marker.read_text().split()[2:] if len(w) == 12]
        except (OSError, UnicodeDecodeError):
            stamps = []
        stamps = [*dict.fromkeys([*stamps[-15:], sources_stamp()])]
        marker.write_text(f"burrforce {__version__}\n" + "\n".join(stamps) + "\n")
    except OSError:
        pass  # a cache numba cannot write either: every start warms only its sessions' burrs


@contextmanager
def filling(wait: bool = True, directory: Path | None = None,
            on_wait: Callable[[], None] | None = None) -> Iterator[bool]:
    """Hold the cache's fill lock (``FILL_LOCK``) for the block: yields True once held,
    False if ``wait`` is False and another process holds it (``on_wait`` is called before
    waiting for it, to say so). One compiler at a time: on two cores a second would only
    halve the first one's speed. A cache that cannot be written (nor locked) yields True:
    nothing can be filling it."""
    directory = directory if directory is not None else cache_dir()
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd = os.open(directory / FILL_LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    except (OSError, AttributeError):
        yield True
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if not wait:
                yield False
                return
            if on_wait is not None:
                on_wait()
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield True
    finally:
        os.close(fd)  # releases the lock


def wait_for_filler(timeout_s: float, directory: Path | None = None) -> bool:
    """Wait until no ``burrforce compile`` fills the cache (at most ``timeout_s``): True if
    none does (any more), False on timeout. What it compiled then loads instead of being
    compiled a second time by the caller. A complete cache is not waited for (nor is its
    lock file touched: an image's cache stays as it was built)."""
    if is_complete(directory):
        return True
    deadline = time.monotonic() + timeout_s
    while True:
        with filling(wait=False, directory=directory) as held:
            if held:
                return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.1)
