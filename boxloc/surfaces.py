"""The result: graspable surfaces with pose, size, grasp point, covariance and pick order.

Each surface comes from one hypothesis chosen by MDL. Its rectangle (from the generating
vertex and the verified dimensions) is moved onto the plane refitted to the range points
inside it; width <= length; the normal points toward the sensor; the grasp point is the
centre (the paper grasps "from the center of gravity of the fully exposed surfaces"). The
pick order takes the top-most surface first (height along ``scan.up``), so the pile is
unloaded from the top.
"""

from __future__ import annotations

import numpy as np

from boxloc.config import Config
from boxloc.products import HypothesisSet, Selection, SurfaceSet, Verification, VertexSet
from boxloc.scan import Scan
from boxloc.vertices import _skew


def make_surfaces(
    scan: Scan,
    vertices: VertexSet,
    hypotheses: HypothesisSet,
    verification: Verification,
    selection: Selection,
    config: Config,
) -> SurfaceSet:
    """Turn the selected hypotheses into graspable surfaces, ordered by pick order.

    Returns
    -------
    SurfaceSet
        ``covariances`` are of (centre, rotation vector), (s, 6, 6), metres and radians.
    """
    rows = []
    for k in np.flatnonzero(selection.chosen):
        j = int(selection.candidates[k])
        h = int(verification.hypothesis[j])
        w = float(hypotheses.att_width[j])
        ln = float(hypotheses.att_length[j])
        o, x, y = hypotheses.origins[h], hypotheses.x_axis[h], hypotheses.y_axis[h]
        nf = verification.plane_normals[j]
        pc = verification.plane_centers[j]
        c = o + 0.5 * w * x + 0.5 * ln * y
        c = c - ((c - pc) @ nf) * nf
        # in-plane axes re-orthogonalized to the refitted normal
        x = x - (x @ nf) * nf
        x /= np.linalg.norm(x)
        y = np.cross(nf, x)
        if w > ln:
            w, ln = ln, w
            x, y = y, -x  # keeps x cross y = normal
        corners = np.array([c - 0.5 * w * x - 0.5 * ln * y, c + 0.5 * w * x - 0.5 * ln * y,
                            c + 0.5 * w * x + 0.5 * ln * y, c - 0.5 * w * x + 0.5 * ln * y])
        Vc = vertices.covariances[h]
        Sd1, Sd2 = Vc[3:6, 3:6], Vc[6:, 6:]
        cov = np.zeros((6, 6))
        cov[:3, :3] = Vc[:3, :3] + 0.25 * (w * w * Sd1 + ln * ln * Sd2)
        # rotation: tilt of the normal (plane refit) and turn about it (the vertex lines)
        Sn = verification.plane_covariances[j][3:, 3:]
        K = _skew(nf)
        cov[3:, 3:] = K.T @ Sn @ K + float(y @ Sd1 @ y + x @ Sd2 @ x) * np.outer(nf, nf)
        q = selection.Q[k, k]
        score = float(q / max(config.mdl_k1 * selection.n_points[k], 1e-12))
        rows.append((h, j, c, nf, x, y, w, ln, corners, score, cov))
    up = hypotheses.up
    heights = np.array([r[2] @ up for r in rows])
    order = np.lexsort((np.array([r[0] for r in rows]), -heights)) if rows else np.zeros(0, int)
    rows = [rows[i] for i in order]
    s = len(rows)

    def col(i: int, shape: tuple[int, ...], dtype: type = np.float64) -> np.ndarray:
        return np.array([r[i] for r in rows], dtype).reshape((s, *shape))

    return SurfaceSet(
        hypothesis=col(0, (), np.int32),
        attempt=col(1, (), np.int32),
        centers=col(2, (3,)),
        normals=col(3, (3,)),
        x_axis=col(4, (3,)),
        y_axis=col(5, (3,)),
        width=col(6, ()),
        length=col(7, ()),
        corners=col(8, (4, 3)),
        grasp_points=col(2, (3,)),
        scores=col(9, ()),
        covariances=col(10, (6, 6)),
        pick_order=np.arange(s, dtype=np.int32),
    )
