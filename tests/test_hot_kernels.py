"""The per-tick and per-packet kernels keep to what makes them fast (``server/hot_kernel.py``)."""

from __future__ import annotations

import dis
import importlib
import pkgutil

import pytest

import burrforce.server as server_pkg

#: The packages whose kernels run every tick or every packet.
HOT_PACKAGES = ("bone", "model", "hotloop", "haptics")
#: Modules there whose kernels are not on that path (loading and scanning whole bones).
NOT_HOT = {"bone.bricks", "bone.seqlock", "bone.phantoms", "bone.loaders", "bone.hounsfield"}


def _kernels():
    """(module name, function name, dispatcher) of every numba kernel in the hot packages."""
    found = []
    for package in HOT_PACKAGES:
        pkg = importlib.import_module(f"burrforce.server.{package}")
        for info in pkgutil.walk_packages(pkg.__path__, f"{pkg.__name__}."):
            module = importlib.import_module(info.name)
            for name, obj in vars(module).items():
                py_func = getattr(obj, "py_func", None)
                if py_func is not None and py_func.__module__ == module.__name__:
                    found.append((module.__name__, name, obj))
    return found


def _short(module_name: str) -> str:
    return module_name.removeprefix(f"{server_pkg.__name__}.")


def test_the_hot_packages_hold_kernels() -> None:
    names = {f"{_short(m)}.{n}" for m, n, _ in _kernels()}
    assert {"bone.tick.bone_tick", "bone.force.cut_voxels", "bone.carve.carve_sphere",
            "hotloop.wire.decode_pose_into"} <= names


def test_no_kernel_passes_its_arguments_as_a_tuple() -> None:
    """A call of over 30 arguments compiles to CALL_FUNCTION_EX: numba then packs and unpacks
    a tuple per call and cannot inline it (180 ns a call, measured on the corner sampler)."""
    offenders = []
    for module, name, kernel in _kernels():
        for ins in dis.get_instructions(kernel.py_func):
            if ins.opname == "CALL_FUNCTION_EX":
                offenders.append(f"{_short(module)}.{name} line {ins.positions.lineno}")
    assert offenders == []


@pytest.mark.parametrize("package", HOT_PACKAGES)
def test_hot_kernels_run_without_reference_counting(package: str) -> None:
    plain = [f"{_short(m)}.{n}" for m, n, k in _kernels()
             if _short(m).startswith(f"{package}.")
             and not any(_short(m).startswith(x) for x in NOT_HOT)
             and k.targetoptions.get("_nrt", True)]
    assert plain == [], "use hot_kernel / hot_inline (server/hot_kernel.py)"
