"""The ``boxloc.v1`` protobuf messages, built at runtime (no protoc, no generated code).

The messages are declared here as a ``FileDescriptorProto``; the MCAP schema of every
boxloc channel is the serialized ``FileDescriptorSet`` of this one file, so any protobuf
reader (Foxglove, ``mcap-protobuf-support``, ``rerun mcap convert``) can decode the records
without our code. The package name carries the major version: a breaking change makes
``boxloc.v2``; compatible additions (new fields, new enum values) keep ``v1`` and bump the
minor version in :data:`recorder.mcap.channels.SCHEMA_VERSION`.

Messages
--------
``Array``      one named n-d array: numpy ``dtype.str``, shape, C-order little/big-endian
               bytes, and an optional lossless filter (byte shuffle; delta then byte
               shuffle for integers; upper triangle then byte shuffle for stacks of
               exactly symmetric matrices; for images, the difference from the left
               neighbour's bits, zigzag, byte shuffle; float64 arrays of float32 values
               as float32), so that the chunk's zstd compresses well.
``Product``    a record made of named arrays (``schema`` says which, e.g.
               ``boxloc.EdgeMap/1.2``): every stage product, the scan info, the sensor model.
``TestRows``   every statistical test of a scan as readable rows (stage, kind, entities,
               statistic, dof, critical value, p-value, alpha, decision).
``Timing``     wall-clock time per stage (never compared).
``PickOutcome`` a pick outcome reported by the robot or by ``boxloc annotate``.
``ScanError``  a scan whose pipeline raised: the stage and the error.
"""

from __future__ import annotations

from functools import cache
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool
from google.protobuf.message_factory import GetMessageClass

from boxloc.stats import TestKind

PACKAGE = "boxloc.v1"
FILE_NAME = "boxloc/v1/records.proto"

_F = descriptor_pb2.FieldDescriptorProto
_OPT, _REP = _F.LABEL_OPTIONAL, _F.LABEL_REPEATED


def _field(
    msg: descriptor_pb2.DescriptorProto,
    name: str,
    number: int,
    ftype: int,
    label: int = _OPT,
    type_name: str | None = None,
) -> None:
    f = msg.field.add(name=name, number=number, type=ftype, label=label)
    if type_name is not None:
        f.type_name = type_name
    if label == _REP and ftype not in (_F.TYPE_STRING, _F.TYPE_BYTES, _F.TYPE_MESSAGE):
        f.options.packed = True


def _enum(
    fdp: descriptor_pb2.FileDescriptorProto, name: str, values: list[tuple[str, int]]
) -> None:
    e = fdp.enum_type.add(name=name)
    for vname, number in values:
        e.value.add(name=vname, number=number)


