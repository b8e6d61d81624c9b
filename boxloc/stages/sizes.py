"""Known carton sizes (issue #21, point 2): a rectangle's dimensions against the cell's
carton list (``Config.box_sizes``), and the splits of a flat region into listed cartons.

A rectangle of width w and length l matches listed size (W, L) if

    T = ((w - W)^2 + (l - L)^2) / sigma^2  <=  chi2_{2, 1-alpha}

in the nearer of the two orientations, with sigma = ``Config.size_tolerance`` (SKU_SIZE,
2 dof). A flat region of extent (U, V) along its two axes is nx x ny cartons of size
(a, b) laid along them (a along U) if

    T = (U - nx a)^2 / (nx sigma^2) + (V - ny b)^2 / (ny sigma^2)  <=  chi2_{2, 1-alpha}

(each carton's tolerance independent, so n of them in a row add n sigma^2), nx, ny >= 1
the nearest integers, nx ny >= 2: a multiple (2x1, 3x1, 2x2, ...). A grid is what the
extent implies only where no other tiling by the listed cartons fits it
(:func:`other_tiling`): a layer laid in a brick or pinwheel pattern has the outline of a
grid too. Such a layer is split only where its seams show how it is laid: the one tiling
whose every carton side inside the region is a seam that shows (:func:`seen_tilings`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from boxloc.stats import chi2_critical

#: Most cartons one flat region is split into (a 1.2 x 0.8 m pallet layer of the smallest
#: cartons a cell handles, 0.15 m, is 8 x 5 = 40).
MAX_PARTS = 64


def size_statistic(w: float, length: float, sizes: tuple[tuple[float, float, float], ...],
                   tolerance: float) -> np.ndarray:
    """SKU_SIZE's statistic against every listed size, (n,) float64 (the nearer of the two
    orientations; sizes are width <= length, so is the nearer one after sorting)."""
    if not sizes:
        return np.zeros(0)
    S = np.asarray([s[:2] for s in sizes], np.float64)
    a, b = sorted((float(w), float(length)))
    t1 = ((a - S[:, 0]) ** 2 + (b - S[:, 1]) ** 2) / tolerance**2
    t2 = ((a - S[:, 1]) ** 2 + (b - S[:, 0]) ** 2) / tolerance**2
    return np.minimum(t1, t2)


def match_size(w: float, length: float, sizes: tuple[tuple[float, float, float], ...],
               tolerance: float, alpha: float) -> tuple[int, float, float, bool]:
    """The listed size nearest a rectangle's dimensions, by SKU_SIZE.

    Returns
    -------
    sku : int
        The row of ``sizes`` with the smallest statistic (-1 if no list).
    statistic, critical : float
        Chi-square, 2 dof, and its critical value at alpha.
    matches : bool
    """
    crit = chi2_critical(2.0, alpha)
    T = size_statistic(w, length, sizes, tolerance)
    if not len(T):
        return -1, np.nan, crit, False
    j = int(np.argmin(T))
    return j, float(T[j]), crit, bool(T[j] <= crit)


@dataclass(frozen=True)
class Split:
    """One way of laying listed cartons over a flat region.

    Attributes
    ----------
    sku : int
        The row of ``Config.box_sizes``.
    a, b : float
        The carton's extent along the region's x and y axes, metres.
    nx, ny : int
        Cartons along x and y.
    statistic : float
        Chi-square (2 dof) of the region's extent against nx a, ny b.
    """

    sku: int
    a: float
    b: float
    nx: int
    ny: int
    statistic: float

    @property
    def parts(self) -> int:
        return self.nx * self.ny

    def cuts(self) -> tuple[list[float], list[float]]:
        """The implied seams' positions along x and y, metres from the region's origin."""
        return ([i * self.a for i in range(1, self.nx)], [j * self.b for j in range(1, self.ny)])


def region_splits(width: float, length: float, sizes: tuple[tuple[float, float, float], ...],
                  tolerance: float, alpha: float, multiples_only: bool = True) -> list[Split]:
    """Every listed size, in either orientation, of which a region of ``width`` x ``length``
    (along its x and y axes, metres) is a grid, by its chi-square at alpha; best first.

    With ``multiples_only`` a single carton (1 x 1) is not a split.
    """
    crit = chi2_critical(2.0, alpha)
    out: list[Split] = []
    for j, (w, ln, _) in enumerate(sizes):
        for a, b in {(w, ln), (ln, w)}:
            nx, ny = max(1, round(width / a)), max(1, round(length / b))
            if nx * ny > MAX_PARTS or (multiples_only and nx * ny < 2):
                continue
            T = ((width - nx * a) ** 2 / nx + (length - ny * b) ** 2 / ny) / tolerance**2
            if T <= crit:
                out.append(Split(j, float(a), float(b), int(nx), int(ny), float(T)))
    out.sort(key=lambda s: (s.statistic, s.sku, s.a))
    return out


def distinct(splits: list[Split]) -> list[Split]:
    """The splits that cut a region differently, best first.

    The parts are measured, the region's extent over the count along each axis
    (:func:`boxloc.stages.hypotheses._plan_split`), so two splits into the same grid
    (nx x ny) cut it at the same places, whichever listed sizes they fit: two sizes within
    the tolerance of each other, or one nearly square carton laid either way (0.534 x 0.545
    m, a region of two of them 1.091 x 0.538 m is 2 x 1 both ways). They are one split,
    the better fitting one.
    """
    out: list[Split] = []
    for s in splits:
        if not any(s.nx == o.nx and s.ny == o.ny for o in out):
            out.append(s)
    return out


@dataclass(frozen=True)
class Row:
    """The listed cartons along one side of a flat region, seen from corner to end.

    Attributes
    ----------
    ways : int
        Distinct ways the listed cartons' edges add up to the side's length (counts of
        each edge length; 2 stands for two or more). Only one way, all of one edge, says
        what lies along the side.
    exhausted : bool
        The search stopped at its budget before deciding.
    sku : int
        The row of ``Config.box_sizes`` of the cartons, -1 where the side does not say
        (not exactly one way; one way of mixed edges, which can lie in any order; or an
        edge shared by listed sizes of different depths).
    along, depth : float
        A carton's extent along the side and across it, metres (NaN without ``sku``).
    n : int
        Cartons along the side (0 without ``sku``).
    statistic : float
        Chi-square (1 dof) of the side's length against ``n`` ``along`` (n tolerances
        added), NaN without ``sku``.
    """

    ways: int
    exhausted: bool
    sku: int = -1
    along: float = np.nan
    depth: float = np.nan
    n: int = 0
    statistic: float = np.nan

    @property
    def unique(self) -> bool:
        """The side's length says which cartons line it."""
        return self.sku >= 0


