"""Tests of the piled-box simulator (boxloc.simulate): geometry, truth, noise, files, CLI."""

from __future__ import annotations

import dataclasses
import json
import math
import zipfile

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.ndimage import binary_dilation, binary_erosion, distance_transform_edt

from boxloc.calibrate.noise import estimate_noise
from boxloc.cli import cli
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.io import read_scan
from boxloc.products import products_equal
from boxloc.scan import NoiseModel, PinholeModel, Scan
from boxloc.simulate import (
    KINDS,
    PALLET_SIZE,
    GroundTruth,
    SceneSpec,
    SimulatedScan,
    format_spec,
    load_truth,
    look_down_pose,
    override_spec,
    parse_spec,
    save_npz,
    scene_suite,
    simulate,
    simulate_boxes,
)
from boxloc.simulate.raycast import _build_world, _cast, _RayIndex
from boxloc.simulate.sensors import _shadowed
from boxloc.simulate.truth import resting_on

#: Near-noiseless sensor without artefacts, for exact geometry checks.
QUIET = ("noise.sigma0=0.00001,noise.k2=0,noise.sigma_angle=0,dropout=0,mixed_pixels=false,"
         "shadows=false")
#: A small image (same field of view as 640x480 at f=525), for the per-kind invariants.
SMALL = "width=160,height=120,f=131.25"

# One box of known pose, seen from 2 m straight above its centre.
BOX = np.array([0.05, -0.02, PALLET_SIZE[2] + 0.1, 0.3, 0.5, 0.2, 0.3])
TOP = BOX[2] + BOX[5] / 2


def _known_box(spec: str = "single:" + QUIET, box: np.ndarray = BOX,
               target: tuple[float, float] | None = None) -> SimulatedScan:
    tx, ty = (BOX[0], BOX[1]) if target is None else target
    T = look_down_pose([tx, ty, TOP], distance=2.0, tilt=0.0, roll=0.2)
    return simulate_boxes(box[None], T, spec)


