"""Box layouts per scene kind, and the tape and labels on the lids (base frame).

Each layout draws from its own generator (the scene's layout stream), so a layout never
shifts the pose or the noise. Kinds: ``single``, ``pallet`` and ``partial`` (neat layers,
part of the top layer unloaded), ``mixed`` (sizes and yaw differ, some stacked),
``touching`` (a row of boxes with gaps of 0-2 mm), ``layered`` (zero gaps, no jitter; laid
as a grid, or interlocked as a basket weave by ``spec.pattern``), and the box-free ``empty``
and ``floor``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from boxloc.simulate.boxes import (
    _PALLET_TOP,
    PALLET_SIZE,
    _collides,
    _footprint_corners,
    _rests_on,
    _rot_z,
)
from boxloc.simulate.spec import SceneSpec

_PLACE_TRIES = 60  # placement attempts per box in the "mixed" layout


def _layout(spec: SceneSpec, rng: np.random.Generator) -> np.ndarray:
    """The boxes of a scene of ``spec.kind``, (B, 7) base frame: cx, cy, cz, sx, sy, sz, yaw."""
    if spec.kind == "single":
        return _layout_single(spec, rng)
    if spec.kind in ("pallet", "partial"):
        return _layout_pallet(spec, rng, partial=spec.kind == "partial")
    if spec.kind == "mixed":
        return _layout_mixed(spec, rng)
    if spec.kind == "touching":
        return _layout_touching(spec, rng)
    if spec.kind == "layered":
        # Zero gaps and no jitter: neighbours touch along whole faces, layer on layer.
        layers = spec.layers if spec.layers is not None else int(rng.integers(2, 4))
        if spec.pattern == "weave":
            return _layout_weave(spec, rng, layers)
        return _layout_pallet(dataclasses.replace(spec, max_gap=0.0, jitter=0.0, yaw_jitter=0.0,
                                                  layers=layers), rng, partial=False)
    return np.zeros((0, 7))


def _sizes(spec: SceneSpec, rng: np.random.Generator) -> tuple[float, float, float]:
    """A box's (short edge, long edge, height), metres, drawn from the spec's ranges."""
    a, b = np.sort(rng.uniform(spec.min_edge, spec.max_edge, 2))
    return float(a), float(b), float(rng.uniform(spec.min_height, spec.max_height))


def _layout_single(spec: SceneSpec, rng: np.random.Generator) -> np.ndarray:
    """One box near the pallet's centre, at any yaw."""
    a, b, h = _sizes(spec, rng)
    yaw = rng.uniform(-math.pi / 2, math.pi / 2)
    xy = rng.uniform(-0.1, 0.1, 2)
    return np.array([[xy[0], xy[1], _PALLET_TOP + h / 2, b, a, h, yaw]])