def row_cartons(length: float, sizes: tuple[tuple[float, float, float], ...],
                tolerance: float, alpha: float, max_states: int = 20000) -> Row:
    """The cartons lining a side of a flat region of ``length`` metres, seen whole (from a
    corner to the region's end), where the listed sizes say (:class:`Row`).

    Every carton touching the side lies with one of its edges along it, so the side is a
    sum of listed edge lengths. Where exactly one sum fits (counts of each distinct edge,
    by chi-square at alpha, 1 dof, each carton's tolerance independent), every term is
    the same edge, and that edge belongs to listed sizes of one depth, the side is lined
    by ``n`` such cartons and they reach that depth into the region: a row of them, whose
    far side no seam need show. Any other fit, or a second one, leaves the side unsaid.
    Edges within ``tolerance`` are one. At most ``max_states`` partial sums are visited.
    """
    crit = chi2_critical(1.0, alpha)
    edges: list[float] = []
    depths: list[list[tuple[int, float]]] = []
    for j, (w, ln, _) in enumerate(sizes):
        for d, e in ((w, ln), (ln, w)):
            k = next((i for i, x in enumerate(edges) if abs(x - d) <= tolerance), None)
            if k is None:
                edges.append(float(d))
                depths.append([])
                k = len(edges) - 1
            depths[k].append((j, float(e)))
    fits: list[tuple[int, ...]] = []
    states = 0

    def search(i: int, counts: tuple[int, ...], total: float, n: int) -> None:
        nonlocal states
        states += 1
        if states > max_states:
            raise _Exhausted
        if i == len(edges):
            if n and (length - total) ** 2 / (n * tolerance**2) <= crit:
                fits.append(counts)
            return
        c = 0
        # more of edge i only while the sum can still come back within the test's reach
        while total + c * edges[i] <= length + math.sqrt(crit * (n + c + 1)) * tolerance:
            search(i + 1, (*counts, c), total + c * edges[i], n + c)
            if len(fits) > 1:
                return
            c += 1

    try:
        search(0, (), 0.0, 0)
    except _Exhausted:
        return Row(ways=min(len(fits), 2), exhausted=True)
    if len(fits) != 1:
        return Row(ways=len(fits), exhausted=False)
    used = [i for i, c in enumerate(fits[0]) if c]
    if len(used) != 1:
        return Row(ways=1, exhausted=False)
    k = used[0]
    d, n = edges[k], fits[0][k]
    if any(abs(e - depths[k][0][1]) > tolerance for _, e in depths[k]):
        return Row(ways=1, exhausted=False)
    sku, e = depths[k][0]
    return Row(ways=1, exhausted=False, sku=sku, along=d, depth=e, n=n,
               statistic=(length - n * d) ** 2 / (n * tolerance**2))


