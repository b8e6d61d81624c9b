"""Wrong rectangles on interlocked layers, with the carton list given.

The simulator's own layers are grids, so ``boxloc bench --packed`` cannot show what a carton
split does to a layer laid another way. Here each scene is one zero-gap layer of cartons
whose long edge is twice the short one (a modular size, as 0.2 x 0.4 m), laid in cells of
two and one column of single cartons: a *grid* (every carton the same way) or a *basket
weave* (each cell turned at random, at least one). Both have the outline of a grid of the
carton, (2 nx + 1) x ny of them, and of no grid of it turned, so the outline alone cannot
tell them apart. Each scene runs with its carton list, and the wrong
rectangles (reported tops that match no box's top) are counted per pattern and sensor.

Usage::

    python scripts/interlocked_layers.py --n 64 --seed 0 --out interlocked.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import defaultdict
from typing import Any

import numpy as np

from boxloc.config import Config
from boxloc.evaluate.packed_bench import score_packed
from boxloc.pipeline import find_graspable_surfaces
from boxloc.simulate import PALLET_SIZE, SceneSpec, look_down_pose, simulate_boxes
from boxloc.simulate.layouts import weave_layer
from boxloc.simulate.zoo import SENSORS

#: Focal length at 640 px per sensor model (the matrix suite's).
F640 = {"laser": 525.0, "tof": 456.0, "structured-light": 580.0, "active-stereo": 440.0}
PATTERNS = ("weave", "grid")


def layer(rng: np.random.Generator, pattern: str) -> tuple[np.ndarray, tuple[float, float, float]]:
    """One layer on the pallet: (B, 7) boxes (base frame) and the carton's (a, 2a, h)."""
    a = round(float(rng.uniform(0.15, 0.25)), 3)
    b, h = 2 * a, round(float(rng.uniform(0.15, 0.35)), 3)
    # cells of b x b and one column of cartons along y at the end: (2 nx + 1) a wide, so
    # the outline is a grid of the carton one way only (turned, 2 nx + 1 is odd)
    nx, ny = int((PALLET_SIZE[0] - a) // b), int(PALLET_SIZE[1] // b)
    turned = rng.random((nx, ny)) < 0.5
    if pattern == "grid":
        turned[:] = False
    elif not turned.any():
        turned[int(rng.integers(nx)), int(rng.integers(ny))] = True
    return weave_layer(a, h, turned, PALLET_SIZE[2] + h / 2), (a, b, h)


def run(n: int, seed: int) -> dict[str, Any]:
    """Scene k: sensor ``SENSORS[k % 4]``, pattern ``PATTERNS[(k // 4) % 2]``, the rest
    drawn from (seed, k). Returns the rows per scene and the sums per pattern and sensor."""
    rows: list[dict[str, Any]] = []
    for k in range(n):
        rng = np.random.default_rng([seed, k])
        sensor = SENSORS[k % len(SENSORS)]
        pattern = PATTERNS[(k // len(SENSORS)) % len(PATTERNS)]
        boxes, size = layer(rng, pattern)
        top = PALLET_SIZE[2] + size[2]
        T = look_down_pose([0.0, 0.0, top], float(rng.uniform(1.2, 2.5)),
                           tilt=float(rng.uniform(0.0, 0.3)),
                           azimuth=float(rng.uniform(0, 2 * math.pi)), roll=0.0)
        spec = SceneSpec(kind="single", sensor=sensor, width=640, height=480, f=F640[sensor],
                         bevel=0.0)
        sim = simulate_boxes(boxes, T, spec=spec, seed=int(rng.integers(2**31)))
        cfg = Config(min_edge=0.15, max_edge=0.6, box_sizes=(size,))
        t0 = time.perf_counter()
        r = find_graspable_surfaces(sim.scan, cfg)
        sc = score_packed(r, sim.truth)
        rows.append({"scene": k, "sensor": sensor, "pattern": pattern, "carton": size,
                     "tops": int(np.sum(sim.truth.fully_exposed)), "tp": sc.match.tp,
                     "fp": sc.match.fp, "reported": len(r.surfaces),
                     "wrong": sc.wrong.n_wrong,
                     "ambiguous": [str(x) for x in sc.to_dict()["ambiguous"]["reason"]],
                     "seconds": round(time.perf_counter() - t0, 2)})
        print(json.dumps(rows[-1]), flush=True)
    groups: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for row in rows:
        for g in (f"{row['pattern']}/{row['sensor']}", str(row["pattern"])):
            for key in ("tops", "tp", "fp", "reported", "wrong"):
                groups[g][key] += int(row[key])
            groups[g]["scenes"] += 1
    return {"n": n, "seed": seed, "groups": {g: dict(v) for g, v in sorted(groups.items())},
            "scenes": rows}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    rep = run(args.n, args.seed)
    print("| pattern/sensor | scenes | tops | TP / FP | wrong rectangles / reported |")
    print("|---|---|---|---|---|")
    for g, v in rep["groups"].items():
        print(f"| {g} | {v['scenes']} | {v['tops']} | {v['tp']} / {v['fp']} | "
              f"{v['wrong']} / {v['reported']} |")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rep, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
