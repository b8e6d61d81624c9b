"""Tests of boxloc.evaluate.funnel (where each exposed top is lost) and its place in the
matrix bench (tiny constructed scenes; no timings)."""

from __future__ import annotations

import dataclasses
import doctest
import io
from typing import Any

import numpy as np
import pytest
from rich.console import Console

import boxloc.evaluate.funnel as fn
import boxloc.evaluate.matrix_bench as bm
import boxloc.simulate as sim
from boxloc.config import Config
from boxloc.evaluate.metrics import iou_matrix, match_surfaces, rect_iou_matrix
from boxloc.pipeline import find_graspable_surfaces
from boxloc.products import DimensionSource, VerifyReason
from boxloc.scan import PinholeModel

#: The site's box range (the matrix bench's only setting).
CFG = Config(min_edge=0.15, max_edge=0.6)
#: A single box at 320 x 240 that the pipeline finds (seeded; pins past output).
SINGLE = sim.SceneSpec(kind="single", seed=2, width=320, height=240, f=262.5)
#: One layer of eight boxes with gaps: every top found (seeded; pins past output).
PALLET = sim.SceneSpec(kind="pallet", seed=3, width=320, height=240, f=262.5, layers=1)


def _touching(**kw: Any) -> sim.SceneSpec:
    """Two boxes of equal height in a row, sharp flat lids, no shadows."""
    base: dict[str, Any] = {"kind": "touching", "seed": 0, "width": 320, "height": 240,
                            "f": 262.5, "n_boxes": 2, "max_gap": 0.0, "bevel": 0.0,
                            "shadows": False}
    return sim.SceneSpec(**{**base, **kw})


def _no_surfaces(surfaces: Any) -> Any:
    """The same SurfaceSet with no rows."""
    n = len(surfaces)
    return dataclasses.replace(surfaces, **{
        f.name: v[:0] for f in dataclasses.fields(surfaces)
        if isinstance(v := getattr(surfaces, f.name), np.ndarray) and v.shape[:1] == (n,)})


@pytest.fixture(scope="module")
def single() -> tuple[Any, Any]:
    s = sim.simulate(SINGLE)
    return s, find_graspable_surfaces(s.scan, CFG)


# --- the stages -------------------------------------------------------------------------


def test_a_found_box_is_found_with_all_its_evidence(single: tuple[Any, Any]) -> None:
    s, res = single
    fl = fn.loss_stages(res, s.truth, s.scan.sensor)
    assert len(fl) == 1 and fl.face.tolist() == [0]
    assert fl.stage_names() == ["found"]
    assert fl.edge_sides[0] == 4 and fl.line_sides[0] >= 2 and fl.vertices[0] >= 1
    assert fl.best_iou[0] > 0.9
    assert fl.best_reason[0] == VerifyReason.ACCEPTED
    assert fl.best_source[0] in {int(v) for v in DimensionSource}
    assert fl.separable.tolist() == [True]
    assert fl.counts() == {**{n: 0 for n in fn.STAGE_NAMES}, "found": 1}
    assert fl.verify_reasons() == {} and fl.hyp_sources() == {}
    d = fl.to_dict()
    assert d["stage"] == ["found"] and d["best_reason"] == ["ACCEPTED"]
    # the bench's match gives the same answer as the one loss_stages makes
    m = match_surfaces(res.surfaces, s.truth)
    assert fn.loss_stages(res, s.truth, s.scan.sensor, match=m).to_dict() == d


def test_without_its_surface_the_box_is_lost_at_selection(single: tuple[Any, Any]) -> None:
    s, res = single
    nothing = dataclasses.replace(res, surfaces=_no_surfaces(res.surfaces))
    fl = fn.loss_stages(nothing, s.truth, s.scan.sensor)
    assert fl.stage_names() == ["select"]  # verified, but no surface is a true positive


