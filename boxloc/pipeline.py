"""The pipeline of the paper's Fig. 2; the only module that knows the order of the stages.

    range image -> (its noise) -> edges -> lines -> vertices -> find_graspable_surfaces
    -> select -> surfaces
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import TypeVar

import numpy as np

from boxloc import __version__
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.observer import NullObserver, Observer
from boxloc.products import EdgeMap, Result
from boxloc.scan import NoiseModel, Scan
from boxloc.stages.ambiguous import ambiguous_regions
from boxloc.stages.edges import detect_edges, noise_gain
from boxloc.stages.hypotheses import generate_hypotheses
from boxloc.stages.lines import find_lines
from boxloc.stages.scan_noise import estimate_scan_noise
from boxloc.stages.select import select
from boxloc.stages.surfaces import make_surfaces
from boxloc.stages.up import estimate_up
from boxloc.stages.vertices import find_vertices

T = TypeVar("T")


def _timed(timing: dict[str, float], name: str, fn: Callable[[], T]) -> T:
    t0 = time.perf_counter()
    out = fn()
    timing[name] = (time.perf_counter() - t0) * 1e3
    return out


def _edges(scan: Scan, config: Config) -> tuple[np.ndarray, EdgeMap]:
    """The scan's local noise gain (:func:`noise_gain`) and its edges, which use it."""
    gain = noise_gain(scan, config)
    return gain, detect_edges(scan, config=config, gain=gain)


def check_scan(scan: Scan, config: Config) -> None:
    """Refuse scans the localizer cannot work on, with a message naming the problem."""
    if not isinstance(scan, Scan):
        raise TypeError(f"scan must be a boxloc.scan.Scan, got {type(scan).__name__}")
    H, W = scan.shape
    if H * W > config.max_pixels:
        raise InputError(
            f"scan of {H}x{W} = {H * W} pixels exceeds max_pixels = {config.max_pixels}"
        )
    if not np.isfinite(scan.range).any():
        raise InputError("scan has no valid range (all NaN)")


def find_graspable_surfaces(
    scan: Scan, config: Config | None = None, observer: Observer | None = None
) -> Result:
    """Find the graspable (fully exposed) box surfaces in a range scan.

    Parameters
    ----------
    scan : Scan
        The range image and its sensor model.
    config : Config, optional
        alpha, the probability of success, the noise model and the priors.
    observer : Observer, optional
        Receives every stage's product, in order (the recorder).

    Returns
    -------
    Result
        All stage products; ``result.surfaces`` are the graspable surfaces in pick order.

    Notes
    -----
    The noise model every test uses is the scan's own (``config.noise_auto``, the
    default), estimated before the edges and handed over as the ``noise`` product.

    Randomness (the Hough trials) is seeded from the scan content (and
    ``config.trial_seed``, 0 by default), so the same scan and config always give the same
    result, bit for bit. Wall-clock time enters only
    ``Result.timing_ms``.

    References
    ----------
    D. Katsoulas, "Localization of Piled Boxes by Means of the Hough Transform", DAGM 2003.
    """
    config = config or Config()
    obs: Observer = observer if observer is not None else NullObserver()
    check_scan(scan, config)
    seed = config.seed_for(scan.seed)
    rng = np.random.default_rng(seed)
    timing: dict[str, float] = {}

    obs.on_scan(scan, config)
    user_config = config
    noise = _timed(timing, "noise", lambda: estimate_scan_noise(scan, user_config))
    obs.on_noise(scan, noise)
    # every later stage tests against the scan's model (the config's, when pinned)
    config = dataclasses.replace(user_config, noise=NoiseModel(**noise.noise_model()))
    # the local noise scale: the edge stage's and the seam tests', computed once
    gain, edges = _timed(timing, "edges", lambda: _edges(scan, config))
    obs.on_edges(scan, edges)
    lines = _timed(timing, "lines", lambda: find_lines(scan, edges, config=config, rng=rng))
    obs.on_lines(scan, lines)
    up = _timed(timing, "up", lambda: estimate_up(scan, config, rng))
    vertices = _timed(timing, "vertices", lambda: find_vertices(lines, config=config, up=up))
    # the hypothesis stage adds the corners of touching neighbours to the vertices
    vertices, hyps, verification = _timed(
        timing, "hypotheses",
        lambda: generate_hypotheses(scan, edges, vertices, config=config, up=up, gain=gain),
    )
    obs.on_vertices(scan, vertices)
    obs.on_hypotheses(scan, hyps)
    obs.on_verification(scan, verification)
    selection = _timed(timing, "select", lambda: select(verification, hyps, config=config))
    obs.on_selection(scan, selection)
    surfaces = _timed(
        timing, "surfaces",
        lambda: make_surfaces(scan, vertices, hyps, verification, selection, config),
    )
    obs.on_surfaces(scan, surfaces)
    # the flat regions not split into boxes: decided by the hypotheses stage, collected
    ambiguous = ambiguous_regions(hyps, verification, config, surfaces.attempt)
    timing["total"] = float(sum(timing.values()))

    result = Result(
        scan_index=scan.index,
        capture_time_ns=scan.capture_time_ns,
        seed=seed,
        config_hash=user_config.hash,
        version=__version__,
        edges=edges,
        lines=lines,
        vertices=vertices,
        hypotheses=hyps,
        verification=verification,
        selection=selection,
        surfaces=surfaces,
        timing_ms=timing,
        noise=noise,
        ambiguous=ambiguous,
    )
    obs.on_result(scan, result)
    return result
