"""Products, scans and records to MCAP message bytes, and back.

Two kinds of messages go into a log:

* **Records of truth** (``boxloc.v1.*`` protobuf, see :mod:`recorder.mcap.proto`): every stage
  product is flattened with :func:`boxloc.products.to_arrays` into named arrays and stored
  bit for bit; the scan's range goes into a ``boxloc.ScanRange`` record exactly as given
  (float32, predicted from the left neighbour, the differences split at the noise and
  compressed, schema 1.6; byte-shuffled up to 1.5 and a Foxglove ``RawImage`` ``32FC1`` up
  to 1.3, both still read); the sensor model and the pose into
  ``boxloc.ScanInfo`` / ``boxloc.SensorModel`` records (float64 bits, not a quaternion).
  Decoding them gives back the same products (:func:`boxloc.products.products_equal` is
  empty) and the same scan. The result's ambiguous regions (an ``AmbiguousSet``, not a
  stage's product) are a record of their own the same way (:func:`encode_ambiguous`).
  The statistical tests of every stage are recorded once, as readable rows (stage, kind,
  entities, statistic, dof, critical value, p-value, alpha, decision) on ``/boxloc/tests``,
  and put back into their products when read.
* **Views** for people and viewers (Foxglove well-known schemas, JSON): the range as a JPEG
  preview, a decimated point cloud, the edge map as an image, a ``SceneUpdate`` of lines,
  vertices, rectangles and surfaces, the ``locate`` JSON. They are derived from the records
  and never read back.

Decoding treats the log as untrusted: dtypes come from a whitelist, every array is bounded
by its declared shape and by :class:`DecodeLimits`, names are checked against the product
type, and nothing is unpickled or evaluated.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
import struct
import typing
from dataclasses import dataclass
from typing import Any

import numpy as np
import zstandard
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from boxloc.errors import LogError
from boxloc.products import (
    PRODUCT_TYPES,
    STAGES,
    AmbiguityReason,
    AmbiguousSet,
    EdgeKind,
    HeightSource,
    HypothesisSet,
    LineSet,
    SurfaceSet,
    Verification,
    VertexSet,
    from_arrays,
    to_arrays,
)
from boxloc.scan import PinholeModel, RayTableModel, Scan, SensorModel
from boxloc.stats import TestKind, TestTable
from recorder.mcap.proto import PACKAGE, message_class

# --- versions and names ----------------------------------------------------------------------

#: Major version of every boxloc record; a reader refuses any other major version.
SCHEMA_MAJOR = 1
#: Minor version: compatible additions (new fields are ignored by older readers). 1.4: the
#: range image is a ``ScanRange`` record (filter 4) instead of a Foxglove RawImage; 1.4
#: readers read both, 1.3 readers cannot read 1.4's range. 1.5 (issue #21): the
#: ``AmbiguousSet`` record on ``/boxloc/ambiguous`` (its tests on ``/boxloc/tests`` as stage
#: ``ambiguous``) and the SurfaceSet's ``height``, ``height_sigma``, ``height_source``,
#: ``sku`` and ``sku_flagged``; older logs read back with an empty set and NaN heights.
#: 1.6 (issue #22 part 5): the range's image filter 5 (split at the noise, each part
#: compressed; :data:`_FILTER_IMAGE_SPLIT`) instead of 4; 1.6 readers read both, 1.4 and
#: 1.5 readers cannot read 1.6's range (:func:`legacy_range_message` rewrites it for them).
#: 1.7 (issue #22 part 5): float64 arrays whose every value is a float32 (the edge points,
#: their covariances and jump heights) in filters 6 and 7, as float32; 1.6 readers cannot
#: read them (:func:`legacy_product_message` rewrites them for them). The tests' rows are
#: unchanged (doubles), though their p-values and the line-pair statistics, now float32
#: values, leave zstd fewer bytes to store.
SCHEMA_MINOR = 7
SCHEMA_VERSION = f"{SCHEMA_MAJOR}.{SCHEMA_MINOR}"

#: Frame of every geometric message (x right, y down, z forward; metres).
SENSOR_FRAME = "sensor"
#: Parent frame of ``/scan/pose``: the robot base.
BASE_FRAME = "base"

#: Record names of the stage products (``boxloc.<Name>/<major>.<minor>``).
PRODUCT_RECORDS: dict[str, str] = {stage: PRODUCT_TYPES[stage].__name__ for stage in STAGES}
SCAN_INFO_RECORD = "ScanInfo"
SENSOR_RECORD = "SensorModel"
RESULT_RECORD = "ResultInfo"
TESTS_RECORD = "TestRows"
TIMING_RECORD = "Timing"
OUTCOME_RECORD = "PickOutcome"
ERROR_RECORD = "ScanError"
LOCATE_RECORD = "Locate"
LABELS_RECORD = "ScanLabels"
SCAN_END_RECORD = "ScanEnd"
RANGE_RECORD = "ScanRange"
AMBIGUOUS_RECORD = "AmbiguousSet"
#: The ``stage`` of the ambiguous regions' tests on ``/boxloc/tests`` (not a pipeline stage:
#: the regions are part of the result, :attr:`boxloc.products.Result.ambiguous`).
AMBIGUOUS_STAGE = "ambiguous"

_RECORD_RE = re.compile(r"^boxloc\.([A-Za-z][A-Za-z0-9]{0,63})/(\d{1,4})\.(\d{1,4})$")


def record_schema(name: str) -> str:
    """The versioned record name written into every boxloc message, e.g. ``boxloc.EdgeMap/1.2``."""
    return f"boxloc.{name}/{SCHEMA_VERSION}"


def check_record_schema(found: str, expected: str) -> tuple[int, int]:
    """Check a message's record name and major version; return ``(major, minor)``.

    Raises
    ------
    LogError
        If the record is not ``expected`` or its major version is not :data:`SCHEMA_MAJOR`.
    """
    m = _RECORD_RE.match(found or "")
    if m is None:
        raise LogError(f"unrecognized record schema {found[:80]!r} (expected boxloc.{expected})")
    name, major, minor = m.group(1), int(m.group(2)), int(m.group(3))
    if name != expected:
        raise LogError(f"record schema {found!r} where boxloc.{expected} was expected")
    if major != SCHEMA_MAJOR:
        raise LogError(
            f"record schema {found!r} has major version {major}; this boxloc reads version "
            f"{SCHEMA_MAJOR} only (use the boxloc version that wrote the log)"
        )
    return major, minor


@dataclass(frozen=True)
class DecodeLimits:
    """Bounds on what a reader will allocate for one message (logs are untrusted input).

    Parameters
    ----------
    max_array_bytes : int
        Largest single decoded array, bytes.
    max_ndim : int
        Most dimensions of an array.
    max_pixels : int
        Largest image (range, ray table), pixels.
    max_record_bytes : int
        Largest MCAP record or decompressed chunk, bytes.
    """

    max_array_bytes: int = 1 << 30
    max_ndim: int = 8
    max_pixels: int = 16_777_216
    max_record_bytes: int = 4 << 30


DEFAULT_LIMITS = DecodeLimits()


# --- arrays ----------------------------------------------------------------------------------

_DTYPE_RE = re.compile(r"^[<>|](?:b1|[iu][1248]|f[248]|U\d{1,6})$")
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}(?:/[A-Za-z_][A-Za-z0-9_]{0,63}){0,3}$")
#: Filter arrays at least this large (elements). Byte shuffle puts the exponents and high
#: bytes of numbers together, so zstd compresses float64 arrays much better; integer arrays
#: that change slowly (sorted pixel indices, offsets) are delta-coded first. Both lossless.
SHUFFLE_MIN_ELEMENTS = 64
_FILTER_NONE, _FILTER_SHUFFLE, _FILTER_DELTA_SHUFFLE, _FILTER_SYMMETRIC_SHUFFLE = 0, 1, 2, 3
#: For images (schema 1.4): each value's bits, as a little-endian unsigned integer, minus
#: those of its left neighbour (the first column: of the pixel above), zigzag, byte shuffle.
#: The bits of positive floats grow with the value, so a smooth surface leaves small
#: differences; what is left is the sensor's noise. Exact for every bit pattern (NaN, -0.0).
#: Read, no longer written (schema 1.6 writes :data:`_FILTER_IMAGE_SPLIT`).
_FILTER_IMAGE_DELTA_SHUFFLE = 4
#: For images (schema 1.6): the differences of filter 4 (NaN pixels first given the bits of
#: the pixel before them, so a dropout costs no jump), split at bit ``k`` and each part
#: compressed on its own (zstd): the low byte, bits 8..k-1 and the rest (``zz >> k``, one
#: byte, 255 = escape to the full value). With ``k`` just below the noise's spread the low
#: parts are nearly uniform (stored at their entropy) and the rest takes a few symbols that
#: Huffman codes well, where a byte shuffle mixed noise and signal in one plane and zstd's
#: blocks straddled planes: 3-5 % smaller on simulated 640x480 scans, every bit kept.
_FILTER_IMAGE_SPLIT = 5
#: For float64 arrays (schema 1.7) whose every value is a float32, bit for bit (the value
#: comes back from float32 with the same float64 bits): the float32 values, byte-shuffled
#: (6), or of a stack of symmetric matrices the upper triangle (7, as 3). Half the bytes
#: of 1 and 3, and the low half of a float64 mantissa was all zeros anyway. Products that
#: the pipeline rounds to float32 precision (:func:`boxloc.stats.float32_precision`) take
#: these filters; any other float64 array that happens to qualify does too.
_FILTER_F32_SHUFFLE, _FILTER_F32_SYMMETRIC_SHUFFLE = 6, 7
#: zstd level of the image filter's parts (the chunk then finds nothing left to compress).
IMAGE_ZSTD_LEVEL = 1
#: filter 5's header: k, flags (bit 0: NaN mask and bits follow), 2 zero bytes, the count
#: of escapes, of NaN pixels, then the byte length of each part (see _IMAGE_PARTS).
_IMAGE_HEADER = struct.Struct("<BBxxII6I")
_IMAGE_PARTS = ("low", "mid", "high", "escapes", "nan_mask", "nan_bits")


def _image_delta(a: np.ndarray) -> np.ndarray:
    """The image filter's zigzagged differences of a 2-D array, (H, W) native uint of the
    array's item size (its bytes read as little-endian integers)."""
    k = a.dtype.itemsize
    u = np.frombuffer(a.tobytes(), f"<u{k}").astype(f"u{k}", copy=False).reshape(a.shape)
    return _zigzag_delta(u)