#: Most skyline states :func:`other_tiling` visits for one region (a few microseconds
#: each): a 1.2 x 0.8 m layer of the smallest cartons needs a few hundred.
MAX_TILING_STATES = 20000


@dataclass(frozen=True)
class Tiling:
    """Whether a split's grid is the only way to lay listed cartons over its extent.

    Attributes
    ----------
    turned : int
        Cartons laid otherwise than the grid's (turned 90 deg, or of another listed size)
        in the first other tiling found; 0 where none exists (the grid is the only one).
    states : int
        Skyline states the search visited.
    exhausted : bool
        The search stopped at its budget before deciding (``turned`` is then 0, and the
        grid is not shown to be the only tiling).
    """

    turned: int
    states: int
    exhausted: bool

    @property
    def unique(self) -> bool:
        """The grid is shown to be the only tiling."""
        return self.turned == 0 and not self.exhausted


class _Exhausted(Exception):
    """The tiling search hit its budget."""


_Skyline = tuple[tuple[float, float], ...]  # (x start, height) per segment, left to right
_Move = tuple[tuple[float, float], float, float, _Skyline]


def _skyline_moves(sky: _Skyline, feet: list[tuple[float, float]], U: float, V: float,
                   tolerance: float) -> tuple[float, float, list[_Move]]:
    """One step of a bottom-left fill of U x V: the lowest, leftmost point left uncovered
    (x0, y0), and each footprint that can lie with its corner there (a gap it leaves is
    filled exactly or has room for a carton; lengths equal within ``tolerance``), with the
    carton's far corner (x1, y1, snapped to a segment's end or the top) and the skyline
    after it (neighbours of one height are one segment, the left one's start). No moves
    once every segment is at the top."""
    i = min(range(len(sky)), key=lambda k: (sky[k][1], k))
    x0, y0 = sky[i]
    if y0 >= V - tolerance:
        return x0, y0, []
    w = (sky[i + 1][0] if i + 1 < len(sky) else U) - x0
    smallest = min(min(f) for f in feet)

    def fits_into(gap: float) -> bool:  # a gap is filled exactly or has room for a carton
        return gap <= tolerance or gap >= smallest - tolerance

    moves: list[_Move] = []
    for f in feet:
        fx, fy = f
        if fx > w + tolerance or y0 + fy > V + tolerance:
            continue
        if not fits_into(w - fx) or not fits_into(V - y0 - fy):
            continue
        y1 = V if abs(V - y0 - fy) <= tolerance else y0 + fy
        wide = w - fx > tolerance
        rest = [(x0, y1), (x0 + fx, y0)] if wide else [(x0, y1)]
        merged: list[tuple[float, float]] = []
        for x, y in [*sky[:i], *rest, *sky[i + 1:]]:
            if merged and abs(merged[-1][1] - y) <= tolerance:
                continue
            merged.append((x, y))
        moves.append((f, x0 + fx if wide else x0 + w, y1, tuple(merged)))
    return x0, y0, moves


