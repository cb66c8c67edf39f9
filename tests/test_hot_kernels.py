"""The per-tick and per-packet kernels keep to what makes them fast (``server/hot_kernel.py``)."""

from __future__ import annotations

import dis
import importlib
import pkgutil

import pytest

import burrforce.server as server_pkg

#: The packages whose kernels run every tick or every packet, and the device host's servo-tick
#: renderer (``devices.render``, 1 kHz on the machine driving the device).
HOT_PACKAGES = ("bone", "model", "hotloop", "haptics", "devices.render")
#: Modules there whose kernels are not on that path: loading and scanning whole bones, and the
#: shared bone's seqlock (a few instructions per tick, no arrays).
NOT_HOT = ("bone.bricks", "bone.seqlock", "bone.phantoms", "bone.loaders", "bone.hounsfield")


def _kernels():
    """(module name without the package prefix, function name, dispatcher) of every numba
    kernel in the hot packages."""
    found = []
    for package in HOT_PACKAGES:
        pkg = importlib.import_module(f"{server_pkg.__name__}.{package}")
        names = ([info.name for info in pkgutil.walk_packages(pkg.__path__, f"{pkg.__name__}.")]
                 if hasattr(pkg, "__path__") else [pkg.__name__])
        for module_name in names:
            module = importlib.import_module(module_name)
            for name, obj in vars(module).items():
                py_func = getattr(obj, "py_func", None)
                if py_func is not None and py_func.__module__ == module.__name__:
                    found.append((module.__name__.removeprefix(f"{server_pkg.__name__}."),
                                  name, obj))
    return found


def _is_hot(module: str) -> bool:
    return not any(module == m or module.startswith(f"{m}.") for m in NOT_HOT)


def test_the_walk_finds_the_kernels_of_every_hot_package_and_every_exception() -> None:
    kernels = _kernels()
    names = {f"{m}.{n}" for m, n, _ in kernels}
    assert {"bone.tick.bone_tick", "bone.force.cut_voxels", "bone.carve.carve_sphere",
            "model.kernels.accumulate_forces", "hotloop.wire.decode_pose_into",
            "haptics.coupling.coupled_finish", "devices.render.render"} <= names
    modules = {m for m, _, _ in kernels}
    for excluded in NOT_HOT:  # an exception that names nothing is stale
        assert any(m == excluded or m.startswith(f"{excluded}.") for m in modules), excluded


def test_no_kernel_passes_its_arguments_as_a_tuple() -> None:
    """A call of over 30 arguments compiles to CALL_FUNCTION_EX: numba then packs and unpacks
    a tuple per call and cannot inline it (180 ns a call, measured on the corner sampler)."""
    offenders = []
    for module, name, kernel in _kernels():
        for ins in dis.get_instructions(kernel.py_func):
            if ins.opname == "CALL_FUNCTION_EX":
                offenders.append(f"{module}.{name} at offset {ins.offset}")
    assert offenders == []


@pytest.mark.parametrize("package", HOT_PACKAGES)
def test_hot_kernels_are_cached_nogil_and_without_reference_counting(package: str) -> None:
    """Every kernel on the per-tick path is a ``hot_kernel`` or ``hot_inline``: reference
    counting off (the force stage took 96 µs with it and 36 µs without), nogil, and cached
    unless it is a helper inlined into its callers (whose cache entries hold its code)."""
    plain = []
    for module, name, kernel in _kernels():
        if not (module == package or module.startswith(f"{package}.")) or not _is_hot(module):
            continue
        options = kernel.targetoptions
        cached = type(kernel._cache).__name__ != "NullCache"  # numba keeps cache= there
        if options.get("_nrt", True) or not options.get("nogil") \
                or cached == bool(options.get("forceinline")):
            plain.append(f"{module}.{name}")
    assert plain == [], "use hot_kernel / hot_inline (server/hot_kernel.py)"