def _zigzag_delta(u: np.ndarray) -> np.ndarray:
    """Filter 4's differences of a (H, W) native unsigned array, zigzagged (same dtype)."""
    d = np.empty_like(u)
    np.subtract(u[:, 1:], u[:, :-1], out=d[:, 1:])  # wraps around: exact modulo 2**bits
    d[0, 0] = u[0, 0]
    np.subtract(u[1:, 0], u[:-1, 0], out=d[1:, 0])
    bits = 8 * u.dtype.itemsize
    # small negatives to small odd numbers: (d << 1) ^ (d >> bits-1, arithmetic)
    sign = (d.view(f"i{u.dtype.itemsize}") >> (bits - 1)).view(d.dtype)
    np.left_shift(d, np.array(1, d.dtype), out=d)
    np.bitwise_xor(d, sign, out=d)
    return d


def _image_undelta(zz: np.ndarray, dt: np.dtype) -> np.ndarray:
    """Invert :func:`_image_delta`: (H, W) zigzagged differences to an array of ``dt``."""
    k = dt.itemsize
    z = zz.astype(f"u{k}")
    one = np.array(1, z.dtype)
    d = (z >> one) ^ (np.zeros_like(z) - (z & one))
    d[:, 0] = np.cumsum(d[:, 0], dtype=z.dtype)  # wraps around like the encoder
    u = np.cumsum(d, axis=1, dtype=z.dtype)
    return np.frombuffer(u.astype(f"<u{k}").tobytes(), dt).reshape(zz.shape)


#: Every how many pixels :func:`_split_bits` looks at: its histogram needs no more.
_SPLIT_SAMPLE = 16
#: The entropy, bits, below which :func:`_split_bits` stops crediting the high part: zstd's
#: Huffman coder spends at least a bit per symbol and loses more the fewer symbols take
#: most pixels (measured: 0.1 bit over the entropy at 4 bits, 0.4 at 2).
_HIGH_MIN_BITS = 4.0


def _split_bits(zz: np.ndarray) -> int:
    """The ``k`` (8..16) of filter 5 that makes the parts smallest, estimated.

    One histogram of ``zz >> 8`` (every :data:`_SPLIT_SAMPLE`-th pixel); each ``k`` costs
    ``k - 8`` raw bits per pixel, the entropy of ``zz >> k`` (255 and above one escape
    symbol; at least :data:`_HIGH_MIN_BITS`) and the escapes' full values.
    """
    b = zz.reshape(-1)[::_SPLIT_SAMPLE] >> np.array(8, zz.dtype)
    h = np.bincount(np.minimum(b, np.array(0xFFFF, b.dtype)), minlength=0x10000)
    n, item_bits = b.size, 8 * zz.dtype.itemsize
    best, best_bits = 8, math.inf
    for k in range(8, min(16, item_bits) + 1):
        if k > 8:
            h = h[0::2] + h[1::2]  # the histogram of zz >> k from that of zz >> k-1
        sym = np.append(h[:255], h[255:].sum()).astype(np.float64)
        p = sym[sym > 0] / n
        high = max(-float((p * np.log2(p)).sum()), _HIGH_MIN_BITS)
        bits = n * (k - 8 + high) + item_bits * float(sym[255])
        if bits < best_bits:
            best, best_bits = k, bits
    return best


def _fill_nan(u: np.ndarray, nan: np.ndarray) -> np.ndarray:
    """A copy of the flat bits ``u`` where each NaN pixel (``nan``, flat bool) has the bits
    of the last pixel before it that is not NaN (raster order; 0 before the first)."""
    idx = np.flatnonzero(nan)
    starts = np.ones(idx.size, bool)
    starts[1:] = idx[1:] != idx[:-1] + 1  # the first NaN of each run
    start_of = idx[np.maximum.accumulate(np.where(starts, np.arange(idx.size), 0))]
    out = u.copy()
    out[idx] = np.where(start_of > 0, u[np.maximum(start_of - 1, 0)], 0)
    return out


def _image_split_bytes(a: np.ndarray) -> bytes:
    """Filter 5's data for a C-contiguous 2-D array of 2, 4 or 8 byte numbers (see
    :data:`_FILTER_IMAGE_SPLIT`).

    Its bytes read as little-endian integers, as filter 4 reads them. A few passes over the
    image (3-6 ms at 640x480 on a busy 2-core machine, 1-2 ms more than filter 4 and the
    chunk's zstd of it).
    """
    item = a.dtype.itemsize
    ut = np.dtype(f"u{item}")
    u = a.view(f"<u{item}").astype(ut, copy=False)  # no copy on a little-endian machine
    nan_mask = nan_bits = b""
    n_nan = 0
    if a.dtype.kind == "f":
        nan = np.isnan(a).reshape(-1)
        n_nan = int(np.count_nonzero(nan))
        if n_nan:
            # a NaN takes the bits of the last number before it (raster order): the run of
            # no return and its end cost two small differences, not two jumps to NaN bits
            flat = u.reshape(-1)
            nan_bits = _shuffle(flat[nan])
            nan_mask = np.packbits(nan).tobytes()
            u = _fill_nan(flat, nan).reshape(a.shape)
    zz = _zigzag_delta(u).reshape(-1)
    k = _split_bits(zz)
    le = zz.astype(f"<u{item}", copy=False).view(np.uint8).reshape(-1, item)
    low = le[:, 0].copy()  # bits 0..7
    mid = le[:, 1] & np.uint8((1 << (k - 8)) - 1) if k > 8 else np.zeros(0, np.uint8)
    if k < 8 * item:
        hi = np.right_shift(zz, np.array(k, ut))
        esc = hi >= 255
        n_esc = int(np.count_nonzero(esc))
        escapes = _shuffle(zz[esc]) if n_esc else b""
        high = np.minimum(hi, np.array(255, ut), out=hi).astype(np.uint8)
    else:  # every bit is in the low and middle parts
        n_esc, escapes, high = 0, b"", np.zeros(zz.size, np.uint8)
    z = zstandard.ZstdCompressor(level=IMAGE_ZSTD_LEVEL)
    parts = [_pack_part(z, p, raw=k > 8 and i == 0)
             for i, p in enumerate((low, mid, high, escapes, nan_mask, nan_bits))]
    head = _IMAGE_HEADER.pack(k, 1 if n_nan else 0, n_esc, n_nan, *(len(p) for p in parts))
    return head + b"".join(parts)


def _pack_part(z: zstandard.ZstdCompressor, part: Any, raw: bool) -> bytes:
    """One part of filter 5: a zstd frame, or the bytes as they are when that is no longer
    (the reader tells them apart by the length: as long as the part is raw).

    ``raw``: do not try (the low byte under the noise is uniform: zstd would spend half a
    millisecond at 640x480 to find that out)."""
    data = bytes(part)
    if raw or not data:
        return data
    packed = z.compress(data)
    return packed if len(packed) < len(data) else data


