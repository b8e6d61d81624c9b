"""The ``log-records`` cases: a small log rewritten as a valid MCAP file whose content is
hostile (protobuf fields, run metadata, attachment names, topics, message order).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from recorder.fuzz.cases import Job, _pick
from recorder.fuzz.log_bytes import log_steps
from recorder.fuzz.mutate import _INTERESTING, mutate_bytes


@dataclass
class LogModel:
    """A log as plain data, to be mutated and written back as valid MCAP."""

    library: str
    metadata: list[tuple[str, dict[str, str]]]
    attachments: list[list[Any]]  # [create_time, log_time, name, media_type, data]
    messages: list[dict[str, Any]]


_LOG_CACHE: dict[str, LogModel] = {}


def read_log_model(path: str | os.PathLike[str]) -> LogModel:
    """A (valid) log as a :class:`LogModel`: header library, metadata, attachments and
    messages in file order (each a dict: topic, encoding, ch_meta, schema, log_time,
    publish_time, sequence, data). Cached per path; a fresh copy is returned."""
    path = str(path)
    if path not in _LOG_CACHE:
        from mcap.reader import make_reader

        with open(path, "rb") as f:
            r = make_reader(f)
            hdr = r.get_header()
            msgs = []
            for sch, ch, m in r.iter_messages(log_time_order=False):
                msgs.append({
                    "topic": ch.topic, "encoding": ch.message_encoding,
                    "ch_meta": dict(ch.metadata),
                    "schema": (sch.name, sch.encoding, sch.data) if sch else ("", "", b""),
                    "log_time": m.log_time, "publish_time": m.publish_time,
                    "sequence": m.sequence, "data": m.data})
            md = [(m.name, dict(m.metadata)) for m in r.iter_metadata()]
            att = [[a.create_time, a.log_time, a.name, a.media_type, a.data]
                   for a in r.iter_attachments()]
        _LOG_CACHE[path] = LogModel(hdr.library, md, att, msgs)
    cached = _LOG_CACHE[path]
    # Every mutable part copied (a message's channel metadata too): a case's mutations must
    # never reach the cache, or the next case of the same worker would start from them.
    return LogModel(cached.library, [(n, dict(v)) for n, v in cached.metadata],
                    [list(a) for a in cached.attachments],
                    [{**x, "ch_meta": dict(x["ch_meta"])} for x in cached.messages])


def write_log_model(m: LogModel, path: Path) -> None:
    """Write a :class:`LogModel` as a valid MCAP file (whatever its content).

    The bytes are a function of ``m`` alone: the chunks are compressed at the recorder's
    zstd level (:data:`recorder.mcap.sink.ZSTD_LEVEL`), whatever this process did before.
    """
    from mcap.writer import CompressionType

    # The recorder's writer, explicitly: mcap's own Writer compresses at the library's level
    # (3). Before, this relied on importing recorder.mcap.sink setting the level of every
    # mcap Writer in the process, and before that, a fresh worker wrote level 3 and one that
    # had recovered a log level 1: the same case gave other bytes depending on its history.
    from recorder.mcap.sink import ZstdLevelWriter

    with open(path, "wb") as f:
        w = ZstdLevelWriter(f, compression=CompressionType.ZSTD)
        w.start(library=m.library)
        for name, md in m.metadata:
            w.add_metadata(name, md)
        for ct, lt, name, mt, data in m.attachments:
            w.add_attachment(ct, lt, name, mt, data)
        schemas: dict[tuple[str, str, bytes], int] = {}
        chans: dict[tuple[str, str, int, str], int] = {}
        for x in m.messages:
            key = x["schema"]
            if key not in schemas:
                schemas[key] = w.register_schema(*key) if key[0] or key[1] else 0
            sid = schemas[key]
            ckey = (x["topic"], x["encoding"], sid, json.dumps(x["ch_meta"], sort_keys=True))
            if ckey not in chans:
                chans[ckey] = w.register_channel(x["topic"], x["encoding"], sid, x["ch_meta"])
            w.add_message(chans[ckey], x["log_time"], x["data"], x["publish_time"],
                          x["sequence"])
        w.finish()


_BAD_NAMES = ("", "../../../../tmp/boxloc-fuzz-escape", "/tmp/boxloc-fuzz-abs", "a\x00b",
              "x" * 5000, "..", ".", "nested/../../up", "C:\\windows\\evil", "\u202etxt.exe",
              "config.toml", "tests/kind", "[/]", "[bold red]x", "[link=file:///etc/passwd]x")
_BAD_DTYPES = ("|O", "<c16", "<f2", "|b1", "<i8", ">f8", "<M8[ns]", "|V8", "|U0", "<U0",
               "|S4", "<U999999", "", "garbage", "<f4", "<u8", "|u1", "<f16", "<U1")
_BAD_JSON = ("", "{", "[]", "null", "1e999", '{"alpha": "x"}', '{"noise": "abc"}',
             '{"noise": [1, 2]}', '{"noise": {"sigma0": "a"}}', '{"workers": 1e300}',
             '{"max_pixels": -1}', '{"alpha": NaN}', '{"kind": "pinhole", "fx": "nan"}',
             '{"kind": "raytable"}', "[" * 50_000 + "]" * 50_000, "[/]", "[bold]",
             '{"a":' * 20_000 + "1" + "}" * 20_000, '"\\ud800"')


def _deep_json() -> str:
    return "[" * 100_000 + "]" * 100_000


def _mutate_product(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    from recorder.mcap.proto import message_class

    msg = message_class("Product")()
    try:
        msg.ParseFromString(data)
    except Exception:  # noqa: BLE001 - then mutate the bytes instead
        return mutate_bytes(rng, data)
    arrays = list(msg.arrays)
    what = str(_pick(rng, ["shape", "dtype", "filter", "name", "data", "schema", "drop",
                           "duplicate", "string", "index"]))
    if what == "schema":
        msg.schema = str(_pick(rng, [msg.schema.replace("/1.", "/2."), "boxloc.Other/1.0", "",
                                     "x" * 1000, re.sub(r"/1\.\d+$", "/1.99", msg.schema),
                                     re.sub(r"/1\.\d+$", "/0.9", msg.schema)]))
    elif what == "index":
        msg.scan_index = int(_pick(rng, [-1, 2**63 - 1, -(2**63), 7]))
    elif not arrays:
        return mutate_bytes(rng, data)
    else:
        a = arrays[int(rng.integers(0, len(arrays)))]
        if what == "shape":
            nd = int(_pick(rng, [0, 1, 2, 2, 3, 3, 9, 40]))
            del a.shape[:]
            a.shape.extend(0 if rng.random() < 0.3 else int(_pick(rng, _INTERESTING))
                           for _ in range(nd))
            if rng.random() < 0.3:
                a.data = b""
        elif what == "dtype":
            a.dtype = str(_pick(rng, _BAD_DTYPES))
            if rng.random() < 0.3:
                a.data = b""
                del a.shape[:]
                a.shape.extend([0] if rng.random() < 0.5 else [])
        elif what == "filter":
            a.filter = int(_pick(rng, [0, 1, 2, 3, 4, 99]))
        elif what == "name":
            a.name = str(_pick(rng, _BAD_NAMES))
        elif what == "data":
            k = int(rng.integers(0, len(a.data) + 2))
            a.data = a.data[:k] if rng.random() < 0.5 else a.data + bytes(k)
        elif what == "drop":
            msg.arrays.remove(a)
        elif what == "duplicate":
            msg.arrays.add().CopyFrom(a)
        elif what == "string":
            s = _deep_json() if rng.random() < 0.5 else str(_pick(rng, _BAD_JSON))
            raw = np.asarray(s)
            a.dtype, a.filter = raw.dtype.str, 0
            del a.shape[:]
            a.data = raw.tobytes()
    return msg.SerializeToString(deterministic=True), f"product-{what}"


def _mutate_image(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    """Mutate a ``/scan/range`` message in its own format: a ``ScanRange`` record (schema
    1.4 on) like a product, an older log's Foxglove RawImage field by field."""
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    from recorder.mcap.encode import is_range_record

    if is_range_record(data):
        out, kind = _mutate_product(rng, data)
        return out, f"range-{kind}"
    msg = RawImage()
    try:
        msg.ParseFromString(data)
    except Exception:  # noqa: BLE001
        return mutate_bytes(rng, data)
    what = str(_pick(rng, ["size", "step", "encoding", "data"]))
    big = [0, 1, 100_000, 2**31 - 1, 2**32 - 1, 65536]
    if what == "size":
        msg.width, msg.height = int(_pick(rng, big)), int(_pick(rng, big))
        msg.step = msg.width * 4 % 2**32
    elif what == "step":
        msg.step = int(_pick(rng, big))
    elif what == "encoding":
        msg.encoding = str(_pick(rng, ["16UC1", "", "32FC3", "x" * 100]))
    else:
        k = int(rng.integers(0, len(msg.data) + 1))
        msg.data = msg.data[:k]
    return msg.SerializeToString(deterministic=True), f"image-{what}"


