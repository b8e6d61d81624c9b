"""boxloc.kernels: the ahead-of-time kernels' argument checks, when the module is used,
and that it gives the JIT's products (set-up builds it: scripts/build_kernels.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from boxloc import kernels

ROOT = Path(__file__).resolve().parents[1]


def _scaled(a: np.ndarray, x: float) -> float:
    return float(a.sum() * x)


@pytest.fixture()
def wrapped(monkeypatch: pytest.MonkeyPatch) -> tuple[Any, list[str]]:
    """``_scaled`` behind the checks of one export (float64 C array, writable; float64),
    the export and the fallback each recording their calls."""
    calls: list[str] = []
    module = types.SimpleNamespace(k0__scaled=lambda a, x: calls.append("aot") or 1.0)

    def miss(qual: str, args: tuple[Any, ...]) -> float:
        calls.append(f"jit {qual} {len(args)}")
        return 2.0

    monkeypatch.setattr(kernels, "_miss", miss)
    spec = [["array", "float64", 1, "C", False], ["float64"]]
    return kernels._wrapper("t._scaled", _scaled, [("k0__scaled", spec)], module), calls


def test_a_call_of_the_built_types_runs_the_export(wrapped: tuple[Any, list[str]]) -> None:
    w, calls = wrapped
    assert w(np.zeros(3), 0.5) == 1.0 and w(np.zeros(3), np.float64(2)) == 1.0
    assert w(a=np.zeros(3), x=1.0) == 1.0  # the kernel's own parameter names
    assert calls == ["aot"] * 3
    assert w.__wrapped__ is _scaled and w._boxloc_kernel == "t._scaled"


@pytest.mark.parametrize("args", [
    (np.zeros(3, np.float32), 0.5),         # another dtype: its bytes would be misread
    (np.zeros((3, 1)), 0.5),                 # other dimensions
    (np.zeros(6)[::2], 0.5),                 # strided, where the export expects C order
    (np.zeros(3), 1),                        # an int where numba's typeof says int64
    (np.zeros(3), np.float32(0.5)),          # a float32 scalar
    ([0.0, 1.0], 0.5),                       # not an array
])
def test_any_other_call_goes_to_the_jit(wrapped: tuple[Any, list[str]],
                                        args: tuple[Any, ...]) -> None:
    w, calls = wrapped
    assert w(*args) == 2.0
    assert calls == ["jit t._scaled 2"]


def test_a_read_only_array_is_not_given_to_a_kernel_that_may_write(
        wrapped: tuple[Any, list[str]]) -> None:
    w, calls = wrapped
    a = np.zeros(3)
    a.flags.writeable = False
    assert w(a, 0.5) == 2.0 and calls == ["jit t._scaled 2"]


def _stamp_at(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, stamp: Any) -> None:
    """A module 'found' in tmp_path, with ``stamp`` (a dict, or raw text) beside it."""
    so = tmp_path / "_kernels_aot.cpython-311-x86_64-linux-gnu.so"
    so.write_bytes(b"")
    (tmp_path / kernels.AOT_STAMP).write_text(stamp if isinstance(stamp, str)
                                              else json.dumps(stamp))
    spec = types.SimpleNamespace(origin=str(so))
    monkeypatch.setattr(kernels.importlib.util, "find_spec",
                        lambda name: spec if name == kernels.AOT_MODULE else None)


def test_a_module_built_from_other_sources_or_versions_is_not_used(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _stamp_at(tmp_path, monkeypatch, {"sources": "0" * 64, "facts": kernels.build_facts()})
    st = kernels.aot_status()
    assert not st.usable and "other sources" in st.reason
    facts = {**kernels.build_facts(), "numpy": "1.0"}
    _stamp_at(tmp_path, monkeypatch, {"sources": kernels.sources_digest(), "facts": facts})
    st = kernels.aot_status()
    assert not st.usable and "built with" in st.reason
    _stamp_at(tmp_path, monkeypatch, "{not json")
    assert "unreadable" in kernels.aot_status().reason


def test_the_digest_covers_every_file_with_a_kernel() -> None:
    """A kernel in a file the digest does not cover would be stale in the module unseen."""
    base = ROOT / "boxloc"
    with_kernels = {str(p.relative_to(base)) for p in base.rglob("*.py")
                    if "\n@kernel" in p.read_text()}
    assert with_kernels and with_kernels | {"kernels.py"} == set(kernels.KERNEL_SOURCES)
    assert not [p for p in base.rglob("*.py") if "numba.njit" in p.read_text()
                and p.name != "kernels.py"]


def _locate(scan: Path, out: Path, choice: str | None) -> tuple[dict[str, Any], str, bool]:
    """`boxloc locate SCAN -o OUT` with BOXLOC_KERNELS=choice (None: unset): the result
    (without its times), the kernels' mode, and whether numba was imported."""
    code = ("import sys\nfrom boxloc.cli import cli\n"
            f"try:\n    cli(['locate', {str(scan)!r}, '-o', {str(out)!r}])\n"
            "except SystemExit as e:\n    assert e.code in (0, None), e.code\n"
            "from boxloc import kernels\nprint(kernels.mode(), 'numba' in sys.modules)\n")
    env = {k: v for k, v in os.environ.items() if k != kernels.ENV}
    if choice is not None:
        env[kernels.ENV] = choice
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=ROOT, env=env, timeout=600)
    assert r.returncode == 0, r.stderr
    mode, numba = r.stdout.split()[-2:]
    res = json.loads(out.read_text())
    res.pop("timing_ms")
    return res, mode, numba == "True"