def _image_split_array(data: bytes, name: str, shape: tuple[int, ...], dt: np.dtype,
                       ) -> np.ndarray:
    """Invert :func:`_image_split_bytes`; every size is checked before it is allocated."""
    def bad(what: str) -> LogError:
        return LogError(f"array {name[:64]!r}: image filter 5: {what}")

    if len(shape) != 2 or 0 in shape or dt.kind not in "iuf" or dt.itemsize not in (2, 4, 8):
        raise bad(f"not valid on shape {shape} {dt}")
    if len(data) < _IMAGE_HEADER.size:
        raise bad(f"{len(data)} bytes, shorter than its header")
    k, flags, n_esc, n_nan, *lengths = _IMAGE_HEADER.unpack_from(data)
    n, item = math.prod(shape), dt.itemsize
    if (not 8 <= k <= 16 or flags not in (0, 1) or n_esc > n or n_nan > n
            or (flags == 0) != (n_nan == 0)):
        raise bad(f"header (k {k}, flags {flags}, {n_esc} escapes, {n_nan} NaN) is not valid")
    if _IMAGE_HEADER.size + sum(lengths) != len(data):
        raise bad(f"parts of {sum(lengths)} bytes do not fill {len(data)} bytes")
    expected = (n, n if k > 8 else 0, n, n_esc * item, -(-n // 8) if n_nan else 0,
                n_nan * item)
    parts: list[bytes] = []
    pos = _IMAGE_HEADER.size
    dz = zstandard.ZstdDecompressor()
    for what, length, size in zip(_IMAGE_PARTS, lengths, expected):
        frame = data[pos:pos + length]
        pos += length
        if length == size:  # stored as it is
            parts.append(frame)
            continue
        try:
            if zstandard.frame_content_size(frame) != size:
                raise bad(f"part {what} does not hold {size} bytes")
            out = dz.decompress(frame, max_output_size=size)
        except zstandard.ZstdError as e:
            raise bad(f"part {what}: {e}") from None
        if len(out) != size:
            raise bad(f"part {what} holds {len(out)} bytes, not {size}")
        parts.append(out)
    low, mid, high, escapes, nan_mask, nan_bits = parts
    ut = np.dtype(f"u{item}")
    zz = np.frombuffer(low, np.uint8).astype(ut)
    if k > 8:
        zz |= np.frombuffer(mid, np.uint8).astype(ut) << np.array(8, ut)
    hi = np.frombuffer(high, np.uint8)
    esc = hi == 255
    if int(np.count_nonzero(esc)) != n_esc:
        raise bad(f"{int(np.count_nonzero(esc))} escape symbols for {n_esc} escapes")
    if k < 8 * item:
        zz |= hi.astype(ut) << np.array(k, ut)
    elif hi.any():
        raise bad(f"high part not zero with k {k} for {dt}")
    if n_esc:
        zz[esc] = _unshuffle(escapes, ut)
    u = _image_undelta(zz.reshape(shape), ut).reshape(-1).copy()
    if n_nan:
        nan = np.unpackbits(np.frombuffer(nan_mask, np.uint8), count=n).astype(bool)
        if int(np.count_nonzero(nan)) != n_nan:
            raise bad(f"NaN mask of {int(np.count_nonzero(nan))} pixels for {n_nan}")
        u[nan] = _unshuffle(nan_bits, ut)
    return np.frombuffer(u.astype(f"<u{item}").tobytes(), dt).reshape(shape)


def _shuffle(a: np.ndarray) -> bytes:
    return a.reshape(-1).view(np.uint8).reshape(-1, a.dtype.itemsize).T.tobytes()


def _unshuffle(data: bytes, dt: np.dtype) -> np.ndarray:
    """Invert :func:`_shuffle`: (n,) of ``dt`` from its byte planes."""
    return np.frombuffer(data, np.uint8).reshape(dt.itemsize, -1).T.copy().view(dt).reshape(-1)


def _delta_pays(a: np.ndarray) -> bool:
    """Whether consecutive differences are much smaller than the values (cheap estimate)."""
    flat = a.reshape(-1)[:65536]  # a sample is enough to decide
    if flat.dtype.kind == "u":  # differences modulo 2**bits, as the filter stores them
        flat = flat.view(flat.dtype.str.replace("u", "i"))
    d = np.diff(flat).astype(np.float64)
    spread = np.abs(flat.astype(np.float64) - float(flat.mean())).mean()
    return bool(np.abs(d).mean() * 4 < spread)


def _bitwise_symmetric(a: np.ndarray) -> bool:
    """Whether a stack of square matrices (..., n, n) equals its transpose bit for bit."""
    if a.ndim < 2 or a.shape[-1] != a.shape[-2] or a.shape[-1] < 2:
        return False
    u = a.view(np.dtype(f"u{a.dtype.itemsize}"))
    return bool(np.array_equal(u, np.swapaxes(u, -1, -2)))


def _float32_exact(a: np.ndarray) -> bool:
    """Whether a float64 array's every value is a float32: it comes back from float32 with
    the same bits (NaN payloads, -0.0 and infinities included)."""
    if a.dtype != np.float64:
        return False
    with np.errstate(over="ignore", invalid="ignore"):
        back = a.astype(np.float32).astype(np.float64)
    return bool(np.array_equal(back.view(np.uint64), a.view(np.uint64)))


def array_to_msg(msg: Any, name: str, a: np.ndarray, *, shuffle: bool = True,
                 image: bool = False, image_filter: int = _FILTER_IMAGE_SPLIT,
                 float32: bool = True) -> None:
    """Fill a ``boxloc.v1.Array`` message with ``a`` (any shape; C-order bytes).

    ``image``: ``a`` is an image (2-D, numbers of 2, 4 or 8 bytes), stored with an image
    filter, which predicts each pixel from its left neighbour: ``image_filter`` 5 (schema
    1.6, the default) or 4 (what schema 1.4 and 1.5 readers read).

    ``float32``: a float64 array whose every value is a float32 is stored as float32
    (filters 6 and 7, schema 1.7); False writes what 1.6 readers read (filters 1 and 3).
    """
    a = np.asarray(a)
    if not _DTYPE_RE.match(a.dtype.str):
        raise TypeError(f"array {name!r}: dtype {a.dtype} cannot be recorded")
    if not a.flags.c_contiguous:
        a = a.copy(order="C")  # not ascontiguousarray: it makes 0-d arrays 1-d
    msg.name = name
    msg.dtype = a.dtype.str
    msg.shape.extend(int(s) for s in a.shape)
    big = a.dtype.itemsize > 1 and a.dtype.kind in "iuf" and a.size >= SHUFFLE_MIN_ELEMENTS
    if image and a.ndim == 2 and a.size and a.dtype.kind in "iuf" and a.dtype.itemsize in (2, 4, 8):
        if image_filter == _FILTER_IMAGE_SPLIT:
            msg.filter = _FILTER_IMAGE_SPLIT
            msg.data = _image_split_bytes(a)
        elif image_filter == _FILTER_IMAGE_DELTA_SHUFFLE:
            msg.filter = _FILTER_IMAGE_DELTA_SHUFFLE
            msg.data = _shuffle(_image_delta(a))
        else:
            raise ValueError(f"image_filter must be 4 or 5, got {image_filter}")
    elif shuffle and big and a.dtype.kind in "iu" and _delta_pays(a):
        flat = a.reshape(-1)
        d = np.empty_like(flat)
        d[0] = flat[0]
        np.subtract(flat[1:], flat[:-1], out=d[1:])  # wraps around: exact modulo 2**bits
        msg.filter = _FILTER_DELTA_SHUFFLE
        msg.data = _shuffle(d)
    elif shuffle and big and a.dtype.kind == "f" and _bitwise_symmetric(a):
        # Covariances: the lower triangle is the upper one, bit for bit; keep it once.
        iu = np.triu_indices(a.shape[-1])
        tri = np.ascontiguousarray(a[..., iu[0], iu[1]])
        if float32 and _float32_exact(tri):
            msg.filter = _FILTER_F32_SYMMETRIC_SHUFFLE
            msg.data = _shuffle(tri.astype(np.float32))
        else:
            msg.filter = _FILTER_SYMMETRIC_SHUFFLE
            msg.data = _shuffle(tri)
    elif shuffle and big and float32 and _float32_exact(a):
        msg.filter = _FILTER_F32_SHUFFLE
        msg.data = _shuffle(a.astype(np.float32))
    elif shuffle and big:
        msg.filter = _FILTER_SHUFFLE
        msg.data = _shuffle(a)
    else:
        msg.data = a.tobytes()


def msg_to_array(msg: Any, limits: DecodeLimits = DEFAULT_LIMITS) -> np.ndarray:
    """Decode a ``boxloc.v1.Array``; refuse anything not bounded by its declared shape."""
    name = msg.name
    if not _DTYPE_RE.match(msg.dtype):
        raise LogError(f"array {name[:64]!r}: dtype {msg.dtype[:32]!r} is not allowed")
    dt = np.dtype(msg.dtype)
    if dt.itemsize == 0:
        raise LogError(f"array {name[:64]!r}: dtype {msg.dtype!r} has no size")
    shape = tuple(int(s) for s in msg.shape)
    if len(shape) > limits.max_ndim:
        raise LogError(f"array {name[:64]!r}: {len(shape)} dimensions exceed {limits.max_ndim}")
    n = math.prod(shape)
    nbytes = n * dt.itemsize
    if nbytes > limits.max_array_bytes:
        raise LogError(
            f"array {name[:64]!r}: {nbytes} bytes exceed the limit of {limits.max_array_bytes}"
        )
    if any(s > limits.max_array_bytes for s in shape):
        # An empty array (a zero dimension) may not claim an absurd other one either.
        raise LogError(f"array {name[:64]!r}: shape {shape} has a dimension beyond the limit "
                       f"of {limits.max_array_bytes}")
    data = msg.data
    if msg.filter == _FILTER_IMAGE_SPLIT:  # compressed: its own sizes are checked inside
        return _image_split_array(data, name, shape, dt)
    stored = nbytes
    f32 = msg.filter in (_FILTER_F32_SHUFFLE, _FILTER_F32_SYMMETRIC_SHUFFLE)
    if f32:
        if dt != np.float64:
            raise LogError(f"array {name!r}: float32 filter on dtype {dt} is not valid")
        stored = n * 4
    if msg.filter in (_FILTER_SYMMETRIC_SHUFFLE, _FILTER_F32_SYMMETRIC_SHUFFLE):
        if len(shape) < 2 or shape[-1] != shape[-2] or dt.kind != "f" or dt.itemsize == 1:
            raise LogError(f"array {name!r}: symmetric filter on shape {shape} {dt} is not valid")
        k = shape[-1]
        stored = (math.prod(shape[:-2]) * (k * (k + 1) // 2)
                  * (4 if f32 else dt.itemsize))
    if len(data) != stored:
        raise LogError(
            f"array {name!r}: {len(data)} bytes of data for shape {shape} of {dt} "
            f"({stored} bytes expected)"
        )
    if msg.filter == _FILTER_IMAGE_DELTA_SHUFFLE:
        if len(shape) != 2 or n == 0 or dt.kind not in "iuf" or dt.itemsize not in (2, 4, 8):
            raise LogError(f"array {name!r}: image filter on shape {shape} {dt} is not valid")
        zz = np.frombuffer(data, np.uint8).reshape(dt.itemsize, n).T.copy().view(
            f"<u{dt.itemsize}")
        return _image_undelta(zz.reshape(shape), dt)
    if msg.filter in (_FILTER_SYMMETRIC_SHUFFLE, _FILTER_F32_SYMMETRIC_SHUFFLE):
        k = shape[-1]
        m = k * (k + 1) // 2
        packed = (_unshuffle(data, np.dtype("<f4")).astype(dt) if f32
                  else np.frombuffer(data, np.uint8).reshape(dt.itemsize, -1).T.copy().view(dt)
                  ).reshape(shape[:-2] + (m,))
        iu = np.triu_indices(k)
        out = np.empty(shape, dt)
        out[..., iu[0], iu[1]] = packed
        out[..., iu[1], iu[0]] = packed
        return out
    if msg.filter == _FILTER_F32_SHUFFLE:
        return _unshuffle(data, np.dtype("<f4")).astype(dt).reshape(shape)
    if msg.filter in (_FILTER_SHUFFLE, _FILTER_DELTA_SHUFFLE):
        if dt.itemsize == 1 or dt.kind not in "iuf":
            raise LogError(f"array {name!r}: filter {msg.filter} on dtype {dt} is not valid")
        a = np.frombuffer(data, np.uint8).reshape(dt.itemsize, n).T.copy().view(dt).reshape(-1)
        if msg.filter == _FILTER_DELTA_SHUFFLE:
            if dt.kind == "f":
                raise LogError(f"array {name!r}: delta filter on dtype {dt} is not valid")
            a = np.cumsum(a, dtype=dt)  # wraps around like the encoder's subtraction
        return a.reshape(shape)
    if msg.filter != _FILTER_NONE:
        raise LogError(f"array {name!r}: unknown filter {msg.filter}")
    a = np.frombuffer(data, dt).reshape(shape)
    return a


def encode_arrays(record: str, arrays: dict[str, np.ndarray], scan_index: int,
                  capture_time_ns: int) -> bytes:
    """Serialize named arrays as a ``boxloc.v1.Product`` message of record ``record``."""
    msg = message_class("Product")()
    msg.schema = record_schema(record)
    msg.scan_index = int(scan_index)
    msg.capture_time_ns = int(capture_time_ns)
    for name, a in arrays.items():
        array_to_msg(msg.arrays.add(), name, a)
    return msg.SerializeToString()


def decode_arrays(
    data: bytes, record: str, limits: DecodeLimits = DEFAULT_LIMITS
) -> tuple[Any, dict[str, np.ndarray]]:
    """Parse a ``boxloc.v1.Product`` of record ``record``; return ``(message, arrays)``.

    Array contents are not decoded here beyond their bounds; names must be unique and
    well formed (they never become paths or attribute lookups outside a known table).
    """
    msg = _parse("Product", data)
    check_record_schema(msg.schema, record)
    out: dict[str, np.ndarray] = {}
    for am in msg.arrays:
        if not _NAME_RE.match(am.name):
            raise LogError(f"record {record}: bad array name {am.name[:64]!r}")
        if am.name in out:
            raise LogError(f"record {record}: array {am.name!r} appears twice")
        out[am.name] = msg_to_array(am, limits)
    return msg, out


def parse_json(text: str | bytes, what: str) -> Any:
    """``json.loads`` for text from a log: bad syntax or nesting too deep for the parser
    (a ``RecursionError``) is a :class:`LogError` naming ``what``."""
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as e:
        raise LogError(f"{what} is not valid JSON: {str(e)[:200]}") from None


def _parse(name: str, data: bytes) -> Any:
    msg = message_class(name)()
    try:
        msg.ParseFromString(data)
    except Exception as e:  # protobuf raises its own DecodeError; keep the message short
        raise LogError(f"cannot parse a {PACKAGE}.{name} message: {e}") from None
    return msg


# --- products --------------------------------------------------------------------------------


def _field_names(cls: type, prefix: str = "", required: bool = False) -> set[str]:
    """The names :func:`to_arrays` produces for a product type; with ``required``, only
    those a log must have (a field with a default is newer than some logs, and
    :func:`~boxloc.products.from_arrays` fills it in)."""
    hints = typing.get_type_hints(cls)
    names: set[str] = set()
    for f in dataclasses.fields(cls):
        if required and f.default is not dataclasses.MISSING:
            continue
        t = hints[f.name]
        if isinstance(t, type) and dataclasses.is_dataclass(t):
            names |= _field_names(t, prefix + f.name + "/", required)
        else:
            names.add(prefix + f.name)
    return names


_PRODUCT_FIELDS: dict[str, set[str]] = {s: _field_names(PRODUCT_TYPES[s]) for s in STAGES}
_REQUIRED_FIELDS: dict[str, set[str]] = {s: _field_names(PRODUCT_TYPES[s], required=True)
                                         for s in STAGES}


#: The TestTable columns stored on ``/boxloc/tests`` (one row per test) instead of inside
#: the product, with the dtype the rows reproduce exactly. A column of another dtype stays
#: in the product record (nothing is ever narrowed).
TEST_COLUMNS: dict[str, np.dtype[Any]] = {
    "kind": np.dtype(np.uint8), "a": np.dtype(np.int32), "b": np.dtype(np.int32),
    "statistic": np.dtype(np.float64), "dof": np.dtype(np.float32),
    "critical": np.dtype(np.float64), "p_value": np.dtype(np.float64),
    "accepted": np.dtype(np.bool_),
}


def encode_product(stage: str, product: Any, scan_index: int, capture_time_ns: int) -> bytes:
    """A stage product as a ``boxloc.v1.Product``, lossless together with its tests.

    The statistical tests (``tests/kind``, ``tests/statistic``, ...) are not repeated here:
    they are recorded once, as rows, on ``/boxloc/tests`` (:func:`encode_test_rows`);
    ``tests/alpha`` stays. :func:`decode_product` puts them back together.
    """
    if stage not in PRODUCT_RECORDS:
        raise ValueError(f"unknown stage {stage!r}")
    if not isinstance(product, PRODUCT_TYPES[stage]):
        raise TypeError(
            f"{stage} product must be a {PRODUCT_TYPES[stage].__name__}, "
            f"got {type(product).__name__}"
        )
    return encode_arrays(PRODUCT_RECORDS[stage], _arrays_without_tests(product), scan_index,
                         capture_time_ns)


def _arrays_without_tests(product: Any) -> dict[str, np.ndarray]:
    """:func:`to_arrays` of a product, less the test columns recorded as rows instead."""
    arrays = to_arrays(product)
    if isinstance(getattr(product, "tests", None), TestTable):
        for col, dt in TEST_COLUMNS.items():
            name = f"tests/{col}"
            if arrays[name].dtype == dt and arrays[name].ndim == 1:
                del arrays[name]
    return arrays


def decode_product(
    stage: str,
    data: bytes,
    tests: dict[str, np.ndarray] | None = None,
    limits: DecodeLimits = DEFAULT_LIMITS,
) -> Any:
    """Inverse of :func:`encode_product`: the same product, bit for bit.

    Parameters
    ----------
    stage : str
    data : bytes
        The product message.
    tests : dict, optional
        The stage's test columns from :func:`decode_test_columns` (``/boxloc/tests``;
        :func:`empty_test_columns` for a stage without rows there); needed unless the
        product carries its tests itself.
    """
    _, arrays = decode_arrays(data, PRODUCT_RECORDS[stage], limits)
    if any(k.startswith("tests/") for k in arrays):  # else a log from before the tests
        for col, a in (tests or {}).items():
            arrays.setdefault(f"tests/{col}", a)  # a column kept in the product wins
    expected = _PRODUCT_FIELDS[stage]
    missing = sorted(_REQUIRED_FIELDS[stage] - set(arrays))
    if missing:
        where = " (its /boxloc/tests rows are missing)" if any(
            m.startswith("tests/") for m in missing) else ""
        raise LogError(f"{PRODUCT_RECORDS[stage]} record lacks field(s): "
                       f"{', '.join(missing)}{where}")
    # Fields unknown to this version come from a newer minor version: ignored.
    known = {k: v for k, v in arrays.items() if k in expected}
    if "tests/kind" in known:
        n = {known[f"tests/{c}"].shape for c in TEST_COLUMNS}
        if len(n) != 1:
            raise LogError(f"{PRODUCT_RECORDS[stage]}: test columns of different lengths {n}")
    try:
        return from_arrays(PRODUCT_TYPES[stage], known)
    except (TypeError, ValueError, KeyError, RecursionError) as e:
        raise LogError(f"{PRODUCT_RECORDS[stage]} record is malformed: {e}") from None


_AMBIGUOUS_FIELDS = _field_names(AmbiguousSet)


def encode_ambiguous(ambiguous: AmbiguousSet, scan_index: int, capture_time_ns: int) -> bytes:
    """The flat regions not split into boxes (:attr:`boxloc.products.Result.ambiguous`) as
    a ``boxloc.AmbiguousSet`` record (schema 1.5), lossless together with its tests, which
    go on ``/boxloc/tests`` as stage :data:`AMBIGUOUS_STAGE` like every product's."""
    if not isinstance(ambiguous, AmbiguousSet):
        raise TypeError(f"ambiguous regions must be an AmbiguousSet, got "
                        f"{type(ambiguous).__name__}")
    return encode_arrays(AMBIGUOUS_RECORD, _arrays_without_tests(ambiguous), scan_index,
                         capture_time_ns)


def decode_ambiguous(data: bytes, tests: dict[str, np.ndarray] | None = None,
                     limits: DecodeLimits = DEFAULT_LIMITS) -> AmbiguousSet:
    """Inverse of :func:`encode_ambiguous`: the same set, bit for bit.

    Parameters
    ----------
    data : bytes
        The ``/boxloc/ambiguous`` message.
    tests : dict, optional
        The :data:`AMBIGUOUS_STAGE` columns of :func:`decode_test_columns`
        (:func:`empty_test_columns` when the scan has no rows of that stage).

    Raises
    ------
    LogError
        A missing field, or arrays whose lengths disagree (K regions: ``corners`` (K, 4, 3),
        the others (K,)).
    """
    _, arrays = decode_arrays(data, AMBIGUOUS_RECORD, limits)
    for col, a in (tests or empty_test_columns()).items():
        arrays.setdefault(f"tests/{col}", a)  # a column kept in the record wins
    missing = sorted(_AMBIGUOUS_FIELDS - set(arrays))
    if missing:
        raise LogError(f"{AMBIGUOUS_RECORD} record lacks field(s): {', '.join(missing)}")
    known = {k: v for k, v in arrays.items() if k in _AMBIGUOUS_FIELDS}
    k = known["hypothesis"].shape
    if len(k) != 1 or known["corners"].shape != (*k, 4, 3) or any(
            known[n].shape != k for n in ("attempt", "area", "width", "length", "reason")):
        shapes = ", ".join(f"{n} {known[n].shape}" for n in sorted(known)
                           if not n.startswith("tests/"))
        raise LogError(f"{AMBIGUOUS_RECORD} record is malformed: arrays of inconsistent "
                       f"shapes ({shapes})")
    if {known[f"tests/{c}"].shape for c in TEST_COLUMNS} != {known["tests/kind"].shape}:
        raise LogError(f"{AMBIGUOUS_RECORD}: test columns of different lengths")
    try:
        return from_arrays(AmbiguousSet, known)
    except (TypeError, ValueError, KeyError, RecursionError) as e:
        raise LogError(f"{AMBIGUOUS_RECORD} record is malformed: {e}") from None


# --- scans -----------------------------------------------------------------------------------


def sensor_arrays(sensor: SensorModel) -> dict[str, np.ndarray]:
    """The exact parameters of a sensor model as arrays (float64 bits, no text rounding)."""
    if isinstance(sensor, PinholeModel):
        return {
            "kind": np.asarray("pinhole"),
            "intrinsics": np.array([sensor.fx, sensor.fy, sensor.cx, sensor.cy], "<f8"),
            "size": np.array([sensor.height, sensor.width], "<i8"),
        }
    if isinstance(sensor, RayTableModel):
        return {
            "kind": np.asarray("raytable"),
            "size": np.array([sensor.height, sensor.width], "<i8"),
            "table": np.asarray(sensor.table, "<f8"),
        }
    raise TypeError(f"unknown sensor model {type(sensor).__name__}")


def sensor_hash(sensor: SensorModel) -> str:
    """A 16-hex-digit digest of the sensor model's exact parameters."""
    h = hashlib.blake2b(digest_size=8)
    for name, a in sorted(sensor_arrays(sensor).items()):
        h.update(name.encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def encode_sensor(sensor: SensorModel, scan_index: int, capture_time_ns: int) -> bytes:
    arrays = sensor_arrays(sensor)
    arrays["hash"] = np.asarray(sensor_hash(sensor))
    return encode_arrays(SENSOR_RECORD, arrays, scan_index, capture_time_ns)


def decode_sensor(
    data: bytes, limits: DecodeLimits = DEFAULT_LIMITS
) -> tuple[str, SensorModel]:
    """Return ``(hash, sensor model)``; the model equals the recorded one bit for bit."""
    _, a = decode_arrays(data, SENSOR_RECORD, limits)
    try:
        kind = str(a["kind"])
        H, W = (int(v) for v in a["size"])
        digest = str(a["hash"])
    except (KeyError, ValueError, TypeError) as e:
        raise LogError(f"{SENSOR_RECORD} record is malformed: {e}") from None
    if not (0 < H * W <= limits.max_pixels):
        raise LogError(f"sensor size {H}x{W} is out of bounds (0 < pixels <= "
                       f"{limits.max_pixels})")
    sensor: SensorModel
    try:
        if kind == "pinhole":
            fx, fy, cx, cy = (float(v) for v in np.asarray(a["intrinsics"]).reshape(-1))
            sensor = PinholeModel(fx, fy, cx, cy, W, H)
        elif kind == "raytable":
            sensor = _raytable_exact(a["table"], H, W)
        else:
            raise LogError(f"unknown sensor kind {kind[:32]!r}")
    except KeyError as e:
        raise LogError(f"{SENSOR_RECORD} record lacks {e}") from None
    except (ValueError, TypeError) as e:  # InputError from the model's own checks
        raise LogError(f"recorded sensor model is invalid: {e}") from None
    if sensor_hash(sensor) != digest:
        raise LogError("recorded sensor model does not match its hash (corrupt log)")
    return digest, sensor


def _raytable_exact(table: np.ndarray, H: int, W: int) -> RayTableModel:
    """A RayTableModel holding exactly ``table``.

    ``RayTableModel.__init__`` renormalizes its rays, which is not idempotent to the last
    bit; a recorded table is already unit, so it is checked and installed as is, so that a
    replayed scan gives the same points, bit for bit.
    """
    if table.shape != (H, W, 3) or table.dtype != np.float64:
        raise LogError(f"ray table has shape {table.shape} {table.dtype}, expected ({H}, {W}, 3)")
    if np.isinf(table).any():
        raise LogError("ray table holds inf")
    with np.errstate(invalid="ignore"):
        n = np.linalg.norm(table, axis=-1)
    ok = np.isfinite(n)
    if ok.any() and np.abs(n[ok] - 1.0).max() > 1e-9:
        raise LogError("ray table rays are not unit vectors")
    model = RayTableModel.__new__(RayTableModel)
    t = np.array(table, dtype=np.float64, order="C", copy=True)
    t.flags.writeable = False
    object.__setattr__(model, "table", t)
    return model


def encode_scan_info(scan: Scan, digest: str) -> bytes:
    """Everything of a scan but the range and the sensor model (which have their own
    messages): index, capture time, pose (exact 4x4), source and meta."""
    arrays: dict[str, np.ndarray] = {
        "index": np.asarray(scan.index, "<i8"),
        "capture_time_ns": np.asarray(scan.capture_time_ns, "<i8"),
        "shape": np.asarray(scan.shape, "<i8"),
        "sensor_hash": np.asarray(digest),
        "source": np.asarray(scan.source),
        "meta": np.asarray(json.dumps(scan.meta, sort_keys=True, default=str)),
        "has_pose": np.asarray(scan.sensor_to_base is not None),
        "sensor_to_base": (np.asarray(scan.sensor_to_base, "<f8") if scan.sensor_to_base
                           is not None else np.zeros((0, 4), "<f8")),
    }
    return encode_arrays(SCAN_INFO_RECORD, arrays, scan.index, scan.capture_time_ns)


@dataclass(frozen=True)
class ScanInfo:
    index: int
    capture_time_ns: int
    shape: tuple[int, int]
    sensor_hash: str
    source: str
    meta: dict[str, Any]
    sensor_to_base: np.ndarray | None


def decode_scan_info(data: bytes, limits: DecodeLimits = DEFAULT_LIMITS) -> ScanInfo:
    _, a = decode_arrays(data, SCAN_INFO_RECORD, limits)
    try:
        H, W = (int(v) for v in a["shape"])
        meta = parse_json(str(a["meta"]), f"{SCAN_INFO_RECORD} meta")
        T = np.array(a["sensor_to_base"], copy=True) if bool(a["has_pose"]) else None
        if T is not None and T.shape != (4, 4):
            raise ValueError(f"pose has shape {T.shape}")
        return ScanInfo(index=int(a["index"]), capture_time_ns=int(a["capture_time_ns"]),
                        shape=(H, W), sensor_hash=str(a["sensor_hash"]),
                        source=str(a["source"]), meta=meta if isinstance(meta, dict) else {},
                        sensor_to_base=T)
    except (KeyError, ValueError, TypeError) as e:
        raise LogError(f"{SCAN_INFO_RECORD} record is malformed: {e}") from None


def build_scan(info: ScanInfo, range_: np.ndarray, sensor: SensorModel) -> Scan:
    """The recorded scan, bit for bit."""
    if range_.shape != info.shape or sensor.shape != info.shape:
        raise LogError(
            f"scan {info.index}: range {range_.shape}, sensor {sensor.shape} and info "
            f"{info.shape} shapes disagree"
        )
    try:
        return Scan(range=range_, sensor=sensor, capture_time_ns=info.capture_time_ns,
                    index=info.index, sensor_to_base=info.sensor_to_base, source=info.source,
                    meta=info.meta)
    except ValueError as e:
        raise LogError(f"scan {info.index}: recorded scan is invalid: {e}") from None


def encode_result_info(result: Any) -> bytes:
    """The Result's own fields (not the products, which have their channels; not timing)."""
    arrays = {
        "scan_index": np.asarray(result.scan_index, "<i8"),
        "capture_time_ns": np.asarray(result.capture_time_ns, "<i8"),
        "seed": np.asarray(result.seed, "<i8"),
        "config_hash": np.asarray(result.config_hash),
        "version": np.asarray(result.version),
    }
    return encode_arrays(RESULT_RECORD, arrays, result.scan_index, result.capture_time_ns)


def decode_result_info(data: bytes, limits: DecodeLimits = DEFAULT_LIMITS) -> dict[str, Any]:
    _, a = decode_arrays(data, RESULT_RECORD, limits)
    try:
        return {"scan_index": int(a["scan_index"]), "capture_time_ns": int(a["capture_time_ns"]),
                "seed": int(a["seed"]), "config_hash": str(a["config_hash"]),
                "version": str(a["version"])}
    except (KeyError, ValueError, TypeError) as e:
        raise LogError(f"{RESULT_RECORD} record is malformed: {e}") from None


# --- small records ---------------------------------------------------------------------------


def encode_test_rows(scan_index: int, tables: dict[str, TestTable]) -> bytes:
    """Every test of a scan, one row each, in stage order.

    This is where the tests are recorded (the product records leave them out): a row has
    the stage, the kind, the entities ``a`` and ``b``, the statistic, the degrees of
    freedom, the critical value, the p-value, alpha and the decision, so a person can read
    and plot them in Foxglove (``/boxloc/tests.rows[:]{stage=="verification"}.p_value``).

    Notes
    -----
    A scan has ten thousand tests or more, so the rows are serialized with NumPy, not one
    protobuf object at a time (which cost more than everything else the recorder does).
    The bytes are plain protobuf: ``boxloc.v1.TestRows`` with its ``rows`` appended, every
    field written, in field order.
    """
    head = message_class("TestRows")()
    head.schema = record_schema(TESTS_RECORD)
    head.scan_index = int(scan_index)
    parts = [head.SerializeToString()]
    for stage, t in tables.items():
        if len(t):
            parts.append(_test_rows_bytes(stage, t))
    return b"".join(parts)


def _varints(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Protobuf varints of uint64 values: (bytes (n, k) uint8, lengths (n,)), k <= 10."""
    v = v.astype(np.uint64, copy=False)
    k = max(1, (int(v.max()).bit_length() + 6) // 7) if v.size else 1
    shifts = np.arange(k, dtype=np.uint64) * np.uint64(7)
    groups = ((v[:, None] >> shifts) & np.uint64(0x7F)).astype(np.uint8)
    length = 1 + (v[:, None] >= (np.uint64(1) << shifts[1:])).sum(1)
    more = np.arange(k) < (length - 1)[:, None]
    return groups | (more.astype(np.uint8) << 7), length


def _zigzag(a: np.ndarray) -> np.ndarray:
    a = a.astype(np.int64, copy=False)
    return ((a << 1) ^ (a >> 63)).view(np.uint64)


def _fields(columns: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Join per-row byte columns (bytes (n, k), lengths (n,)) into (bytes, mask)."""
    data = np.concatenate([c for c, _ in columns], axis=1)
    mask = np.concatenate([np.arange(c.shape[1]) < n[:, None] for c, n in columns], axis=1)
    return data, mask


def _test_rows_bytes(stage: str, t: TestTable) -> bytes:
    n = len(t)
    stage_b = stage.encode()
    if len(stage_b) > 127:
        raise ValueError(f"stage name too long: {stage!r}")

    def fixed(b: bytes) -> tuple[np.ndarray, np.ndarray]:
        return np.broadcast_to(np.frombuffer(b, np.uint8), (n, len(b))), np.full(n, len(b))

    def tagged_varint(tag: int, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b, ln = _varints(v)
        return np.concatenate([np.full((n, 1), tag, np.uint8), b], 1), ln + 1

    doubles = np.zeros(n, dtype=[(f"t{i}", "u1") if i % 2 == 0 else (f"v{i}", "<f8")
                                 for i in range(10)])
    for i, (tag, col) in enumerate([(0x29, t.statistic), (0x31, t.dof), (0x39, t.critical),
                                    (0x41, t.p_value),
                                    (0x49, np.full(n, float(t.alpha)))]):
        doubles[f"t{2 * i}"] = tag
        # float64 NaN bits are kept as they are (a copy of the bytes, not a Python float)
        doubles[f"v{2 * i + 1}"] = np.asarray(col).astype(np.float64)
    dbl = doubles.view(np.uint8).reshape(n, 45)
    acc = np.stack([np.full(n, 0x50, np.uint8), np.asarray(t.accepted, bool).astype(np.uint8)],
                   1)
    body = [
        fixed(bytes([0x0A, len(stage_b)]) + stage_b),
        tagged_varint(0x10, np.asarray(t.kind).astype(np.uint64)),
        tagged_varint(0x18, _zigzag(np.asarray(t.a))),
        tagged_varint(0x20, _zigzag(np.asarray(t.b))),
        (dbl, np.full(n, 45)),
        (acc, np.full(n, 2)),
    ]
    row_len = np.sum([ln for _, ln in body], axis=0)
    lb, ll = _varints(row_len.astype(np.uint64))
    data, mask = _fields([fixed(b"\x1a"), (lb, ll), *body])
    return data[mask].tobytes()


def decode_test_columns(data: bytes) -> dict[str, dict[str, np.ndarray]]:
    """``{stage: {column: array}}`` from ``/boxloc/tests``, in :data:`TEST_COLUMNS` dtypes."""
    msg = _parse("TestRows", data)
    check_record_schema(msg.schema, TESTS_RECORD)
    by_stage: dict[str, list[Any]] = {}
    for r in msg.rows:
        by_stage.setdefault(r.stage, []).append(r)
    out: dict[str, dict[str, np.ndarray]] = {}
    for stage, rows in by_stage.items():
        n = len(rows)
        cols = {c: np.fromiter((getattr(r, c) for r in rows), np.float64, n)
                for c in ("statistic", "dof", "critical", "p_value")}
        ints = {c: np.fromiter((getattr(r, c) for r in rows), np.int64, n)
                for c in ("kind", "a", "b")}
        if (ints["kind"] < 0).any() or (ints["kind"] > 255).any():
            raise LogError(f"test kind out of range in stage {stage[:32]!r}")
        cols["accepted"] = np.fromiter((r.accepted for r in rows), np.bool_, n)
        # Narrowing is exact for the columns stored here (int32, float32 dof); a wider
        # column is in the product record, which wins over these.
        out[stage] = {c: (ints[c] if c in ints else cols[c]).astype(dt, copy=False)
                      for c, dt in TEST_COLUMNS.items()}
    return out


def empty_test_columns() -> dict[str, np.ndarray]:
    """The columns of a stage that made no test (no rows on ``/boxloc/tests``)."""
    return {c: np.zeros(0, dt) for c, dt in TEST_COLUMNS.items()}


def decode_test_rows(data: bytes) -> list[dict[str, Any]]:
    """The tests as plain rows (for reports), kinds by name."""
    msg = _parse("TestRows", data)
    check_record_schema(msg.schema, TESTS_RECORD)
    out = []
    for r in msg.rows:
        try:
            kind = TestKind(r.kind).name
        except ValueError:
            kind = str(r.kind)
        out.append({"stage": r.stage, "kind": kind, "a": r.a, "b": r.b,
                    "statistic": r.statistic, "dof": r.dof, "critical": r.critical,
                    "p_value": r.p_value, "alpha": r.alpha, "accepted": r.accepted})
    return out


def encode_timing(scan_index: int, timing_ms: dict[str, float], record_ms: float) -> bytes:
    msg = message_class("Timing")()
    msg.schema = record_schema(TIMING_RECORD)
    msg.scan_index = int(scan_index)
    for stage, ms in timing_ms.items():
        msg.stages.add(stage=str(stage), ms=float(ms))
    msg.record_ms = float(record_ms)
    return msg.SerializeToString()


def decode_timing(data: bytes) -> tuple[dict[str, float], float]:
    msg = _parse("Timing", data)
    check_record_schema(msg.schema, TIMING_RECORD)
    return {s.stage: s.ms for s in msg.stages}, msg.record_ms


@dataclass(frozen=True)
class PickOutcome:
    """A pick outcome: did the robot pick surface ``surface_id`` of scan ``scan_index``?

    ``source`` is who reported it (``robot``, ``annotate``); ``wall_time_ns`` is when
    (wall clock, informational); ``origin`` is where it was read from (``log`` channel or
    ``sidecar`` file).
    """

    scan_index: int
    surface_id: int
    ok: bool
    reason: str = ""
    source: str = ""
    wall_time_ns: int = 0
    origin: str = "log"

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def encode_outcome(o: PickOutcome) -> bytes:
    msg = message_class("PickOutcome")()
    msg.schema = record_schema(OUTCOME_RECORD)
    msg.scan_index = int(o.scan_index)
    msg.surface_id = int(o.surface_id)
    msg.ok = bool(o.ok)
    msg.reason = o.reason
    msg.source = o.source
    msg.wall_time_ns = int(o.wall_time_ns)
    return msg.SerializeToString()


def decode_outcome(data: bytes) -> PickOutcome:
    msg = _parse("PickOutcome", data)
    check_record_schema(msg.schema, OUTCOME_RECORD)
    return PickOutcome(scan_index=msg.scan_index, surface_id=msg.surface_id, ok=msg.ok,
                       reason=msg.reason, source=msg.source, wall_time_ns=msg.wall_time_ns,
                       origin="log")


def encode_error(scan_index: int, stage: str, exc_type: str, message: str) -> bytes:
    msg = message_class("ScanError")()
    msg.schema = record_schema(ERROR_RECORD)
    msg.scan_index = int(scan_index)
    msg.stage = stage
    msg.error_type = exc_type
    msg.message = message
    return msg.SerializeToString()


def decode_error(data: bytes) -> dict[str, Any]:
    msg = _parse("ScanError", data)
    check_record_schema(msg.schema, ERROR_RECORD)
    return {"scan_index": msg.scan_index, "stage": msg.stage, "error_type": msg.error_type,
            "message": msg.message}


def encode_labels(labels: np.ndarray, scan_index: int, capture_time_ns: int) -> bytes:
    """Per-pixel segment labels of a scan (e.g. mOSD ground truth), (H, W) integers, exact."""
    a = np.asarray(labels)
    if a.ndim != 2 or a.dtype.kind not in "iu":
        raise TypeError(f"labels must be a 2-D integer array, got {a.dtype} {a.shape}")
    return encode_arrays(LABELS_RECORD, {"labels": a}, scan_index, capture_time_ns)


def decode_labels(data: bytes, limits: DecodeLimits = DEFAULT_LIMITS) -> np.ndarray:
    _, a = decode_arrays(data, LABELS_RECORD, limits)
    lab = a.get("labels")
    if lab is None or lab.ndim != 2 or lab.dtype.kind not in "iu":
        raise LogError(f"{LABELS_RECORD} record is malformed: needs a 2-D integer 'labels'")
    if lab.size > limits.max_pixels:
        raise LogError(f"{LABELS_RECORD}: {lab.size} pixels exceed {limits.max_pixels}")
    return np.array(lab, copy=True)


def encode_scan_end(scan_index: int, capture_time_ns: int, origin: str) -> bytes:
    """Closes a scan recorded without a pipeline run; ``origin`` says what recorded it."""
    arrays = {"scan_index": np.asarray(scan_index, "<i8"), "origin": np.asarray(origin)}
    return encode_arrays(SCAN_END_RECORD, arrays, scan_index, capture_time_ns)


def decode_scan_end(data: bytes, limits: DecodeLimits = DEFAULT_LIMITS) -> dict[str, Any]:
    _, a = decode_arrays(data, SCAN_END_RECORD, limits)
    try:
        return {"scan_index": int(a["scan_index"]), "origin": str(a["origin"])}
    except (KeyError, ValueError, TypeError) as e:
        raise LogError(f"{SCAN_END_RECORD} record is malformed: {e}") from None


# --- JSON view of the result -----------------------------------------------------------------

LOCATE_JSON_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": f"{PACKAGE}.{LOCATE_RECORD}",
    "description": "The graspable surfaces of one scan, in pick order (the `boxloc locate` "
                   "records). Metres, sensor frame. A view: /boxloc/surfaces is the record.",
    "type": "object",
    "properties": {
        "schema": {"type": "string"},
        "scan_index": {"type": "integer"},
        "surfaces": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "id": {"type": "integer"},
                    "pick_order": {"type": "integer"},
                    "hypothesis": {"type": "integer"},
                    "attempt": {"type": "integer"},
                    "center": {"type": "array", "items": {"type": ["number", "null"]}},
                    "normal": {"type": "array", "items": {"type": ["number", "null"]}},
                    "x_axis": {"type": "array", "items": {"type": ["number", "null"]}},
                    "y_axis": {"type": "array", "items": {"type": ["number", "null"]}},
                    "width": {"type": ["number", "null"]},
                    "length": {"type": ["number", "null"]},
                    "grasp_point": {"type": "array", "items": {"type": ["number", "null"]}},
                    "score": {"type": ["number", "null"]},
                    "bulge": {"type": ["number", "null"]},
                    # schema 1.5 (issue #21)
                    "height": {"type": ["number", "null"]},
                    "height_sigma": {"type": ["number", "null"]},
                    "height_source": {"enum": ["none", "side", "step", "sku"]},
                    "sku": {"type": ["integer", "null"]},
                    "size_flagged": {"type": "boolean"},
                },
            },
        },
        "ambiguous": {
            "description": "Flat regions whose extent the evidence cannot split into boxes: "
                           "not surfaces, not graspable as they are (schema 1.5).",
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "id": {"type": "integer"},
                    "hypothesis": {"type": "integer"},
                    "attempt": {"type": "integer"},
                    "corners": {"type": "array", "items": {
                        "type": "array", "items": {"type": ["number", "null"]}}},
                    "area": {"type": ["number", "null"]},
                    "width": {"type": ["number", "null"]},
                    "length": {"type": ["number", "null"]},
                    "reason": {"enum": [r.name.lower() for r in AmbiguityReason]},
                    "tests": {"type": "array", "items": {"type": "object"}},
                },
            },
        },
    },
}