def test_rejected_attempts_are_verify_losses_with_their_reason(
        single: tuple[Any, Any]) -> None:
    s, res = single
    v = res.verification
    refused = dataclasses.replace(v, accepted=np.zeros_like(v.accepted),
                                  reason=np.full_like(v.reason, VerifyReason.BOUNDARY))
    no_surf = _no_surfaces(res.surfaces)
    fl = fn.loss_stages(dataclasses.replace(res, verification=refused, surfaces=no_surf),
                        s.truth, s.scan.sensor)
    assert fl.stage_names() == ["verify"]
    assert fl.verify_reasons() == {"BOUNDARY": 1}


def test_no_lines_is_a_lines_or_edges_loss() -> None:
    s = sim.simulate(PALLET)
    full = fn.loss_stages(find_graspable_surfaces(s.scan, CFG), s.truth, s.scan.sensor)
    assert set(full.stage_names()) == {"found"} and len(full) == 8
    # a line budget of one neighbour point: the Hough stage stops before any box side
    res = find_graspable_surfaces(s.scan, dataclasses.replace(CFG, max_line_work=1))
    fl = fn.loss_stages(res, s.truth, s.scan.sensor)
    assert len(res.surfaces) == 0
    assert set(fl.stage_names()) <= {"lines", "edges"} and "lines" in fl.stage_names()
    assert (fl.line_sides <= 1).all()
    # the edges are the same as with the full budget: only the lines are missing
    assert fl.edge_sides.tolist() == full.edge_sides.tolist()
    assert (fl.edge_sides >= fn.MIN_SIDES).all()
    # no edges at all: every top is lost there
    blank = dataclasses.replace(res, edges=dataclasses.replace(
        res.edges, labels=np.zeros_like(res.edges.labels)))
    assert set(fn.loss_stages(blank, s.truth, s.scan.sensor).stage_names()) == {"edges"}


# --- separable --------------------------------------------------------------------------


def test_touching_flush_tops_are_not_separable() -> None:
    s = sim.simulate(_touching())
    t = s.truth
    assert len(t) == 2 and t.fully_exposed.all()
    assert abs(t.normals[0] @ (t.centers[1] - t.centers[0])) < 1e-6  # one plane
    # the render labels the seam (two objects meet) although the range image is one plane
    assert fn.sides_shown(t.edge_labels, t.corners, s.scan.sensor).all()
    assert fn.separable_faces(t, s.scan.sensor).tolist() == [False, False]
    # with relief along the seam (a bevel or a bulge) it would show
    assert fn.separable_faces(t, s.scan.sensor, flush_seams_show=True).tolist() == [True, True]
    res = find_graspable_surfaces(s.scan, CFG)
    assert fn.loss_stages(res, t, s.scan.sensor).separable.tolist() == [False, False]


def test_a_gap_makes_touching_tops_separable() -> None:
    s = sim.simulate(_touching(max_gap=0.03))
    assert fn.separable_faces(s.truth, s.scan.sensor).tolist() == [True, True]


def test_a_layer_packed_without_gaps_is_not_separable() -> None:
    s = sim.simulate(sim.SceneSpec(kind="layered", seed=0, width=320, height=240, f=262.5,
                                   layers=1, bevel=0.0, shadows=False))
    assert len(s.truth) >= 2
    assert not fn.separable_faces(s.truth, s.scan.sensor).any()


# --- the pieces -------------------------------------------------------------------------