def file_descriptor_proto() -> descriptor_pb2.FileDescriptorProto:
    """The ``boxloc/v1/records.proto`` file, as a descriptor."""
    fdp = descriptor_pb2.FileDescriptorProto(name=FILE_NAME, package=PACKAGE, syntax="proto3")
    _enum(fdp, "Filter", [("FILTER_NONE", 0), ("FILTER_BYTE_SHUFFLE", 1),
                           ("FILTER_DELTA_SHUFFLE", 2), ("FILTER_SYMMETRIC_SHUFFLE", 3),
                           ("FILTER_IMAGE_DELTA_SHUFFLE", 4), ("FILTER_IMAGE_SPLIT", 5),
                           ("FILTER_F32_SHUFFLE", 6), ("FILTER_F32_SYMMETRIC_SHUFFLE", 7)])
    # Enum values are package-scoped in protobuf, hence the TEST_ prefix.
    _enum(fdp, "TestKind", [("TEST_UNSPECIFIED", 0)]
          + [(f"TEST_{k.name}", int(k)) for k in TestKind])

    m = fdp.message_type.add(name="Array")
    _field(m, "name", 1, _F.TYPE_STRING)
    _field(m, "dtype", 2, _F.TYPE_STRING)
    _field(m, "shape", 3, _F.TYPE_UINT64, _REP)
    _field(m, "data", 4, _F.TYPE_BYTES)
    _field(m, "filter", 5, _F.TYPE_ENUM, type_name=f".{PACKAGE}.Filter")

    m = fdp.message_type.add(name="Product")
    _field(m, "schema", 1, _F.TYPE_STRING)
    _field(m, "scan_index", 2, _F.TYPE_INT64)
    _field(m, "capture_time_ns", 3, _F.TYPE_INT64)
    _field(m, "arrays", 4, _F.TYPE_MESSAGE, _REP, f".{PACKAGE}.Array")

    m = fdp.message_type.add(name="TestRow")
    _field(m, "stage", 1, _F.TYPE_STRING)
    _field(m, "kind", 2, _F.TYPE_ENUM, type_name=f".{PACKAGE}.TestKind")
    _field(m, "a", 3, _F.TYPE_SINT64)
    _field(m, "b", 4, _F.TYPE_SINT64)
    _field(m, "statistic", 5, _F.TYPE_DOUBLE)
    _field(m, "dof", 6, _F.TYPE_DOUBLE)
    _field(m, "critical", 7, _F.TYPE_DOUBLE)
    _field(m, "p_value", 8, _F.TYPE_DOUBLE)
    _field(m, "alpha", 9, _F.TYPE_DOUBLE)
    _field(m, "accepted", 10, _F.TYPE_BOOL)

    m = fdp.message_type.add(name="TestRows")
    _field(m, "schema", 1, _F.TYPE_STRING)
    _field(m, "scan_index", 2, _F.TYPE_INT64)
    _field(m, "rows", 3, _F.TYPE_MESSAGE, _REP, f".{PACKAGE}.TestRow")

    m = fdp.message_type.add(name="StageTime")
    _field(m, "stage", 1, _F.TYPE_STRING)
    _field(m, "ms", 2, _F.TYPE_DOUBLE)

    m = fdp.message_type.add(name="Timing")
    _field(m, "schema", 1, _F.TYPE_STRING)
    _field(m, "scan_index", 2, _F.TYPE_INT64)
    _field(m, "stages", 3, _F.TYPE_MESSAGE, _REP, f".{PACKAGE}.StageTime")
    _field(m, "record_ms", 4, _F.TYPE_DOUBLE)

    m = fdp.message_type.add(name="PickOutcome")
    _field(m, "schema", 1, _F.TYPE_STRING)
    _field(m, "scan_index", 2, _F.TYPE_INT64)
    _field(m, "surface_id", 3, _F.TYPE_INT32)
    _field(m, "ok", 4, _F.TYPE_BOOL)
    _field(m, "reason", 5, _F.TYPE_STRING)
    _field(m, "source", 6, _F.TYPE_STRING)
    _field(m, "wall_time_ns", 7, _F.TYPE_INT64)

    m = fdp.message_type.add(name="ScanError")
    _field(m, "schema", 1, _F.TYPE_STRING)
    _field(m, "scan_index", 2, _F.TYPE_INT64)
    _field(m, "stage", 3, _F.TYPE_STRING)
    _field(m, "error_type", 4, _F.TYPE_STRING)
    _field(m, "message", 5, _F.TYPE_STRING)
    return fdp


@cache
def _pool() -> descriptor_pool.DescriptorPool:
    # A private pool: never collides with anything registered in the default pool.
    pool = descriptor_pool.DescriptorPool()
    pool.Add(file_descriptor_proto())
    return pool


@cache
def message_class(name: str) -> Any:
    """The Python class of ``boxloc.v1.<name>`` (e.g. ``"Product"``)."""
    return GetMessageClass(_pool().FindMessageTypeByName(f"{PACKAGE}.{name}"))


@cache
def file_descriptor_set_bytes() -> bytes:
    """The MCAP schema data of every ``boxloc.v1`` channel: a one-file FileDescriptorSet."""
    fds = descriptor_pb2.FileDescriptorSet()
    fds.file.append(file_descriptor_proto())
    return fds.SerializeToString()
