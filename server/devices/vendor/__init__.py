"""Haptic devices driven through their makers' SDKs: optional back-ends behind import guards.

=================  ==========================  ==============================================
back-end           Python package (extra)      native part
=================  ==========================  ==============================================
``forcedimension`` ``forcedimension-core``     Force Dimension SDK (``libdrd``), found via
                                               ``FDSDK``
``openhaptics``    ``pyOpenHaptics``           3D Systems OpenHaptics (``libHD.so``) and the
                                               Touch device driver
``haply``          ``HaplyHardwareAPI``        none (the wheel talks to the serial port)
=================  ==========================  ==============================================

Importing this package or its modules imports no vendor code: each back-end imports its
vendor package in ``open()`` (:func:`import_vendor`), so a missing package or SDK surfaces as
:class:`~burrforce.server.devices.base.VendorLibraryMissing` naming what to install.

None of these back-ends has been run against hardware; their tests drive fakes of the vendors'
Python APIs (same names and signatures as the published wheels).
"""

from __future__ import annotations

import importlib
from types import ModuleType

import numpy as np

from ..base import VendorLibraryMissing, clamp_force

__all__ = ["checked_force", "import_vendor"]


def import_vendor(module: str, *, extra: str, native_hint: str) -> ModuleType:
    """Import ``module`` of a vendor package, or raise VendorLibraryMissing saying what to
    install: ``pip install 'burrforce[<extra>]'`` when the package is absent, ``native_hint``
    (the vendor SDK and the environment it needs) when the package is there but its native
    library did not load."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        top = module.split(".")[0]
        if exc.name is None or exc.name.split(".")[0] == top:
            raise VendorLibraryMissing(
                f"the Python package for the {extra} back-end is not installed (no module "
                f"{top!r}): pip install 'burrforce[{extra}]'; then {native_hint}") from exc
        raise VendorLibraryMissing(
            f"{top} is installed but its dependency {exc.name!r} is missing: "
            f"pip install 'burrforce[{extra}]'") from exc
    except (ImportError, OSError) as exc:
        # Vendor wrappers load their native library at import time (ctypes.CDLL).
        raise VendorLibraryMissing(
            f"{module.split('.')[0]} is installed but its native library did not load ({exc}); "
            f"{native_hint}") from exc


def checked_force(force_N: np.ndarray, max_force_N: float) -> np.ndarray:
    """``force_N`` as a float (3,) array in N, scaled to at most ``max_force_N``; a non-finite
    force becomes zero. Raises ValueError for any other shape."""
    f = np.asarray(force_N, dtype=float)
    if f.shape != (3,):
        raise ValueError(f"a force must be a (3,) vector in N, got shape {f.shape}")
    return clamp_force(f, max_force_N)[0]
