"""The typed, immutable products of each stage (the paper's Fig. 2, one dataclass per stage).

Every product is a frozen dataclass of NumPy arrays and scalars. Entities carry stable
integer ids (their row index within the scan), so logs, diffs and explanations can refer
to them. Variable-length per-row data is stored CSR-style: a flat ``values`` array and an
``offsets`` array of length n + 1 (row i is ``values[offsets[i]:offsets[i+1]]``).

:func:`to_arrays` / :func:`from_arrays` turn any product into a flat ``{name: ndarray}``
mapping and back, losslessly; the recorder encodes that mapping, nothing is pickled.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np

from boxloc.stats import TestTable


class EdgeKind(IntEnum):
    """Label of an edge pixel."""

    NONE = 0
    #: depth discontinuity; the edge point lies on the nearer (occluding) surface
    JUMP = 1
    #: convex fold (e.g. a box top meeting its own side)
    CREASE_CONVEX = 2
    #: concave fold (e.g. a box side meeting the top of a lower box)
    CREASE_CONCAVE = 3
    #: a narrow dip between two collinear, continuous surfaces: the seam of touching boxes
    GROOVE = 4


class DimensionSource(IntEnum):
    """Where a hypothesis got its width and length (paper Fig. 2, lines 4 and 7)."""

    NONE = 0
    VERTICES = 1
    EDGES = 2
    #: from the edge accumulators and a seam (:mod:`boxloc.stages.seams`) for a far side
    SEAMS = 3
    #: from how far the face's plane runs along each arm (:func:`boxloc.stages.verify.face_extent`)
    #: for a far side the edge accumulators did not show
    EXTENT = 4
    #: the whole flat region the face's plane covers (its extent along both arms, beyond
    #: ``max_edge``): verified as a region, reported as ambiguous or split, never a surface
    REGION = 5
    #: one part of a flat region split at the seams a listed carton size implies
    SKU_SPLIT = 6
    #: the listed cartons lining one side of a flat region that did not verify whole (it
    #: runs out of sight, or a far side shows no end): the side's length, seen from corner
    #: to end, is n of one listed edge and no other sum of listed edges
    #: (:func:`boxloc.stages.sizes.row_cartons`), so the cartons reach that size's depth
    #: into it. Verified as a region with that far side on the size's evidence, then split
    #: like one; never a surface, and never reported as ambiguous (its far side is the
    #: list's, not the scan's)
    ROW = 7
    #: half (or third) of a candidate that failed because a seam showed at its middle (or
    #: seams at its thirds: VERIFY_SEAM_MIDLINE rejected along that axis, two or three
    #: boxes side by side): the box at the vertex ends at the nearest seam, so the part
    #: next to it is tried next, within the vertex's budget
    MIDLINE = 8
    #: one part of a flat region split, without a carton list, at the seams a carton size
    #: the scan shows implies (``SEEN_CARTON``: a verified box that a rectangle beside it
    #: repeats, and another of its size apart from it), as SKU_SPLIT with a listed size
    SEEN_SPLIT = 9


#: The parts of a split flat region: by a listed size, or by a size the scan shows.
SPLIT_SOURCES = (DimensionSource.SKU_SPLIT, DimensionSource.SEEN_SPLIT)


class VerifyReason(IntEnum):
    """Why a verification passed or failed (the first failing test, in order)."""

    ACCEPTED = 0
    TOO_FEW_POINTS = 1
    TILTED = 2
    NOT_EXPOSED = 3
    INLIERS = 4
    MEAN_OFFSET = 5
    INTERIOR_EDGES = 6
    #: the rectangle, or the strip beyond one of its sides, leaves the image: the face
    #: may run on out of sight
    OUTSIDE_IMAGE = 7
    #: a side of the rectangle is not a convex boundary (jump, convex crease, groove)
    BOUNDARY = 8
    #: a seam (a line of points behind the plane) crosses the interior: two faces, not one
    INTERIOR_SEAM = 9
    #: the face's plane continues beyond a side that is not a seam: the rectangle is cut
    #: short inside a larger face
    CONTINUES = 10
    #: every test passed, but the flat region is larger than a box (``max_edge``) or a
    #: multiple of a listed size that no evidence splits: ambiguous, not a surface
    AMBIGUOUS = 11


class SelectReason(IntEnum):
    """Why a verified hypothesis was or was not selected by MDL."""

    CHOSEN = 0
    #: adding it would lower the objective because it overlaps chosen ones
    OVERLAPS_CHOSEN = 1
    #: its own MDL gain is not positive
    NO_GAIN = 2


class HeightSource(IntEnum):
    """Where a box's height (:attr:`SurfaceSet.height`) came from."""

    #: not measured: no side face or step seen, no listed height
    NONE = 0
    #: the visible side face below the top's edge, down to where it meets what it stands on
    SIDE = 1
    #: the step down from the top to the neighbouring surface or the layer below it
    STEP = 2
    #: the height of the matched listed carton size (``Config.box_sizes``)
    SKU = 3


