"""Compile boxloc's numba kernels ahead of time into one extension module; set-up runs it.

A process that has this module runs its kernels without importing numba or loading numba's
cache (:mod:`boxloc.kernels`): about 1.5 s less before its first scan. The steps:

1. In a fresh numba cache (a temporary directory: numba links a kernel's callees from
   their compiled IR, which a cache entry no longer holds), with numba's JIT
   (``BOXLOC_KERNELS=jit``), run set-up's warm-up (``scripts/warm_up.py``: the pipeline
   on a small scan, and the kernels it does not reach), so that every kernel has compiled
   the signatures a scan calls it with.
2. Export each kernel's signatures from a module built by ``numba.pycc`` (literal
   arguments as their type; arrays as the warm-up saw them). Each export is a one-line
   function calling the kernel's dispatcher, so the kernel compiles with its own options
   (``error_model``), and its callees with theirs. Generic code for the machine's
   architecture (``pycc``'s default), so the module runs on any CPU of it.
3. Check the module: the warm-up scan with it (``BOXLOC_KERNELS=aot``, in a new process)
   must give products identical, bit for bit, to the JIT's
   (:func:`boxloc.products.products_equal`). Only then are the module and its description
   (``boxloc/_kernels_aot.json``: the exports' argument types, the digest of the kernels'
   sources, the versions) moved into place.

Needs a C compiler and Python's headers (Debian: gcc, python3-dev). Without them, or on
any failure, it says why and exits 1, and boxloc keeps numba's JIT and cache: set-up goes
on. About 2 minutes on one core.

Usage: python scripts/build_kernels.py [--if-stale]

``--if-stale``: only when the module is missing, or not current (a no-op otherwise).
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
#: The check: the warm-up scan's Result and the kernels' mode, pickled to a file of ours
#: for :func:`boxloc.products.products_equal` in the parent.
_CHECK = """
import pickle, sys
sys.path.insert(0, {scripts!r})
from warm_up import warm_up_scan
from boxloc import kernels
r = warm_up_scan()
with open({out!r}, "wb") as f:
    pickle.dump((kernels.mode(), r), f)
"""


def _base(t: Any) -> Any:
    """A literal argument's type (a constant a kernel passed a kernel): int64 for an int."""
    from numba.core import types

    if isinstance(t, types.IntegerLiteral):
        return types.int64
    return t.literal_type if isinstance(t, types.Literal) else t


def _spec(t: Any) -> list[Any] | None:
    """A numba type as :mod:`boxloc.kernels` checks it, or None if it cannot."""
    from numba.core import types

    t = _base(t)
    if isinstance(t, types.Array):
        return ["array", str(t.dtype), t.ndim, t.layout, not t.mutable]
    if t == types.int64:
        return ["int64"]
    if t == types.float64:
        return ["float64"]
    if t == types.boolean:
        return ["bool"]
    return None


def _trampoline(disp: Any, n: int, name: str) -> Any:
    """``def name(a0, ...): return disp(a0, ...)``: the kernel called from the export."""
    args = ", ".join(f"a{i}" for i in range(n))
    ns: dict[str, Any] = {"disp": disp}
    exec(f"def {name}({args}):\n    return disp({args})\n", ns)  # noqa: S102
    return ns[name]


def build(out: Path) -> dict[str, Any]:
    """Steps 1-2 into directory ``out``; returns the description (without the digest)."""
    from numba.pycc import CC

    sys.path.insert(0, str(ROOT / "scripts"))
    import warm_up

    if warm_up.warm_up() != 0:
        raise SystemExit("build_kernels: the warm-up did not reach every kernel")
    cc = CC("_kernels_aot")
    cc.output_dir = str(out)
    exports: dict[str, list[tuple[str, list[list[Any]]]]] = {}
    n_exports = 0
    for qual, disp in sorted(warm_up.kernels().items()):
        seen = []
        for cres in disp.overloads.values():
            sig = cres.signature
            specs = [_spec(t) for t in sig.args]
            if any(s is None for s in specs):
                raise SystemExit(f"build_kernels: {qual}{sig.args}: an argument type "
                                 "boxloc.kernels cannot check")
            if specs in seen:
                continue
            seen.append(specs)
            argtys = [_base(t) for t in sig.args]
            name = f"k{n_exports}_{qual.split('.')[-1]}"
            n_exports += 1
            cc.export(name, sig.return_type(*argtys))(_trampoline(disp, len(argtys), name))
            exports.setdefault(qual, []).append((name, specs))
    t0 = time.perf_counter()
    cc.compile()
    print(f"build_kernels: {n_exports} signatures of "
          f"{len(exports)} kernels compiled in {time.perf_counter() - t0:.0f} s",
          file=sys.stderr)
    return {"exports": exports}


