"""Plain JSON values from the numpy-laden dicts of results, benchmarks and diffs."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np


def jsonable(x: Any) -> Any:
    """Strict-JSON form: numpy -> python, NaN/inf -> None, tuples -> lists."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.generic):
        return jsonable(x.item())
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if x is None or isinstance(x, bool | int | str):
        return x
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return jsonable(dataclasses.asdict(x))
    return repr(x)  # a section returned something JSON cannot hold: keep it readable


__all__ = ["jsonable"]
