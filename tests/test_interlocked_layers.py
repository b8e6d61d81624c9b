"""scripts/interlocked_layers.py: a grid and a basket weave with the same outline."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "interlocked_layers.py"


def _module() -> Any:
    spec = importlib.util.spec_from_file_location("interlocked_layers", SCRIPT)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _outline(boxes: np.ndarray) -> tuple[float, float, float, float]:
    x0 = float((boxes[:, 0] - boxes[:, 3] / 2).min())
    x1 = float((boxes[:, 0] + boxes[:, 3] / 2).max())
    y0 = float((boxes[:, 1] - boxes[:, 4] / 2).min())
    y1 = float((boxes[:, 1] + boxes[:, 4] / 2).max())
    return x0, x1, y0, y1


@pytest.mark.parametrize("seed", range(6))
def test_grid_and_weave_fill_the_same_outline_without_overlap(seed: int) -> None:
    m = _module()
    grid, (a, b, h) = m.layer(np.random.default_rng([seed, 0]), "grid")
    weave, size = m.layer(np.random.default_rng([seed, 0]), "weave")
    assert size == (a, b, h) and b == 2 * a
    assert len(grid) == len(weave)
    np.testing.assert_allclose(_outline(grid), _outline(weave), atol=1e-12)
    x0, x1, y0, y1 = _outline(weave)
    # an odd number of short edges wide: a grid of the carton one way only
    nx = round((x1 - x0) / a)
    assert nx % 2 == 1 and (x1 - x0) == pytest.approx(nx * a)
    # the cartons tile it: their areas add up to it, and no two overlap
    assert float((weave[:, 3] * weave[:, 4]).sum()) == pytest.approx((x1 - x0) * (y1 - y0))
    for B in (grid, weave):
        lo, hi = B[:, :2] - B[:, 3:5] / 2, B[:, :2] + B[:, 3:5] / 2
        ov = (np.minimum(hi[:, None], hi[None]) - np.maximum(lo[:, None], lo[None])).clip(0)
        area = ov[..., 0] * ov[..., 1]
        np.fill_diagonal(area, 0.0)
        assert area.max() < 1e-9
    # the grid lays every carton along y; the weave turns at least one cell
    assert (grid[:, 3] == a).all() and (weave[:, 3] == b).any()


def test_run_reports_each_pattern_and_sensor() -> None:
    rep = _module().run(2, 0)
    assert [s["pattern"] for s in rep["scenes"]] == ["weave", "weave"]
    assert set(rep["groups"]) == {"weave", "weave/laser", "weave/tof"}
    assert rep["groups"]["weave"]["scenes"] == 2