class AmbiguityReason(IntEnum):
    """Why a flat region is not reported as a surface (:class:`AmbiguousSet`)."""

    #: a side without evidence of a box's end (no jump, crease, groove, seam or size)
    NO_END_EVIDENCE = 1
    #: longer than the longest box edge (``max_edge``) along an arm: several boxes whose
    #: seams the range points do not show
    LARGER_THAN_MAX_BOX = 2
    #: with a carton list: the region is no multiple (1x1, 2x1, 3x1, 2x2, ...) of a listed
    #: size
    NOT_A_MULTIPLE_OF_A_SIZE = 3
    #: with a carton list: the region is a multiple of more than one listed size (or of
    #: one in two ways), and no seam shows which
    SEVERAL_SPLITS = 4
    #: with a carton list: the region is a multiple of a listed size, but stands less than
    #: that carton's listed height above what lies beyond its sides (a bare pallet)
    TOO_LOW_FOR_THE_SIZE = 5
    #: with a carton list: the region is a grid of a listed size, but the cartons can be
    #: laid over it another way too (turned, a brick, pinwheel or basket weave), and its
    #: seams show neither the grid's cuts nor one other tiling's carton sides
    SEVERAL_TILINGS = 6
    #: n (2, 3, ...) of a verified box beside it in its plane (``REPEATS_NEIGHBOUR``):
    #: as many cartons of that size whose seams the range points do not show, or one box
    MULTIPLE_OF_A_NEIGHBOUR = 7


class NoiseSource(IntEnum):
    """Where the noise model every later stage used came from."""

    #: the config pins it (``noise_auto = false``)
    CONFIG = 0
    #: estimated from this scan's flat regions
    SCAN = 1
    #: ``noise_auto``, but the scan has neither flat tiles nor smooth scan lines to fit: the
    #: config's model
    FALLBACK = 2
    #: ``noise_auto``, too few flat tiles (noise too strong or quantized for a tile to pass
    #: as flat): fitted to the second differences of the ranges along rows and columns
    DIFFERENCES = 3


#: Order of :attr:`NoiseEstimate.model`'s values (the fields of ``NoiseModel``).
NOISE_FIELDS: tuple[str, ...] = (
    "sigma0", "k1", "k2", "sigma_angle", "min_cos", "edge_px", "row_corr", "incidence_exponent",
    "corr_px_rows", "corr_px_cols", "exceed_rate", "exceed_dispersion", "exceed_corr_px")


def _f(*shape: int, dtype: Any = np.float64) -> np.ndarray:
    return np.zeros(shape, dtype)


@dataclass(frozen=True, eq=False)
class NoiseEstimate:
    """The range-noise model of this scan (stage 1b, before the edges), and how well the
    scan's own flat regions agree with it.

    Attributes
    ----------
    source : int
        :class:`NoiseSource`.
    reason : str
        Why that source, in words (e.g. too few flat tiles).
    model : (13,) float64
        The model every later stage used, in :data:`NOISE_FIELDS` order (metres, radians;
        logs before the exceedance terms hold the first 10, before their correlation the
        first 12).
    nominal : (13,) float64
        The config's model (the fallback, and what a pinned run uses).
    n_tiles, n_tiles_used, n_points : int
        Tiles examined, flat tiles accepted, residuals in them.
    bin_range, bin_tiles, bin_std, bin_model_std, bin_z : (B,) float64
        Per range bin with enough tiles: median range (m), tiles, robust residual std along
        the ray at normal incidence (m), the model's (m), and the NOISE_FIT z of the bin
        (beyond the scale margin; positive means off by more than the margin): the
        standard normal quantile of the bin's Student t tail probability (logs before
        ``bin_dof`` hold the t itself, taken as normal).
    correlation : (2, 4) float64
        Residual correlation along rows and along columns at 1, 2, 4, 8 pixels (NaN
        where undefined).
    tails : (3,) float64
        Share of residuals beyond 3, 4, 5 model sigmas (a normal: 2.7e-3, 6.3e-5, 5.7e-7).
    tests : TestTable
        NOISE_FIT (none when no range bin has enough flat tiles).
    bin_design : (B,) float64
        Per range bin, the design effect of its tiles' correlated scales: how many times
        the variance of independent tiles' mean its mean has (1 in logs before it).
    bin_dof : (B,) float64
        Per range bin, the degrees of freedom of the t its z comes from (inf in logs before
        it: the normal).
    tile_correlation : (4,) float64
        (c_r, a_r, c_c, a_c): the flat tiles' log scales correlate as ``c_r * a_r ** k``
        between tiles k tile-grid steps apart along a row, ``c_c * a_c ** k`` along a
        column (zeros: not at all, and in logs before it).
    fit_all : (4,) float64
        NOISE_FIT's test of all flat tiles together: z, tiles, design effect, dof (NaN when
        there was no bin to test, and in logs before it).
    """

    source: int
    reason: str
    model: np.ndarray
    nominal: np.ndarray
    n_tiles: int
    n_tiles_used: int
    n_points: int
    bin_range: np.ndarray
    bin_tiles: np.ndarray
    bin_std: np.ndarray
    bin_model_std: np.ndarray
    bin_z: np.ndarray
    correlation: np.ndarray
    tails: np.ndarray
    tests: TestTable
    bin_design: np.ndarray = None  # type: ignore[assignment]
    bin_dof: np.ndarray = None  # type: ignore[assignment]
    tile_correlation: np.ndarray = None  # type: ignore[assignment]
    fit_all: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        nb = self.bin_range.shape[0]
        for name, value in (("bin_design", np.ones(nb)), ("bin_dof", np.full(nb, np.inf)),
                            ("tile_correlation", np.zeros(4)),
                            ("fit_all", np.full(4, np.nan))):
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)

    def noise_model(self) -> dict[str, float]:
        """The model in use as ``NoiseModel`` keyword arguments."""
        return {k: float(v) for k, v in zip(NOISE_FIELDS, self.model)}

    @property
    def fits(self) -> bool:
        """Whether every test of the scan's residuals accepted the model in use."""
        return bool(np.all(self.tests.accepted))


