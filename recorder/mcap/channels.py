"""The log layout: the one table of topic -> schema -> encoding -> encoder/decoder.

Every MCAP channel boxloc writes is declared here and nowhere else. Two families:

* Foxglove well-known protobuf schemas (``foxglove.RawImage``, ``foxglove.PointCloud``,
  ...), so a log opens in Foxglove and converts with ``rerun mcap convert``;
* the algorithm's own records, protobuf messages of package ``boxloc.v1`` (built at
  runtime, see :mod:`recorder.mcap.proto`) whose ``schema`` field names the record and its
  version (``boxloc.EdgeMap/1.2``), plus one JSON view with a JSON Schema.

Time: every message of a scan has ``log_time = publish_time =`` :func:`scan_log_time` and
``sequence =`` the scan index. Session messages (pick outcomes) carry the log time of the
latest scan written, so log time never goes back within a file.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from functools import cache
from typing import Any

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap_protobuf.schema import build_file_descriptor_set

from recorder.mcap import encode as E
from recorder.mcap.proto import PACKAGE, file_descriptor_set_bytes

#: Version of the log layout as a whole (this table); in the ``boxloc.run`` metadata.
LAYOUT_VERSION = "1"
#: MCAP header profile (free-form; Foxglove's "protobuf" readers need none).
PROFILE = ""
#: Metadata record names.
RUN_METADATA = "boxloc.run"
RECOVERY_METADATA = "boxloc.recovery"
#: Attachment names (fixed; never built from data).
CONFIG_ATTACHMENT = "config.toml"
CALIBRATION_ATTACHMENT = "calibration.json"
RAYTABLE_ATTACHMENT = "raytable.npy"
#: The carton list a run or replay was given (``--box-sizes FILE``): the file's bytes as
#: they were (``text/csv``), once per file. The parsed sizes are in the recorded config
#: (``box_sizes``), so a replay needs no attachment to reproduce the run.
BOX_SIZES_ATTACHMENT = "box_sizes.csv"
BOX_SIZES_MEDIA_TYPE = "text/csv"

#: Log time step per scan index when a scan has no capture time (capture_time_ns == 0):
#: ``log_time = index * SYNTHETIC_PERIOD_NS`` (10 Hz), distinct and increasing.
SYNTHETIC_PERIOD_NS = 100_000_000


def scan_log_time(capture_time_ns: int, index: int) -> int:
    """The log time of a scan's messages, integer nanoseconds.

    The capture time when known, so recording is deterministic; for scans without one
    (``capture_time_ns == 0``), ``index * SYNTHETIC_PERIOD_NS``.
    """
    if capture_time_ns > 0:
        return int(capture_time_ns)
    return int(index) * SYNTHETIC_PERIOD_NS


class Scope(Enum):
    """Whether a channel's messages belong to one scan or to the session."""

    SCAN = "scan"
    SESSION = "session"


class Role(Enum):
    """What a channel is for."""

    #: the record of truth: read back by boxloc, lossless
    RECORD = "record"
    #: derived for people and viewers; never read back
    VIEW = "view"
    #: wall clock and other things that are never compared
    CLOCK = "clock"


@dataclass(frozen=True)
class ChannelSpec:
    """One channel of the log.

    Attributes
    ----------
    topic : str
    schema_name : str
        MCAP schema name: the protobuf message's full name, or the JSON Schema title.
    message_encoding : str
        ``protobuf`` or ``json``.
    record : str or None
        For boxloc records, the record name inside the message (``EdgeMap``); its version
        is :data:`recorder.mcap.encode.SCHEMA_VERSION`.
    scope, role : Scope, Role
    content : str
        What the channel holds (for ``boxloc info`` and the README).
    encoder, decoder : callable or None
        The functions of :mod:`recorder.mcap.encode` that make and read its messages.
    """

    topic: str
    schema_name: str
    message_encoding: str
    record: str | None
    scope: Scope
    role: Role
    content: str
    encoder: Callable[..., bytes] | None = field(default=None, repr=False, compare=False)
    decoder: Callable[..., Any] | None = field(default=None, repr=False, compare=False)

    @property
    def schema_encoding(self) -> str:
        return "jsonschema" if self.message_encoding == "json" else "protobuf"

    @property
    def record_schema(self) -> str:
        """``boxloc.<Record>/<major>.<minor>`` or the Foxglove schema name."""
        return E.record_schema(self.record) if self.record else self.schema_name

    def schema_data(self) -> bytes:
        return _schema_data(self.schema_name)

    def channel_metadata(self) -> dict[str, str]:
        return {"boxloc.record": self.record_schema, "boxloc.role": self.role.value,
                "boxloc.scope": self.scope.value}


