"""The ``npz`` cases: adversarial arrays, hand-made ``.npy`` headers (absurd shapes, object
dtypes with a pickle payload) and byte mutations of valid files.
"""

from __future__ import annotations

import io
import struct
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from recorder.fuzz.cases import Job, _pick
from recorder.fuzz.mutate import mutate_bytes
from recorder.fuzz.scan_files import _adv_array, _file_job, _intrinsics_kw


def _npy_member(descr: str, shape: tuple[int, ...], payload: bytes = b"",
                fortran: bool = False) -> bytes:
    f = io.BytesIO()
    np.lib.format.write_array_header_1_0(f, {"descr": descr, "fortran_order": fortran,
                                             "shape": shape})
    return f.getvalue() + payload


#: The members' modification time: the zip format's earliest, so that a case's bytes do not
#: depend on the clock (``writestr`` with a name stamps the current local time).
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)


def _write_zip(path: Path, members: dict[str, bytes]) -> None:
    """Write ``members`` (``{name: bytes}``, in order) as an uncompressed zip, as
    :func:`numpy.savez` does, with a fixed member time."""
    with zipfile.ZipFile(path, "w") as zf:
        for k, v in members.items():
            info = zipfile.ZipInfo(k, date_time=_ZIP_TIME)
            info.external_attr = 0o600 << 16  # what writestr(name, ...) gives: rw-------
            zf.writestr(info, v)


def _npy(a: np.ndarray) -> bytes:
    f = io.BytesIO()
    np.lib.format.write_array(f, np.asarray(a), allow_pickle=False)
    return f.getvalue()


#: A pickle that would create a file named ``PWNED`` in the working directory if anything
#: ever unpickled it (it is only ever written, as the payload of an ``|O`` npy member).
PICKLE_BOMB = b"cposix\nsystem\n(Vtouch PWNED\ntR."


def _gen_npz(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    p = d / "fuzzed.npz"
    kw: dict[str, Any] = {"intrinsics": _intrinsics_kw(rng, corpus)}
    u = rng.random()
    if u < 0.25:
        src = Path(corpus["npz"][int(rng.integers(0, len(corpus["npz"])))])
        data, op = mutate_bytes(rng, src.read_bytes())
        p.write_bytes(data)
        return _file_job(f"mutate-{op}", p, kw, d)
    with np.load(corpus["npz"][0], allow_pickle=False) as z:
        good = {k: np.array(z[k]) for k in z.files}
    if u < 0.45:
        # A member whose header declares something absurd, with little or no data behind it.
        key = str(_pick(rng, ["range", "points", "intrinsics", "capture_time_ns",
                              "sensor_to_base"]))
        shapes = [(1, 10**9, 3), (10**9, 10**9), (2**62, 2**62), (2**40, 4), (4096, 4097),
                  (-1, 5), (0, 0), (3, 3), (4, 4), (), (1,), (2**63 - 1,), (48, 36),
                  (36, 48, 3), (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17)]
        descrs = ["<f4", "<f8", "|O", "<c16", "|b1", "<f2", "<i8", "<u8", ">f4", "<U4", "|V16",
                  "<M8[ns]", "<f16", "|S3"]
        shape = shapes[int(rng.integers(0, len(shapes)))]
        descr = str(_pick(rng, descrs))
        payload = PICKLE_BOMB if descr == "|O" else bytes(int(_pick(rng, [0, 12, 4096])))
        members = {f"{k}.npy": _npy(v) for k, v in good.items() if k != key}
        members[f"{key}.npy"] = _npy_member(descr, shape, payload,
                                            fortran=bool(rng.random() < 0.2))
        if rng.random() < 0.1:
            members["range.npy"] = b"\x93NUMPY\x01\x00" + struct.pack("<H", 60000) + b"{"
        _write_zip(p, members)
        return _file_job(f"header-{key}:{descr}{list(shape)}", p, kw, d)
    # Adversarial arrays, written the ordinary way.
    keys = [k for k in ("range", "points", "intrinsics", "sensor_to_base", "capture_time_ns")
            if rng.random() < 0.7]
    arrays = {k: good[k] for k in keys if k in good}
    target = str(_pick(rng, ["range", "points", "intrinsics", "sensor_to_base",
                             "capture_time_ns"]))
    if target == "range":
        arrays[target], what = _adv_array(rng, 2)
    elif target == "points":
        arrays[target], what = _adv_array(rng, 3, last=int(_pick(rng, [3, 3, 3, 2, 4])))
    elif target == "intrinsics":
        K = good["intrinsics"].copy()
        opts = [np.full((3, 3), np.nan), np.zeros((3, 3)), -K, K * 1e308, K[:2], np.eye(4),
                K.astype(np.int64), K.astype(np.complex128), K + 1e-3, K[..., None]]
        i = int(rng.integers(0, len(opts)))
        arrays[target], what = opts[i], f"K#{i}"
    elif target == "sensor_to_base":
        opts = [np.full((4, 4), np.nan), np.eye(3), np.eye(4) * 1e308, np.eye(4, dtype=int),
                np.zeros((4, 4)), np.full((4, 4), np.inf), np.eye(4)[None]]
        i = int(rng.integers(0, len(opts)))
        arrays[target], what = opts[i], f"T#{i}"
    else:
        times: list[np.generic | np.ndarray] = [
            np.uint64(2**64 - 1), np.int64(-1), np.float64(1.5), np.int64(2**63 - 1),
            np.zeros((2, 2), np.int64), np.uint64(2**63), np.array("1"), np.int8(-128),
            np.bool_(True)]
        i = int(rng.integers(0, len(times)))
        arrays[target], what = np.asarray(times[i]), f"t#{i}"
    members = {}
    for k, v in arrays.items():
        if v.dtype == object:  # what a careless writer would produce, without the pickle
            members[f"{k}.npy"] = _npy_member("|O", v.shape, PICKLE_BOMB)
        else:
            members[f"{k}.npy"] = _npy(v)
    _write_zip(p, members)
    return _file_job(f"arrays-{target}:{what}", p, kw, d)
