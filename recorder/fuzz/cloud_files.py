"""PCD and PLY files: valid bytes written here (for the corpus), and the ``cloud`` cases
(adversarial content and headers, byte mutations of valid clouds).
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np

from recorder.fuzz.cases import Job, _pick
from recorder.fuzz.mutate import mutate_bytes
from recorder.fuzz.scan_files import _file_job, _intrinsics_kw, _storm


def _lzf_literal(data: bytes) -> bytes:
    """LZF stream of literal runs only (valid LZF, no compression), for PCD
    ``binary_compressed``."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i:i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def _xyz_records(P: np.ndarray, labels: np.ndarray | None, byte_order: str, label_type: str
                 ) -> tuple[np.ndarray, list[tuple[str, str]]]:
    """The (H, W, 3) cloud ``P`` (and optional labels) as one flat record array, with its
    fields: float32 x, y, z and ``label`` of ``label_type``, in ``byte_order``."""
    fields = [(c, byte_order + "f4") for c in "xyz"]
    if labels is not None:
        fields.append(("label", byte_order + label_type))
    rec = np.zeros(P.shape[0] * P.shape[1], dtype=fields)
    flat = P.reshape(-1, 3)
    for i, c in enumerate("xyz"):
        rec[c] = flat[:, i]
    if labels is not None:
        rec["label"] = labels.reshape(-1)
    return rec, fields


def pcd_bytes(P: np.ndarray, data: str, *, labels: np.ndarray | None = None,
              header: dict[str, str] | None = None) -> bytes:
    """An organized PCD file of the (H, W, 3) float32 cloud ``P`` (``data``: ascii, binary or
    binary_compressed), optionally with a uint32 ``label`` field; ``header`` overrides
    header lines by key."""
    H, W = P.shape[:2]
    n = H * W
    rec, fields = _xyz_records(P, labels, "<", "u4")
    head = {
        "VERSION": "0.7", "FIELDS": " ".join(f for f, _ in fields),
        "SIZE": " ".join("4" for _ in fields),
        "TYPE": " ".join("U" if f == "label" else "F" for f, _ in fields),
        "COUNT": " ".join("1" for _ in fields), "WIDTH": str(W), "HEIGHT": str(H),
        "VIEWPOINT": "0 0 0 1 0 0 0", "POINTS": str(n), "DATA": data,
    }
    head.update(header or {})
    text = "# .PCD v0.7 - fuzz\n" + "".join(f"{k} {v}\n" for k, v in head.items())
    if data == "ascii":
        body = "".join(" ".join(repr(float(v)) if isinstance(v, float) else str(int(v))
                                for v in row) + "\n" for row in rec.tolist()).encode()
    elif data == "binary_compressed":
        cols = b"".join(np.ascontiguousarray(rec[f]).tobytes() for f, _ in fields)
        comp = _lzf_literal(cols)
        body = struct.pack("<II", len(comp), len(cols)) + comp
    else:
        body = rec.tobytes()
    return text.encode() + body


def ply_bytes(P: np.ndarray, fmt: str, *, labels: np.ndarray | None = None,
              header_lines: list[str] | None = None) -> bytes:
    """An organized PLY (``obj_info num_cols/num_rows``) of the (H, W, 3) cloud ``P``."""
    H, W = P.shape[:2]
    n = H * W
    bo = ">" if fmt == "binary_big_endian" else "<"
    rec, _ = _xyz_records(P, labels, bo, "i4")
    lines = header_lines or [
        f"format {fmt} 1.0", f"obj_info num_cols {W}", f"obj_info num_rows {H}",
        f"element vertex {n}", "property float x", "property float y", "property float z",
    ] + (["property int label"] if labels is not None else [])
    head = "ply\n" + "".join(ln + "\n" for ln in lines) + "end_header\n"
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(v)) if isinstance(v, float) else str(int(v))
                                for v in row) + "\n" for row in rec.tolist()).encode()
    else:
        body = rec.tobytes()
    return head.encode() + body