_FOXGLOVE = {
    "foxglove.RawImage": RawImage,
    "foxglove.CameraCalibration": CameraCalibration,
    "foxglove.CompressedImage": CompressedImage,
    "foxglove.FrameTransform": FrameTransform,
    "foxglove.PointCloud": PointCloud,
    "foxglove.SceneUpdate": SceneUpdate,
}


@cache
def _schema_data(schema_name: str) -> bytes:
    if schema_name in _FOXGLOVE:
        return build_file_descriptor_set(_FOXGLOVE[schema_name]).SerializeToString()
    if schema_name.startswith(PACKAGE + ".") and schema_name != f"{PACKAGE}.{E.LOCATE_RECORD}":
        return file_descriptor_set_bytes()
    if schema_name == f"{PACKAGE}.{E.LOCATE_RECORD}":
        return json.dumps(E.LOCATE_JSON_SCHEMA, sort_keys=True).encode()
    raise KeyError(schema_name)


# --- topics ----------------------------------------------------------------------------------

SCAN_SENSOR = "/scan/sensor"
SCAN_INFO = "/scan/info"
SCAN_RANGE = "/scan/range"
SCAN_PREVIEW = "/scan/range/preview"
SCAN_CALIBRATION = "/scan/calibration"
SCAN_POSE = "/scan/pose"
SCAN_POINTS = "/scan/points"
SCAN_LABELS = "/scan/labels"
SCAN_END = "/scan/end"
EDGES = "/boxloc/edges"
NOISE = "/boxloc/noise"
EDGE_MAP = "/boxloc/edges/map"
EDGE_POINTS = "/boxloc/edges/points"
LINES = "/boxloc/lines"
VERTICES = "/boxloc/vertices"
HYPOTHESES = "/boxloc/hypotheses"
VERIFICATION = "/boxloc/verification"
SELECTION = "/boxloc/selection"
SURFACES = "/boxloc/surfaces"
AMBIGUOUS = "/boxloc/ambiguous"
LOCATE = "/boxloc/locate"
RESULT = "/boxloc/result"
ERROR = "/boxloc/error"
TESTS = "/boxloc/tests"
SCENE = "/boxloc/scene"
TIMING = "/boxloc/timing"
PICK_OUTCOME = "/pick/outcome"

#: The topic of each stage's product.
STAGE_TOPICS: dict[str, str] = {
    "noise": NOISE, "edges": EDGES, "lines": LINES, "vertices": VERTICES, "hypotheses": HYPOTHESES,
    "verification": VERIFICATION, "selection": SELECTION, "surfaces": SURFACES,
}
TOPIC_STAGES: dict[str, str] = {v: k for k, v in STAGE_TOPICS.items()}

_PRODUCT = f"{PACKAGE}.Product"
_S, _SS = Scope.SCAN, Scope.SESSION
_R, _V, _C = Role.RECORD, Role.VIEW, Role.CLOCK

