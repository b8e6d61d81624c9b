"""``boxloc import``: turn a folder of real scans into an MCAP log, without running anything.

Field data then flows through ``run``, ``replay`` and ``diff`` like any recording:
``boxloc import frames/ --out field.mcap`` then ``boxloc run field.mcap --record out.mcap``.

Every scan is written with :meth:`recorder.mcap.sink.McapRecorder.record_scan`: the range bit
for bit, the sensor model, the pose if the file has one, and, for PCD/PLY files with an
integer ``label`` field (mOSD), the labels on ``/scan/labels`` so that logs can be scored.
Scans are numbered 0, 1, ... in the order given (files of a directory in name order, as
:func:`boxloc.io.read_scans` reads them); a file without a capture time gets none, so its
log time is ``index * 100 ms`` (:func:`recorder.mcap.channels.scan_log_time`): deterministic,
never the clock.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import click
import numpy as np

from boxloc.cli import config_options, load_config, scan_options
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.scan import Scan
from recorder.commands import rosbag_options

__all__ = ["ImportReport", "import_scans", "import_cmd"]

_LABELLED = (".pcd", ".ply")


@dataclass(frozen=True)
class ImportReport:
    """What :func:`import_scans` wrote.

    Attributes
    ----------
    paths : list of Path
        The log file(s) written (more than one only with rotation).
    n_scans : int
    n_labelled : int
        Scans recorded with their labels.
    sources : list of str
        The file of each scan, in index order.
    """

    paths: list[Path]
    n_scans: int
    n_labelled: int
    sources: list[str]


def _scans(sources: Sequence[str | os.PathLike[str]], *, intrinsics: Any,
           depth_scale: float | None, max_pixels: int, **bag: Any) -> Iterator[Scan]:
    from boxloc.io import read_scans

    for src in sources:
        yield from read_scans(src, intrinsics=intrinsics, depth_scale=depth_scale,
                              max_pixels=max_pixels, **bag)


def _labels_of(scan: Scan, max_pixels: int) -> np.ndarray | None:
    """The scan file's integer ``label`` field, or None when it has none."""
    from boxloc.io import read_labels

    p = Path(scan.source)
    if p.suffix.lower() not in _LABELLED:
        return None
    try:
        lab = read_labels(p, max_pixels=max_pixels)
    except InputError as e:
        if "no 'label' field" in str(e):
            return None
        raise
    return lab if lab.shape == scan.shape else None


def import_scans(
    sources: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    *,
    intrinsics: Any = None,
    depth_scale: float | None = None,
    config: Config | None = None,
    labels: bool = True,
    overwrite: bool = False,
    rotate_bytes: int | None = None,
    depth_topic: str | None = None,
    info_topic: str | None = None,
    base_frame: str | None = None,
) -> ImportReport:
    """Record the scans of ``sources`` (files or directories) into an MCAP log.

    Parameters
    ----------
    sources : sequence of path
        Scan files or directories of them (see :func:`boxloc.io.read_scans`), in order.
    out : path
        The log ``NAME.mcap`` (or a directory, which receives a session file).
    intrinsics, depth_scale
        As for :func:`boxloc.io.read_scan` (depth images need both).
    config : Config, optional
        Stored as the log's config: ``boxloc run LOG.mcap`` runs with it unless given
        ``--config``. Default ``Config()``.
    labels : bool
        Record the ``label`` field of PCD/PLY files that have one.
    overwrite : bool
        Replace an existing log.
    rotate_bytes : int, optional
        Start a new file when the current one reaches this size.
    depth_topic, info_topic, base_frame : str, optional
        For ROS 2 bags (:func:`boxloc.io.rosbag.open_bag`); each scan keeps the bag, topic and
        message times in its ``source`` and ``meta["rosbag"]``.

    Returns
    -------
    ImportReport

    Raises
    ------
    InputError
        No source, an unreadable scan (the log written so far is finished and valid), an
        existing output without ``overwrite``.
    """
    from recorder.mcap.sink import McapRecorder

    if not sources:
        raise InputError("import needs at least one scan file or directory")
    cfg = config or Config()
    scans = _scans(sources, intrinsics=intrinsics, depth_scale=depth_scale,
                   max_pixels=cfg.max_pixels, depth_topic=depth_topic, info_topic=info_topic,
                   base_frame=base_frame)
    first = next(scans, None)  # a bad first file is refused before any log is created
    if first is None:
        raise InputError("no scan was imported")
    written: list[str] = []
    n_labelled = 0
    with McapRecorder(out, config=cfg, overwrite=overwrite, rotate_bytes=rotate_bytes) as rec:
        scan: Scan | None = first
        while scan is not None:
            i = len(written)
            if scan.index != i:  # number the scans across all sources
                scan = dataclasses.replace(scan, index=i)
            lab = _labels_of(scan, cfg.max_pixels) if labels else None
            rec.record_scan(scan, cfg, labels=lab)
            n_labelled += lab is not None
            written.append(scan.source)
            try:
                scan = next(scans, None)
            except InputError as e:
                raise InputError(f"{e} (the log keeps the {len(written)} scan(s) imported "
                                 "before it)") from None
    return ImportReport(paths=list(rec.paths), n_scans=len(written), n_labelled=n_labelled,
                        sources=written)


@click.command("import")
@click.argument("sources", metavar="SRC...", nargs=-1, required=True, type=click.Path())
@click.option("--out", "-o", "out", required=True, type=click.Path(),
              metavar="LOG.mcap", help="The log to write.")
@click.option("--no-labels", is_flag=True,
              help="Do not record the 'label' field of PCD/PLY files.")
@click.option("--force", is_flag=True, help="Overwrite an existing LOG.mcap.")
@click.option("--rotate-size", type=click.FloatRange(min=0.001), default=None, metavar="MB",
              help="Start a new MCAP file when the current one reaches MB megabytes.")
@rosbag_options
@scan_options
@config_options
def import_cmd(sources: tuple[str, ...], out: str, no_labels: bool, force: bool,
               rotate_size: float | None, depth_topic: str | None, info_topic: str | None,
               base_frame: str | None, intrinsics: str | None, depth_scale: float | None,
               config_path: str | None, overrides: tuple[str, ...]) -> None:
    """Record real scans (files, directories or ROS 2 bags, in order) into an MCAP log,
    without running the localizer: `boxloc run LOG.mcap` processes them later.

    Each scan keeps its range bit for bit and its sensor model; PCD/PLY labels (mOSD ground
    truth) go on /scan/labels; a bag's frames keep the bag, topic and message times.
    --config/--set set the config stored with the log.
    """
    cfg = load_config(config_path, overrides)
    rep = import_scans(sources, out, intrinsics=intrinsics, depth_scale=depth_scale,
                       config=cfg, labels=not no_labels, overwrite=force,
                       rotate_bytes=None if rotate_size is None else int(rotate_size * 1e6),
                       depth_topic=depth_topic, info_topic=info_topic, base_frame=base_frame)
    paths = ", ".join(str(p) for p in rep.paths)
    click.echo(f"imported {rep.n_scans} scan(s) ({rep.n_labelled} with labels) -> {paths}",
               err=True)