def test_sides_shown_on_a_drawn_square() -> None:
    cam = PinholeModel(fx=100.0, fy=100.0, cx=50.0, cy=50.0, width=100, height=100)
    sq = np.array([[[-0.2, -0.2, 1.0], [0.2, -0.2, 1.0], [0.2, 0.2, 1.0], [-0.2, 0.2, 1.0]]])
    labels = np.zeros((100, 100), np.uint8)
    labels[30, 30:71] = 1  # side 0 (v = 30)
    labels[30:71, 72] = 2  # side 1 (u = 70), 2 px off: within EDGE_TOL_PX
    labels[70:71, 30:45] = 1  # side 2 (v = 70), a third of it: below SIDE_SHOWN
    labels[30:71, 27] = 1  # side 3 (u = 30), 3 px off: outside
    assert fn.sides_shown(labels, sq, cam).tolist() == [[True, True, False, False]]
    # a square behind the camera or out of the image shows nothing
    assert not fn.sides_shown(labels, sq * [1, 1, -1], cam).any()
    assert not fn.sides_shown(labels, sq + [5.0, 0, 0], cam).any()
    assert fn.sides_shown(labels, np.zeros((0, 4, 3)), cam).shape == (0, 4)


@pytest.mark.parametrize(("labels", "corners", "match"), [
    (np.zeros((4, 4, 3)), np.zeros((1, 4, 3)), "labels must have shape"),
    (np.zeros((4, 4)), np.zeros((1, 3, 3)), "corners must have shape"),
])
def test_sides_shown_refuses_bad_shapes(labels: Any, corners: Any, match: str) -> None:
    cam = PinholeModel(fx=10.0, fy=10.0, cx=2.0, cy=2.0, width=4, height=4)
    with pytest.raises(ValueError, match=match):
        fn.sides_shown(labels, corners, cam)


def test_the_funnels_iou_is_the_bench_iou() -> None:
    """The funnel's IoU of attempts (metrics.rect_iou_matrix on arrays) against
    metrics.iou_matrix (the bench's) on random rectangles near random faces: the same
    figure, gates included."""
    rng = np.random.default_rng(7)
    F, K = 6, 60
    nrm = np.tile([0.0, 0.0, -1.0], (F, 1))
    truth = dataclasses.make_dataclass("T", ["centers", "normals", "x_axis", "y_axis",
                                             "width", "length"])(
        rng.uniform([-1, -1, 2], [1, 1, 2.05], (F, 3)), nrm,
        np.tile([1.0, 0, 0], (F, 1)), np.tile([0, -1.0, 0], (F, 1)),
        rng.uniform(0.15, 0.6, F), rng.uniform(0.15, 0.6, F))
    f = rng.integers(0, F, K)
    a = rng.uniform(0, 2 * np.pi, K)
    x = np.stack([np.cos(a), np.sin(a), rng.normal(0, 0.05, K)], 1)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(nrm[f], x)
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    o = truth.centers[f] + rng.normal(0, 0.15, (K, 3)) * [1, 1, 0.05]
    w, ln = rng.uniform(0.05, 0.7, (2, K))
    c = np.stack([o, o + x * w[:, None], o + x * w[:, None] + y * ln[:, None],
                  o + y * ln[:, None]], 1)
    c[3] = np.nan  # an attempt without a rectangle scores 0

    class Rects:
        centers, corners, normals = c.mean(axis=1), c, nrm[f]

        def __len__(self) -> int:
            return K

    want = iou_matrix(Rects(), truth, max_plane_offset=fn.MAX_PLANE_OFFSET)  # type: ignore[arg-type]
    with np.errstate(invalid="ignore"):
        got = rect_iou_matrix(c.mean(axis=1), c, nrm[f], truth,
                              max_plane_offset=fn.MAX_PLANE_OFFSET)
    assert (want > 0).sum() > 20  # the case is not trivial
    assert not got[3].any()
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_funnel_figures_pool_the_scans() -> None:
    scans = [(["found", "verify", "edges"], [True, True, False], [True, False, False],
              {"verify": {"BOUNDARY": 1}, "hyp": {}}),
             (["none", "verify", "hyp"], [False, True, True], [False, False, False],
              {"verify": {"CONTINUES": 1}, "hyp": {"REGION": 1}}),
             ([], [], [], {})]
    f = fn.funnel_figures(scans)
    assert f["faces"] == 6
    assert f["stages"] == {**{n: 0 for n in fn.STAGE_NAMES}, "found": 1, "verify": 2,
                           "edges": 1, "hyp": 1, "none": 1}
    assert list(f["stages"]) == [*fn.STAGE_NAMES, fn.NO_PRODUCTS]
    assert f["verify_reasons"] == {"BOUNDARY": 1, "CONTINUES": 1}
    assert f["hyp_sources"] == {"REGION": 1}
    assert (f["separable"], f["separable_tp"]) == (4, 1)
    assert f["separable_recall"] == pytest.approx(1 / 4)
    assert f["inseparable_misses"] == 2
    assert fn.funnel_figures([])["separable_recall"] is None