def _check(env: dict[str, str], out: Path, extra_path: Path | None = None
           ) -> tuple[str, Any]:
    """The check scan's kernels' mode and Result, from a new process with ``env``."""
    code = _CHECK.format(scripts=str(ROOT / "scripts"), out=str(out))
    if extra_path is not None:  # the candidate module, before it is moved into place
        code = f"import boxloc; boxloc.__path__.insert(0, {str(extra_path)!r})\n" + code
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       cwd=ROOT, timeout=900)
    if r.returncode != 0:
        raise SystemExit(f"build_kernels: the check scan failed:\n{r.stderr[-2000:]}")
    with open(out, "rb") as f:
        mode, result = pickle.load(f)  # noqa: S301 - written just now by our own process
    return str(mode), result


def main() -> int:
    if os.environ.get("BOXLOC_BUILD_STEP") == "compile":
        out = Path(os.environ["BOXLOC_BUILD_OUT"])
        desc = build(out)
        (out / "exports.json").write_text(json.dumps(desc))
        return 0
    from boxloc import kernels
    from boxloc.products import products_equal

    if "--if-stale" in sys.argv[1:]:
        status = kernels.aot_status()
        if status.usable:
            print("build_kernels: the ahead-of-time kernels are current", file=sys.stderr)
            return 0
        print(f"build_kernels: building: the ahead-of-time kernels are {status.reason}",
              file=sys.stderr)
    pkg = Path(kernels.__file__).parent
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        out.mkdir()
        env = {**os.environ, "NUMBA_CACHE_DIR": str(Path(tmp) / "numba"),
               kernels.ENV: "jit", "BOXLOC_BUILD_STEP": "compile",
               "BOXLOC_BUILD_OUT": str(out)}
        r = subprocess.run([sys.executable, __file__], env=env, cwd=ROOT, timeout=1800)
        if r.returncode != 0:
            print("build_kernels: not built; boxloc uses numba's JIT and cache",
                  file=sys.stderr)
            return 1
        so = [p for p in out.iterdir() if p.name.startswith("_kernels_aot.")]
        if len(so) != 1:
            print(f"build_kernels: expected one module in {out}, found {so}", file=sys.stderr)
            return 1
        desc = json.loads((out / "exports.json").read_text())
        stamp = {"sources": kernels.sources_digest(), "facts": kernels.build_facts(),
                 "exports": desc["exports"]}
        # the check: the candidate (in a directory of its own, first on boxloc's path)
        cand = Path(tmp) / "cand"
        cand.mkdir()
        shutil.copy2(so[0], cand / so[0].name)
        (cand / kernels.AOT_STAMP).write_text(json.dumps(stamp))
        base = {k: v for k, v in os.environ.items() if k != "BOXLOC_BUILD_STEP"}
        _, jit = _check({**base, kernels.ENV: "jit"}, Path(tmp) / "jit.pkl")
        mode, aot = _check({**base, kernels.ENV: "aot"}, Path(tmp) / "aot.pkl", cand)
        differ = products_equal(jit, aot)
        if mode != "aot" or differ:
            print(f"build_kernels: not kept: with the module ({mode}) the check scan's "
                  f"products differ from the JIT's in {differ[:8]}", file=sys.stderr)
            return 1
        shutil.copy2(so[0], pkg / (so[0].name + ".tmp"))
        os.replace(pkg / (so[0].name + ".tmp"), pkg / so[0].name)
        for old in pkg.glob("_kernels_aot.*"):  # one built for another Python
            if old.name not in (so[0].name, kernels.AOT_STAMP):
                old.unlink()
        tmp_stamp = pkg / (kernels.AOT_STAMP + ".tmp")
        tmp_stamp.write_text(json.dumps(stamp, indent=1) + "\n")
        os.replace(tmp_stamp, pkg / kernels.AOT_STAMP)
    digest = hashlib.sha256((pkg / so[0].name).read_bytes()).hexdigest()[:12]
    print(f"build_kernels: {pkg / so[0].name} ({digest}) checked against numba's JIT "
          f"(products identical) and kept, in {time.perf_counter() - t0:.0f} s",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