def other_tiling(split: Split, sizes: tuple[tuple[float, float, float], ...],
                 tolerance: float, max_states: int = MAX_TILING_STATES,
                 seams: tuple[list[float], list[float]] = ([], [])) -> Tiling:
    """Another way than ``split``'s grid to lay listed cartons over its extent.

    A grid is what the extent implies only if no other tiling fits it. Cartons of one size
    in one orientation tile an nx a x ny b rectangle one way, the grid; turned ones can
    tile it otherwise wherever sums of the two edges agree (a 0.6 x 0.4 m region of
    0.2 x 0.4 m cartons is three side by side, or two turned across one end and one
    along). A layer laid so (brick or pinwheel patterns, interlocked within a layer) shows
    the same outline, and where its seams do not show, a grid laid over it cuts tops in
    two. So the search looks for any tiling of the grid's nominal extent by the listed
    footprints, either way round, that is not the grid. Only cartons of the grid's
    carton's height make up one layer with it: listed heights more than three tolerances
    apart do not (a height not listed matches any).

    Exhaustive bottom-left fill on a skyline (every tiling places a carton's corner at
    the lowest, leftmost point left uncovered), footprints other than the grid's tried
    first, with the dead skylines remembered; two lengths are equal within ``tolerance``.
    At most ``max_states`` skylines. A seam seen along a whole cut of the grid
    (``seams``) is a line no carton crosses: only tilings that have it count.

    Parameters
    ----------
    split : Split
        The grid (nx x ny cartons of a x b).
    sizes : tuple of (width, length, height), metres (height NaN: not listed)
    tolerance : float, metres
    seams : (list, list) of float, metres
        The grid's cuts along x and along y (multiples of a and b) where a seam is seen.

    Returns
    -------
    Tiling
    """
    a, b = split.a, split.b
    U, V = split.nx * a, split.ny * b
    feet = layer_footprints(split, sizes, tolerance)

    def grid_like(f: tuple[float, float]) -> bool:
        return abs(f[0] - a) <= tolerance and abs(f[1] - b) <= tolerance

    feet.sort(key=grid_like)  # the others first: a non-grid tiling is found early
    dead: set[tuple[tuple[int, ...], bool]] = set()
    states = 0

    def search(sky: _Skyline, turned: int) -> int:
        """The turned cartons of a non-grid tiling reached from skyline ``sky``, 0 if none."""
        nonlocal states
        key = (tuple(int(round(v * 1e3)) for s in sky for v in s), turned > 0)
        if key in dead:
            return 0
        states += 1
        if states > max_states:
            raise _Exhausted
        x0, y0, moves = _skyline_moves(sky, feet, U, V, tolerance)
        if y0 >= V - tolerance:  # every segment at the top: a tiling
            return turned
        for f, _, _, after in moves:
            fx, fy = f
            if (any(x0 + tolerance < c < x0 + fx - tolerance for c in seams[0])
                    or any(y0 + tolerance < c < y0 + fy - tolerance for c in seams[1])):
                continue  # it would lie across a seam that is seen
            t = search(after, turned + (0 if grid_like(f) else 1))
            if t:
                return t
        dead.add(key)
        return 0

    try:
        turned = search(((0.0, 0.0),), 0)
    except _Exhausted:
        return Tiling(0, states, True)
    return Tiling(turned, states, False)


#: A carton laid in a region by :func:`seen_tilings`: its corner (x, y) and its extent along
#: x and y, metres, in the grid's nominal frame (0 to nx a, 0 to ny b).
Placed = tuple[float, float, float, float]


