"""The decorators of the kernels that run every tick or every packet.

They are ``@njit(cache=True, nogil=True)`` plus ``_nrt=False``: compiled without numba's
reference counting (where numba knows that private option: ``_without_reference_counting``).
These kernels only read and write arrays their caller owns and never allocate, so the counts
protect nothing, yet numba keeps an atomic increment and decrement per
array per inlined helper where its pruning pass cannot prove them useless: measured on
``bench accuracy``'s groove, the force stage took 96 µs with them and 36 µs without, with the
same result to the last bit. A kernel that must allocate (``np.empty``, a returned array) does
not compile under these decorators and stays a plain ``@njit``.

A call between kernels keeps to 30 arguments (pack tables into a tuple beyond that): CPython
passes a longer call's arguments as one tuple (``CALL_FUNCTION_EX``), which numba can neither
inline nor call cheaply. Measured: 180 ns per call, for each of the ~550 corners a tick samples.
"""

from __future__ import annotations

from numba import njit


def _without_reference_counting() -> dict[str, bool]:
    """``{"_nrt": False}`` where this numba knows the option (a private one; CI runs numba
    0.68), else nothing: a numba without it then compiles these kernels slower but right,
    instead of every kernel failing on its first call with an unknown option
    (``tests/test_hot_kernels.py`` fails on it, so CI notices)."""
    try:
        from numba.core.cpu import CPUTargetOptions
    except ImportError:
        return {}
    return {"_nrt": False} if hasattr(CPUTargetOptions, "_nrt") else {}


_OPTIONS = {"cache": True, "nogil": True, **_without_reference_counting()}
#: A kernel called once per tick or packet (or from one).
hot_kernel = njit(**_OPTIONS)
#: A small helper inlined into its callers at numba's IR level.
hot_inline = njit(**_OPTIONS, inline="always")