def _mutate_rows(rng: np.random.Generator, data: bytes, topic: str) -> tuple[bytes, str]:
    from recorder.mcap.proto import message_class

    name = {"/boxloc/tests": "TestRows", "/boxloc/timing": "Timing",
            "/boxloc/error": "ScanError", "/pick/outcome": "PickOutcome"}[topic]
    msg = message_class(name)()
    try:
        msg.ParseFromString(data)
    except Exception:  # noqa: BLE001
        return mutate_bytes(rng, data)
    if rng.random() < 0.3:
        msg.schema = str(_pick(rng, [msg.schema.replace("/1.", "/7."), "", "boxloc.X/1.0"]))
    elif name == "TestRows":
        r = msg.rows.add()
        r.stage = str(_pick(rng, ["edges", "", "x" * 1000, "nonsense", "verification"]))
        r.kind = int(_pick(rng, [-1, 0, 255, 256, 2**31 - 1]))
        r.a, r.b = int(_pick(rng, [-(2**63), 2**63 - 1, 0])), -1
        r.statistic = float(_pick(rng, [np.nan, np.inf, -np.inf, 0.0]))
    elif name == "Timing":
        s = msg.stages.add()
        s.stage, s.ms = "x" * int(rng.integers(0, 5000)), float("nan")
    elif name == "ScanError":
        msg.stage = str(_pick(rng, ["\x00" * 10, "[/]", "[bold]"]))
        msg.message = str(_pick(rng, ["line one\nline two", "[/]", "x" * 5000]))
    else:
        msg.surface_id = int(_pick(rng, [-1, 2**31 - 1]))
        msg.scan_index = int(_pick(rng, [-1, 2**63 - 1]))
    return msg.SerializeToString(deterministic=True), f"{name}-fields"