def _finite_or_none(v: Any) -> Any:
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, list):
        return [_finite_or_none(x) for x in v]
    return v


def encode_locate_json(scan_index: int, surfaces: SurfaceSet,
                       ambiguous: AmbiguousSet | None = None) -> bytes:
    """The ``boxloc locate`` rows of a scan (less the covariances), plus each surface's
    hypothesis and attempt, and the ambiguous regions (``ambiguous``: none given, an empty
    list), as JSON."""
    rows = []
    for i, r in enumerate(surfaces.to_json_list()):
        r.pop("covariance", None)  # 36 numbers per surface; the record has them
        r["hypothesis"] = int(surfaces.hypothesis[i])
        r["attempt"] = int(surfaces.attempt[i])
        rows.append({k: _finite_or_none(v) for k, v in r.items()})
    amb = []
    if ambiguous is not None:
        for k, r in enumerate(ambiguous.to_json_list()):
            r["hypothesis"] = int(ambiguous.hypothesis[k])
            r["attempt"] = int(ambiguous.attempt[k])
            amb.append({key: _finite_or_none(v) for key, v in r.items()})
    doc = {"schema": record_schema(LOCATE_RECORD), "scan_index": int(scan_index),
           "surfaces": rows, "ambiguous": amb}
    return json.dumps(doc, separators=(",", ":")).encode()