@dataclass(frozen=True, eq=False)
class EdgeMap:
    """Edges of the range image (stage 2), from scan-line approximation.

    Attributes
    ----------
    labels : (H, W) uint8
        :class:`EdgeKind` per pixel.
    pixels : (N, 2) int32
        (row, column) of each edge point.
    points : (N, 3) float64, metres, sensor frame
        Sub-pixel edge point: the fitted segments' intersection (crease) or the fitted
        segment's end on the nearer surface (jump). To float32 precision, like
        ``covariances`` and ``strength`` (:func:`boxloc.stats.float32_precision`).
    covariances : (N, 3, 3) float64, metres squared
    kinds : (N,) uint8
        :class:`EdgeKind`.
    strength : (N,) float64
        Jump height, metres (inf at a no-return border: nothing was measured beyond), or
        fold angle, radians.
    scan_dir : (N,) uint8
        Bit 1: found on a row; bit 2: found on a column.
    tests : TestTable
        The JUMP and CREASE decision at every breakpoint, and the NO_RETURN decision at
        every surface that runs into no return out to the image border.
    """

    labels: np.ndarray
    pixels: np.ndarray
    points: np.ndarray
    covariances: np.ndarray
    kinds: np.ndarray
    strength: np.ndarray
    scan_dir: np.ndarray
    tests: TestTable

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass(frozen=True, eq=False)
class LineSet:
    """3D line segments (stage 3) from a series of constrained Hough transforms.

    Attributes
    ----------
    points : (L, 3) float64
        Centroid of each segment's support, metres.
    directions : (L, 3) float64
        Unit direction.
    covariances : (L, 6, 6) float64
        Joint covariance of (centroid, direction).
    starts, ends : (L, 3) float64
        Segment end points on the line, metres.
    n_support : (L,) int32
    support_offsets : (L + 1,) int64
    support : (M,) int32
        Edge-point ids of each segment's support.
    support_statistic : (M,) float32
        The point-on-line test statistic (chi2, 2 dof) of each support point.
    kinds : (L,) uint8
        Majority :class:`EdgeKind` of the support.
    trial : (L,) int32
        The Hough trial that found each line.
    direction_votes, position_votes : (L,) float64
        Peak heights of the direction and position accumulators.
    n_trials : int
        Trials run (distinguished points drawn).
    epsilon : float
        Fraction of edge points in the smallest line worth finding, at the start.
    p_success : float
    seed : int
        The seed of the trials (derived from the scan and ``Config.trial_seed``).
    tests : TestTable
    """

    points: np.ndarray
    directions: np.ndarray
    covariances: np.ndarray
    starts: np.ndarray
    ends: np.ndarray
    n_support: np.ndarray
    support_offsets: np.ndarray
    support: np.ndarray
    support_statistic: np.ndarray
    kinds: np.ndarray
    trial: np.ndarray
    direction_votes: np.ndarray
    position_votes: np.ndarray
    n_trials: int
    epsilon: float
    p_success: float
    seed: int
    tests: TestTable

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def support_of(self, i: int) -> np.ndarray:
        return self.support[self.support_offsets[i] : self.support_offsets[i + 1]]