_PRODUCT_TOPICS = ("/scan/sensor", "/scan/info", "/boxloc/edges", "/boxloc/lines",
                   "/boxloc/vertices", "/boxloc/hypotheses", "/boxloc/verification",
                   "/boxloc/selection", "/boxloc/surfaces", "/boxloc/result", "/scan/labels",
                   "/scan/end")


def _gen_log_records(rng: np.random.Generator, corpus: dict[str, Any], d: Path) -> Job:
    small = corpus["small_logs"]
    m = read_log_model(small[int(rng.integers(0, len(small)))])
    what = str(_pick(rng, ["payload"] * 6 + ["metadata", "attachment", "topic", "order"]))
    kind = what
    if what == "payload":
        records = [x for x in m.messages if x["topic"] in _PRODUCT_TOPICS]
        pool = records if records and rng.random() < 0.6 else m.messages
        x = pool[int(rng.integers(0, len(pool)))]
        t = x["topic"]
        if t in _PRODUCT_TOPICS:
            x["data"], kind = _mutate_product(rng, x["data"])
        elif t == "/scan/range":
            x["data"], kind = _mutate_image(rng, x["data"])
        elif t in ("/boxloc/tests", "/boxloc/timing", "/boxloc/error", "/pick/outcome"):
            x["data"], kind = _mutate_rows(rng, x["data"], t)
        else:
            x["data"], kind = mutate_bytes(rng, x["data"])
        kind = f"{t}:{kind}"
    elif what == "metadata":
        name, md = m.metadata[0] if m.metadata else ("boxloc.run", {})
        key = str(_pick(rng, ["config", "sensor", "session", "boxloc_version", "new", "host",
                              "git_commit", "git_dirty", "created_utc", "part"]))
        md[key] = _deep_json() if rng.random() < 0.2 else str(_pick(rng, _BAD_JSON))
        m.metadata[0:1] = [(name, md)]
        if rng.random() < 0.2:
            m.metadata.append((str(_pick(rng, _BAD_NAMES)), {"k": "v"}))
        kind = f"metadata-{key}"
    elif what == "attachment":
        for a in m.attachments:
            if rng.random() < 0.7:
                a[2] = str(_pick(rng, _BAD_NAMES))
            if rng.random() < 0.3:
                a[4] = mutate_bytes(rng, a[4])[0]
        m.attachments.append([0, 0, str(_pick(rng, _BAD_NAMES)), "application/octet-stream",
                              b"payload"])
    elif what == "topic":
        x = m.messages[int(rng.integers(0, len(m.messages)))]
        topics = sorted({y["topic"] for y in m.messages})
        for y in m.messages:
            if y["topic"] == x["topic"]:
                y["topic"] = (str(_pick(rng, topics)) if rng.random() < 0.5
                              else str(_pick(rng, _BAD_NAMES)))
                if rng.random() < 0.3:
                    y["encoding"] = str(_pick(rng, ["json", "cdr", ""]))
    else:
        op = str(_pick(rng, ["drop", "duplicate", "swap", "reverse", "sequence", "time"]))
        i = int(rng.integers(0, len(m.messages)))
        j = int(rng.integers(0, len(m.messages)))
        if op == "drop":
            del m.messages[i]
        elif op == "duplicate":
            m.messages.insert(j, dict(m.messages[i]))
        elif op == "swap":
            m.messages[i], m.messages[j] = m.messages[j], m.messages[i]
        elif op == "reverse":
            m.messages.reverse()
        elif op == "sequence":
            m.messages[i]["sequence"] = int(_pick(rng, [0, 2**32 - 1, 12345]))
        else:
            m.messages[i]["log_time"] = int(_pick(rng, [0, 2**64 - 1, 1]))
        kind = f"order-{op}"
    out = d / "fuzzed.mcap"
    write_log_model(m, out)
    return Job(kind, log_steps(out, d))
