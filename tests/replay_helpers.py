"""Small recorded logs for the diff / explain / side-by-side tests.

Scans are simulated at 160 x 120 pixels (f = 131.25 px, the 640 x 480 camera scaled down),
so the pipeline takes a few tens of milliseconds per scan. The tests do not pin what the
localizer finds on them (the algorithm keeps improving): they look up which scans have
surfaces and which exposed faces were missed, and only need the mix of a few of each,
which single boxes and small piles at this resolution reliably give; the empty scene is a
scan with no surface by construction.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from boxloc.config import Config
from boxloc.pipeline import find_graspable_surfaces
from boxloc.simulate import parse_spec, simulate
from recorder.mcap.sink import McapRecorder

SINGLE = "single:width=160,height=120,f=131.25"
MIXED = "mixed:width=160,height=120,f=131.25"
PALLET = "pallet:width=160,height=120,f=131.25"
#: the floor alone: a scan with nothing to find, whatever the localizer becomes
EMPTY = "empty:width=160,height=120,f=131.25"
#: (spec, seed) of scan 0, 1, 2, 3, 4, 5
SCENES: tuple[tuple[str, int], ...] = (
    (SINGLE, 0), (SINGLE, 2), (MIXED, 2), (MIXED, 3), (PALLET, 1), (EMPTY, 0))
ALL = tuple(range(len(SCENES)))


def sim(k: int) -> Any:
    """The SimulatedScan of scene k (scan index k)."""
    spec, seed = SCENES[k]
    s = simulate(parse_spec(spec), seed)
    return dataclasses.replace(s, scan=dataclasses.replace(s.scan, index=k))


def record(path: Path, config: Config | None = None,
           scenes: Sequence[int] = ALL, *, index_of: dict[int, int] | None = None
           ) -> Path:
    """Run the pipeline on the given scenes and record them to ``path``.

    ``index_of`` gives a scene another scan index (to build a log whose scan k is not the
    baseline's scan k).
    """
    cfg = config or Config()
    with McapRecorder(path, config=cfg, fsync=False) as rec:
        for k in scenes:
            scan = sim(k).scan
            if index_of and k in index_of:
                scan = dataclasses.replace(scan, index=index_of[k])
            find_graspable_surfaces(scan, cfg, observer=rec)
    return path


def missed_faces(log_path: Path) -> list[tuple[int, int, Any]]:
    """(scan index, face, SimulatedScan) of every fully exposed face no surface matched."""
    from boxloc.evaluate.metrics import match_surfaces
    from recorder.mcap.log import open_log

    out = []
    for r in open_log(log_path).scans():
        s = sim(r.index)
        m = match_surfaces(r.surfaces, s.truth)
        hit = {int(f) for _, f in m.tp_pairs}
        out += [(r.index, int(f), s) for f in range(len(s.truth.centers))
                if s.truth.fully_exposed[f] and int(f) not in hit]
    return out