def decode_locate_json(data: bytes) -> dict[str, Any]:
    doc = parse_json(data, f"a {LOCATE_RECORD} message")
    if not isinstance(doc, dict):
        raise LogError(f"{LOCATE_RECORD} JSON message is not an object")
    check_record_schema(str(doc.get("schema", "")), LOCATE_RECORD)
    return doc


# --- Foxglove views --------------------------------------------------------------------------

RANGE_ENCODING = "32FC1"
EDGE_MAP_ENCODING = "mono8"
#: Edge-map pixel value per :class:`EdgeKind` level (0, 85, 170, 255), so it is visible.
EDGE_MAP_SCALE = 85


def encode_range(scan: Scan, t_ns: int) -> bytes:
    """The range image, float32, bit for bit (range along the ray, metres): a
    ``boxloc.ScanRange`` record with the array ``range`` (H, W) ``<f4`` (image filter).

    ``t_ns`` (the log time) is not stored: the message's own times carry it.
    """
    msg = message_class("Product")()
    msg.schema = record_schema(RANGE_RECORD)
    msg.scan_index = int(scan.index)
    msg.capture_time_ns = int(scan.capture_time_ns)
    array_to_msg(msg.arrays.add(), "range", np.ascontiguousarray(scan.range, "<f4"),
                 image=True)
    return msg.SerializeToString()


