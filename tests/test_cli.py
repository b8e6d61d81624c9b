"""The boxloc command line: locate and config on good and bad input.

One run is a real subprocess (what a user's shell sees on stdout); the others run in this
process through click's test runner (tests/cli_run.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_run import invoke, run

from boxloc.simulate import save_npz, simulate


@pytest.fixture(scope="module")
def pallet_npz(tmp_path_factory):
    p = tmp_path_factory.mktemp("cli") / "pallet.npz"
    # 320 x 240: the same pallet as the 640 x 480 default, its pipeline 7 times quicker
    save_npz(simulate("pallet:width=320,height=240,f=262.5", seed=1), p)
    return p


def test_locate_prints_the_public_json(pallet_npz, tmp_path):
    r = run("locate", str(pallet_npz))
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["surfaces"] and out["version"]
    s = out["surfaces"][0]
    assert s["width"] <= s["length"]
    assert [x["pick_order"] for x in out["surfaces"]] == list(range(len(out["surfaces"])))
    # --output writes the same surfaces
    o = tmp_path / "out.json"
    r2 = invoke("locate", str(pallet_npz), "--output", str(o), "--set", "workers=2")
    assert r2.returncode == 0, r2.stderr
    assert json.loads(o.read_text())["surfaces"] == out["surfaces"]


def test_locate_empty_scene_is_zero_surfaces(tmp_path):
    p = tmp_path / "empty.npz"
    save_npz(simulate("empty", seed=2), p)
    r = invoke("locate", str(p))
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["surfaces"] == []


@pytest.mark.parametrize(
    "make,args,needle",
    [
        (None, ["missing.npz"], "missing.npz"),
        ("txt", ["scan.txt"], "scan.txt"),
        ("nan", ["nan.npz"], "no valid range"),
        ("shape", ["shape.npz"], "shape"),
        (None, ["x.npz", "--set", "alpha=2"], "alpha"),
        (None, ["x.npz", "--set", "nope=1"], "nope"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, make, args, needle):
    if make == "txt":
        (tmp_path / "scan.txt").write_text("hello")
    elif make == "nan":
        np.savez(tmp_path / "nan.npz", points=np.full((24, 32, 3), np.nan, np.float32),
                 intrinsics=np.array([[50, 0, 15.5], [0, 50, 11.5], [0, 0, 1.0]]))
    elif make == "shape":
        np.savez(tmp_path / "shape.npz", points=np.zeros((24, 32), np.float32))
    if args[0] == "x.npz":
        save_npz(simulate("single:width=64,height=48,f=52.5", seed=1), tmp_path / "x.npz")
    r = invoke("locate", *args, cwd=tmp_path)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, r.stderr
    assert needle in lines[0]
    assert "Traceback" not in r.stderr


def test_config_prints_loadable_toml(tmp_path):
    r = invoke("config")
    assert r.returncode == 0
    f = tmp_path / "c.toml"
    f.write_text(r.stdout.replace("alpha = 0.01", "alpha = 0.05"))
    from boxloc.config import Config

    assert Config.load(f).alpha == 0.05
