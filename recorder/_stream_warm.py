"""Imported by the forkserver of :mod:`recorder.stream` only: warm the workers' first scan.

Importing this module runs the pipeline on a small simulated scan (160 x 120), which loads
every kernel's compiled code from numba's cache (about half a second) where the kernels are
not compiled ahead of time, and builds the tables a first scan builds (the Hough direction
tables). The workers are forked from the server afterwards and inherit both, so none of
them pays it again on its first scan. Nothing here changes a result: the kernels are the
same code either way. (With the kernels compiled ahead of time the scan takes 0.3 s; runs
of 2 and 32 scans with and without it differed by less than this machine's noise.)

Never import it in a process that runs scans itself (it would only cost time there); a
failure here is swallowed, since the workers then simply load the kernels on their own.
"""

from __future__ import annotations


def _warm() -> None:
    import dataclasses

    from boxloc.config import Config
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.simulate import scene_suite, simulate

    # the scan scripts/warm_up.py compiles the kernels with: it reaches every one of them
    spec = scene_suite(1, 0)[0]
    spec = dataclasses.replace(spec, width=160, height=120, f=float(spec.f) * 160 / spec.width)
    find_graspable_surfaces(simulate(spec).scan, Config())


try:
    _warm()
except Exception:  # noqa: BLE001, S110 - an optimization only; a forkserver must not die here
    pass