#: How a ``ScanRange`` record's bytes begin: field 1 (``schema``), its length, the name.
_RANGE_PREFIX = b"boxloc." + RANGE_RECORD.encode() + b"/"


def is_range_record(data: bytes) -> bool:
    """Whether ``/scan/range`` bytes are a ``ScanRange`` record (schema >= 1.4), not a
    Foxglove RawImage (<= 1.3), whose first field (a Timestamp) never starts so."""
    return data[:1] == b"\x0a" and data[2:2 + len(_RANGE_PREFIX)] == _RANGE_PREFIX


def legacy_range_message(data: bytes, limits: DecodeLimits = DEFAULT_LIMITS) -> bytes:
    """A ``/scan/range`` message as schema 1.4 and 1.5 readers read it: the same
    ``ScanRange`` record, the range in image filter 4 (byte shuffle) instead of 5.

    For older code reading a newer log (``replay --rev`` of a revision before 1.6); the
    range is the same, bit for bit. A message in another form is returned as it is.

    Raises
    ------
    LogError
        If ``data`` is a ``ScanRange`` record that cannot be decoded.
    """
    if not is_range_record(data):
        return data
    msg, arrays = decode_arrays(data, RANGE_RECORD, limits)
    if all(a.filter != _FILTER_IMAGE_SPLIT for a in msg.arrays):
        return data
    del msg.arrays[:]
    for name, a in arrays.items():
        array_to_msg(msg.arrays.add(), name, a, image=a.ndim == 2,
                     image_filter=_FILTER_IMAGE_DELTA_SHUFFLE)
    return bytes(msg.SerializeToString())


