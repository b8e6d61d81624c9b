"""boxloc: localization of piled boxes in range scans.

The method is D. Katsoulas, "Localization of Piled Boxes by Means of the Hough
Transform", DAGM 2003 (LNCS 2781). The pipeline follows the paper's Fig. 2:

    range image -> edges -> 3D lines -> vertices -> hypotheses -> verify -> select

>>> import boxloc
>>> scan = boxloc.read_scan("scan.pcd")                        # doctest: +SKIP
>>> result = boxloc.find_graspable_surfaces(scan, boxloc.Config())  # doctest: +SKIP

The package reads top to bottom as the data flows:

* core: :mod:`boxloc.scan` (the range image and its sensor), :mod:`boxloc.config`,
  :mod:`boxloc.products` (one immutable dataclass per stage), :mod:`boxloc.stats` (the
  statistical tests), :mod:`boxloc.observer` (how products leave), :mod:`boxloc.pipeline`
  (the order of the stages) and :mod:`boxloc.cli`;
* :mod:`boxloc.stages`: one module per stage of Fig. 2;
* :mod:`boxloc.io`: scan files, one module per format;
* :mod:`boxloc.simulate`: scenes with exact ground truth, and the sensors that see them;
* :mod:`boxloc.calibrate`: sensor parameters estimated from scans;
* :mod:`boxloc.evaluate`: metrics, the open3d baseline and the benches.

This package is pure algorithm: it knows nothing of recording. Each stage returns an
immutable product and hands it to an optional :class:`boxloc.observer.Observer`.
The public names below load on first use, so that ``import boxloc`` (and ``boxloc --help``)
stays quick.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

# public name -> the module that defines it
_PUBLIC = {
    "find_graspable_surfaces": "boxloc.pipeline",
    "read_scan": "boxloc.io",
    "read_scans": "boxloc.io",
    "Scan": "boxloc.scan",
    "Config": "boxloc.config",
    "Result": "boxloc.products",
    "Observer": "boxloc.observer",
    "BoxlocError": "boxloc.errors",
}

__all__ = ["BoxlocError", "Config", "Observer", "Result", "Scan", "__version__",
           "find_graspable_surfaces", "read_scan", "read_scans"]
assert set(__all__) == {"__version__", *_PUBLIC}

if TYPE_CHECKING:
    from boxloc.config import Config
    from boxloc.errors import BoxlocError
    from boxloc.io import read_scan, read_scans
    from boxloc.observer import Observer
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.products import Result
    from boxloc.scan import Scan


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'boxloc' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
