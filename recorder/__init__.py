"""Recording: MCAP logs (the record of truth) and Rerun views of every scan and product.

``recorder`` imports ``boxloc``; ``boxloc`` never imports ``recorder``.

The packages, in the order the data flows:

- :mod:`recorder.commands`: ``boxloc run``, ``info``, ``annotate``, ``recover``;
  :mod:`recorder.stream`: scans run in worker processes and handed to the recorders in scan
  order (``boxloc run --workers N``); :mod:`recorder.import_cmd`: ``boxloc import``.
- :mod:`recorder.mcap` (the record of truth): :mod:`~recorder.mcap.channels` (the log
  layout, one table of topic -> schema -> encoder/decoder), :mod:`~recorder.mcap.encode`
  (products and scans to messages and back, bit for bit), :mod:`~recorder.mcap.sink`
  (:class:`McapRecorder`, the observer that writes logs), :mod:`~recorder.mcap.log`
  (:func:`open_log`), :mod:`~recorder.mcap.recover` (:func:`recover_log`),
  :mod:`~recorder.mcap.footprint` (bytes per scan by channel) and
  :mod:`~recorder.mcap.ros2_publish` (the surfaces and ambiguous regions as a ROS 2
  bag).
- :mod:`recorder.rerun`: the Rerun view (:mod:`~recorder.rerun.sink`, one ``log_*`` per
  product; the blueprint; ``boxloc view``; the headless screenshot).
- :mod:`recorder.fuzz`: fuzzing every reader of untrusted data.
- :mod:`recorder.annotate`: pick outcomes in a sidecar next to a log;
  :mod:`recorder.overhead` and :mod:`recorder.recording_bench`: what recording costs.

The names below are imported lazily, so ``import recorder`` stays cheap.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_LAZY = {
    "McapRecorder": "recorder.mcap.sink",
    "RecordingError": "recorder.mcap.sink",
    "open_log": "recorder.mcap.log",
    "Log": "recorder.mcap.log",
    "ScanRecord": "recorder.mcap.log",
    "recover_log": "recorder.mcap.recover",
    "append_outcome": "recorder.annotate",
    "read_sidecar": "recorder.annotate",
    "PickOutcome": "recorder.mcap.encode",
    "measure_overhead": "recorder.overhead",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'recorder' has no attribute {name!r}")