@dataclass(frozen=True, eq=False)
class VertexSet:
    """Vertices (stage 4): pairs of segments that meet orthogonally near an end of both.

    Attributes
    ----------
    points : (V, 3) float64
        Intersection point, metres.
    d1, d2 : (V, 3) float64
        Unit directions from the point into each segment; ``normals = d1 x d2`` (unit),
        turned toward the sensor by the order of d1 and d2.
    normals : (V, 3) float64
    covariances : (V, 9, 9) float64
        Joint covariance of (point, d1, d2).
    line_a, line_b : (V,) int32
        The two lines (``d1`` runs along ``line_a``); -1 for a neighbour's corner, and for
        the third edge of a box corner.
    tests : TestTable
        LINES_MEET, LINES_ORTHOGONAL and AT_SEGMENT_ENDS for every pair considered;
        NEIGHBOUR_CORNER for every corner offered across a seam.
    parent, parent_side : (V,) int32
        A neighbour's corner (added by the hypothesis stage): the vertex whose verified
        rectangle has this corner on its seam side ``parent_side`` (0-3: v=0, v=length,
        u=0, u=width); or a box corner's vertex of the face across a crease
        (``parent_side`` 4, :func:`boxloc.stages.vertices.corner_vertices`), whose parent is the
        vertex of two lines it was derived from; or a corner of a part of a flat region
        split at a listed carton size's seams (``parent_side`` 5, the parent the region's
        vertex); -1 for a vertex of two lines. Logs
        written before these fields existed read back as all -1.
    """

    points: np.ndarray
    d1: np.ndarray
    d2: np.ndarray
    normals: np.ndarray
    covariances: np.ndarray
    line_a: np.ndarray
    line_b: np.ndarray
    tests: TestTable
    parent: np.ndarray = None  # type: ignore[assignment]
    parent_side: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        for name in ("parent", "parent_side"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(len(self), -1, np.int32))

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass(frozen=True, eq=False)
class HypothesisSet:
    """One rectangle hypothesis per vertex (stage 5), with every dimension attempt.

    Row i is the hypothesis generated by vertex ``vertex[i]``. Its frame: origin at the
    vertex, ``x_axis = d1``, ``y_axis = d2``; width runs along x, length along y (here
    width may exceed length; :class:`SurfaceSet` sorts them).

    Attempts are the (width, length) candidates tried in the paper's order, each then
    verified; the hypothesis keeps the first verified attempt (``attempt``, -1 if none).

    Attributes
    ----------
    vertex : (n,) int32
    source : (n,) uint8
        :class:`DimensionSource` of the kept attempt.
    attempt : (n,) int32
        The kept attempt's id, or -1.
    origins, x_axis, y_axis, normals : (n, 3) float64
    width, length : (n,) float64
        Dimensions of the kept attempt, metres (NaN if none).
    corners : (n, 4, 3) float64
        Rectangle corners (origin, +x, +x+y, +y), metres (NaN if none).
    acc_bin : (n,) float64
        Bin width of the 1-D accumulators, metres.
    acc_x_offsets, acc_y_offsets : (n + 1,) int64
    acc_x, acc_y : float32
        The accumulators A_x and A_y (votes per bin), ragged per hypothesis.
    peaks_x_offsets, peaks_y_offsets : (n + 1,) int64
    peaks_x, peaks_y : float64
        Peak positions M_x, M_y, metres.
    n_candidates : (n,) int32
        |P_c|: edge points coplanar with the rectangle and in its first quadrant.
    att_hypothesis, att_source, att_diagonal : (k,) int32 / uint8 / int32
        Attempt owner, source, and the diagonal vertex used (-1 for edges).
    att_width, att_length : (k,) float64
    att_support, att_threshold : (k,) float64
        |P_f| and the threshold p (edges); the diagonal's test statistic total (vertices).
    att_verified : (k,) bool
        A REGION attempt (a flat region larger than a box, or a multiple of a listed size;
        :func:`boxloc.stages.hypotheses.dimensions_from_region`) is never verified as a
        surface: its ``att_support`` is the number of parts it was split into (0: not
        split, -1: the same region found from another vertex), its ``att_threshold`` the
        :class:`AmbiguityReason` it was left ambiguous for (NaN: split). With a carton list
        a region's split is tried from up to four of its vertices in turn; each one tried
        records its own reason, and where a later one splits it, the first found becomes
        the -1 (:func:`boxloc.stages.hypotheses._split_regions`). A ROW attempt (the
        cartons lining one side of a region that did not verify whole) is one too, but is
        never reported ambiguous; -1 also marks two rows at one corner that disagree on
        its carton (``SEVERAL_TILINGS``). A SKU_SPLIT attempt's ``att_support`` is the
        region's (or row's) hypothesis.
    up : (3,) float64
        The up direction the tilt prior and the pick order used (see :mod:`boxloc.stages.up`).
    tests : TestTable
        COPLANAR, PARALLEL, FIRST_QUADRANT, POINT_ON_PLANE and EDGE_SUPPORT.
    """

    vertex: np.ndarray
    source: np.ndarray
    attempt: np.ndarray
    origins: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    normals: np.ndarray
    width: np.ndarray
    length: np.ndarray
    corners: np.ndarray
    acc_bin: np.ndarray
    acc_x_offsets: np.ndarray
    acc_x: np.ndarray
    acc_y_offsets: np.ndarray
    acc_y: np.ndarray
    peaks_x_offsets: np.ndarray
    peaks_x: np.ndarray
    peaks_y_offsets: np.ndarray
    peaks_y: np.ndarray
    n_candidates: np.ndarray
    att_hypothesis: np.ndarray
    att_source: np.ndarray
    att_diagonal: np.ndarray
    att_width: np.ndarray
    att_length: np.ndarray
    att_support: np.ndarray
    att_threshold: np.ndarray
    att_verified: np.ndarray
    up: np.ndarray
    tests: TestTable

    def __len__(self) -> int:
        return int(self.vertex.shape[0])

    @property
    def n_attempts(self) -> int:
        return int(self.att_hypothesis.shape[0])