def test_the_ahead_of_time_kernels_give_the_jits_products(tmp_path: Path) -> None:
    """Set-up builds the module (scripts/build_kernels.py; it needs gcc and Python's
    headers). `boxloc locate` uses it unless told otherwise, and then imports no numba;
    its surfaces and every test row are the JIT's, bit for bit."""
    st = kernels.aot_status()
    assert st.usable, f"the ahead-of-time kernels are {st.reason}: run scripts/setup.sh"
    from boxloc.simulate import parse_spec, simulate_to_files

    (path, _), = simulate_to_files(parse_spec("mixed:seed=3,width=320,height=240,f=290,"
                                              "sensor=structured-light"),
                                   str(tmp_path / "s.npz"))
    aot = _locate(path, tmp_path / "aot.json", None)
    jit = _locate(path, tmp_path / "jit.json", "jit")
    assert aot[1:] == ("aot", False) and jit[1:] == ("jit", True)
    assert aot[0] == jit[0] and aot[0]["surfaces"]


def test_the_library_uses_them_too_and_jit_on_request(tmp_path: Path) -> None:
    """The pipeline imported as a library (or by `run`, `replay`, `bench`) uses the module as
    `locate` does; BOXLOC_KERNELS=jit keeps numba's JIT (and an unknown choice is refused)."""
    code = "import boxloc.pipeline\nfrom boxloc import kernels\nprint(kernels.mode())"
    env = {k: v for k, v in os.environ.items() if k != kernels.ENV}
    for choice, want in ((None, "aot"), ("jit", "jit"), ("AOT", "aot")):
        e = env if choice is None else {**env, kernels.ENV: choice}
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           cwd=ROOT, env=e, timeout=300)
        assert r.returncode == 0 and r.stdout.split() == [want], (choice, r.stderr)
    from boxloc.simulate import parse_spec, simulate_to_files

    (path, _), = simulate_to_files(parse_spec("single:seed=2,width=96,height=72,f=90"),
                                   str(tmp_path / "s.npz"))
    r = subprocess.run([sys.executable, "-m", "boxloc.cli", "locate", str(path)],
                       capture_output=True, text=True, cwd=ROOT,
                       env={**env, kernels.ENV: "fast"}, timeout=300)
    assert (r.returncode, r.stderr) == (2, "boxloc: error: BOXLOC_KERNELS must be auto, "
                                           "aot or jit, got 'fast'\n")


def test_a_call_the_module_was_not_built_for_switches_the_process_to_the_jit() -> None:
    """A float32 array for a float64 kernel: a warning, numba's JIT from then on for every
    kernel (bound in the modules, so that kernels calling kernels compile), the right
    value; the pipeline still runs."""
    code = """
import warnings, numpy as np
from boxloc import kernels
import boxloc.stages.seams as S
from boxloc.pipeline import find_graspable_surfaces
from boxloc.config import Config
from boxloc.simulate import parse_spec, simulate
assert kernels.mode() == "aot"
x = np.arange(7, dtype=np.float32)[::-1]
with warnings.catch_warnings(record=True) as w:
    warnings.simplefilter("always")
    m = S._median(x)
r = find_graspable_surfaces(simulate(parse_spec("single:seed=2,width=96,height=72,f=90")).scan,
                            Config())
print(m == np.median(x), kernels.mode(), type(S._median).__name__, len(w),
      "float32" in str(w[0].message), len(r.surfaces))
"""
    env = {k: v for k, v in os.environ.items() if k != kernels.ENV}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                       env=env, timeout=600)
    assert r.returncode == 0, r.stderr
    same, mode, kind, n_warn, named, n_surf = r.stdout.split()
    assert (same, mode, kind, n_warn, named) == ("True", "jit", "CPUDispatcher", "1", "True")
    assert int(n_surf) >= 1