def test_the_docstring_examples_hold() -> None:
    out = doctest.testmod(fn, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert out.attempted >= 2 and out.failed == 0


# --- in the matrix bench ----------------------------------------------------------------


def _tiny(pick: tuple[int, ...]) -> list[Any]:
    base = sim.matrix_suite(32, 0)
    return [dataclasses.replace(base[i], width=160, height=120,
                                f=base[i].f * 160 / base[i].width) for i in pick]


def test_the_matrix_bench_reports_the_funnel() -> None:
    specs = _tiny((4, 5, 20, 28))  # laser and tof pallets, a laser layered pallet, a floor
    r = bm.run_matrix_bench(specs=specs, progress=False, warmup=False)
    assert [x["status"] for x in r["scenes"]] == ["ok"] * 4, r["errors"]
    for x in r["scenes"]:
        fl = x["funnel"]
        assert len(fl["face"]) == x["n_exposed"] == len(fl["stage"]) == len(fl["separable"])
        assert fl["stage"].count("found") == x["match"]["tp"]
    groups = [r["groups"]["overall"]["all"], r["groups"]["overall"]["development"],
              *r["groups"]["sensors"].values(), *r["groups"]["cells"].values()]
    for g in groups:
        f = g["funnel"]
        assert f["faces"] == g["n_exposed"] == sum(f["stages"].values())
        assert f["stages"]["found"] == g["tp"] and f["stages"]["none"] == 0
        assert sum(f["verify_reasons"].values()) == f["stages"]["verify"]
        assert sum(f["hyp_sources"].values()) == f["stages"]["hyp"]
        assert f["separable_tp"] <= min(f["separable"], g["tp"])
        assert f["inseparable_misses"] == g["fn"] - (f["separable"] - f["separable_tp"])
        assert f["funnel_errors"] == 0
    rows = r["scenes"]
    sep = sum(sum(x["funnel"]["separable"]) for x in rows)
    assert r["groups"]["overall"]["all"]["funnel"]["separable"] == sep
    # the layered pallet's tops touch flush (no bevel, no gap): none is separable
    layered = rows[2]
    assert layered["kind"] == "layered" and layered["n_exposed"] > 0
    if not specs[2].bulge:
        assert not any(layered["funnel"]["separable"])
    assert r["timing"]["funnel_ms"]["total"] > 0
    # the printed table has a loss line per sensor and overall
    con = Console(file=io.StringIO(), width=250, no_color=True)
    bm.print_matrix_report(r, con)
    text = con.file.getvalue()  # type: ignore[attr-defined]
    assert "where the exposed tops were lost" in text
    for s in ("laser", "tof (held out)", "all but tof", "all, tof included"):
        line = next(ln for ln in text.splitlines() if ln.strip().startswith(s + "  "))
        assert "tops:" in line and "separable" in line
    # ... and a line of its false surfaces by kind, which add up to its false positives
    assert "what the false surfaces are" in text
    after = text.split("what the false surfaces are")[1].splitlines()
    for s, key in (("laser", "laser"), ("all but tof", None)):
        fig = (r["groups"]["sensors"][key] if key else r["groups"]["overall"]["development"])
        line = next(ln for ln in after if ln.strip().startswith(s + "  "))
        assert line.split()[len(s.split())] == str(fig["fp"])
        assert sum(int(w.rstrip(",")) for w in line.split(":")[-1].split()[1::2]
                   if ":" in line) == (fig["fp"] if ":" in line else 0)


def test_a_scan_without_stage_products_counts_its_misses_as_none() -> None:
    specs = _tiny((4,))
    truth = sim.simulate(specs[0]).truth
    ex = np.flatnonzero(truth.fully_exposed)

    def two_tops(scan: Any, config: Any) -> Any:  # surfaces only: no stage products
        from types import SimpleNamespace

        from boxloc.evaluate.baseline import surface_set_from_rects

        k = ex[:2]
        return SimpleNamespace(surfaces=surface_set_from_rects(
            truth.centers[k], truth.normals[k], truth.x_axis[k], truth.width[k],
            truth.length[k], up=scan.up), edges=None, timing_ms={})

    r = bm.run_matrix_bench(specs=specs, localizer=two_tops, progress=False, warmup=False)
    (row,) = r["scenes"]
    assert row["funnel"] is None and row["match"]["tp"] == 2
    f = r["groups"]["overall"]["all"]["funnel"]
    assert f["stages"]["found"] == 2 and f["stages"]["none"] == len(ex) - 2
    assert f["faces"] == len(ex)
    assert r["timing"]["funnel_ms"]["total"] == 0.0


# --- the vertex normals' calibration ------------------------------------------------------


def _rotated(vertices: Any, angle: float) -> Any:
    """The vertices with d1 and d2 (and so the normal) turned by ``angle`` about d1."""
    d1, d2 = vertices.d1, vertices.d2
    n = np.cross(d1, d2)
    d2r = np.cos(angle) * d2 + np.sin(angle) * n
    return dataclasses.replace(vertices, d2=d2r, normals=np.cross(d1, d2r))


def test_a_vertex_normal_off_by_k_sigma_scores_k_squared(single: tuple[Any, Any]) -> None:
    s, r = single
    V = r.vertices
    base = fn.vertex_normal_chi2(V, s.truth)
    assert base.size >= 1 and np.all(np.isfinite(base))
    # put the true normal on the vertex nearest an exposed corner, then turn it by 10 sigma
    exposed = np.flatnonzero(s.truth.fully_exposed)
    corners = s.truth.corners[exposed].reshape(-1, 3)
    i = int(np.argmin(np.linalg.norm(V.points[:, None] - corners[None], axis=-1).min(axis=1)))
    Vi = dataclasses.replace(V, **{f: getattr(V, f)[i:i + 1] for f in
                                   ("points", "d1", "d2", "normals", "covariances",
                                    "line_a", "line_b")})
    f = s.truth.normals[exposed[np.argmax(np.abs(s.truth.normals[exposed] @ Vi.normals[0]))]]
    f = f * np.sign(f @ Vi.normals[0])
    d1 = Vi.d1[0] - (Vi.d1[0] @ f) * f
    d1 /= np.linalg.norm(d1)
    exact = dataclasses.replace(Vi, d1=d1[None], d2=np.cross(f, d1)[None], normals=f[None])
    assert fn.vertex_normal_chi2(exact, s.truth)[0] == pytest.approx(0.0, abs=1e-9)
    from boxloc.stages.vertices import normal_covariance
    Sn = normal_covariance(exact)[0]
    axis = np.cross(f, d1)  # turning about d1 moves the normal along d2
    # the standard deviation along that axis given the other (the Mahalanobis scale)
    B = np.stack([d1, axis])
    sigma = float(1.0 / np.sqrt(np.linalg.inv(B @ Sn @ B.T)[1, 1]))
    turned = _rotated(exact, 10.0 * sigma)
    assert fn.vertex_normal_chi2(turned, s.truth)[0] == pytest.approx(100.0, rel=0.05)


def test_vertices_far_from_every_exposed_corner_do_not_count(single: tuple[Any, Any]) -> None:
    s, r = single
    far = dataclasses.replace(r.vertices, points=r.vertices.points + 0.5)
    assert fn.vertex_normal_chi2(far, s.truth).size == 0
    assert fn.vertex_normal_figures([]) == {"n": 0, "median": None, "beyond_p99": None}
    fig = fn.vertex_normal_figures([0.5, 1.0, 20.0, 30.0])
    assert fig["n"] == 4 and fig["median"] == pytest.approx(10.5)
    assert fig["beyond_p99"] == pytest.approx(0.5)


# --- the lines' direction calibration -------------------------------------------------------


def _one_line_along(lines: Any, a: np.ndarray, b: np.ndarray, turn: np.ndarray | None = None
                    ) -> Any:
    """``lines``' first line moved onto the segment a-b (its covariance and kind kept),
    its direction turned by the vector ``turn`` (then renormalized) if given."""
    d = (b - a) / np.linalg.norm(b - a)
    if turn is not None:
        d = (d + turn) / np.linalg.norm(d + turn)
    one = {f: getattr(lines, f)[:1].copy() for f in
           ("points", "directions", "covariances", "starts", "ends", "kinds")}
    one.update(points=(0.5 * (a + b))[None], directions=d[None], starts=a[None],
               ends=b[None])
    return dataclasses.replace(lines, **one)


def test_a_line_turned_out_of_the_top_by_k_sigma_scores_k(single: tuple[Any, Any]) -> None:
    s, r = single
    z, kinds = fn.line_direction_z(r.lines, s.truth)
    assert z.size >= 2 and np.all(np.isfinite(z)) and kinds.shape == z.shape
    C, n = s.truth.corners[0], s.truth.normals[0] / np.linalg.norm(s.truth.normals[0])
    on = _one_line_along(r.lines, C[0], C[1])
    assert fn.line_direction_z(on, s.truth)[0] == pytest.approx([0.0], abs=1e-9)
    sigma = float(np.sqrt(n @ on.covariances[0, 3:, 3:] @ n))
    turned = _one_line_along(r.lines, C[0], C[1], turn=5.0 * sigma * n)
    assert abs(fn.line_direction_z(turned, s.truth)[0][0]) == pytest.approx(5.0, rel=0.02)
    # a line across the top (not along a side) and one far off it do not count
    across = _one_line_along(r.lines, C[0], C[2])
    far = _one_line_along(r.lines, C[0] + 0.3 * n, C[1] + 0.3 * n)
    assert fn.line_direction_z(across, s.truth)[0].size == 0
    assert fn.line_direction_z(far, s.truth)[0].size == 0


def test_line_direction_figures_pool_jump_and_crease_lines_apart() -> None:
    fig = fn.line_direction_figures([0.1, -3.0, 0.5, 2.0, -0.2], [1, 1, 2, 3, 4])
    assert fig["jump"] == {"n": 2, "median_abs": pytest.approx(1.55), "beyond_p99": 0.5}
    assert fig["crease"] == {"n": 2, "median_abs": pytest.approx(1.25), "beyond_p99": 0.0}
    assert fn.line_direction_figures([], [])["jump"] == {
        "n": 0, "median_abs": None, "beyond_p99": None}


def test_the_false_kind_line_names_the_kinds_there_are_most_first() -> None:
    fig = {"fp": 15, "false_kinds": {"no_top": 4, "covered": 1, "seen_in_part": 0,
                                     "wrong_rectangle": 10, "normal": 0}}
    assert bm.false_kind_line(fig) == "15 false: wrong_rectangle 10, no_top 4, covered 1"
    assert bm.false_kind_line({"fp": 0, "false_kinds": dict.fromkeys(fig["false_kinds"], 0)}
                              ) == "0 false"