@dataclass(frozen=True, eq=False)
class Verification:
    """Verification of every attempt (stage 6) by the range points inside its rectangle.

    Row j verifies attempt j of the :class:`HypothesisSet`.

    Attributes
    ----------
    attempt, hypothesis : (k,) int32
    n_inside : (k,) int32
        Pixels inside the rasterized rectangle.
    n_valid : (k,) int32
        Of those, pixels with a return.
    n_inliers, n_front, n_behind : (k,) int32
        Points on the plane, significantly in front of it, behind it (point-on-plane, 1 dof).
    inlier_fraction : (k,) float64
        ``n_inliers`` over the returns inside plus ``Config.hole_weight`` of the holes
        (``VERIFY_INLIERS`` row 0).
    mean_distance, sigma_mean : (k,) float64
        Mean signed distance of the inliers to the plane and its standard deviation, metres.
    n_interior_edges : (k,) int32
        Edge points on the face's plane inside the rectangle, beyond the band where its
        sides' own edges lie: the points ``VERIFY_INTERIOR`` looks for a line in (their
        number is recorded, not tested).
    plane_centers, plane_normals : (k, 3) float64
        Plane refitted to the inliers (normal toward the sensor).
    plane_covariances : (k, 6, 6) float64
        Covariance of (center, normal) of the refit.
    rms : (k,) float64
        RMS of inlier distances, metres.
    error : (k,) float64
        Sum of the inliers' squared normalized distances (the MDL error xi).
    accepted : (k,) bool
    reason : (k,) uint8
        :class:`VerifyReason`.
    inlier_offsets : (k + 1,) int64
    inlier_pixels : int32
        Flat pixel indices (row * W + col) of each attempt's inliers.
    tests : TestTable
    """

    attempt: np.ndarray
    hypothesis: np.ndarray
    n_inside: np.ndarray
    n_valid: np.ndarray
    n_inliers: np.ndarray
    n_front: np.ndarray
    n_behind: np.ndarray
    inlier_fraction: np.ndarray
    mean_distance: np.ndarray
    sigma_mean: np.ndarray
    n_interior_edges: np.ndarray
    plane_centers: np.ndarray
    plane_normals: np.ndarray
    plane_covariances: np.ndarray
    rms: np.ndarray
    error: np.ndarray
    accepted: np.ndarray
    reason: np.ndarray
    inlier_offsets: np.ndarray
    inlier_pixels: np.ndarray
    tests: TestTable

    def __len__(self) -> int:
        return int(self.attempt.shape[0])

    def inliers_of(self, j: int) -> np.ndarray:
        return self.inlier_pixels[self.inlier_offsets[j] : self.inlier_offsets[j + 1]]


