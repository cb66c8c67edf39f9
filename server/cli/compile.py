"""``burrforce compile``: compile every numba kernel the server uses into the cache, ahead of
the first ``serve`` (an install step, a container image's build).

Each step runs the code path a command takes on first use (the hot loop's warm-up, the
phantoms, meshes, bone files, the device loop), so exactly the signatures the server asks for
are compiled. Then every cached kernel of the loaded modules is counted: one never compiled
is named, so a kernel added later without a warm-up here does not go unnoticed.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "compile", help="compile the numba kernels into the cache (so serve starts at once)",
        description="Compile every numba kernel serve, the device loop and the benches use "
                    "into numba's cache (NUMBA_CACHE_DIR, else "
                    "$XDG_CACHE_HOME/burrforce/numba-VERSION-DIGEST), so that no later start "
                    "compiles. Kernels already in the cache are loaded, not compiled again. "
                    "The cache is for this CPU unless NUMBA_CPU_NAME is set (e.g. generic, "
                    "for an image that runs on other machines).")
    p.add_argument("--quiet", action="store_true", help="print only the summary line")
    p.set_defaults(func=main)


def _phantoms() -> None:
    from ..bone import PHANTOMS, phantom

    for name in PHANTOMS:
        phantom(name)


def _hot_loop() -> None:
    """What a hot-loop process (a worker or the spare) loads before it serves: a session on
    a bone in shared memory, as the control plane hands it over, through every path of a
    tick, plus the coupled output's kernels; and the control plane's reads of that bone
    (status, snapshots for exports and the journal)."""
    import shutil

    from ..bone import phantom
    from ..bone.shared import SharedBone, publish, run_directory
    from ..haptics.stage import warm_up as warm_haptics
    from ..hotloop.dispatch import Dispatcher
    from ..hotloop.spec import SessionSpec, build_session

    bone = phantom("workpiece", 0.5)
    folder = run_directory()
    try:
        ref = publish(bone, folder, "compile")
        dispatcher = Dispatcher()
        dispatcher.add(build_session(SessionSpec(bone=ref)))
        dispatcher.warm_up()
        warm_haptics()
        del dispatcher
        reader = SharedBone(ref)
        reader.snapshot().grid.bone_volume_by_label_mm3()
        reader.close()
    finally:  # the map outlives the file: unlinking it now is safe
        shutil.rmtree(folder, ignore_errors=True)


def _meshes() -> None:
    from ..bone import phantom
    from ..bone.mesh import surface_mesh

    grid = phantom("workpiece", 0.5).grid
    surface_mesh(grid, step=2)
    surface_mesh(grid, step=1, labels=[1])


def _bone_files() -> None:
    """CT (int16 HU), label (uint8) and density (float32) volumes, as the loaders read them."""
    from ..bone import LoadOptions, load_bone

    rng = np.random.default_rng(0)
    volumes = {"ct": rng.integers(-1000, 2000, (12, 12, 12)).astype(np.int16),
               "labels": rng.integers(0, 3, (12, 12, 12)).astype(np.uint8),
               "density": rng.random((12, 12, 12)).astype(np.float32)}
    with tempfile.TemporaryDirectory(prefix="burrforce-compile-") as folder:
        for kind, volume in volumes.items():
            path = Path(folder) / f"{kind}.npy"
            np.save(path, volume)
            load_bone(path, LoadOptions(kind=kind, spacing_mm=(0.2, 0.2, 0.2)))


def _model() -> None:
    """The cutting model alone (``experiment``, ``bench model``), round and other burrs."""
    from ..model import CuttingModel, CuttingParams
    from ..model.revolved import RevolvedModel
    from ..model.shapes import Burr, Cylinder, Fluted

    centre, axis = np.array([0.0, 0.0, 1.5]), np.array([0.0, 0.0, 1.0])
    feed = np.array([1.0, 0.0, 0.0])
    CuttingModel(CuttingParams()).evaluate(centre, axis, feed, 80_000.0)
    RevolvedModel(Burr(Cylinder(1.0, 4.0), Fluted(6))).evaluate(centre, axis, feed, 80_000.0)


def _device_loop() -> None:
    from ..devices.falcon.device import _commands_for_force, _sense
    from ..devices.render import CouplingRenderer
    from ..haptics.profiles import PROFILES

    CouplingRenderer(PROFILES["generic"]).warm_up()
    grip_m = np.array([0.0, 0.0, 0.11])  # near the Falcon's workspace centre
    _sense(np.zeros(3), grip_m.copy())
    _commands_for_force(grip_m, np.zeros(3))


#: (what, how): in the order a server needs them.
STEPS: tuple[tuple[str, Callable[[], None]], ...] = (
    ("hot loop (tick, wire, haptics)", _hot_loop),
    ("phantoms", _phantoms),
    ("surface meshes", _meshes),
    ("bone files", _bone_files),
    ("cutting model", _model),
    ("device loop", _device_loop),
)


def cached_kernels() -> list[tuple[str, bool]]:
    """Every ``cache=True`` numba kernel in the burrforce modules imported so far, as
    (module.name, in the cache). A kernel only ever called from other kernels is compiled
    into them, and written to the cache when they are compiled, so "in the cache" is its
    index file being there, not its having run in this process (a caller loaded from the
    cache does not load its callees). ``inline="always"`` kernels are left out: they exist
    only inside their callers."""
    from numba.core.registry import CPUDispatcher

    found = {}
    for module_name, module in list(sys.modules.items()):
        if not module_name.startswith("burrforce.") or module is None:
            continue
        for name, value in list(vars(module).items()):
            if isinstance(value, CPUDispatcher) and value._cache is not None \
                    and value.py_func.__module__ == module_name \
                    and value.targetoptions.get("inline") != "always":
                index = getattr(getattr(value._cache, "_cache_file", None), "_index_path", "")
                found[f"{module_name.removeprefix('burrforce.')}.{name}"] = \
                    bool(value.signatures) or (bool(index) and os.path.exists(index))
    return sorted(found.items())


def main(args: argparse.Namespace) -> int:
    say = (lambda text: None) if args.quiet else (lambda text: print(text, flush=True))
    cache_dir = os.environ.get("NUMBA_CACHE_DIR", "(numba's default)")
    cpu = os.environ.get("NUMBA_CPU_NAME") or "this machine's CPU"
    say(f"compiling into {cache_dir} for {cpu} (kernels already there are only loaded)")
    t0 = time.perf_counter()
    for what, step in STEPS:
        t = time.perf_counter()
        step()
        say(f"  {what:32s} {time.perf_counter() - t:6.1f} s")
    kernels = cached_kernels()
    missing = [name for name, cached in kernels if not cached]
    print(f"{len(kernels) - len(missing)} of {len(kernels)} cached kernels in {cache_dir} "
          f"({time.perf_counter() - t0:.1f} s)", flush=True)
    if missing:
        say("not in the cache (no step uses them: compiled on first use): "
            + ", ".join(missing))
    return 0
