"""Simulated scans as ``.npz`` files: writing them with their truth, reading the truth back,
and the ``boxloc simulate`` command's paths and summary lines.
"""

from __future__ import annotations

import json
import math
import os
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from boxloc.errors import InputError
from boxloc.products import from_arrays, to_arrays
from boxloc.scan import PinholeModel
from boxloc.simulate.scene import SimulatedScan, simulate
from boxloc.simulate.spec import SceneSpec, parse_spec
from boxloc.simulate.truth import GroundTruth

__all__ = ["save_npz", "load_truth", "output_paths", "simulate_to_files", "summary_line"]

_JSON_SEP = (",", ":")
_TRUTH = "truth/"


def save_npz(sim: SimulatedScan, path: str | os.PathLike[str]) -> None:
    """Write a simulated scan and its truth to ``path`` (written as given), atomically.

    Keys: ``points`` (H, W, 3) float32, ``intrinsics`` (3, 3), ``range`` (H, W) float32,
    ``sensor_to_base`` (4, 4), ``capture_time_ns`` 0-d int64, ``spec`` (JSON string) and
    ``truth/<field>`` for every :class:`GroundTruth` field. The scan keys are the public
    layout :func:`boxloc.io.read_scan` reads. The same scan always gives the same bytes.
    """
    if not isinstance(sim, SimulatedScan):
        raise TypeError(f"sim must be a SimulatedScan, got {type(sim).__name__}")
    scan = sim.scan
    assert isinstance(scan.sensor, PinholeModel)
    arrays: dict[str, np.ndarray] = {
        "points": np.ascontiguousarray(scan.points, dtype=np.float32),
        "intrinsics": scan.sensor.K,
        "range": np.ascontiguousarray(scan.range, dtype=np.float32),
        "sensor_to_base": np.asarray(scan.sensor_to_base, dtype=np.float64),
        "capture_time_ns": np.asarray(scan.capture_time_ns, dtype=np.int64),
        "spec": np.asarray(json.dumps(sim.spec.to_dict(), sort_keys=True, separators=_JSON_SEP)),
    }
    arrays.update(to_arrays(sim.truth, prefix=_TRUTH))
    from boxloc.io import write_arrays_npz  # io reads scans; it does not need the simulator

    write_arrays_npz(path, arrays)


def load_truth(path: str | os.PathLike[str]) -> GroundTruth | None:
    """The ground truth stored in an ``.npz`` by :func:`save_npz`; None if it has none.

    Raises
    ------
    InputError
        The file is missing, not an ``.npz``, or its truth is incomplete or corrupt.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"scan file not found: {p}")
    try:
        with np.load(p, allow_pickle=False) as z:
            arrays = {k[len(_TRUTH):]: z[k] for k in z.files if k.startswith(_TRUTH)}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        raise InputError(f"{p}: cannot read the .npz: {str(e).splitlines()[0]}") from None
    if not arrays:
        return None
    try:
        return from_arrays(GroundTruth, arrays)
    except KeyError as e:
        raise InputError(f"{p}: incomplete ground truth: {e.args[0]}") from None
    except (ValueError, TypeError) as e:
        raise InputError(f"{p}: bad ground truth: {str(e).splitlines()[0]}") from None


def output_paths(out: str | os.PathLike[str], spec: SceneSpec, seeds: list[int],
                 numbered: bool) -> list[Path]:
    """Where ``boxloc simulate`` writes each scan.

    An existing directory (or a path ending in a separator) gets ``KIND_SEED.npz`` files;
    otherwise ``numbered`` gives ``STEM_000.npz``, ``STEM_001.npz``... next to ``out``, and a
    single scan goes to ``out`` itself (``.npz`` appended if missing).
    """
    text = os.fspath(out)
    p = Path(text)
    if p.is_dir() or text.endswith(("/", os.sep)):
        return [p / f"{spec.kind}_{s:04d}.npz" for s in seeds]
    stem = p.name[:-4] if p.name.endswith(".npz") else p.name
    if numbered:
        return [p.with_name(f"{stem}_{i:03d}.npz") for i in range(len(seeds))]
    return [p.with_name(stem + ".npz")]


def simulate_to_files(spec: SceneSpec | str, out: str | os.PathLike[str],
                      seed: int | None = None,
                      count: int | None = None) -> Iterator[tuple[Path, SimulatedScan]]:
    """Simulate ``count`` scans (seeds ``seed``, ``seed + 1``...) and save each as ``.npz``.

    Yields ``(path, sim)`` after each file is written (paths from :func:`output_paths`).

    Raises
    ------
    InputError
        A bad spec, a count < 1, or an output directory that does not exist.
    """
    if isinstance(spec, str):
        spec = parse_spec(spec)
    if count is not None and (isinstance(count, bool) or count < 1):
        raise InputError(f"count must be >= 1, got {count}")
    base = spec.seed if seed is None else seed
    if isinstance(base, bool) or not isinstance(base, int) or base < 0:
        raise InputError(f"seed must be an integer >= 0, got {base!r}")
    seeds = [base + i for i in range(count or 1)]
    paths = output_paths(out, spec, seeds, numbered=count is not None)
    parent = paths[0].parent
    if os.fspath(out).endswith(("/", os.sep)):
        parent.mkdir(parents=True, exist_ok=True)
    if not parent.is_dir():
        raise InputError(f"output directory does not exist: {parent}")
    for path, s in zip(paths, seeds):
        sim = simulate(spec, seed=s)
        save_npz(sim, path)
        yield path, sim


def summary_line(path: str | os.PathLike[str], sim: SimulatedScan) -> str:
    """One line about a saved scan: boxes, faces, graspable faces, sensor distance and tilt."""
    t = sim.truth
    sp = sim.spec
    return (f"{os.fspath(path)}: {sp.kind} seed={sp.seed} boxes={t.boxes.shape[0]} "
            f"faces={len(t)} graspable={int(t.fully_exposed.sum())} "
            f"distance={sp.distance:.2f}m tilt={math.degrees(sp.tilt or 0.0):.1f}deg"
            + (f" sensor={sp.sensor}" + (f"/{sp.sensor_class}" if sp.sensor_class else "")
               + f" noise_scale={sp.noise_scale:g}" if sp.sensor else ""))
