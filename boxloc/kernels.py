"""Compiled kernels: the numba code compiled ahead of time at set-up, or by numba's JIT.

Every numba kernel of boxloc is declared with :func:`kernel` instead of ``numba.njit``.
Set-up (``scripts/build_kernels.py``) compiles them all ahead of time into one extension
module, ``boxloc/_kernels_aot*.so``, with numba's own AOT compiler (``numba.pycc``), for
the argument types the pipeline calls them with. A process that finds that module, built
from the present sources, calls it and never imports numba: it saves numba's import and
the loading of every kernel from numba's cache (about 1.5 s before the first scan of a
process, where the scan itself takes about half a second). Without it (no C compiler at
set-up, or a source changed since), each kernel is ``numba.njit(cache=True)`` as before.

The compiled code is the same either way: the extension module calls the very kernels
numba's JIT compiles, and set-up checks that a scan's products are the same bit for bit
before it keeps the module (``scripts/build_kernels.py``).

A call whose argument types the module was not built for (another dtype, a strided array,
a read-only one where the kernel writes) would be unsafe there: the module's wrappers do
not check types. So each kernel's wrapper checks them first (dtype, dimensions, layout,
writability; scalars by type, as numba's ``typeof`` would see them). A call that matches
none of its signatures switches the whole process to numba's JIT (with a warning), so that
kernels calling kernels stay one kind, and the call is compiled as before.

Which one a process uses: ``BOXLOC_KERNELS`` = ``auto`` (the default) uses the module when
it is there and current, else numba's JIT; ``aot`` requires the module (an error if it is
missing or stale); ``jit`` always uses numba's JIT. The compiled code runs as fast either
way (within this machine's noise, 32 matrix scans alternating), but a call costs a little
more: numba's dispatcher checks the arguments in C, the wrappers here in Python, 2-3
microseconds more per call, some 3,000-5,000 calls a 640 x 480 scan (about 1 % of it).
Against that, every process saves 1.3 s at its start (docs/benchmarks.md, "Start-up").
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.util
import inspect
import json
import os
import platform
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar, overload

import numpy as np

from boxloc.errors import InputError

__all__ = ["ENV", "KERNEL_SOURCES", "AotStatus", "aot_status", "kernel", "mode",
           "sources_digest"]

F = TypeVar("F", bound=Callable[..., Any])

#: Environment variable choosing the kernels: ``jit``, ``aot`` or ``auto`` (the default).
ENV = "BOXLOC_KERNELS"
#: The files that hold kernels (relative to this package), and this one: the ahead-of-time
#: module is current while their digest is the one it was built from.
KERNEL_SOURCES = ("kernels.py", "stages/edges.py", "stages/lines.py", "stages/raster.py",
                  "stages/scan_noise.py", "stages/seams.py", "stages/verify.py",
                  "calibrate/noise.py")
#: The extension module set-up builds, and its description beside it (exports, digest,
#: versions).
AOT_MODULE = "boxloc._kernels_aot"
AOT_STAMP = "_kernels_aot.json"
#: Argument types a wrapper can check (numba's names): arrays, and these scalars.
SCALARS = {"int64": (int, np.int64), "float64": (float, np.float64), "bool": (bool, np.bool_)}


def sources_digest(root: Path | None = None) -> str:
    """SHA-256 of :data:`KERNEL_SOURCES` (under ``root``, default this package)."""
    base = Path(__file__).parent if root is None else root
    h = hashlib.sha256()
    for rel in KERNEL_SOURCES:
        h.update(rel.encode() + b"\0" + (base / rel).read_bytes() + b"\0")
    return h.hexdigest()


def _numba_version() -> str | None:
    """numba's installed version, from the name of its metadata directory (without
    importing numba, or importlib.metadata's scan of every distribution: 50 ms)."""
    spec = importlib.util.find_spec("numba")
    if spec is None or not spec.origin:
        return None
    for d in sorted(Path(spec.origin).parent.parent.glob("numba-*.dist-info")):
        return d.name[len("numba-"): -len(".dist-info")]
    return None


def build_facts() -> dict[str, Any]:
    """What an ahead-of-time module must have been built with to be used here, besides
    the sources: the versions of the compiler and the array ABI, and the machine."""
    return {"numba": _numba_version(), "numpy": np.__version__,
            "python": list(sys.version_info[:2]), "machine": platform.machine()}


@dataclass(frozen=True)
class AotStatus:
    """Whether the ahead-of-time module can be used, and why not."""

    usable: bool
    reason: str
    exports: dict[str, list[tuple[str, list[list[Any]]]]] = field(default_factory=dict)
    module: Any = None


def aot_status() -> AotStatus:
    """Find the ahead-of-time module and check it against the sources and versions."""
    spec = importlib.util.find_spec(AOT_MODULE)
    if spec is None or spec.origin is None:
        return AotStatus(False, "not built (scripts/build_kernels.py)")
    try:
        stamp = json.loads(Path(spec.origin).with_name(AOT_STAMP).read_text())
    except (OSError, ValueError) as e:
        return AotStatus(False, f"its description is unreadable: {e}")
    if stamp.get("sources") != sources_digest():
        return AotStatus(False, "built from other sources (run scripts/build_kernels.py)")
    facts = build_facts()
    if stamp.get("facts") != facts:
        return AotStatus(False, f"built with {stamp.get('facts')}, here {facts}")
    try:
        module = importlib.import_module(AOT_MODULE)
    except ImportError as e:
        return AotStatus(False, f"does not load: {e}")
    exports = {q: [(name, types) for name, types in sigs]
               for q, sigs in stamp.get("exports", {}).items()}
    return AotStatus(True, "current", exports, module)


