"""Where the real scans live, for the tests marked ``real_data``.

The mOSD frames are external data (``../shared/data/mosd`` beside the checkout), not part of
the repository. A test that reads them is marked ``@pytest.mark.real_data("learn17.pcd", ...)``
with the frames it needs (``learn0.pcd`` when none is named); tests/conftest.py skips it,
naming the missing files, when they are absent. That set is the only one allowed to skip.
"""

from __future__ import annotations

from pathlib import Path

#: the Kinect frames of the mOSD data set (learn0.pcd ... with their labels)
MOSD = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mosd"

#: the frame a real_data test needs when its marker names none
DEFAULT_FRAME = "learn0.pcd"


def missing(frames: tuple[str, ...]) -> list[str]:
    """The frames (file names under :data:`MOSD`) that are not there."""
    return [f for f in (frames or (DEFAULT_FRAME,)) if not (MOSD / f).exists()]