_PCD_VALUES = ("0", "-1", "1", "3", "1e9", "nan", "", "abc", "99999999999999999999", "4097",
               "16777217", "2.5")


def _gen_cloud(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    kw = {"intrinsics": _intrinsics_kw(rng, corpus) if rng.random() < 0.3 else None}
    u = rng.random()
    if u < 0.3:
        src = Path(corpus["clouds"][int(rng.integers(0, len(corpus["clouds"])))])
        data, op = mutate_bytes(rng, src.read_bytes())
        p = d / f"fuzzed{src.suffix}"
        p.write_bytes(data)
        return _file_job(f"mutate-{op}", p, kw, d, labels=True)
    H, W = int(_pick(rng, [1, 2, 5, 36])), int(_pick(rng, [1, 4, 48]))
    P, kind = _storm(rng, (H, W, 3))
    if rng.random() < 0.3:  # a plausible organized cloud: a plane 1.5 m ahead
        v, uu = np.mgrid[0:H, 0:W].astype(np.float32)
        P = np.stack([(uu - W / 2) * 0.03, (v - H / 2) * 0.03, np.full_like(uu, 1.5)], -1)
        kind = "plane"
    labels = (np.arange(H * W) % 5).astype(np.uint32).reshape(H, W)
    if rng.random() < 0.5:
        data_kind = str(_pick(rng, ["ascii", "binary", "binary_compressed"]))
        header: dict[str, str] = {}
        if u < 0.7:
            key = str(_pick(rng, ["WIDTH", "HEIGHT", "POINTS", "SIZE", "TYPE", "COUNT",
                                  "VIEWPOINT", "DATA", "FIELDS"]))
            vals = {"SIZE": ["4 4 4 4", "8 4 4 4", "0 4 4 4", "4 4 4", "3 4 4 4"],
                    "TYPE": ["F F F U", "I F F U", "F F F F", "X F F U", "F F F"],
                    "COUNT": ["1 1 1 1", "0 1 1 1", "3 1 1 1", "1 1 1 1000000000"],
                    "VIEWPOINT": ["0 0 0 1 0 0 0", "nan 0 0 1 0 0 0", "0 0 0 0 0 0 0", "1 2",
                                  "0 0 0 1e308 1e308 0 0"],
                    "DATA": ["binary_compressed", "binary", "ascii", "lzma", ""],
                    "FIELDS": ["x y z label", "x y label z", "a b c d", "x y z z"]}
            header[key] = str(_pick(rng, vals.get(key, list(_PCD_VALUES))))
            kind += f"-{key}={header[key][:12]}"
        data = pcd_bytes(P, data_kind, labels=labels, header=header)
        p = d / "fuzzed.pcd"
    else:
        fmt = str(_pick(rng, ["ascii", "binary_little_endian", "binary_big_endian"]))
        lines = None
        if u < 0.7:
            lines = [f"format {fmt} 1.0", f"obj_info num_cols {W}", f"obj_info num_rows {H}",
                     f"element vertex {H * W}", "property float x", "property float y",
                     "property float z", "property int label"]
            i = int(rng.integers(0, len(lines)))
            bad = [f"obj_info num_cols {rng.choice(_PCD_VALUES)}",
                   f"element vertex {rng.choice(_PCD_VALUES)}", "property list uchar int x",
                   "property double y", "element camera 1", "format binary_little_endian 2.0",
                   "property float64 z", "element range_grid 3",
                   "property list uint8 int vertex_indices", "comment " + "c" * 70_000,
                   "element face 4000000000", f"element vertex {H * W}"]
            lines[i] = str(_pick(rng, bad))
            kind += f"-line{i}"
        data = ply_bytes(P, fmt, labels=labels, header_lines=lines)
        p = d / "fuzzed.ply"
    p.write_bytes(data)
    return _file_job(f"write-{p.suffix[1:]}:{kind}", p, kw, d, labels=True)