@dataclass
class _State:
    mode: str  # "aot" or "jit"
    status: AotStatus
    #: every kernel declared so far, by qualified name: (function, numba options)
    kernels: dict[str, tuple[Callable[..., Any], dict[str, Any]]] = field(default_factory=dict)
    jit: dict[str, Any] = field(default_factory=dict)  # their numba dispatchers, once JIT


_STATE: _State | None = None


def _state() -> _State:
    global _STATE
    if _STATE is None:
        want = os.environ.get(ENV, "").strip().lower() or "auto"
        if want not in ("auto", "aot", "jit"):
            raise InputError(f"{ENV} must be auto, aot or jit, got {want!r}")
        status = AotStatus(False, f"{ENV}=jit") if want == "jit" else aot_status()
        if want == "aot" and not status.usable:
            raise InputError(f"{ENV}=aot, but the ahead-of-time kernels are {status.reason}")
        _STATE = _State("aot" if status.usable else "jit", status)
    return _STATE


def mode() -> str:
    """``"aot"`` or ``"jit"``: how this process runs its kernels (``"jit"`` from the first
    call no ahead-of-time signature matched)."""
    return _state().mode


def _njit(fn: Callable[..., Any], options: dict[str, Any]) -> Any:
    import numba

    return numba.njit(cache=True, **options)(fn)


@overload
def kernel(fn: F, /) -> F: ...
@overload
def kernel(**options: Any) -> Callable[[F], F]: ...
def kernel(fn: Any = None, /, **options: Any) -> Any:
    """Declare a numba kernel: ``@kernel`` or ``@kernel(error_model="numpy")``.

    ``options`` are ``numba.njit``'s (``cache=True`` always). Returns the compiled kernel:
    the ahead-of-time module's, behind a check of the argument types, or numba's
    dispatcher.
    """
    if fn is None:
        return lambda f: kernel(f, **options)
    st = _state()
    qual = f"{fn.__module__}.{fn.__qualname__}"
    st.kernels[qual] = (fn, options)
    if st.mode == "jit":
        st.jit[qual] = _njit(fn, options)
        return st.jit[qual]
    return _wrapper(qual, fn, st.status.exports.get(qual, []), st.status.module)


def _check(spec: list[Any]) -> Callable[[Any], bool]:
    """Whether an argument has the type ``spec`` (see scripts/build_kernels.py): an array's
    dtype, dimensions, layout and (where the kernel may write) writability; a scalar's
    Python or NumPy type, as numba's ``typeof`` would type it."""
    if spec[0] != "array":
        kinds = SCALARS[spec[0]]
        return lambda a: type(a) in kinds
    _, dtype, ndim, layout, readonly = spec
    dt, nd = np.dtype(dtype), int(ndim)
    c_order, f_order, write = layout == "C", layout == "F", not readonly

    def ok(a: Any) -> bool:
        if not isinstance(a, np.ndarray) or a.ndim != nd or a.dtype != dt:
            return False
        flags = a.flags
        return ((not c_order or flags.c_contiguous) and (not f_order or flags.f_contiguous)
                and (not write or flags.writeable))

    return ok


def _wrapper(qual: str, fn: Callable[..., Any], exports: list[tuple[str, list[list[Any]]]],
             module: Any) -> Callable[..., Any]:
    """``fn``'s ahead-of-time exports behind their argument checks; a call that matches
    none goes to numba's JIT (:func:`_to_jit`)."""
    table = [(getattr(module, name), [_check(s) for s in specs]) for name, specs in exports]
    signature = inspect.signature(fn)
    miss = _miss

    @functools.wraps(fn)
    def call(*args: Any, **kwargs: Any) -> Any:
        if kwargs:  # the kernel's own parameter names, as numba's dispatcher takes them
            args = signature.bind(*args, **kwargs).args
        for export, checks in table:
            if len(checks) == len(args):
                for check, a in zip(checks, args, strict=True):
                    if not check(a):
                        break
                else:
                    return export(*args)
        return miss(qual, args)

    call._boxloc_kernel = qual  # type: ignore[attr-defined]
    return call


def _miss(qual: str, args: tuple[Any, ...]) -> Any:
    """A call no ahead-of-time signature of ``qual`` matches: numba's JIT from now on."""
    kinds = ", ".join(f"{type(a).__name__}" + (f"[{a.dtype}, {a.ndim}d]"
                                               if isinstance(a, np.ndarray) else "")
                      for a in args)
    warnings.warn(f"boxloc: {qual}({kinds}) is not among the ahead-of-time kernels' "
                  "signatures; numba's JIT compiles every kernel from now on",
                  RuntimeWarning, stacklevel=3)
    return _to_jit()[qual](*args)


def _to_jit() -> dict[str, Any]:
    """Switch the process to numba's JIT: a dispatcher for every kernel, bound wherever a
    module of boxloc holds its ahead-of-time wrapper (so that a kernel calling a kernel
    calls a dispatcher)."""
    st = _state()
    if st.mode != "jit":
        st.jit = {q: _njit(fn, opts) for q, (fn, opts) in st.kernels.items()}
        st.mode = "jit"
        for name, mod in list(sys.modules.items()):
            if name.split(".")[0] != "boxloc":
                continue
            for attr, val in list(vars(mod).items()):
                q = getattr(val, "_boxloc_kernel", None)
                if isinstance(q, str) and q in st.jit and callable(val):
                    setattr(mod, attr, st.jit[q])
    return st.jit