def _grid(a: float, b: float, g: float, orient: int) -> tuple[int, int, float, float]:
    """Cells of a pallet layer: (nx, ny, size x, size y); orient 1 turns the boxes 90 deg."""
    sx, sy = (b, a) if orient == 0 else (a, b)
    nx = int((PALLET_SIZE[0] + g + 1e-9) // (sx + g))
    ny = int((PALLET_SIZE[1] + g + 1e-9) // (sy + g))
    return nx, ny, sx, sy


def _layout_pallet(spec: SceneSpec, rng: np.random.Generator, partial: bool) -> np.ndarray:
    """Neat layers of one box size; ``partial`` unloads part of the top layer."""
    max_gap = 0.005 if spec.max_gap is None else spec.max_gap
    need = 2 if partial else 1
    a, b, h = _sizes(spec, rng)
    g = float(rng.uniform(0, max_gap))
    for _ in range(50):  # partial needs >= 2 boxes per layer; shrink the draw until they fit
        counts = [n[0] * n[1] for n in (_grid(a, b, g, 0)[:2], _grid(a, b, g, 1)[:2])]
        if max(counts) >= need:
            break
        a, b = max(spec.min_edge, 0.9 * a), max(spec.min_edge, 0.9 * b)
    if spec.layers is not None:
        n_layers = spec.layers
    else:
        n_layers = int(rng.integers(2, 4) if partial else rng.integers(1, 4))
    best = int(np.argmax(counts))
    # Real pallets interlock: alternate layers turn 90 deg when that loses few boxes.
    interlock = rng.random() < 0.5 and counts[1 - best] >= max(1, math.ceil(0.7 * counts[best]))
    boxes: list[np.ndarray] = []
    for layer in range(n_layers):
        orient = (1 - best) if (interlock and layer % 2 == 1) else best
        nx, ny, sx, sy = _grid(a, b, g, orient)
        ext_x, ext_y = nx * sx + (nx - 1) * g, ny * sy + (ny - 1) * g
        off = rng.uniform(-0.5, 0.5, 2) * 0.5 * np.array(
            [PALLET_SIZE[0] - ext_x, PALLET_SIZE[1] - ext_y])
        z = _PALLET_TOP + layer * h + h / 2
        for ix in range(nx):
            for iy in range(ny):
                cx = off[0] - ext_x / 2 + sx / 2 + ix * (sx + g)
                cy = off[1] - ext_y / 2 + sy / 2 + iy * (sy + g)
                j = rng.uniform(-1, 1, 3) * np.array([spec.jitter, spec.jitter, spec.yaw_jitter])
                boxes.append(_jitter_in_cell(cx, cy, z, sx, sy, h, g, j))
    out = np.asarray(boxes)
    if partial:
        top = np.flatnonzero(np.isclose(out[:, 2], out[:, 2].max()))
        if len(top) >= 2:
            # Unload from one side, as a robot or a person would.
            theta = rng.uniform(0, 2 * math.pi)
            order = top[np.argsort(out[top, 0] * math.cos(theta) + out[top, 1] * math.sin(theta),
                                   kind="stable")]
            n_remove = int(rng.integers(1, len(top)))
            out = np.delete(out, order[:n_remove], axis=0)
    return out


def _layout_weave(spec: SceneSpec, rng: np.random.Generator, n_layers: int) -> np.ndarray:
    """Zero-gap layers of one carton, twice as long as wide (a x 2a), in a basket weave
    (:func:`weave_layer`): as many cells as fit the pallet, each turned at random (at least
    one per layer), the column of single cartons at either end.

    Real pallets interlock their layers so; a carton list alone cannot tell such a layer
    from a grid, only seams that show can.
    """
    a = float(rng.uniform(spec.min_edge, spec.max_edge / 2))
    h = float(rng.uniform(spec.min_height, spec.max_height))
    while True:  # at least one cell: shrink the draw until it fits the pallet
        nx = int((PALLET_SIZE[0] - a + 1e-9) // (2 * a))
        ny = int((PALLET_SIZE[1] + 1e-9) // (2 * a))
        if (nx >= 1 and ny >= 1) or a <= spec.min_edge:
            break
        a = max(spec.min_edge, 0.9 * a)
    nx, ny = max(nx, 1), max(ny, 1)
    layers = []
    for layer in range(n_layers):
        turned = rng.random((nx, ny)) < 0.5
        if not turned.any():
            turned[int(rng.integers(nx)), int(rng.integers(ny))] = True
        column_first = bool(rng.random() < 0.5)
        ext = np.array([(2 * nx + 1) * a, ny * 2 * a])
        off = rng.uniform(-0.5, 0.5, 2) * 0.5 * np.maximum(np.array(PALLET_SIZE[:2]) - ext, 0.0)
        layers.append(weave_layer(a, h, turned, _PALLET_TOP + layer * h + h / 2,
                                  (float(off[0]), float(off[1])), column_first))
    return np.concatenate(layers)


def weave_layer(a: float, h: float, turned: np.ndarray, z: float,
                centre: tuple[float, float] = (0.0, 0.0), column_first: bool = False
                ) -> np.ndarray:
    """One zero-gap layer of cartons a x 2a x h laid as a basket weave, (B, 7) base frame.

    ``turned`` (nx, ny) bool: nx x ny square cells of 2a, each of two cartons side by side
    along x (False) or one above the other in y, their long edges along x (True); then one
    column of single cartons along y, their long edges along y, after the cells (before
    them if ``column_first``). The layer is (2 nx + 1) a by 2 ny a, centred on ``centre``
    (metres), its boxes' centres at height ``z``: the outline of a grid of the carton laid
    one way (and of no grid of it turned, 2 nx + 1 being odd), which it is only where no
    cell is turned.
    """
    nx, ny = turned.shape
    b = 2 * a
    ext_x, ext_y = (2 * nx + 1) * a, ny * b
    x0 = centre[0] - ext_x / 2 + (a if column_first else 0.0)
    xc = centre[0] - ext_x / 2 + a / 2 if column_first else centre[0] + ext_x / 2 - a / 2
    y0 = centre[1] - ext_y / 2
    boxes: list[list[float]] = []
    for j in range(ny):
        cy = y0 + (j + 0.5) * b
        for i in range(nx):
            cx = x0 + (i + 0.5) * b
            for s in (-0.5, 0.5):
                if turned[i, j]:
                    boxes.append([cx, cy + s * a, z, b, a, h, 0.0])
                else:
                    boxes.append([cx + s * a, cy, z, a, b, h, 0.0])
        boxes.append([xc, cy, z, a, b, h, 0.0])
    return np.asarray(boxes, dtype=np.float64)


def _jitter_in_cell(cx: float, cy: float, z: float, sx: float, sy: float, h: float, g: float,
                    j: np.ndarray) -> np.ndarray:
    """A box jittered by ``j`` = (dx, dy, dyaw), shrunk until it stays inside its cell."""
    for scale in (1.0, 0.5, 0.25, 0.125):
        box = np.array([cx + scale * j[0], cy + scale * j[1], z, sx, sy, h, scale * j[2]])
        c = _footprint_corners(box)
        if (np.abs(c[:, 0] - cx) <= (sx + g) / 2 + 1e-12).all() and \
                (np.abs(c[:, 1] - cy) <= (sy + g) / 2 + 1e-12).all():
            return box
    return np.array([cx, cy, z, sx, sy, h, 0.0])


def _layout_mixed(spec: SceneSpec, rng: np.random.Generator) -> np.ndarray:
    """Boxes of different sizes and yaw, without overlap, some stacked on others."""
    n = spec.n_boxes if spec.n_boxes is not None else int(rng.integers(4, 11))
    hx, hy = PALLET_SIZE[0] / 2, PALLET_SIZE[1] / 2
    overhang = 0.03
    placed: list[np.ndarray] = []
    for _ in range(n):
        for _try in range(_PLACE_TRIES):
            a, b, h = _sizes(spec, rng)
            yaw = float(rng.uniform(-math.pi / 2, math.pi / 2))
            u = rng.uniform(-1, 1, 2)
            stack = bool(placed) and rng.random() < 0.35
            s = placed[int(rng.integers(len(placed)))] if placed else None
            if stack and s is not None:
                xy = s[:2] + _rot_z(s[6]) @ (u * s[3:5] / 2)
                box = np.array([xy[0], xy[1], s[2] + s[5] / 2 + h / 2, b, a, h, yaw])
                # Fully on the support's top, so it is stable and rests on exactly that box.
                local = (_footprint_corners(box) - s[:2]) @ _rot_z(s[6])
                if (np.abs(local) > s[3:5] / 2 + 1e-12).any():
                    continue
            else:
                xy = u * np.array([hx, hy])
                box = np.array([xy[0], xy[1], _PALLET_TOP + h / 2, b, a, h, yaw])
                c = _footprint_corners(box)
                if (np.abs(c[:, 0]) > hx + overhang).any() or \
                        (np.abs(c[:, 1]) > hy + overhang).any():
                    continue
            if not _collides(box, placed, clearance=0.003):
                placed.append(box)
                break
    return np.asarray(placed).reshape(-1, 7)


def _layout_touching(spec: SceneSpec, rng: np.random.Generator) -> np.ndarray:
    """2-4 boxes of equal height in a row along x, touching (gaps 0-2 mm)."""
    n = spec.n_boxes if spec.n_boxes is not None else int(rng.integers(2, 5))
    max_gap = 0.002 if spec.max_gap is None else spec.max_gap
    h = float(rng.uniform(spec.min_height, spec.max_height))
    sx = rng.uniform(spec.min_edge, spec.max_edge, n)
    sy = rng.uniform(spec.min_edge, spec.max_edge, n)
    gaps = rng.uniform(0, max_gap, max(n - 1, 0))
    dy = rng.uniform(-0.03, 0.03, n)
    shift = rng.uniform(-0.5, 0.5)
    # A drawn count gives way to the box sizes; a requested one is kept (boxes narrowed).
    while spec.n_boxes is None and n > 2 and sx[:n].sum() + gaps[: n - 1].sum() > PALLET_SIZE[0]:
        n -= 1
    sx, sy, gaps, dy = sx[:n], sy[:n], gaps[: n - 1], dy[:n]
    room = PALLET_SIZE[0] - gaps.sum()
    if sx.sum() > room:  # the row does not fit on the pallet: narrow the boxes
        sx = sx * room / sx.sum()
    total = sx.sum() + gaps.sum()
    x0 = -total / 2 + shift * (PALLET_SIZE[0] - total)
    left = x0 + np.concatenate([[0.0], np.cumsum(sx[:-1] + gaps)])
    cy = np.clip(dy, -(PALLET_SIZE[1] / 2 - sy / 2), PALLET_SIZE[1] / 2 - sy / 2)
    cy = np.where(sy / 2 > PALLET_SIZE[1] / 2, 0.0, cy)
    return np.stack([left + sx / 2, cy, np.full(n, _PALLET_TOP + h / 2), sx, sy,
                     np.full(n, h), np.zeros(n)], 1)


_TAPE, _LABEL = 0, 1


def _decorations(spec: SceneSpec, boxes: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Tape strips and labels on the lids that nothing rests on, (D, 9): slab (cx, cy, cz,
    sx, sy, sz, yaw) in the base frame, host box, material (0 tape, 1 label).

    Tape runs along the lid's long axis near its centre line, 48-75 mm wide (at most 0.4 of
    the short side) and 1-3 mm thick, stopping short of the bevels; a label is 70-120 x
    100-160 mm, 0.5-2 mm thick, anywhere on the lid it fits. Every box draws the same
    numbers whether it gets them or not, so one box's draw never shifts another's.
    """
    out = []
    free = ~_rests_on(boxes)
    for i, b in enumerate(boxes):
        u = rng.random(2)
        t_w, t_th = rng.uniform(0.048, 0.075), rng.uniform(0.001, 0.003)
        t_off = rng.uniform(-1, 1)
        l_w, l_l = rng.uniform(0.07, 0.12), rng.uniform(0.10, 0.16)
        l_th = rng.uniform(0.0005, 0.002)
        l_pos = rng.uniform(-1, 1, 2)
        if not free[i]:
            continue
        cx, cy, cz, sx, sy, sz, yaw = b
        top = cz + sz / 2
        along_x = sx >= sy
        long_, short = (sx, sy) if along_x else (sy, sx)
        rot = _rot_z(yaw)
        inner = 2 * spec.bevel + 0.004
        if u[0] < spec.tape:
            w = min(t_w, 0.4 * short)
            off = t_off * max(0.0, min(0.02, (short - w) / 2 - inner))
            local = np.array([0.0, off]) if along_x else np.array([off, 0.0])
            size = (long_ - inner, w) if along_x else (w, long_ - inner)
            xy = b[:2] + rot @ local
            out.append([xy[0], xy[1], top + t_th / 2, *size, t_th, yaw, i, _TAPE])
        if u[1] < spec.labels:
            room = np.array([sx, sy]) - inner - np.array([l_l, l_w] if along_x else [l_w, l_l])
            if (room > 0).all():
                local = l_pos * room / 2
                size = (l_l, l_w) if along_x else (l_w, l_l)
                xy = b[:2] + rot @ local
                out.append([xy[0], xy[1], top + l_th / 2, *size, l_th, yaw, i, _LABEL])
    return np.asarray(out, dtype=np.float64).reshape(-1, 9)