@dataclass(frozen=True)
class SeenTilings:
    """The tilings of a region whose every inner carton side is a seam that shows.

    Attributes
    ----------
    tilings : list of list of Placed
        At most ``limit`` of them, in the order found.
    states : int
        Skyline states the search visited.
    exhausted : bool
        The search stopped at its budget before deciding.
    """

    tilings: list[list[Placed]]
    states: int
    exhausted: bool

    @property
    def unique(self) -> bool:
        """Exactly one such tiling, the search complete."""
        return len(self.tilings) == 1 and not self.exhausted


def layer_footprints(split: Split, sizes: tuple[tuple[float, float, float], ...],
                     tolerance: float) -> list[tuple[float, float]]:
    """The listed footprints that make up one layer with ``split``'s carton, either way
    round, each once (two within ``tolerance`` along both axes are one): cartons of its
    height (listed heights more than three tolerances apart are not; a height not listed
    matches any)."""
    h0 = sizes[split.sku][2]
    feet: list[tuple[float, float]] = []
    for w, ln, h in sizes:
        if np.isfinite(h0) and np.isfinite(h) and abs(h - h0) > 3.0 * tolerance:
            continue  # not of the layer's height
        for fx, fy in ((w, ln), (ln, w)):
            if not any(abs(fx - gx) <= tolerance and abs(fy - gy) <= tolerance
                       for gx, gy in feet):
                feet.append((fx, fy))
    return feet


def seen_tilings(split: Split, sizes: tuple[tuple[float, float, float], ...],
                 tolerance: float, seen: Callable[[int, float, float, float], bool],
                 limit: int = 2, max_states: int = MAX_TILING_STATES) -> SeenTilings:
    """Every way (up to ``limit``) to lay the listed cartons over ``split``'s extent whose
    cartons' sides inside it are all seams that show.

    A layer laid otherwise than a grid (a brick, pinwheel or basket weave) has the outline
    of one, and where another tiling fits, the outline cannot say which it is
    (:func:`other_tiling`); the seams can. Each carton placed must have a seam along each
    of its sides that is not on the outline: ``seen(axis, at, start, end)`` says whether
    the line ``x = at`` (``axis`` 0) or ``y = at`` (1) shows one from ``start`` to ``end``
    along it, metres in the grid's nominal frame. A carton side is one seam however many
    neighbours it touches. The search is :func:`other_tiling`'s bottom-left fill on a
    skyline, every footprint tried, the skylines with no tiling remembered; at most
    ``max_states`` of them.

    Returns
    -------
    SeenTilings
        Its ``tilings``: one is the region's cartons; none or several, the seams do not say.
    """
    U, V = split.nx * split.a, split.ny * split.b
    feet = layer_footprints(split, sizes, tolerance)
    dead: set[tuple[int, ...]] = set()
    found: list[list[Placed]] = []
    states = 0

    def sides_seen(x0: float, y0: float, fx: float, fy: float) -> bool:
        x1, y1 = x0 + fx, y0 + fy
        return ((x0 <= tolerance or seen(0, x0, y0, y1))
                and (x1 >= U - tolerance or seen(0, x1, y0, y1))
                and (y0 <= tolerance or seen(1, y0, x0, x1))
                and (y1 >= V - tolerance or seen(1, y1, x0, x1)))

    def search(sky: _Skyline, placed: list[Placed]) -> bool:
        """Tilings completed from skyline ``sky`` (into ``found``); True if any."""
        nonlocal states
        key = tuple(int(round(v * 1e3)) for sg in sky for v in sg)
        if key in dead:
            return False
        states += 1
        if states > max_states:
            raise _Exhausted
        x0, y0, moves = _skyline_moves(sky, feet, U, V, tolerance)
        if y0 >= V - tolerance:
            found.append(list(placed))
            return True
        any_found = False
        for _, x1, y1, after in moves:
            if not sides_seen(x0, y0, x1 - x0, y1 - y0):
                continue
            if search(after, [*placed, (x0, y0, x1 - x0, y1 - y0)]):
                any_found = True
            if len(found) >= limit:
                return True
        if not any_found:
            dead.add(key)
        return any_found

    try:
        search(((0.0, 0.0),), [])
    except _Exhausted:
        return SeenTilings(found, states, True)
    return SeenTilings(found, states, False)
