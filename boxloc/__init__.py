"""boxloc: localization of piled boxes in range scans.

The method is D. Katsoulas, "Localization of Piled Boxes by Means of the Hough
Transform", DAGM 2003 (LNCS 2781). The pipeline follows the paper's Fig. 2:

    range image -> edges -> 3D lines -> vertices -> hypotheses -> verify -> select

This package is pure algorithm: it knows nothing of recording. Each stage returns an
immutable product (see :mod:`boxloc.products`) and hands it to an optional
:class:`boxloc.observer.Observer`.
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__"]