def _local_uv(sim: SimulatedScan, box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's ray meets the box's top plane, in the box's local (u, v), metres."""
    T = sim.truth.sensor_to_base
    rays = sim.scan.sensor.rays()
    d_base = rays @ T[:3, :3].T
    t = (box[2] + box[5] / 2 - T[2, 3]) / d_base[..., 2]
    P = T[:3, 3] + t[..., None] * d_base
    c, s = math.cos(box[6]), math.sin(box[6])
    dx, dy = P[..., 0] - box[0], P[..., 1] - box[1]
    return dx * c + dy * s, -dx * s + dy * c


# --- the spec ------------------------------------------------------------------------------


def test_default_noise_is_the_localizers() -> None:
    assert SceneSpec().noise == Config().noise


def test_parse_spec_reads_kind_and_keys() -> None:
    s = parse_spec("mixed:seed=3,distance=2.0,bulge=0.01")
    assert (s.kind, s.seed, s.distance, s.bulge) == ("mixed", 3, 2.0, 0.01)
    assert s.tilt is None and s.noise == NoiseModel()
    s = parse_spec(" Pallet : shadows=false, noise.k2=0.001, layers=none, tilt=0 ")
    assert s.kind == "pallet" and s.shadows is False and s.layers is None and s.tilt == 0.0
    assert s.noise == NoiseModel(k2=0.001)
    assert parse_spec("empty") == SceneSpec(kind="empty")


@pytest.mark.parametrize("spec", [
    SceneSpec(), SceneSpec(kind="mixed", seed=12, distance=1.2345678901234, tilt=0.1),
    SceneSpec(kind="touching", noise=NoiseModel(sigma0=0.003), shadows=False, n_boxes=3),
    SceneSpec(kind="layered", seed=5, pattern="weave"),
])
def test_format_spec_round_trips(spec: SceneSpec) -> None:
    assert parse_spec(format_spec(spec)) == spec
    assert SceneSpec.from_dict(json.loads(json.dumps(spec.to_dict()))) == spec


@pytest.mark.parametrize("text, match", [
    ("boxes", "unknown scene kind 'boxes'"),
    ("", "unknown scene kind"),
    ("pallet:foo=1", "unknown scene key 'foo'"),
    ("pallet:noise.bar=1", "unknown scene key 'noise.bar'"),
    ("pallet:distance", "must be key=value"),
    ("pallet:distance=abc", "distance='abc' is not a valid float"),
    ("pallet:seed=1.5", "seed='1.5' is not a valid int"),
    ("pallet:shadows=maybe", "shadows='maybe' is not a valid bool"),
    ("pallet:seed=1,seed=2", "given twice"),
    ("pallet:distance=-1", "scene distance must be in"),
    ("pallet:tilt=2", "scene tilt must be in"),
    ("pallet:dropout=1", "scene dropout must be in"),
    ("pallet:min_edge=0.5,max_edge=0.3", "scene min_edge must be in"),
    ("pallet:noise.k2=-1", "noise parameter k2"),
    ("pallet:kind=mixed", "unknown scene key 'kind'"),
    ("layered:pattern=herringbone", "scene pattern must be one of grid, weave"),
    ("pallet:pattern=weave", "scene pattern must be grid unless the kind is layered"),
    ("layered:pattern=weave,min_edge=0.35", "unless max_edge >= 2 min_edge"),
])
def test_parse_spec_errors_name_the_problem(text: str, match: str) -> None:
    with pytest.raises(InputError, match=match):
        parse_spec(text)


def test_bad_spec_objects() -> None:
    with pytest.raises(TypeError, match="NoiseModel"):
        SceneSpec(noise={"sigma0": 0.001})  # type: ignore[arg-type]
    with pytest.raises(InputError, match="scene seed"):
        simulate("single", seed=-1)
    with pytest.raises(InputError, match="must be a string"):
        parse_spec(3)  # type: ignore[arg-type]


# --- determinism and the scan contract -------------------------------------------------------


def test_simulate_is_deterministic() -> None:
    a = simulate("partial:seed=5,bulge=0.01")
    b = simulate(SceneSpec(kind="partial", bulge=0.01), seed=5)
    assert a.scan.range.tobytes() == b.scan.range.tobytes()
    assert products_equal(a.truth, b.truth) == []
    assert a.scan.capture_time_ns == b.scan.capture_time_ns
    assert a.spec == b.spec
    # The returned spec has the drawn distance and tilt; it rebuilds the same scan.
    assert a.spec.distance is not None and 1 <= a.spec.distance <= 3
    assert a.spec.tilt is not None and 0 <= a.spec.tilt <= 0.25
    c = simulate(a.spec)
    assert c.scan.range.tobytes() == a.scan.range.tobytes()
    assert products_equal(c.truth, a.truth) == []
    d = simulate("partial:seed=6,bulge=0.01")
    assert d.scan.range.tobytes() != a.scan.range.tobytes()
    assert d.scan.capture_time_ns != a.scan.capture_time_ns


def test_scan_contract() -> None:
    sim = simulate("pallet:seed=2")
    scan = sim.scan
    assert isinstance(scan, Scan) and isinstance(scan.sensor, PinholeModel)
    assert scan.shape == (480, 640) and scan.range.dtype == np.float32
    assert scan.sensor.fx == scan.sensor.fy == 525.0
    assert (scan.sensor.cx, scan.sensor.cy) == (319.5, 239.5)
    assert scan.index == 0 and scan.capture_time_ns > 0
    assert np.array_equal(scan.sensor_to_base, sim.truth.sensor_to_base)
    # The sensor sits `distance` above the pile top, looking down at `tilt`.
    top = float((sim.truth.boxes[:, 2] + sim.truth.boxes[:, 5] / 2).max())
    assert scan.sensor_to_base[2, 3] == pytest.approx(top + sim.spec.distance, abs=1e-9)
    axis = scan.sensor_to_base[:3, 2]
    assert math.acos(-axis[2]) == pytest.approx(sim.spec.tilt, abs=1e-9)
    assert np.allclose(scan.up, [0, 0, 1] @ scan.sensor_to_base[:3, :3])
    # Nearly every pixel returns; the pallet and boxes fill the middle of the view.
    assert 0.9 < scan.valid.mean() < 1.0
    assert (sim.truth.face_ids[200:280, 280:360] >= 0).mean() > 0.5


# --- ground truth geometry ---------------------------------------------------------------------


def test_single_box_at_known_pose() -> None:
    sim = _known_box()
    t = sim.truth
    assert len(t) == 1 and t.boxes.shape == (1, 7)
    assert t.width[0] == pytest.approx(0.3, abs=1e-12)
    assert t.length[0] == pytest.approx(0.5, abs=1e-12)
    # Straight above the face centre at 2 m: the centre is on the optical axis.
    assert np.allclose(t.centers[0], [0, 0, 2.0], atol=1e-12)
    assert np.allclose(t.normals[0], [0, 0, -1], atol=1e-12)
    assert bool(t.fully_exposed[0]) and t.visible_fraction[0] == pytest.approx(1.0, abs=0.02)
    # Corners: c - x w/2 - y l/2, then +x, +x+y, +y; all at the face's distance.
    x, y = t.x_axis[0], t.y_axis[0]
    c0 = t.centers[0] - x * 0.15 - y * 0.25
    want = np.stack([c0, c0 + 0.3 * x, c0 + 0.3 * x + 0.5 * y, c0 + 0.5 * y])
    assert np.allclose(t.corners[0], want, atol=1e-12)
    assert np.allclose(t.corners[0][:, 2], 2.0, atol=1e-12)
    # x along the box's 0.3 m side (base yaw 0.3), y along its 0.5 m side.
    x_base = t.sensor_to_base[:3, :3] @ x
    assert abs(x_base @ [math.cos(0.3), math.sin(0.3), 0]) == pytest.approx(1, abs=1e-12)
    # The face region: every pixel whose ray meets the top well inside the rectangle sees
    # face 0, and none well outside does (2 px = 7.6 mm at 2 m).
    u, v = _local_uv(sim, BOX)
    px = 2.0 / 525.0
    inside = (np.abs(u) < 0.15 - 2 * px) & (np.abs(v) < 0.25 - 2 * px)
    outside = (np.abs(u) > 0.15 + 2 * px) | (np.abs(v) > 0.25 + 2 * px)
    assert inside.sum() > 9000
    assert (t.face_ids[inside] == 0).all()
    assert (t.face_ids[outside] == -1).all()
    # The measured points lie on the top plane (inside the bevel band), in the base frame.
    P = sim.scan.points[inside].astype(np.float64)
    z = P @ t.sensor_to_base[2, :3] + t.sensor_to_base[2, 3]
    assert np.abs(z - TOP).max() < 2e-4


def test_single_kind_face_is_the_box_top() -> None:
    sim = simulate("single:seed=3")
    t = sim.truth
    b = t.boxes[0]
    assert t.width[0] == min(b[3], b[4]) and t.length[0] == max(b[3], b[4])
    top_base = np.array([b[0], b[1], b[2] + b[5] / 2])
    T = t.sensor_to_base
    assert np.allclose(T[:3, :3] @ t.centers[0] + T[:3, 3], top_base, atol=1e-12)
    assert b[2] - b[5] / 2 == pytest.approx(PALLET_SIZE[2])  # it stands on the pallet
    assert bool(t.fully_exposed[0])


def test_visible_fraction_of_a_face_half_out_of_view() -> None:
    # Aim the sensor so that the image's left border (column -0.5) cuts the face in half.
    u_edge = -0.5 - 319.5
    R = look_down_pose([0, 0, 0], 1.0, roll=0.2)[:3, :3]
    shift = R @ np.array([u_edge / 525.0 * 2.0, 0.0, 0.0])  # 2 m below the sensor
    sim = _known_box(target=(BOX[0] - shift[0], BOX[1] - shift[1]))
    assert sim.truth.visible_fraction[0] == pytest.approx(0.5, abs=0.03)
    assert not bool(sim.truth.fully_exposed[0])


@pytest.mark.parametrize("kind", KINDS)
def test_truth_is_consistent(kind: str) -> None:
    sim = simulate(f"{kind}:seed=11,{SMALL}")
    t = sim.truth
    F = len(t)
    assert isinstance(t, GroundTruth)
    assert F == t.boxes.shape[0] and t.box_index.tolist() == list(range(F))
    assert t.centers.shape == (F, 3) and t.corners.shape == (F, 4, 3)
    assert t.face_ids.shape == t.edge_labels.shape == (120, 160)
    assert t.face_ids.dtype == np.int32 and t.edge_labels.dtype == np.uint8
    assert t.fully_exposed.dtype == np.bool_ and t.box_index.dtype == np.int32
    assert set(np.unique(t.edge_labels)) <= {0, 1, 2}
    assert t.face_ids.min() >= -1 and t.face_ids.max() < max(F, 1)
    for a in (t.normals, t.x_axis, t.y_axis):
        assert np.allclose(np.linalg.norm(a, axis=1), 1, atol=1e-12)
    assert np.allclose(np.cross(t.x_axis, t.y_axis), t.normals, atol=1e-12)
    assert ((t.normals * t.centers).sum(1) < 0).all()  # toward the sensor at the origin
    assert (t.width <= t.length).all()
    assert np.allclose(t.corners.mean(1), t.centers, atol=1e-12)
    assert ((t.visible_fraction >= 0) & (t.visible_fraction <= 1)).all()
    assert (t.visible_fraction[t.fully_exposed] >= 0.9).all()
    # a face is graspable when nothing rests on it and it is seen: not covered, seen >= 0.9
    covered = resting_on(t)
    assert covered.shape == (F,) and covered.dtype == np.bool_
    assert (t.fully_exposed == (~covered & (t.visible_fraction >= 0.9))).all()
    with pytest.raises(ValueError):
        t.centers[0, 0] = 1.0  # read-only, like every product
    if kind in ("empty", "floor"):
        assert F == 0 and (t.face_ids == -1).all() and not t.fully_exposed.any()
    else:
        assert F >= 1 and t.fully_exposed.any()
        # Boxes never interpenetrate.
        from boxloc.simulate.boxes import _collides

        for i, b in enumerate(t.boxes):
            others = [o for j, o in enumerate(t.boxes) if j != i]
            assert not _collides(b, others, clearance=-1e-6)


def test_empty_has_no_faces() -> None:
    t = simulate("empty:seed=2").truth
    assert len(t) == 0 and t.boxes.shape == (0, 7) and t.corners.shape == (0, 4, 3)
    assert (t.face_ids == -1).all()
    assert (t.edge_labels == 1).any()  # the pallet's border over the floor


def test_partial_has_covered_faces() -> None:
    seen_covered = 0
    for seed in range(3):
        t = simulate(f"partial:seed={seed},{SMALL}").truth
        assert t.fully_exposed.any() and not t.fully_exposed.all()
        b = t.boxes
        top = b[:, 2] + b[:, 5] / 2
        lower = np.flatnonzero(top < top.max() - 1e-6)
        assert lower.size and not t.fully_exposed[lower].all()
        seen_covered += int((~t.fully_exposed[lower] & (t.visible_fraction[lower] > 0.05)).sum())
    # Some lower face is partly seen yet not graspable: a top-layer box rests on part of it.
    assert seen_covered > 0


def test_pallet_layers_are_neat() -> None:
    t = simulate("pallet:seed=4,layers=3,jitter=0.003").truth
    b = t.boxes
    assert len(np.unique(np.round(b[:, 5], 12))) == 1  # one box size
    assert len({tuple(r) for r in np.round(np.sort(b[:, 3:5], 1), 12)}) == 1
    assert np.abs(b[:, 6]).max() <= math.radians(1) + 1e-12
    levels = np.unique(np.round(b[:, 2], 9))
    assert len(levels) == 3
    n_top = int((np.round(b[:, 2], 9) == levels[-1]).sum())
    assert t.fully_exposed.sum() <= n_top
    assert not t.fully_exposed[np.round(b[:, 2], 9) < levels[-1]].any()


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_weave_layers_have_a_grids_outline_and_are_no_grid(seed: int) -> None:
    spec = SceneSpec(kind="layered", seed=seed, pattern="weave")
    assert "pattern" not in SceneSpec(kind="layered").to_dict()  # old specs' dicts unchanged
    assert spec.to_dict()["pattern"] == "weave"
    b = simulate(spec).truth.boxes
    a = float(np.min(b[:, 3:5]))
    assert np.allclose(np.sort(b[:, 3:5], 1), [a, 2 * a])  # one carton, twice as long as wide
    assert np.all(b[:, 6] == 0) and np.ptp(b[:, 5]) == 0
    for z in np.unique(b[:, 2]):
        lay = b[b[:, 2] == z]
        lo = (lay[:, :2] - lay[:, 3:5] / 2).min(axis=0)
        hi = (lay[:, :2] + lay[:, 3:5] / 2).max(axis=0)
        ext = hi - lo
        # zero gaps, no overlap: the cartons fill their outline exactly ...
        assert np.prod(lay[:, 3:5], axis=1).sum() == pytest.approx(np.prod(ext), rel=1e-9)
        for i in range(len(lay)):
            for j in range(i):
                d = np.abs(lay[i, :2] - lay[j, :2]) - (lay[i, 3:5] + lay[j, 3:5]) / 2
                assert d.max() >= -1e-9, "two cartons overlap"
        # ... which is a grid of the carton one way round: (2 nx + 1) a by ny 2a ...
        nx, ny = (ext[0] / a - 1) / 2, ext[1] / (2 * a)
        assert nx == pytest.approx(round(nx)) and ny == pytest.approx(round(ny))
        assert round(nx) >= 1 and round(ny) >= 1
        # ... but laid with both orientations, one cell of two turned at least
        turned = int((lay[:, 3] > lay[:, 4]).sum())
        assert turned >= 2 and turned % 2 == 0 and turned < len(lay)


def test_touching_boxes_share_height_and_nearly_touch() -> None:
    t = simulate("touching:seed=3,n_boxes=3").truth
    b = t.boxes[np.argsort(t.boxes[:, 0])]
    assert len(b) == 3 and np.ptp(b[:, 5]) == 0 and np.ptp(b[:, 2]) == 0
    gaps = (b[1:, 0] - b[1:, 3] / 2) - (b[:-1, 0] + b[:-1, 3] / 2)
    assert ((gaps >= -1e-12) & (gaps <= 0.002 + 1e-12)).all()


def test_bulge_raises_the_face_centre() -> None:
    flat = _known_box()
    bulged = _known_box("single:bulge=0.01," + QUIET)
    assert products_equal(flat.truth, bulged.truth) == []  # the truth is the nominal face
    c = (240, 320)  # the face centre is on the optical axis
    assert flat.scan.range[c] - bulged.scan.range[c] == pytest.approx(0.01, abs=2e-4)
    u, v = _local_uv(bulged, BOX)
    near_edge = (np.abs(u) < 0.14) & (np.abs(v) > 0.24) & (np.abs(v) < 0.245)
    assert np.abs(flat.scan.range[near_edge] - bulged.scan.range[near_edge]).max() < 1.5e-3


# --- edge labels ----------------------------------------------------------------------------------


def test_edge_labels_outline_a_box() -> None:
    sim = _known_box()
    lab = sim.truth.edge_labels
    u, v = _local_uv(sim, BOX)
    px = 2.0 / 525.0
    # The outline: pixels within about a pixel of the rectangle's border.
    du, dv = np.abs(u) - 0.15, np.abs(v) - 0.25
    border = (np.maximum(du, dv) > -1.5 * px) & (np.maximum(du, dv) < 0.75 * px)
    labelled = binary_dilation(lab > 0, np.ones((3, 3), bool))
    assert labelled[border].mean() > 0.97
    # No labels well inside the face, nor well outside it (the flat pallet).
    inner = np.maximum(du, dv) < -5 * px
    assert (lab[inner] == 0).all()
    away = (np.maximum(du, dv) > 5 * px) & (np.maximum(du, dv) < 10 * px)
    assert (lab[away] == 0).all()
    # Seen from straight above, the box's edge is a jump onto the pallet, labelled on the
    # (nearer) box side; the bevel gives creases just inside.
    jumps = (lab == 1) & (np.abs(np.maximum(du, dv)) < 3 * px)  # not the pallet's border
    assert jumps.sum() > 300
    assert (sim.truth.face_ids[jumps] == 0).mean() > 0.95
    assert ((lab == 2) & (sim.truth.face_ids == 0)).sum() > 100
    # A thin line: the jump pixels sit in the outermost pixel of the face (its bevel band).
    d_jump = np.maximum(du, dv)[jumps] / px
    assert ((d_jump > -1.6) & (d_jump < 0.05)).all()


def test_seam_between_touching_boxes_is_labelled() -> None:
    sim = simulate("touching:seed=3,n_boxes=3,tilt=0.05,distance=1.5," + QUIET)
    f, lab = sim.truth.face_ids, sim.truth.edge_labels
    seam = np.zeros_like(f, bool)
    h = (f[:, :-1] >= 0) & (f[:, 1:] >= 0) & (f[:, :-1] != f[:, 1:])
    v = (f[:-1] >= 0) & (f[1:] >= 0) & (f[:-1] != f[1:])
    seam[:, :-1] |= h
    seam[:-1] |= v
    assert seam.sum() > 100
    near = binary_dilation(lab > 0, np.ones((3, 3), bool))
    assert near[seam].mean() > 0.98
    # The seam is a V groove between the bevels: creases, not an occlusion.
    around = binary_dilation(seam, np.ones((5, 5), bool))
    assert (lab[around] == 2).sum() > (lab[around] == 1).sum()


# --- the sensor's artefacts ---------------------------------------------------------------------


@pytest.mark.parametrize("tilt, distance", [(0.0, 2.0), (0.25, 2.8)])
def test_noise_matches_the_model_on_the_floor(tilt: float, distance: float) -> None:
    sim = simulate(f"empty:seed=4,tilt={tilt},distance={distance},mixed_pixels=false,"
                   "shadows=false,dropout=0")
    scan = sim.scan
    T = scan.sensor_to_base
    rays = scan.sensor.rays()
    # The noise-free range to the floor plane z = 0, and the model's sigma there.
    n = T[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    nu = rays @ n
    r0 = -T[2, 3] / nu
    sigma = NoiseModel().sigma_range(r0, nu)
    P = scan.points.astype(np.float64)
    z = P @ T[2, :3] + T[2, 3]
    floor = binary_erosion(np.isfinite(scan.range) & (np.abs(z) < 0.05), iterations=3)
    assert floor.sum() > 50_000
    res = (scan.range.astype(np.float64) - r0)[floor] / sigma[floor]
    assert abs(res.mean()) < 0.05
    assert res.std() == pytest.approx(1.0, rel=0.15)
    # The range noise grows with range: far pixels scatter more in metres.
    far = floor & (r0 > np.percentile(r0[floor], 80))
    near = floor & (r0 < np.percentile(r0[floor], 20))
    dr = scan.range.astype(np.float64) - r0
    assert dr[far].std() > dr[near].std()


def test_override_spec_replaces_fields_and_keeps_the_rest() -> None:
    s = parse_spec("mixed:seed=3,distance=2.0,noise.k2=0.001")
    t = override_spec(s, ["distance=2.5", "noise.row_corr=0.2"])
    assert (t.kind, t.seed, t.distance) == ("mixed", 3, 2.5)
    assert (t.noise.k2, t.noise.row_corr) == (0.001, 0.2)
    assert override_spec(s, []) == s
    with pytest.raises(InputError, match="bogus"):
        override_spec(s, ["bogus=1"])
    with pytest.raises(InputError, match="key=value"):
        override_spec(s, ["distance"])


def test_row_correlated_noise_is_shared_along_rows() -> None:
    spec = parse_spec("empty:seed=4,tilt=0.1,distance=2,mixed_pixels=false,shadows=false,"
                      "dropout=0")
    iid = simulate(spec).scan
    rho = 0.3
    rows = simulate(dataclasses.replace(
        spec, noise=dataclasses.replace(spec.noise, row_corr=rho))).scan
    model, _ = estimate_noise([rows])
    assert model.row_corr == pytest.approx(rho, abs=0.05)
    assert estimate_noise([iid])[0].row_corr < 0.03
    # the same total noise: the row offsets are a share of it, not more of it
    assert model.sigma_range(2.0) == pytest.approx(
        estimate_noise([iid])[0].sigma_range(2.0), rel=0.1)


def test_dropouts() -> None:
    none = simulate("pallet:seed=1,dropout=0,shadows=false")
    assert np.isfinite(none.scan.range).all()
    some = simulate("pallet:seed=1,dropout=0.05,shadows=false")
    assert np.isnan(some.scan.range).mean() == pytest.approx(0.05, abs=0.005)


def test_shadows_fall_beside_jumps_and_match_a_full_cast() -> None:
    lit = simulate("mixed:seed=2,dropout=0,shadows=false")
    dark = simulate("mixed:seed=2,dropout=0")
    shadow = np.isnan(dark.scan.range)
    assert shadow.sum() > 50 and np.isfinite(lit.scan.range).all()
    # Shadows are strips next to depth jumps (here at most f b (1/z_near - 1/z_far), a few
    # px, wide).
    assert distance_transform_edt(dark.truth.edge_labels != 1)[shadow].max() < 10
    # The fast path (only pixels near a surface change) equals casting every pixel.
    spec = dark.spec
    T = dark.truth.sensor_to_base
    world = _build_world(dark.truth.boxes, T, spec.bevel, spec.bulge)
    rays = dark.scan.sensor.rays().reshape(-1, 3)
    r0, surf, _ = _cast(world, np.zeros(3), rays, _RayIndex(rays, (480, 640)))
    X = np.where(np.isfinite(r0), r0, np.nan)[:, None] * rays
    fast = _shadowed(world, X, surf, spec.baseline, spec.f, (480, 640))
    full = _shadowed(world, X, surf, spec.baseline, spec.f, (480, 640), everywhere=True)
    assert np.array_equal(fast, full)
    assert np.array_equal(fast.reshape(480, 640), shadow)


def test_mixed_pixels_sit_between_the_surfaces_of_a_jump() -> None:
    quiet = QUIET.replace("mixed_pixels=false", "mixed_fraction=1")
    on = _known_box("single:" + quiet)
    off = _known_box("single:" + quiet.replace("mixed_fraction=1", "mixed_pixels=false"))
    r_on, r_off = on.scan.range.astype(np.float64), off.scan.range.astype(np.float64)
    near_box = binary_dilation(on.truth.face_ids == 0, np.ones((7, 7), bool))
    changed = (np.abs(r_on - r_off) > 0.005) & near_box
    assert changed.sum() > 100
    # Only at jumps: every changed pixel is a jump pixel or next to one.
    jumps = binary_dilation(on.truth.edge_labels == 1, np.ones((3, 3), bool))
    assert jumps[changed].all()
    # Their ranges lie strictly between the box top (2 m) and the pallet (2.2 m).
    assert ((r_on[changed] > 2.0 + 0.002) & (r_on[changed] < 2.2 - 0.002)).mean() > 0.9


# --- files ---------------------------------------------------------------------------------------


def test_save_npz_and_load_truth_round_trip(tmp_path) -> None:
    sim = simulate("partial:seed=8,bulge=0.005")
    p = tmp_path / "scan.npz"
    save_npz(sim, p)
    with np.load(p, allow_pickle=False) as z:
        keys = set(z.files)
        assert {"points", "intrinsics", "range", "sensor_to_base", "capture_time_ns",
                "spec"} <= keys
        assert z["points"].dtype == np.float32 and z["points"].shape == (480, 640, 3)
        assert z["range"].dtype == np.float32
        assert z["capture_time_ns"].dtype == np.int64 and z["capture_time_ns"].shape == ()
        assert int(z["capture_time_ns"]) == sim.scan.capture_time_ns
        assert np.array_equal(z["intrinsics"], sim.scan.sensor.K)
        spec = SceneSpec.from_dict(json.loads(str(z["spec"])))
        assert np.array_equal(z["points"], sim.scan.points, equal_nan=True)
    assert spec == sim.spec
    assert {k for k in keys if k.startswith("truth/")} == {
        "truth/" + f.name for f in dataclasses.fields(GroundTruth)}
    truth = load_truth(p)
    assert truth is not None and products_equal(truth, sim.truth) == []
    # The scan part is the public layout that boxloc.io reads.
    scan = read_scan(p)
    assert scan.range.tobytes() == sim.scan.range.tobytes()
    assert np.array_equal(scan.sensor_to_base, sim.scan.sensor_to_base)
    # Same scan, same bytes.
    q = tmp_path / "again.npz"
    save_npz(simulate(sim.spec), q)
    assert p.read_bytes() == q.read_bytes()


def test_load_truth_without_truth_or_file(tmp_path) -> None:
    p = tmp_path / "plain.npz"
    np.savez(p, range=np.ones((4, 4), np.float32))
    assert load_truth(p) is None
    with pytest.raises(InputError, match="not found"):
        load_truth(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(InputError, match="cannot read"):
        load_truth(bad)
    part = tmp_path / "part.npz"
    with zipfile.ZipFile(part, "w") as zf, zf.open("truth/centers.npy", "w") as f:
        np.lib.format.write_array(f, np.zeros((0, 3)))
    with pytest.raises(InputError, match="incomplete ground truth"):
        load_truth(part)


# --- the suite ----------------------------------------------------------------------------------


def test_scene_suite() -> None:
    a = scene_suite(12, seed=1)
    assert a == scene_suite(12, seed=1)
    assert scene_suite(5, seed=1) == a[:5]
    assert a != scene_suite(12, seed=2)
    kinds = {s.kind for s in a}
    assert kinds == set(KINDS) - {"empty", "layered", "floor"}  # the suite predates these
    assert all(1 <= s.distance <= 3 and 0 <= s.tilt <= 0.25 for s in a)
    assert any(s.bulge > 0 for s in a) and any(s.bulge == 0 for s in a)
    assert len({s.seed for s in a}) == 12
    assert scene_suite(0) == []
    with pytest.raises(InputError, match="suite size"):
        scene_suite(-1)


# --- the command line -------------------------------------------------------------------------


def test_cli_simulate_writes_files(tmp_path) -> None:
    runner = CliRunner()
    out = tmp_path / "one.npz"
    r = runner.invoke(cli, ["simulate", "single:" + SMALL, "--seed", "4", "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert out.is_file() and "boxes=1 faces=1 graspable=1" in r.output
    t = load_truth(out)
    assert t is not None and products_equal(t, simulate("single:" + SMALL, seed=4).truth) == []

    r = runner.invoke(cli, ["simulate", "touching:" + SMALL, "--count", "2",
                            "--out", str(tmp_path / "many.npz")])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in tmp_path.glob("many_*.npz")) == ["many_000.npz",
                                                                   "many_001.npz"]
    assert len(r.output.strip().splitlines()) == 2

    d = tmp_path / "dir"
    d.mkdir()
    r = runner.invoke(cli, ["simulate", "empty:" + SMALL, "--seed", "7", "--out", str(d)])
    assert r.exit_code == 0, r.output
    assert [p.name for p in d.iterdir()] == ["empty_0007.npz"]
    assert "faces=0 graspable=0" in r.output


@pytest.mark.parametrize("args, match", [
    (["simulate", "crates", "--out", "x.npz"], "unknown scene kind 'crates'"),
    (["simulate", "pallet:distance=zero", "--out", "x.npz"], "distance='zero'"),
    (["simulate", "pallet", "--count", "0", "--out", "x.npz"], "count must be >= 1"),
    (["simulate", "pallet", "--out", "no/such/dir/x.npz"], "output directory does not exist"),
])
def test_cli_simulate_errors_are_one_line(tmp_path, monkeypatch, args, match) -> None:
    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(cli, args)
    assert r.exit_code == 2
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and match in lines[0] and "Traceback" not in r.output
    assert not list(tmp_path.glob("*.npz"))
