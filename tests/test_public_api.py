"""The top package's public API, and the layout's dependency rules."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import boxloc

ROOT = Path(__file__).resolve().parents[1]


def test_public_names_are_the_real_objects() -> None:
    from boxloc.config import Config
    from boxloc.io import read_scan
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.scan import Scan

    assert boxloc.find_graspable_surfaces is find_graspable_surfaces
    assert boxloc.read_scan is read_scan
    assert boxloc.Scan is Scan
    assert boxloc.Config is Config
    assert set(boxloc.__all__) <= set(dir(boxloc))


def test_unknown_name_is_an_attribute_error() -> None:
    try:
        boxloc.no_such_thing  # noqa: B018
    except AttributeError as e:
        assert "no_such_thing" in str(e)
    else:
        raise AssertionError("boxloc.no_such_thing resolved")


def test_importing_the_package_loads_no_stage() -> None:
    """``import boxloc`` stays quick: the public names load on first use."""
    code = ("import sys, boxloc; "
            "print(sorted(m for m in sys.modules if m.startswith('boxloc.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]", out


def test_a_scan_runs_through_the_public_api(tmp_path: Path) -> None:
    from boxloc.simulate import simulate

    sim = simulate("single:width=160,height=120,f=131.25,distance=1.0", seed=3)
    result = boxloc.find_graspable_surfaces(sim.scan, boxloc.Config())
    assert isinstance(result, boxloc.Result)
    assert len(result.surfaces.hypothesis) >= 1


def _imports(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def test_the_layout_keeps_the_dependency_direction() -> None:
    """boxloc imports neither recorder, replay, rerun nor mcap; the stages import no
    simulation, evaluation or calibration (the algorithm stands alone)."""
    for path in (ROOT / "boxloc").rglob("*.py"):
        bad = {m for m in _imports(path)
               if m.split(".")[0] in {"recorder", "replay", "rerun", "mcap"}}
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"
    for path in (ROOT / "boxloc" / "stages").rglob("*.py"):
        bad = {m for m in _imports(path)
               if m.startswith(("boxloc.simulate", "boxloc.evaluate", "boxloc.cli"))}
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


def test_reading_products_does_not_import_scipy_stats() -> None:
    """Processes that only read products (log readers, ``run --workers``' parent) do not
    pay for scipy.stats (~0.7 s of CPU); the tests import it when they compute."""
    code = ("import sys, boxloc.products, recorder.mcap.log; "
            "print('scipy.stats' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "False"
