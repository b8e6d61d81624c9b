"""Fuzzing the readers: mutated logs, mutated and adversarial scan files, degenerate scans.

Every case is one bad (or odd) input handed to the code that reads untrusted data:

``log-bytes``
    A log (the repository's sample logs, or small logs made here) with its bytes mutated:
    truncated, bits flipped, spans overwritten, inserted, deleted, duplicated or zeroed,
    two logs spliced, a record's length or opcode changed, a chunk's content mutated with
    its CRC fixed (so the records inside reach the parsers), or its pick-outcome sidecar
    mutated.
``log-records``
    A small log rewritten as a *valid* MCAP file whose content is hostile: a message's
    protobuf fields (array shapes, dtypes, filters, names, data, record versions, image
    sizes), the ``boxloc.run`` metadata (config and sensor JSON), attachment names, channel
    topics, message order and sequence numbers.
``npz``, ``image``, ``cloud``
    Scan files: ``.npz`` with adversarial arrays (NaN and inf storms, zero sizes, absurd
    shapes declared in the ``.npy`` header, int, complex, object, bool, float16 dtypes),
    PNG/TIFF depth images (adversarial content, headers claiming huge sizes, other formats
    under a depth-image name), organized PCD/PLY clouds (adversarial content and headers),
    and byte mutations of valid files of each format.
``bag``
    ROS 2 bags (:mod:`boxloc.io.rosbag`): a small ``.mcap`` and ``.db3`` bag with their bytes
    mutated, or written valid by ``rosbags`` with hostile messages (image sizes, steps,
    encodings and data lengths that disagree, non-finite or zero intrinsics, distortion,
    unorganized or malformed clouds, degenerate or cyclic /tf). Every frame read is recorded
    and read back bit for bit; a damaged bag must end in one clean error.
``scan``, ``pipeline``
    :class:`boxloc.scan.Scan`, :meth:`~boxloc.scan.Scan.from_points` and the sensor models on
    adversarial arrays, and :func:`boxloc.pipeline.find_graspable_surfaces` (recorded, read
    back and compared bit for bit) on tiny degenerate scans: one valid pixel, all-equal
    range, a single plane, one row, extreme scales.

A log is opened strictly and with ``allow_truncated``, every scan is decoded, it is
recovered with :func:`recorder.mcap.recover.recover_log` and the recovered log read back, and
``boxloc info`` is computed for it. A scan file that reads is recorded to a log and read
back bit for bit.

Each case ends as one of

* ``ok``: handled (read, recovered, localized);
* ``error``: a clean refusal, a :class:`~boxloc.errors.BoxlocError` (``InputError``,
  ``LogError``, ``RecordingError``) with a one-line message;
* ``failure``: anything else: another exception (a crash traceback), a multi-line error
  message, a case that ran longer than ``timeout_s`` (the worker is killed), a worker that
  died, or a case whose peak resident memory grew by more than ``mem_bound_mb`` (measured
  per case from ``VmHWM``, reset through ``/proc/self/clear_refs``; workers also run under
  an address-space limit, so a runaway allocation fails instead of exhausting the machine).

Cases run in worker processes; each case is generated from ``(seed, case index)`` and the
corpus alone, byte for byte: not from ``PYTHONHASHSEED``, the clock, or the cases its worker
ran before. So a case can be regenerated; the corpus itself is built per run (its logs hold
wall-clock timings), and ``python -m recorder.fuzz --write-cases DIR --corpus C`` writes
the inputs of a run's cases from a shared corpus without running them, to compare two runs.
The input of every failing case is saved under ``workdir/failures/case-NNNNN/`` with
``case.json`` (what failed, the traceback); ``python -m recorder.fuzz --case DIR`` runs it
again in-process.

Registered as the ``fuzz`` section of ``boxloc bench`` (entry-point group ``boxloc.bench``);
``boxloc bench --fuzz N`` runs only it, with N cases.

Modules
-------
:mod:`~recorder.fuzz.cases`, :mod:`~recorder.fuzz.generate`
    What a case is, the plan of a run; each category's generator.
:mod:`~recorder.fuzz.corpus`, :mod:`~recorder.fuzz.mutate`
    The valid inputs to mutate; byte, record and chunk mutations.
:mod:`~recorder.fuzz.log_bytes`, :mod:`~recorder.fuzz.log_records`
    The ``log-bytes`` and ``log-records`` cases.
:mod:`~recorder.fuzz.scan_files`, :mod:`~recorder.fuzz.npz_files`,
:mod:`~recorder.fuzz.image_files`, :mod:`~recorder.fuzz.cloud_files`
    The scan-file cases (what they share, then one module per format).
:mod:`~recorder.fuzz.degenerate`, :mod:`~recorder.fuzz.bags`
    The ``scan`` and ``pipeline`` cases; the ``bag`` cases.
:mod:`~recorder.fuzz.execute`, :mod:`~recorder.fuzz.pool`, :mod:`~recorder.fuzz.run`
    One case in this process; the worker processes; a run and its report.
:mod:`~recorder.fuzz.cli`
    The bench section and ``python -m recorder.fuzz``.
"""

from __future__ import annotations

from recorder.fuzz.bags import bag_steps
from recorder.fuzz.cases import (
    CATEGORIES,
    DEFAULT_MEM_BOUND_MB,
    DEFAULT_TIMEOUT_S,
    Case,
    Job,
    Step,
    plan,
)
from recorder.fuzz.cli import fuzz_section, main, reproduce
from recorder.fuzz.cloud_files import pcd_bytes, ply_bytes
from recorder.fuzz.corpus import build_corpus, default_sample_logs
from recorder.fuzz.execute import run_case, run_step, save_failure
from recorder.fuzz.generate import generate
from recorder.fuzz.log_bytes import log_steps
from recorder.fuzz.log_records import LogModel, read_log_model, write_log_model
from recorder.fuzz.mutate import _mutate_chunk_content, _mutate_record_frame, mutate_bytes
from recorder.fuzz.npz_files import PICKLE_BOMB
from recorder.fuzz.run import run_fuzz, summarize
from recorder.fuzz.scan_files import scan_file_steps

__all__ = [
    "CATEGORIES", "DEFAULT_MEM_BOUND_MB", "DEFAULT_TIMEOUT_S", "PICKLE_BOMB",
    "Case", "Job", "LogModel", "Step",
    "_mutate_chunk_content", "_mutate_record_frame",
    "bag_steps", "build_corpus", "default_sample_logs", "fuzz_section", "generate",
    "log_steps", "main", "mutate_bytes", "pcd_bytes", "plan", "ply_bytes", "read_log_model",
    "reproduce", "run_case", "run_fuzz", "run_step", "save_failure", "scan_file_steps",
    "summarize", "write_log_model",
]