@dataclass(frozen=True, eq=False)
class Selection:
    """MDL selection (stage 7): maximize m^T Q m over the verified attempts.

    Attributes
    ----------
    candidates : (c,) int32
        Attempt ids that passed verification.
    hypothesis : (c,) int32
    n_points : (c,) int32
        n_i, inliers explained.
    error : (c,) float64
        xi_i, sum of squared normalized residuals.
    n_params : (c,) int32
        N_i (8 for a rectangle).
    Q : (c, c) float64
        The MDL matrix (q_ii on the diagonal, q_ij off it).
    chosen : (c,) bool
    order : (s,) int32
        Candidate indices in the order the greedy search added them.
    objective : float
        m^T Q m at the chosen m.
    beaten_by : (c,) int32
        For a candidate not chosen, the chosen candidate it overlaps most (-1 if none).
    reason : (c,) uint8
        :class:`SelectReason`.
    k1, k2, k3 : float
        The MDL weights used.
    unit : (c,) float64
        Points a face of the smallest box has at each candidate's place (its rasterized
        pixels per square metre times ``min_edge``^2); its model cost K3 N_i enters Q
        times ``unit / face_points``. NaN where the cost was raw points (``face_points``
        0, and logs before it).
    face_points : float
        ``Config.mdl_face_points``: how many points a smallest face counts as; 0 for raw
        points.
    """

    candidates: np.ndarray
    hypothesis: np.ndarray
    n_points: np.ndarray
    error: np.ndarray
    n_params: np.ndarray
    Q: np.ndarray
    chosen: np.ndarray
    order: np.ndarray
    objective: float
    beaten_by: np.ndarray
    reason: np.ndarray
    k1: float
    k2: float
    k3: float
    unit: np.ndarray = None  # type: ignore[assignment]
    face_points: float = 0.0

    def __post_init__(self) -> None:
        if self.unit is None:  # a log from before the density-free MDL: raw points
            object.__setattr__(self, "unit", np.full(len(self), np.nan))

    def __len__(self) -> int:
        return int(self.candidates.shape[0])


@dataclass(frozen=True, eq=False)
class SurfaceSet:
    """The graspable surfaces (the result), ordered by pick order (top-most first).

    Attributes
    ----------
    hypothesis, attempt : (s,) int32
        Where each surface came from.
    centers, normals, x_axis, y_axis : (s, 3) float64
        Pose in the sensor frame; normal toward the sensor; x along width, y along length.
    width, length : (s,) float64
        Metres, width <= length.
    corners : (s, 4, 3) float64
    grasp_points : (s, 3) float64
    scores : (s,) float64
        The surface's MDL gain q_ii normalized by its point count (in [.., 1]).
    covariances : (s, 6, 6) float64
        Covariance of (center, rotation vector) in the sensor frame.
    pick_order : (s,) int32
        0 is picked first.
    bulge : (s,) float64
        How far the middle of the lid stands above the rim's plane (the box's top),
        metres (:func:`boxloc.stages.surfaces.fit_bulge`); the centre is on the rim's plane when
        its SURFACE_BULGE test rejects a flat lid, else on the points' plane.
    tests : TestTable
        SURFACE_BULGE per surface (``a`` = attempt) whose inliers determine the fit (at
        least ``boxloc.stages.surfaces.MIN_BULGE_POINTS``, not all on one line); a surface
        without one has ``bulge`` 0 and its centre on the points' plane. END_EVIDENCE per
        side of every surface; SKU_SIZE per surface when ``Config.box_sizes`` lists sizes;
        BOX_HEIGHT per height found; HEIGHT_WITHIN_BOX per height measurement deeper than
        any carton is tall (not used); HEIGHT_SKU_AGREEMENT per measured height with a listed
        one; LAYER_HEIGHT per top of a flush layer whose height
        was weighed against the layer's smallest side-face height.
    height, height_sigma : (s,) float64
        The box's height (its top above what it stands on) and its standard deviation,
        metres; NaN where none was measured or listed.
    height_source : (s,) int8
        :class:`HeightSource`.
    sku : (s,) int32
        The row of ``Config.box_sizes`` the surface's dimensions match (SKU_SIZE), -1 for
        none or no list.
    sku_flagged : (s,) bool
        Sizes were listed and the surface matches none of them.

    Logs written before ``bulge`` and ``tests`` existed read back with zeros and no tests;
    before the heights and SKUs, with NaN heights (source NONE), ``sku`` -1, not flagged.
    """

    hypothesis: np.ndarray
    attempt: np.ndarray
    centers: np.ndarray
    normals: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    width: np.ndarray
    length: np.ndarray
    corners: np.ndarray
    grasp_points: np.ndarray
    scores: np.ndarray
    covariances: np.ndarray
    pick_order: np.ndarray
    bulge: np.ndarray = None  # type: ignore[assignment]
    tests: TestTable = None  # type: ignore[assignment]
    height: np.ndarray = None  # type: ignore[assignment]
    height_sigma: np.ndarray = None  # type: ignore[assignment]
    height_source: np.ndarray = None  # type: ignore[assignment]
    sku: np.ndarray = None  # type: ignore[assignment]
    sku_flagged: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        n = len(self)
        if self.bulge is None:
            object.__setattr__(self, "bulge", np.zeros(n))
        if self.tests is None:
            object.__setattr__(self, "tests", TestTable.empty(np.nan))
        for name, value in (("height", np.full(n, np.nan)), ("height_sigma", np.full(n, np.nan)),
                            ("height_source", np.full(n, HeightSource.NONE, np.int8)),
                            ("sku", np.full(n, -1, np.int32)), ("sku_flagged", np.zeros(n, bool))):
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return int(self.centers.shape[0])

    def to_json_list(self) -> list[dict[str, Any]]:
        """The public ``locate`` JSON records (ids are row indices)."""
        out = []
        for i in range(len(self)):
            out.append(
                {
                    "id": i,
                    "center": self.centers[i].tolist(),
                    "normal": self.normals[i].tolist(),
                    "x_axis": self.x_axis[i].tolist(),
                    "y_axis": self.y_axis[i].tolist(),
                    "width": float(self.width[i]),
                    "length": float(self.length[i]),
                    "grasp_point": self.grasp_points[i].tolist(),
                    "score": float(self.scores[i]),
                    "covariance": self.covariances[i].tolist(),
                    "pick_order": int(self.pick_order[i]),
                    "bulge": float(self.bulge[i]),
                    "height": _finite_or_none(self.height[i]),
                    "height_sigma": _finite_or_none(self.height_sigma[i]),
                    "height_source": HeightSource(int(self.height_source[i])).name.lower(),
                    "sku": int(self.sku[i]) if self.sku[i] >= 0 else None,
                    "size_flagged": bool(self.sku_flagged[i]),
                }
            )
        return out