def legacy_product_message(data: bytes, limits: DecodeLimits = DEFAULT_LIMITS) -> bytes:
    """A ``boxloc.v1.Product`` message as schema 1.6 readers read it: each float64 array
    stored as float32 (filters 6 and 7, schema 1.7) in filter 1 or 3 instead.

    For older code reading a newer log (``replay --rev`` of a revision before 1.7); every
    array is the same, bit for bit. A message with no such array is returned as it is.

    Raises
    ------
    LogError
        If ``data`` is not a ``Product`` message or an array in filter 6 or 7 cannot be
        decoded.
    """
    msg = _parse("Product", data)
    if all(a.filter not in (_FILTER_F32_SHUFFLE, _FILTER_F32_SYMMETRIC_SHUFFLE)
           for a in msg.arrays):
        return data
    for arr in msg.arrays:
        if arr.filter in (_FILTER_F32_SHUFFLE, _FILTER_F32_SYMMETRIC_SHUFFLE):
            name, a = arr.name, msg_to_array(arr, limits)
            arr.Clear()
            array_to_msg(arr, name, a, float32=False)
    return bytes(msg.SerializeToString())


def decode_range(data: bytes, limits: DecodeLimits = DEFAULT_LIMITS) -> np.ndarray:
    """The range image of a ``/scan/range`` message, (H, W) float32, exact bits.

    Reads both formats: the ``ScanRange`` record (schema 1.4 on) and the Foxglove RawImage
    ``32FC1`` of older logs.
    """
    if is_range_record(data):
        _, arrays = decode_arrays(data, RANGE_RECORD, limits)
        r = arrays.get("range")
        if r is None or r.ndim != 2 or r.dtype.str != "<f4" or len(arrays) != 1:
            raise LogError(f"{RANGE_RECORD} record is malformed: needs one 2-D <f4 'range'")
        if not 0 < r.size <= limits.max_pixels:
            raise LogError(f"range image of {r.shape[1]}x{r.shape[0]} pixels is not in "
                           f"1..{limits.max_pixels}")
        return r.astype(np.float32)
    msg = RawImage()
    try:
        msg.ParseFromString(data)
    except Exception as e:
        raise LogError(f"cannot parse the range image: {e}") from None
    H, W = msg.height, msg.width
    if msg.encoding != RANGE_ENCODING:
        raise LogError(f"range image has encoding {msg.encoding[:16]!r}, expected 32FC1")
    if not (0 < H * W <= limits.max_pixels) or msg.step != W * 4 or len(msg.data) != H * W * 4:
        raise LogError(
            f"range image of {W}x{H}, step {msg.step}, {len(msg.data)} bytes is inconsistent"
        )
    return np.frombuffer(msg.data, "<f4").reshape(H, W).astype(np.float32)


#: The range preview: every k-th pixel of every k-th row, k the least that brings the width
#: to at most PREVIEW_MAX_WIDTH, as a JPEG of this quality: about 7 kB for a 640x480 scan
#: (20 kB at full size; the exact range takes 700 kB), enough to see the pile.
PREVIEW_MAX_WIDTH = 320
PREVIEW_JPEG_QUALITY = 80


def encode_range_preview(scan: Scan, t_ns: int) -> bytes:
    """The range image for viewers: a Foxglove CompressedImage, JPEG, grey, at most
    :data:`PREVIEW_MAX_WIDTH` pixels wide (a 640x480 scan: 320x240).

    Near is bright and far dark, stretched over the scan's own range; no return is black.
    Lossy, and never read back: the ``ScanRange`` record is the range.
    """
    import cv2

    k = max(1, -(-scan.range.shape[1] // PREVIEW_MAX_WIDTH))
    r = np.asarray(scan.range[::k, ::k], np.float32)
    with np.errstate(invalid="ignore"):
        ok = r > 0  # False for NaN
    valid = r[ok]
    grey = np.zeros(r.shape, np.uint8)
    if valid.size:  # float32 throughout: a millisecond, not four, at 640x480
        lo, hi = float(valid.min()), float(valid.max())
        g = np.float32(255.5) - (r - np.float32(lo)) * np.float32(254.0 / max(hi - lo, 1e-9))
        grey = np.where(ok, g, np.float32(0)).astype(np.uint8)  # 1..255, rounded
    done, jpeg = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, PREVIEW_JPEG_QUALITY])
    if not done:
        raise ValueError(f"cannot encode a {r.shape[1]}x{r.shape[0]} range preview as JPEG")
    msg = CompressedImage(frame_id=SENSOR_FRAME, format="jpeg", data=jpeg.tobytes())
    msg.timestamp.FromNanoseconds(t_ns)
    return msg.SerializeToString()


def encode_calibration(sensor: PinholeModel, t_ns: int) -> bytes:
    """The pinhole as a Foxglove CameraCalibration (no distortion)."""
    msg = CameraCalibration(frame_id=SENSOR_FRAME, width=sensor.width, height=sensor.height,
                            distortion_model="plumb_bob")
    msg.D.extend([0.0] * 5)
    msg.K.extend(sensor.K.reshape(-1).tolist())
    msg.R.extend([1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0])
    msg.P.extend([sensor.fx, 0.0, sensor.cx, 0.0, 0.0, sensor.fy, sensor.cy, 0.0,
                  0.0, 0.0, 1.0, 0.0])
    msg.timestamp.FromNanoseconds(t_ns)
    return msg.SerializeToString()


