"""The scan's sensor model: a pinhole camera's rays."""

from __future__ import annotations

import numpy as np
import pytest

from boxloc.scan import PinholeModel


def _rays_by_norm(fx: float, fy: float, cx: float, cy: float, w: int, h: int) -> np.ndarray:
    """The rays as first written: (x, y, 1) on the pixel grid over np.linalg.norm."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    d = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


@pytest.mark.parametrize("fx,fy,cx,cy,w,h", [
    (525.0, 525.0, 319.5, 239.5, 640, 480),    # the Kinect frames'
    (1050.0, 1049.3, 641.7, 478.2, 1280, 960),  # unequal focal lengths, an odd centre
    (290.0, 290.0, 400.0, -20.0, 320, 240),     # the centre off the image
])
def test_pinhole_rays_are_the_normalized_grid_bit_for_bit(fx, fy, cx, cy, w, h) -> None:
    """The rays built from their columns' and rows' terms are the normalized (x, y, 1) of
    every pixel, bit for bit (every range, point and test downstream is built on them)."""
    d = PinholeModel(fx, fy, cx, cy, w, h).rays()
    assert d.shape == (h, w, 3) and d.dtype == np.float64 and not d.flags.writeable
    ref = _rays_by_norm(fx, fy, cx, cy, w, h)
    assert np.array_equal(d.view(np.uint64), ref.view(np.uint64))
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0, rtol=0, atol=1e-15)