def _finite_or_none(x: float) -> float | None:
    """A JSON number, or null for NaN (JSON has no NaN)."""
    return float(x) if np.isfinite(x) else None


@dataclass(frozen=True, eq=False)
class AmbiguousSet:
    """Flat regions that may hold graspable tops but whose extent the evidence cannot split
    into boxes (issue #21): not surfaces, so that the cell can fall back (push, re-scan, ask
    an operator). One row per region.

    Attributes
    ----------
    hypothesis : (K,) int64
        The hypothesis whose region it is, or -1.
    attempt : (K,) int64
        The attempt that verified the region (its tests are the rows with ``a`` = this id
        in ``Verification.tests`` and in ``tests`` below), or -1.
    corners : (K, 4, 3) float64
        The region's outline, metres, sensor frame (origin, +x, +x+y, +y).
    area : (K,) float64
        Its area, m^2.
    width, length : (K,) float64
        Its extent along its two axes, metres, width <= length.
    reason : (K,) int8
        :class:`AmbiguityReason`.
    tests : TestTable
        The tests that made it ambiguous (END_EVIDENCE, SKU_SIZE, SKU_SPLIT_SEAM, ...), ``a``
        = ``attempt``.

    Logs written before it existed read back as an empty set.
    """

    hypothesis: np.ndarray = None  # type: ignore[assignment]
    attempt: np.ndarray = None  # type: ignore[assignment]
    corners: np.ndarray = None  # type: ignore[assignment]
    area: np.ndarray = None  # type: ignore[assignment]
    width: np.ndarray = None  # type: ignore[assignment]
    length: np.ndarray = None  # type: ignore[assignment]
    reason: np.ndarray = None  # type: ignore[assignment]
    tests: TestTable = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        n = 0 if self.hypothesis is None else int(np.asarray(self.hypothesis).shape[0])
        for name, value in (("hypothesis", np.zeros(n, np.int64)),
                            ("attempt", np.full(n, -1, np.int64)),
                            ("corners", np.zeros((n, 4, 3))), ("area", np.zeros(n)),
                            ("width", np.full(n, np.nan)), ("length", np.full(n, np.nan)),
                            ("reason", np.zeros(n, np.int8)),
                            ("tests", TestTable.empty(np.nan))):
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return int(self.hypothesis.shape[0])

    def tests_of(self, k: int) -> TestTable:
        """The rows of ``tests`` behind region k."""
        return self.tests.select(self.tests.a == int(self.attempt[k]))

    def to_json_list(self) -> list[dict[str, Any]]:
        """The ``"ambiguous"`` records of the ``locate`` JSON."""
        out = []
        for k in range(len(self)):
            out.append({
                "id": k,
                "corners": self.corners[k].tolist(),
                "area": float(self.area[k]),
                "width": _finite_or_none(self.width[k]),
                "length": _finite_or_none(self.length[k]),
                "reason": AmbiguityReason(int(self.reason[k])).name.lower(),
                "tests": [
                    {"kind": r["kind"], "b": r["b"],
                     "statistic": _finite_or_none(float(r["statistic"])),  # type: ignore[arg-type]
                     "dof": r["dof"], "critical": _finite_or_none(float(r["critical"])),  # type: ignore[arg-type]
                     "decision": "accepted" if r["accepted"] else "rejected"}
                    for r in self.tests_of(k).rows()
                ],
            })
        return out


