"""Compile boxloc's numba kernels into numba's on-disk cache; scripts/setup.sh runs it.

The kernels (``@kernel`` of :mod:`boxloc.kernels`, in the files of its ``KERNEL_SOURCES``),
run by numba's JIT, compile on their first call, about 90 s on one core, and are then
written to numba's cache: beside the sources
(``boxloc/stages/__pycache__/*.nbi, *.nbc``, and boxloc/calibrate's) for a checkout or an
editable install, or under
``NUMBA_CACHE_DIR`` when that is set (then it must be set the same way when boxloc runs).
An entry is valid until its source file changes (numba keys it on the file's time stamp and
size), so after a ``git pull`` that touches a kernel, running set-up again rebuilds it.
Set-up then compiles the same kernels ahead of time (``scripts/build_kernels.py``), which a
process running one scan uses instead; this cache serves every other process, and one
whose ahead-of-time module is missing or stale.

It first saves the line stage's direction tables
(:func:`boxloc.stages.lines.save_direction_tables`), which a process's first scan would
otherwise build. Running the whole pipeline once on a small simulated scan (160 x 120)
compiles every kernel with the argument types of any scan, since the stages convert their
inputs to float64 and int64 arrays first; then the first ``boxloc locate`` after set-up
loads compiled code, as the second does. Exit status 1 if a kernel was never called (a new
kernel the scan here does not reach: make it reach it). A kernel called only by others whose
entries are current while its own are not (a source changed and restored) is not a new
kernel: its source's entries are removed and the warm-up runs again, once.

Usage: python scripts/warm_up.py
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

#: Set in the second warm-up a stale cache asks for (there is no third).
_RETRY = "BOXLOC_WARM_UP_RETRY"


def kernels() -> dict[str, Any]:
    """Every numba dispatcher in the loaded boxloc modules, by qualified name."""
    from numba.core.registry import CPUDispatcher

    found = {}
    for name, mod in list(sys.modules.items()):
        if name == "boxloc" or name.startswith("boxloc."):
            for attr, obj in vars(mod).items():
                if isinstance(obj, CPUDispatcher) and obj.__module__ == name:
                    found[f"{name}.{attr}"] = obj
    return found


def compilations() -> int:
    """numba compilations so far in this process: cache misses of every boxloc kernel."""
    return sum(sum(k.stats.cache_misses.values()) for k in kernels().values())


def _cached(kernel: Any) -> bool:
    """Whether numba's cache holds code for KERNEL's current source (a kernel called only
    from other kernels gets no signatures in a process that loads its callers' code)."""
    try:  # numba's own check: the index is empty when the source's stamp changed
        return bool(kernel._cache._cache_file._load_index())
    except Exception:  # noqa: BLE001 - numba's private API moved: count it as not cached
        return False


def _seam_kernels() -> None:
    """The seam statistic with image rows sharing noise (``row_corr`` > 0, the Kinect's):
    the simulated scan above has none, so its kernel is called here on a few points."""
    import numpy as np

    from boxloc.stages.seams import seam_z

    coord = np.linspace(0.0, 0.1, 50)
    seam_z(coord, np.zeros(50), 0.001, np.array([0.05]), 0.005, np.arange(50) // 5, 0.25)


def _noise_kernels() -> None:
    """The calibration's robust std (``boxloc calibrate-noise``; the pipeline's per-scan fit
    takes its bins' in one kernel) and the tiles' design effect with correlated tiles (the
    simulated scan above has none): their kernels are called here on a few values."""
    import numpy as np

    from boxloc.calibrate.noise import _robust_std
    from boxloc.stages.scan_noise import design_effect

    _robust_std(np.linspace(-1.0, 1.0, 11))
    design_effect(np.arange(4) // 2, np.arange(4) % 2, np.array([0.5, 0.5, 0.5, 0.5]))


def warm_up_scan() -> Any:
    """The pipeline's Result on the warm-up's 160 x 120 simulated scan (every kernel)."""
    from boxloc.config import Config
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.simulate import scene_suite, simulate

    spec = scene_suite(1, 0)[0]
    spec = dataclasses.replace(spec, width=160, height=120,
                               f=float(spec.f) * 160 / spec.width)
    return find_graspable_surfaces(simulate(spec).scan, Config())


def warm_up() -> int:
    """Run the pipeline on a 160 x 120 simulated scan; print what was compiled or loaded.

    Returns
    -------
    int
        0 when every kernel has compiled code; 1 when one was never called.
    """
    from boxloc.stages.lines import default_direction_tables, save_direction_tables

    t0 = time.perf_counter()
    path = save_direction_tables()
    print(f"warm-up: the Hough direction tables of {len(default_direction_tables())} vote "
          f"caps saved to {path} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    t0 = time.perf_counter()
    warm_up_scan()
    _seam_kernels()
    _noise_kernels()
    found = kernels()
    compiled = compilations()
    loaded = sum(sum(k.stats.cache_hits.values()) for k in found.values())
    idle = sorted(n for n, k in found.items() if not k.signatures and not _cached(k))
    print(f"warm-up: {len(found)} numba kernels, {compiled} compiled and cached, {loaded} "
          f"loaded from the cache, in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    if idle and not os.environ.get(_RETRY):
        # numba keys a cache entry on its source file's stamp, per kernel: after a source is
        # changed and restored, a caller's entry can be current and its callees' not, and a
        # process that loads the caller never compiles them. Drop those files' entries and
        # warm up again in a new process (this one has loaded the callers).
        stale = _cache_files([found[n] for n in idle])
        for f in stale:
            f.unlink(missing_ok=True)
        print(f"warm-up: {', '.join(idle)} not cached beside their callers: "
              f"{len(stale)} cache files of their sources removed, warming up again",
              file=sys.stderr)
        return subprocess.run([sys.executable, *sys.argv], env={**os.environ, _RETRY: "1"},
                              check=False).returncode
    if idle:
        print(f"warm-up: never called, so not cached: {', '.join(idle)}", file=sys.stderr)
        return 1
    return 0


def _cache_files(dispatchers: list[Any]) -> list[Path]:
    """numba's cache files (index and data) of every kernel in the source files that hold
    these dispatchers."""
    out: set[Path] = set()
    for k in dispatchers:
        try:  # numba's private API, as _cached: where this kernel's entries are written
            where = Path(k._cache._cache_path)
        except Exception:  # noqa: BLE001 - nothing to remove then; the retry says so
            continue
        stem = Path(k.py_func.__code__.co_filename).stem
        out.update(p for p in where.glob(f"{stem}.*") if p.suffix in (".nbi", ".nbc"))
    return sorted(out)


if __name__ == "__main__":
    # numba's cache is what this fills: the JIT's kernels, not the ahead-of-time module's
    # (boxloc.kernels; a process falls back to the cache if it cannot use that module)
    os.environ["BOXLOC_KERNELS"] = "jit"
    sys.exit(warm_up())