CHANNELS: tuple[ChannelSpec, ...] = (
    ChannelSpec(SCAN_SENSOR, _PRODUCT, "protobuf", E.SENSOR_RECORD, _SS, _R,
                "sensor model, exact (pinhole intrinsics or the full ray table); written with "
                "the first scan of a file and whenever it changes",
                E.encode_sensor, E.decode_sensor),
    ChannelSpec(SCAN_INFO, _PRODUCT, "protobuf", E.SCAN_INFO_RECORD, _S, _R,
                "scan index, capture time, exact sensor_to_base 4x4, source, meta, sensor hash; "
                "opens a scan", E.encode_scan_info, E.decode_scan_info),
    ChannelSpec(SCAN_RANGE, _PRODUCT, "protobuf", E.RANGE_RECORD, _S, _R,
                "range image, (H, W) float32 metres along each ray, bit for bit; each pixel "
                "predicted from its left neighbour, the differences split at the noise and "
                "compressed (schema 1.6; byte-shuffled in 1.4 and 1.5, a foxglove.RawImage "
                "32FC1 up to 1.3, all still read)", E.encode_range, E.decode_range),
    ChannelSpec(SCAN_PREVIEW, "foxglove.CompressedImage", "protobuf", None, _S, _V,
                "the range image for viewers: JPEG, grey, at most 320 pixels wide, near "
                "bright, stretched over the scan's range, no return black (lossy; the record "
                "is /scan/range)",
                E.encode_range_preview),
    ChannelSpec(SCAN_CALIBRATION, "foxglove.CameraCalibration", "protobuf", None, _S, _V,
                "pinhole intrinsics (pinhole sensors only)", E.encode_calibration),
    ChannelSpec(SCAN_POSE, "foxglove.FrameTransform", "protobuf", None, _S, _V,
                "sensor pose in the robot base frame (base -> sensor), when known",
                E.encode_pose),
    ChannelSpec(SCAN_POINTS, "foxglove.PointCloud", "protobuf", None, _S, _V,
                "organized cloud decimated on a pixel grid (x, y, z float32)",
                E.encode_points),
    ChannelSpec(SCAN_LABELS, _PRODUCT, "protobuf", E.LABELS_RECORD, _S, _R,
                "per-pixel segment labels that came with the scan (mOSD ground truth: 0 none, "
                "1-9 table, 10k+j part j of object k), (H, W) integers, exact; `boxloc "
                "import` only", E.encode_labels, E.decode_labels),
    ChannelSpec(SCAN_END, _PRODUCT, "protobuf", E.SCAN_END_RECORD, _S, _R,
                "closes a scan recorded without running the pipeline (`boxloc import`): the "
                "scan is whole, nothing was run on it", E.encode_scan_end, E.decode_scan_end),
    ChannelSpec(NOISE, _PRODUCT, "protobuf", E.PRODUCT_RECORDS["noise"], _S, _R,
                "NoiseEstimate: the noise model every test of the scan used, where it came from "
                "(the scan's flat tiles, or the config), its fit per range bin, residual "
                "correlation and tails (schema 1.3)", E.encode_product, E.decode_product),
    ChannelSpec(EDGES, _PRODUCT, "protobuf", E.PRODUCT_RECORDS["edges"], _S, _R,
                "EdgeMap: labels, edge points, covariances, kinds, strengths (points, "
                "covariances and strengths to float32 precision, stored as float32: schema "
                "1.7)",
                E.encode_product, E.decode_product),
    ChannelSpec(EDGE_MAP, "foxglove.RawImage", "protobuf", None, _S, _V,
                f"edge labels, mono8, {E.EDGE_MAP_SCALE} x EdgeKind", E.encode_edge_map),
    ChannelSpec(EDGE_POINTS, "foxglove.PointCloud", "protobuf", None, _S, _V,
                "edge points (x, y, z, kind)", E.encode_edge_points),
    ChannelSpec(LINES, _PRODUCT, "protobuf", E.PRODUCT_RECORDS["lines"], _S, _R,
                "LineSet: segments, (centroid, direction) covariances, support, Hough votes, "
                "trials", E.encode_product, E.decode_product),
    ChannelSpec(VERTICES, _PRODUCT, "protobuf", E.PRODUCT_RECORDS["vertices"], _S, _R,
                "VertexSet: points, directions, normals, covariances, line pairs",
                E.encode_product, E.decode_product),
    ChannelSpec(HYPOTHESES, _PRODUCT, "protobuf", E.PRODUCT_RECORDS["hypotheses"], _S, _R,
                "HypothesisSet: rectangles, dimension source (vertices/edges), accumulators "
                "and peaks, support, every attempt", E.encode_product, E.decode_product),
    ChannelSpec(VERIFICATION, _PRODUCT, "protobuf", E.PRODUCT_RECORDS["verification"], _S, _R,
                "Verification of every attempt: counts, refitted planes, verdicts, reasons, "
                "inlier pixels", E.encode_product, E.decode_product),
    ChannelSpec(SELECTION, _PRODUCT, "protobuf", E.PRODUCT_RECORDS["selection"], _S, _R,
                "Selection: MDL terms (n, xi, N, Q), chosen set, greedy order, objective, "
                "reasons; the points a smallest face has at each candidate, which scale its "
                "model cost (unit, face_points; older logs: NaN, 0)",
                E.encode_product, E.decode_product),
    ChannelSpec(SURFACES, _PRODUCT, "protobuf", E.PRODUCT_RECORDS["surfaces"], _S, _R,
                "SurfaceSet: the chosen surfaces with pose, size, covariance and pick order; "
                "the box height, its sigma and source, the matched carton size (SKU) or the "
                "flag of none (schema 1.5)", E.encode_product, E.decode_product),
    ChannelSpec(AMBIGUOUS, _PRODUCT, "protobuf", E.AMBIGUOUS_RECORD, _S, _R,
                "AmbiguousSet: flat regions whose extent the evidence cannot split into "
                "boxes (not surfaces): outline, area, extent, reason; their END_EVIDENCE / "
                "SKU tests on /boxloc/tests as stage `ambiguous` (schema 1.5; older logs: "
                "none)", E.encode_ambiguous, E.decode_ambiguous),
    ChannelSpec(LOCATE, f"{PACKAGE}.{E.LOCATE_RECORD}", "json", E.LOCATE_RECORD, _S, _V,
                "the surfaces as `boxloc locate` JSON rows, in pick order, and the "
                "ambiguous regions",
                E.encode_locate_json, E.decode_locate_json),
    ChannelSpec(TESTS, f"{PACKAGE}.TestRows", "protobuf", E.TESTS_RECORD, _S, _R,
                "every statistical test of the scan, one row each: stage, kind, entities, "
                "statistic, dof, critical value, p-value, alpha, decision (the products' "
                "tests, recorded here once)", E.encode_test_rows, E.decode_test_columns),
    ChannelSpec(SCENE, "foxglove.SceneUpdate", "protobuf", None, _S, _V,
                "lines, vertices, hypothesis rectangles (green verified, red rejected), "
                "surfaces labelled with their pick order and height, ambiguous regions "
                "outlined in magenta", E.encode_scene),
    ChannelSpec(RESULT, _PRODUCT, "protobuf", E.RESULT_RECORD, _S, _R,
                "the Result's own fields (seed, config hash, version); closes a scan",
                E.encode_result_info, E.decode_result_info),
    ChannelSpec(ERROR, f"{PACKAGE}.ScanError", "protobuf", E.ERROR_RECORD, _S, _R,
                "the stage and error of a scan whose pipeline raised or was interrupted; "
                "closes a scan", E.encode_error, E.decode_error),
    ChannelSpec(TIMING, f"{PACKAGE}.Timing", "protobuf", E.TIMING_RECORD, _S, _C,
                "wall-clock ms per stage and of the recorder (never compared)",
                E.encode_timing, E.decode_timing),
    ChannelSpec(PICK_OUTCOME, f"{PACKAGE}.PickOutcome", "protobuf", E.OUTCOME_RECORD, _SS, _R,
                "pick outcomes reported by the robot while recording",
                E.encode_outcome, E.decode_outcome),
)

BY_TOPIC: dict[str, ChannelSpec] = {c.topic: c for c in CHANNELS}
#: Topics whose message closes a scan.
END_TOPICS: frozenset[str] = frozenset({RESULT, ERROR, SCAN_END})
#: Topic whose message opens a scan.
START_TOPIC = SCAN_INFO


def spec(topic: str) -> ChannelSpec:
    """The channel of ``topic``; KeyError names the topic if boxloc does not write it."""
    try:
        return BY_TOPIC[topic]
    except KeyError:
        raise KeyError(f"no boxloc channel {topic!r}") from None