def quaternion_from_matrix(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (Shepperd's method; for display only)."""
    R = np.asarray(R, dtype=np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        w, x, y, z = 0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (
            R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        w, x, y, z = (R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (
            R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        w, x, y, z = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (
            R[1, 2] + R[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        w, x, y, z = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (
            R[1, 2] + R[2, 1]) / s, 0.25 * s
    n = math.sqrt(w * w + x * x + y * y + z * z) or 1.0
    return x / n, y / n, z / n, w / n


def encode_pose(sensor_to_base: np.ndarray, t_ns: int) -> bytes:
    """The sensor pose in the base frame as a FrameTransform (base -> sensor)."""
    T = np.asarray(sensor_to_base, dtype=np.float64)
    msg = FrameTransform(parent_frame_id=BASE_FRAME, child_frame_id=SENSOR_FRAME)
    msg.timestamp.FromNanoseconds(t_ns)
    msg.translation.x, msg.translation.y, msg.translation.z = (float(v) for v in T[:3, 3])
    q = quaternion_from_matrix(T[:3, :3])
    msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = q
    return msg.SerializeToString()


#: Grid of the point clouds' coordinates in the views, metres: 2**-10 (0.98 mm), below any
#: sensor's noise, so nothing visible changes, and the low mantissa bits are zero, which
#: halves the clouds in the log. The records keep every point exactly.
VIEW_GRID = 2.0**-10


def _cloud(P: np.ndarray, t_ns: int, extra: dict[str, np.ndarray] | None = None) -> bytes:
    """A PointCloud of float32 fields x, y, z on the :data:`VIEW_GRID` (+ extra float32
    fields, as they are)."""
    P = np.rint(np.asarray(P, np.float64) / VIEW_GRID) * VIEW_GRID
    cols = [np.asarray(P[:, i], "<f4") for i in range(3)]
    names = ["x", "y", "z"]
    for k, v in (extra or {}).items():
        cols.append(np.asarray(v, "<f4"))
        names.append(k)
    data = np.stack(cols, 1) if cols[0].size else np.zeros((0, len(cols)), "<f4")
    msg = PointCloud(frame_id=SENSOR_FRAME, point_stride=4 * len(cols),
                     data=np.ascontiguousarray(data, "<f4").tobytes())
    msg.timestamp.FromNanoseconds(t_ns)
    msg.pose.orientation.w = 1.0
    for i, name in enumerate(names):
        msg.fields.add(name=name, offset=4 * i, type=PackedElementField.FLOAT32)
    return msg.SerializeToString()


def encode_points(scan: Scan, t_ns: int, max_points: int) -> bytes:
    """The organized cloud, decimated on a regular pixel grid to at most ``max_points``."""
    H, W = scan.shape
    stride = max(1, math.ceil(math.sqrt(H * W / max(max_points, 1))))
    # Only the kept pixels, as Scan.points computes each (range times ray, float32): the
    # whole cloud would cost the recorder 3-5 ms at 640x480 when the pipeline has not
    # made it yet (the recorder sees the scan first).
    r = scan.range[::stride, ::stride]
    with np.errstate(invalid="ignore"):
        P = (r[..., None].astype(np.float64) * scan.sensor.rays()[::stride, ::stride]).astype(
            np.float32).reshape(-1, 3)
    return _cloud(P[np.isfinite(r).reshape(-1) & np.isfinite(P).all(1)], t_ns)


def encode_edge_map(edges: Any, t_ns: int) -> bytes:
    """Edge labels as a mono8 image, ``EDGE_MAP_SCALE`` x :class:`EdgeKind` per pixel."""
    labels = np.asarray(edges.labels, np.uint8)
    H, W = labels.shape
    msg = RawImage(frame_id=SENSOR_FRAME, width=W, height=H, encoding=EDGE_MAP_ENCODING,
                   step=W, data=(labels * np.uint8(EDGE_MAP_SCALE)).tobytes())
    msg.timestamp.FromNanoseconds(t_ns)
    return msg.SerializeToString()


def encode_edge_points(edges: Any, t_ns: int) -> bytes:
    """Edge points with a ``kind`` field (:class:`EdgeKind`)."""
    return _cloud(np.asarray(edges.points), t_ns, {"kind": np.asarray(edges.kinds)})


_EDGE_COLORS = {
    int(EdgeKind.JUMP): (1.0, 0.55, 0.0, 1.0),
    int(EdgeKind.CREASE_CONVEX): (0.0, 0.8, 1.0, 1.0),
    int(EdgeKind.CREASE_CONCAVE): (1.0, 0.0, 0.8, 1.0),
}
_GREY = (0.6, 0.6, 0.6, 1.0)
_ACCEPTED = (0.1, 0.9, 0.2, 1.0)
_REJECTED = (0.9, 0.15, 0.1, 0.8)
_VERTEX = (1.0, 0.9, 0.0, 1.0)
_SURFACE = (0.2, 0.4, 1.0, 0.45)
#: ambiguous regions: magenta, unlike every other entity (not graspable as they are)
_AMBIGUOUS = (1.0, 0.2, 0.9, 1.0)
_TEXT = (1.0, 1.0, 1.0, 1.0)


def _color(msg: Any, rgba: tuple[float, float, float, float]) -> None:
    msg.r, msg.g, msg.b, msg.a = rgba


def _points(field: Any, P: np.ndarray) -> None:
    for x, y, z in np.asarray(P, dtype=np.float64).tolist():
        p = field.add()
        p.x, p.y, p.z = x, y, z


def _colors(field: Any, rgbas: list[tuple[float, float, float, float]]) -> None:
    for c in rgbas:
        _color(field.add(), c)


def _entity(update: Any, entity_id: str, t_ns: int, meta: dict[str, str]) -> Any:
    e = update.entities.add(id=entity_id, frame_id=SENSOR_FRAME)
    e.timestamp.FromNanoseconds(t_ns)
    for k, v in meta.items():
        e.metadata.add(key=k, value=v)
    return e


def _rect_segments(o: np.ndarray, x: np.ndarray, y: np.ndarray, w: np.ndarray,
                   ln: np.ndarray) -> np.ndarray:
    """(n, 8, 3) endpoints of the 4 sides of n rectangles, for a LINE_LIST."""
    c0 = o
    c1 = o + w[:, None] * x
    c2 = c1 + ln[:, None] * y
    c3 = o + ln[:, None] * y
    return np.stack([c0, c1, c1, c2, c2, c3, c3, c0], 1)


def encode_scene(products: dict[str, Any], scan_index: int, t_ns: int) -> bytes:
    """A SceneUpdate with what the scan's products show in 3D (sensor frame).

    Entities: ``lines`` (segments coloured by edge kind), ``vertices`` (spheres and their
    two directions), ``hypotheses`` (every attempted rectangle, green when verified, red
    when rejected), ``surfaces`` (filled, labelled with their pick order and height) and
    ``ambiguous`` (``products["ambiguous"]``, an AmbiguousSet: outlines in magenta,
    labelled with the reason and the area). The update first deletes everything, so
    nothing of the previous scan lingers.
    """
    upd = SceneUpdate()
    d = upd.deletions.add(type=SceneEntityDeletion.ALL)
    d.timestamp.FromNanoseconds(t_ns)
    scan_meta = {"scan": str(scan_index)}

    lines: LineSet | None = products.get("lines")
    if lines is not None and len(lines):
        e = _entity(upd, "lines", t_ns, scan_meta)
        prim = e.lines.add(type=2, thickness=0.004)  # LINE_LIST
        _color(prim.color, _GREY)
        seg = np.stack([lines.starts, lines.ends], 1).reshape(-1, 3)
        _points(prim.points, seg)
        _colors(prim.colors, [_EDGE_COLORS.get(int(k), _GREY) for k in lines.kinds
                              for _ in range(2)])

    verts: VertexSet | None = products.get("vertices")
    if verts is not None and len(verts):
        e = _entity(upd, "vertices", t_ns, scan_meta)
        for p in np.asarray(verts.points, np.float64).tolist():
            s = e.spheres.add()
            s.pose.position.x, s.pose.position.y, s.pose.position.z = p
            s.pose.orientation.w = 1.0
            s.size.x = s.size.y = s.size.z = 0.015
            _color(s.color, _VERTEX)
        prim = e.lines.add(type=2, thickness=0.003)
        _color(prim.color, _VERTEX)
        arms = np.concatenate([
            np.stack([verts.points, verts.points + 0.05 * verts.d1], 1),
            np.stack([verts.points, verts.points + 0.05 * verts.d2], 1)]).reshape(-1, 3)
        _points(prim.points, arms)

    hyps: HypothesisSet | None = products.get("hypotheses")
    ver: Verification | None = products.get("verification")
    if hyps is not None and hyps.n_attempts:
        h = hyps.att_hypothesis
        ok = (np.asarray(ver.accepted, bool) if ver is not None and len(ver) == hyps.n_attempts
              else np.asarray(hyps.att_verified, bool))
        seg = _rect_segments(hyps.origins[h], hyps.x_axis[h], hyps.y_axis[h], hyps.att_width,
                             hyps.att_length)
        good = np.isfinite(seg).all((1, 2))
        if good.any():
            e = _entity(upd, "hypotheses", t_ns, {**scan_meta,
                                                   "verified": str(int(ok[good].sum())),
                                                   "attempts": str(int(good.sum()))})
            prim = e.lines.add(type=2, thickness=0.002)
            _color(prim.color, _REJECTED)
            _points(prim.points, seg[good].reshape(-1, 3))
            _colors(prim.colors, [_ACCEPTED if v else _REJECTED for v in ok[good]
                                  for _ in range(8)])

    surf: SurfaceSet | None = products.get("surfaces")
    if surf is not None and len(surf):
        e = _entity(upd, "surfaces", t_ns, scan_meta)
        tri = e.triangles.add()
        tri.pose.orientation.w = 1.0
        _color(tri.color, _SURFACE)
        c = np.asarray(surf.corners, np.float64)
        _points(tri.points, c[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3))
        for i in range(len(surf)):
            t = e.texts.add(billboard=True, font_size=14.0, scale_invariant=True)
            t.pose.position.x, t.pose.position.y, t.pose.position.z = (
                float(v) for v in surf.centers[i])
            t.pose.orientation.w = 1.0
            _color(t.color, _TEXT)
            t.text = (f"#{i} pick {int(surf.pick_order[i])}: "
                      f"{surf.width[i] * 1e3:.0f}x{surf.length[i] * 1e3:.0f} mm, "
                      f"score {surf.scores[i]:.2f}" + _height_text(surf, i))

    amb: AmbiguousSet | None = products.get("ambiguous")
    if amb is not None and len(amb):
        c = np.asarray(amb.corners, np.float64)
        seg = c[:, [0, 1, 1, 2, 2, 3, 3, 0]]
        good = np.isfinite(seg).all((1, 2))
        if good.any():
            e = _entity(upd, "ambiguous", t_ns, {**scan_meta, "regions": str(int(good.sum()))})
            prim = e.lines.add(type=2, thickness=0.006)  # LINE_LIST
            _color(prim.color, _AMBIGUOUS)
            _points(prim.points, seg[good].reshape(-1, 3))
            for k in np.flatnonzero(good):
                t = e.texts.add(billboard=True, font_size=14.0, scale_invariant=True)
                t.pose.position.x, t.pose.position.y, t.pose.position.z = (
                    float(v) for v in c[k].mean(axis=0))
                t.pose.orientation.w = 1.0
                _color(t.color, _AMBIGUOUS)
                t.text = f"ambiguous #{k}: {ambiguous_label(amb, int(k))}"
    return upd.SerializeToString()


def _height_text(surf: SurfaceSet, i: int) -> str:
    """``, height 250 mm (side)`` when the surface's box height was measured, else ``""``."""
    h = float(surf.height[i])
    if not math.isfinite(h):
        return ""
    src = HeightSource(int(surf.height_source[i])).name.lower()
    return f", height {h * 1e3:.0f} mm ({src})"


def ambiguous_label(amb: AmbiguousSet, k: int) -> str:
    """One line on ambiguous region k for viewers: reason, extent and area."""
    try:
        reason = AmbiguityReason(int(amb.reason[k])).name.lower().replace("_", " ")
    except ValueError:
        reason = f"reason {int(amb.reason[k])}"
    w, ln = float(amb.width[k]), float(amb.length[k])
    size = f"{w * 1e3:.0f}x{ln * 1e3:.0f} mm, " if math.isfinite(w) and math.isfinite(ln) \
        else ""
    return f"{reason}, {size}{float(amb.area[k]):.3f} m2"
