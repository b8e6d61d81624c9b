"""The ``scan`` and ``pipeline`` cases: :class:`boxloc.scan.Scan` and the sensor models on
adversarial arrays, and the pipeline (recorded and read back) on tiny degenerate scans.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from recorder.fuzz.cases import Job, _pick
from recorder.fuzz.scan_files import _adv_array, _roundtrip


def _gen_scan(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    from boxloc.scan import PinholeModel, RayTableModel, Scan

    what = str(_pick(rng, ["range", "range", "points", "points", "pinhole", "raytable"]))
    if what == "range":
        a, desc = _adv_array(rng, 2)
        hw = a.shape if a.ndim == 2 and a.shape[0] > 0 and a.shape[1] > 0 else (1, 1)
        if rng.random() < 0.1:
            hw = (hw[0] + 1, hw[1])
        _save(d, "range", a)
        t_ns = int(_pick(rng, [0, 1, 2**62]))

        def make() -> Any:
            return Scan(range=a, sensor=PinholeModel(40.0, 40.0, hw[1] / 2, hw[0] / 2,
                                                     int(hw[1]), int(hw[0])),
                        capture_time_ns=t_ns)
    elif what == "points":
        P, desc = _adv_array(rng, 3, last=int(_pick(rng, [3, 3, 3, 2])))
        _save(d, "points", P)
        K = None if rng.random() < 0.6 else np.array([[40.0, 0, 10], [0, 40, 10], [0, 0, 1]])

        def make() -> Any:
            return Scan.from_points(P, K)
    elif what == "pinhole":
        vals = [np.nan, np.inf, -np.inf, 0.0, -1.0, 1e-300, 1e300, 5.0, 40.0]
        fx, fy, cx, cy = (float(_pick(rng, vals)) for _ in range(4))
        W, H = int(_pick(rng, [0, -1, 1, 3, 40])), int(_pick(rng, [0, -1, 1, 3, 30]))
        desc = f"fx={fx},fy={fy},cx={cx},cy={cy},{W}x{H}"

        def make() -> Any:
            s = PinholeModel(fx, fy, cx, cy, W, H)
            return Scan(range=np.full((H, W), 1.5, np.float32), sensor=s)
    else:
        T, desc = _adv_array(rng, 3)
        _save(d, "table", T)

        def make() -> Any:
            s = RayTableModel(T)
            return Scan(range=np.full(s.shape, 1.5, np.float32), sensor=s)

    def build() -> None:
        scan = make()
        _ = (scan.points, scan.seed, scan.valid, scan.up)
        if isinstance(scan.sensor, RayTableModel):
            _ = scan.sensor.pixel_angle
        _roundtrip(scan, d)

    return Job(f"{what}:{desc}", [(f"Scan({what})", build)])


def _save(d: Path, name: str, a: np.ndarray) -> None:
    """Keep an in-memory input for reproduction (objects as their repr only)."""
    if a.dtype == object:
        (d / f"{name}.repr.txt").write_text(repr(a)[:100_000])
    else:
        np.save(d / f"{name}.npy", a, allow_pickle=False)


def _degenerate_range(rng: np.random.Generator, H: int, W: int, f: float
                      ) -> tuple[np.ndarray, str]:
    """A degenerate range image of (H, W) for a pinhole of focal length ``f``."""
    from boxloc.scan import PinholeModel

    rays = PinholeModel(f, f, (W - 1) / 2, (H - 1) / 2, W, H).rays()
    kind = str(_pick(rng, ["one-valid", "all-equal", "plane", "tilted-plane", "noise",
                           "step", "checker-nan", "tiny-scale", "huge-scale", "subnormal",
                           "row", "column", "all-nan", "box", "two-valid"]))
    z = np.full((H, W), np.nan)
    if kind == "one-valid":
        z[int(rng.integers(0, H)), int(rng.integers(0, W))] = 1.5
        r = z
    elif kind == "two-valid":
        z.flat[rng.choice(H * W, size=min(2, H * W), replace=False)] = 1.5
        r = z
    elif kind == "all-equal":
        r = np.full((H, W), 1.5)
    elif kind in ("plane", "tilted-plane", "step", "box", "checker-nan"):
        n = np.array([0.0, 0.0, -1.0]) if kind != "tilted-plane" else np.array(
            [0.2, -0.3, -1.0])
        n /= np.linalg.norm(n)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = (n @ np.array([0.0, 0.0, 1.5])) / (rays @ n)
        if kind == "step":
            r[:, : W // 2] *= 0.9
        if kind == "box":
            r[H // 4: 3 * H // 4 + 1, W // 4: 3 * W // 4 + 1] *= 0.85
        if kind == "checker-nan":
            r[(np.add.outer(np.arange(H), np.arange(W)) % 2) == 0] = np.nan
    elif kind == "noise":
        r = rng.uniform(0.5, 3.0, (H, W))
    elif kind == "tiny-scale":
        r = np.full((H, W), 1e-6) * (1 + 0.1 * rng.random((H, W)))
    elif kind == "huge-scale":
        r = np.full((H, W), 1e30) * (1 + 0.1 * rng.random((H, W)))
    elif kind == "subnormal":
        r = np.full((H, W), 1e-44)
    elif kind == "row":
        z[H // 2, :] = 1.5
        r = z
    elif kind == "column":
        z[:, W // 2] = 1.5
        r = z
    else:
        r = z
    with np.errstate(all="ignore"):
        return np.asarray(r, np.float64).astype(np.float32), kind


def _gen_pipeline(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    from boxloc.config import Config
    from boxloc.scan import PinholeModel, Scan

    H = int(_pick(rng, [1, 2, 3, 8, 24, 48]))
    W = int(_pick(rng, [1, 2, 5, 16, 32, 64]))
    f = float(_pick(rng, [0.8 * W + 1, 0.8 * W + 1, 1e-3, 1e6]))
    r, kind = _degenerate_range(rng, H, W, f)
    _save(d, "range", r)
    cfg = Config() if rng.random() < 0.6 else Config(
        alpha=float(_pick(rng, [1e-9, 0.001, 0.2, 0.49])),
        min_edge=float(_pick(rng, [0.001, 0.1, 0.5])), max_edge=float(_pick(rng, [1.0, 50.0])),
        direction_granularity=int(_pick(rng, [2, 4])))

    def run() -> None:
        from boxloc.pipeline import find_graspable_surfaces
        from boxloc.products import STAGES, products_equal
        from recorder.mcap.log import open_log
        from recorder.mcap.sink import McapRecorder

        scan = Scan(range=r, sensor=PinholeModel(f, f, (W - 1) / 2, (H - 1) / 2, W, H),
                    index=3, capture_time_ns=1_700_000_000_000_000_000)
        p = d / "run.mcap"
        with McapRecorder(p, config=cfg, fsync=False, max_points=200, session="fuzz") as rec:
            res = find_graspable_surfaces(scan, cfg, observer=rec)
        (back,) = list(open_log(p).scans())
        diff = [s for s in STAGES if products_equal(getattr(res, s), back.products[s])]
        if diff or back.scan.range.tobytes() != scan.range.tobytes():
            raise AssertionError(f"the recorded result differs from the run: {diff}")

    return Job(f"{kind}-{H}x{W}-f{f:g}", [("find_graspable_surfaces", run)])