@dataclass(frozen=True, eq=False)
class Result:
    """Everything one pass of the pipeline produced for one scan.

    ``timing_ms`` is wall-clock and never part of a comparison (see :func:`products_equal`).
    """

    scan_index: int
    capture_time_ns: int
    seed: int
    config_hash: str
    version: str
    edges: EdgeMap
    lines: LineSet
    vertices: VertexSet
    hypotheses: HypothesisSet
    verification: Verification
    selection: Selection
    surfaces: SurfaceSet
    timing_ms: dict[str, float] = field(default_factory=dict)
    #: None only in results read from logs written before the noise stage
    noise: NoiseEstimate | None = None
    #: flat regions not split into boxes (empty in results from before issue #21)
    ambiguous: AmbiguousSet = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.ambiguous is None:
            object.__setattr__(self, "ambiguous", AmbiguousSet())

    def to_json(self) -> dict[str, Any]:
        """The public ``boxloc locate`` output."""
        return {
            "surfaces": self.surfaces.to_json_list(),
            "ambiguous": self.ambiguous.to_json_list(),
            "timing_ms": {k: round(float(v), 3) for k, v in self.timing_ms.items()},
            "version": self.version,
        }


STAGES: tuple[str, ...] = (
    "noise", "edges", "lines", "vertices", "hypotheses", "verification", "selection",
    "surfaces",
)
#: Stages that logs written before them do not have.
OPTIONAL_STAGES: frozenset[str] = frozenset({"noise"})
PRODUCT_TYPES: dict[str, type] = {
    "noise": NoiseEstimate,
    "edges": EdgeMap, "lines": LineSet, "vertices": VertexSet, "hypotheses": HypothesisSet,
    "verification": Verification, "selection": Selection, "surfaces": SurfaceSet,
}


# --- lossless flat encoding ----------------------------------------------------------------

_SEP = "/"


def to_arrays(obj: Any, prefix: str = "") -> dict[str, np.ndarray]:
    """Flatten a product into ``{name: ndarray}``; nested products use ``a/b`` names.

    Scalars become 0-d arrays; strings become 0-d unicode arrays. Lossless with
    :func:`from_arrays`.
    """
    out: dict[str, np.ndarray] = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        name = prefix + f.name
        if dataclasses.is_dataclass(v):
            out.update(to_arrays(v, name + _SEP))
        elif isinstance(v, dict):
            out[name] = np.asarray(json.dumps(v, sort_keys=True))
        else:
            out[name] = np.asarray(v)
    return out


def from_arrays(cls: type, arrays: dict[str, np.ndarray], prefix: str = "") -> Any:
    """Inverse of :func:`to_arrays`."""
    hints = typing.get_type_hints(cls)
    kw: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        name = prefix + f.name
        t = hints[f.name]
        if isinstance(t, type) and dataclasses.is_dataclass(t):
            if f.default is not dataclasses.MISSING and not any(
                    k.startswith(name + _SEP) for k in arrays):
                continue  # a product newer than the log
            kw[f.name] = from_arrays(t, arrays, name + _SEP)
            continue
        if name not in arrays:
            if f.default is not dataclasses.MISSING:  # a field newer than the log
                continue
            raise KeyError(f"missing field {name!r} for {cls.__name__}")
        a = arrays[name]
        if t is int:
            kw[f.name] = int(a)
        elif t is float:
            kw[f.name] = float(a)
        elif t is str:
            kw[f.name] = str(a)
        elif t == dict[str, float] or typing.get_origin(t) is dict:
            kw[f.name] = json.loads(str(a))
        else:
            kw[f.name] = np.asarray(a)
    return cls(**kw)


def products_equal(a: Any, b: Any, ignore: tuple[str, ...] = ("timing_ms",)) -> list[str]:
    """Bit-for-bit comparison of two products; returns the names of fields that differ."""
    fa, fb = to_arrays(a), to_arrays(b)
    diffs = []
    for k in sorted(set(fa) | set(fb)):
        if k.split(_SEP)[-1] in ignore:
            continue
        if k not in fa or k not in fb:
            diffs.append(k)
            continue
        x, y = fa[k], fb[k]
        if x.dtype != y.dtype or x.shape != y.shape:
            diffs.append(k)
        elif np.ascontiguousarray(x).tobytes() != np.ascontiguousarray(y).tobytes():
            diffs.append(k)
    return diffs
