"""Start-up: what `import boxloc.cli`, `boxloc --help` and `boxloc locate` import, the help
listing read without importing the plugins, the quick exit, and the numba warm-up.

Imports are checked in fresh interpreters (subprocesses), since pytest's own process has
imported everything by the time a test runs. Times are the benchmark's business, not these
tests': they check the mechanisms that make start-up quick.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import click
import pytest

from boxloc.cli import _described, cli

ROOT = Path(__file__).resolve().parents[1]

#: modules only the recording, viewing, baseline and replay verbs need
HEAVY = ("open3d", "rerun", "dask", "distributed", "mcap", "mcap_protobuf", "pyarrow",
         "recorder.mcap.sink", "recorder.rerun.sink", "replay.executors")
#: what `boxloc --help` does without, too: the algorithm's own dependencies
ALGORITHM = ("numpy", "scipy", "numba", "cv2", "rich")


def _imported_after(code: str, *, env: dict[str, str] | None = None) -> tuple[list[str], str]:
    """Run CODE in a fresh interpreter; the modules of HEAVY + ALGORITHM it left imported."""
    probe = (f"{code}\nimport sys, json\n"
             f"print(json.dumps(sorted(m for m in {HEAVY + ALGORITHM!r} if m in sys.modules)))")
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                       cwd=ROOT, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1]), r.stdout


def _run_cli(args: list[str]) -> str:
    return ("from boxloc.cli import cli\n"
            "try:\n"
            f"    cli({args!r}, prog_name='boxloc')\n"
            "except SystemExit as e:\n"
            "    assert e.code in (0, None), e.code\n")


def test_import_boxloc_cli_imports_nothing_heavy() -> None:
    mods, _ = _imported_after("import boxloc.cli")
    assert mods == []


def test_help_imports_no_plugin_and_no_algorithm_dependency() -> None:
    mods, out = _imported_after(_run_cli(["--help"]))
    assert mods == []
    for verb in ("locate", "run", "replay", "diff", "view", "import", "explain"):
        assert f"\n  {verb} " in out  # the plugins are listed all the same


def test_the_pipeline_and_the_simulator_import_no_scipy_signal() -> None:
    """The forkserver of `run --workers` imports both before its workers can start;
    scipy.signal (0.4 s) waits until a sensor model's correlated noise needs it."""
    r = subprocess.run([sys.executable, "-c", "import boxloc.pipeline, boxloc.simulate, sys; "
                        "print('scipy.signal' in sys.modules)"], capture_output=True,
                       text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == "False", r.stderr


@pytest.fixture(scope="module")
def small_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small simulated scan with a box in it, as .npz."""
    from boxloc.simulate import parse_spec, simulate_to_files

    out = tmp_path_factory.mktemp("startup") / "s.npz"
    (path, sim), = simulate_to_files(parse_spec("single:seed=2,width=96,height=72,f=90"),
                                     str(out))
    return path


def test_locate_on_npz_imports_no_recorder_rerun_dask_or_mcap(small_scan: Path,
                                                              tmp_path: Path) -> None:
    path = small_scan
    mods, _ = _imported_after(_run_cli(["locate", str(path), "-o", str(tmp_path / "o.json")]))
    assert not set(mods) & set(HEAVY), mods
    assert "scipy" in mods  # it did run the pipeline (numba: only without the AOT kernels)
    assert json.loads((tmp_path / "o.json").read_text())["surfaces"] is not None


def test_the_help_listing_reads_each_plugins_first_line_as_click_would() -> None:
    """The stand-ins read from the sources (``_described``) give every plugin verb the same
    one-line help as its real command, which is loaded here to compare."""
    ctx = click.Context(cli)
    plugins = cli._plugins()
    assert {"run", "replay", "view", "import"} <= set(plugins)
    for name, ep in plugins.items():
        stand_in = _described(ep, name)
        real = ep.load()
        assert stand_in is not None and stand_in is not real, name  # read, not loaded
        for limit in (30, 45, 80):
            assert stand_in.get_short_help_str(limit) == real.get_short_help_str(limit), name
        assert cli.get_command(ctx, name) is real


def test_a_mistyped_verb_suggests_plugins_too() -> None:
    r = subprocess.run([sys.executable, "-m", "boxloc.cli", "replya"], capture_output=True,
                       text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2
    if "Did you mean" in r.stderr:  # click >= 8.4 suggests
        assert "'replay'" in r.stderr


def _console(args: list[str], **kw: object) -> subprocess.CompletedProcess[str]:
    """The console script's entry point, main(), as `boxloc ARGS` runs it."""
    return subprocess.run([sys.executable, "-c", "from boxloc.cli import main; main()", *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=300, **kw)


def test_quick_exit_keeps_the_output_and_the_exit_status(small_scan: Path,
                                                         tmp_path: Path) -> None:
    """`boxloc locate` ends without the interpreter's teardown; what it printed to a pipe
    arrives whole, atexit handlers run, and a user error still exits 2."""
    r = _console(["locate", str(small_scan), "--table"])
    assert r.returncode == 0, r.stderr
    assert len(json.loads(r.stdout)["surfaces"]) >= 1
    assert "graspable surface" in r.stderr
    r = _console(["locate", str(tmp_path / "missing.npz")])
    assert r.returncode == 2 and r.stderr.startswith("boxloc: error:"), r.stderr
    # atexit handlers run before the quick exit
    code = ("import atexit, sys; atexit.register(lambda: print('atexit ran', file=sys.stderr));"
            "sys.argv = ['boxloc', 'config']; from boxloc.cli import main; main()")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode == 0 and "alpha" in r.stdout and "atexit ran" in r.stderr
    # what is still buffered (a pipe, no PYTHONUNBUFFERED) is flushed; the status is the verb's
    code = ("import sys; from boxloc.cli import _quick_exit; sys.stdout.write('x' * 100);"
            "sys.stderr.write('y'); _quick_exit(3)")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                       env=env, timeout=120)
    assert (r.returncode, len(r.stdout), r.stderr) == (3, 100, "y")


def test_setup_runs_the_warm_up() -> None:
    lines = (ROOT / "scripts" / "setup.sh").read_text().splitlines()
    for script in ("scripts/warm_up.py", "scripts/build_kernels.py"):
        assert any(script in ln and not ln.lstrip().startswith("#") for ln in lines), script


@pytest.mark.slow
def test_after_the_warm_up_a_full_scan_compiles_nothing(tmp_path: Path) -> None:
    """With an empty numba cache, scripts/warm_up.py (as set-up runs it) leaves nothing for a
    640 x 480 scan to compile: every kernel it calls is loaded from the cache (numba's JIT,
    as a process without the ahead-of-time kernels, or told to, runs them)."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "BOXLOC_KERNELS": "jit"}
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "warm_up.py")], env=env,
                       capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr
    assert any((tmp_path / "numba").rglob("*.nbc"))
    # a callee's entries lost while its callers' stay (a source changed and restored): the
    # warm-up removes that source's entries and runs again, instead of failing set-up
    callee = sorted((tmp_path / "numba").rglob("lines._vote_directions-*"))
    assert callee
    for f in callee:
        f.unlink()
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "warm_up.py")], env=env,
                       capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "not cached beside their callers" in r.stderr
    assert sorted((tmp_path / "numba").rglob("lines._vote_directions-*"))
    code = ("import sys; sys.path.insert(0, 'scripts')\n"
            "from boxloc.config import Config\n"
            "from boxloc.pipeline import find_graspable_surfaces\n"
            "from boxloc.simulate import scene_suite, simulate\n"
            "from warm_up import kernels\n"
            "spec = scene_suite(1, 3)[0]\n"
            "assert (spec.width, spec.height) == (640, 480)\n"
            "find_graspable_surfaces(simulate(spec).scan, Config())\n"
            "ks = kernels().values()\n"
            "print(sum(sum(k.stats.cache_misses.values()) for k in ks),"
            " sum(sum(k.stats.cache_hits.values()) for k in ks))\n")
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr
    compiled, loaded = map(int, r.stdout.split())
    assert compiled == 0 and loaded > 0
