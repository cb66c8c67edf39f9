"""The decorators of the kernels that run every tick or every packet.

They are ``@njit(cache=True, nogil=True)`` (the inlined helpers without ``cache``: see
``hot_inline``) plus ``_nrt=False``: compiled without numba's
reference counting (where numba knows that private option: ``_without_reference_counting``).
These kernels only read and write arrays their caller owns and never allocate, so the counts
protect nothing, yet numba keeps an atomic increment and decrement per
array per inlined helper where its pruning pass cannot prove them useless: measured on
``bench accuracy``'s groove, the force stage took 96 µs with them and 36 µs without, with the
same result to the last bit. A kernel that must allocate (``np.empty``, a returned array) does
not compile under these decorators and stays a plain ``@njit``.

They may also fuse a multiplication and the addition that uses it into one instruction
(``fastmath={"contract"}``: an FMA, rounded once instead of twice), and nothing else of
fastmath: no reordering of sums, and NaN and infinity keep their meaning. The trilinear
weights, the dot products and the element sums are mostly such pairs. Measured on ``bench
accuracy``'s groove (0.1 mm, 1152 elements), runs paired on the two cores: the tick 63 → 61
µs. On 18 test grooves the carved bone stayed the same voxel for voxel, and no output moved by
more than 2·10⁻⁵ of its largest value.

A call between kernels keeps to 30 arguments (pack tables into a tuple beyond that): CPython
passes a longer call's arguments as one tuple (``CALL_FUNCTION_EX``), which numba can neither
inline nor call cheaply. Measured: 180 ns per call, for each of the ~550 corners a tick samples.
"""

from __future__ import annotations

import functools

from numba import njit, types
from numba.extending import overload


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


_OPTIONS = {"cache": True, "nogil": True, "fastmath": {"contract"},
            **_without_reference_counting()}
#: A kernel called once per tick or packet (or from one).
hot_kernel = njit(**_OPTIONS)
#: A helper inlined into its callers by LLVM (``forceinline``: the function is marked
#: ``alwaysinline``), compiled once by numba whatever the number of call sites.
#:
#: Not numba's own ``inline="always"``, which copies the helper's IR into every call site
#: before typing and types each copy again, nested copies included: the bone tick took
#: 100 s per burr family to compile that way (``numba:compile`` events; deep copies of the
#: IR were half of it), and 15 s this way, with the same inlined code to run (the round
#: tick's instruction count within 3.5 %, the revolved one's 22 % lower: its sampler, a
#: call of ~100 arguments before, is now inlined too).
#:
#: Not cached on its own: its code lives in its callers' cache entries (a caller loaded
#: from the cache never loads it), so an entry of its own would only be read by a process
#: that compiles another caller, and writing one costs more than it saves there. Measured
#: on a first start's critical path, the round burr's tick (49 such helpers): 26–28 s with
#: entries, 22–24 s without; ``burrforce compile`` as a whole used the same CPU time.
hot_inline = njit(**{**_OPTIONS, "cache": False}, forceinline=True)


def hot_hook(stub):
    """Decorate the typing function of a shape hook (``bone.cutters``): an overload of
    ``stub`` whose implementation the typing function picks by its arguments' types, inlined
    into the calling kernel by LLVM as ``hot_inline`` is. Hooks must be defined at module
    level, where numba's cache finds them again."""
    options = {k: v for k, v in _OPTIONS.items() if k != "cache"} | {"forceinline": True}
    return overload(stub, jit_options=options)


class DirectCall:
    """One hot kernel bound to the arguments its caller passes unchanged every call (its
    buffers and tables, the same objects each time), called without numba's dispatch.

    numba's dispatcher types every argument on every call before it unboxes them: ~35 ns an
    argument, 1.7 µs of the bone tick's 4.8 µs from Python for its 50 (measured far from bone,
    where the kernel itself does almost nothing). Here the specialization is looked up once,
    for the types of ``fixed`` and of ``example_tail``, and each call unboxes only. The
    caller's duty is what the dispatcher did: every call's trailing arguments must have the
    types of ``example_tail`` (an array of another dtype or layout would be read as if it had
    them), and ``fixed`` must still be the objects the kernel should see, as they were typed
    (an array made read-only since would be written all the same).

    Args:
        kernel: a ``hot_kernel``.  fixed: its leading arguments.
        example_tail: values of the types its trailing arguments will have on every call.
        owners: the objects ``fixed`` was taken from, kept for the caller to check by identity.
        previous: the binding this one replaces, if any: only the arguments that are not the
            very objects it bound are typed again (numba types in Python, ~7 µs an argument:
            binding all 50 of the bone tick's took ~0.35 ms, a stall in the tick after a
            parameter change), and its specialization is kept if the types are the same. A
            tuple (the burr's tables) is typed again item by item, the same way.
    """

    def __init__(self, kernel, fixed: tuple, example_tail: tuple, owners: tuple = (),
                 previous: DirectCall | None = None) -> None:
        same_shape = (previous is not None and previous.kernel is kernel
                      and len(previous.fixed) == len(fixed)
                      and len(previous.signature) == len(fixed) + len(example_tail))
        if same_shape:
            old = previous.signature
            signature = tuple(_retyped(kernel, a, previous.fixed[n], old[n])
                              for n, a in enumerate(fixed)) + old[len(fixed):]
        else:
            signature = tuple(kernel.typeof_pyval(a) for a in (*fixed, *example_tail))
        entry = (previous.entry if same_shape and signature == previous.signature
                 else kernel.compile(signature))
        self.kernel = kernel
        self.signature = signature
        self.entry = entry
        #: Call with the trailing arguments only (C-level: no Python frame per call).
        self.call = functools.partial(entry, *fixed)
        self.fixed = fixed
        self.owners = owners


def _retyped(kernel, value, old_value, old_type):
    """numba's type of ``value``, an argument that replaces ``old_value`` (of ``old_type``):
    the old type if it is the very object; for a tuple of the same class and length, the
    old items' types where the items are the very objects (``DirectCall``)."""
    if value is old_value:
        return old_type
    if (isinstance(value, tuple) and type(value) is type(old_value)
            and len(value) == len(old_value) and isinstance(old_type, types.BaseTuple)):
        items = tuple(old_type.types[n] if v is old_value[n] else kernel.typeof_pyval(v)
                      for n, v in enumerate(value))
        return types.BaseTuple.from_types(items, type(value))
    return kernel.typeof_pyval(value)
