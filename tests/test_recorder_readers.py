"""Third-party readers accept our logs: `pymcap-cli doctor`, `rerun mcap check`, and the
Foxglove channels decode with mcap-protobuf-support. Also provenance and rotation."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest
from factories import feed, make_result, make_scan
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from boxloc.config import Config
from recorder.mcap import channels as C
from recorder.mcap import encode as E
from recorder.mcap.log import open_log
from recorder.mcap.sink import McapRecorder

BIN = Path(sys.executable).parent
DOCTOR = shutil.which("pymcap-cli", path=str(BIN)) or shutil.which("pymcap-cli")
RERUN = shutil.which("rerun", path=str(BIN)) or shutil.which("rerun")


def doctor(path: Path) -> None:
    """`pymcap-cli doctor` must pass the file: CRCs, indexes, summary."""
    assert DOCTOR is not None, "pymcap-cli is not installed: pip install -e '.[test]'"
    p = subprocess.run([DOCTOR, "doctor", str(path), "--format", "jsonl"], capture_output=True,
                       text=True, timeout=120)
    findings = [json.loads(line) for line in p.stdout.splitlines() if line.startswith("{")]
    bad = [f for f in findings if str(f.get("severity", "")).lower() in ("error", "warning")]
    assert p.returncode == 0 and not bad, f"doctor failed on {path}:\n{p.stdout}\n{p.stderr}"


def rerun_check(path: Path) -> None:
    """`rerun mcap check` must find no issue in any topic."""
    assert RERUN is not None, "the rerun CLI is not installed: pip install -e '.[test]'"
    p = subprocess.run([RERUN, "mcap", "check", str(path)], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, f"rerun mcap check failed on {path}:\n{p.stdout}\n{p.stderr}"
    rows = [ln.split() for ln in p.stdout.splitlines() if ln.strip().startswith(("ok", "warn",
                                                                                    "error"))]
    assert rows, p.stdout
    assert all(r[0] == "ok" and r[-1] in ("—", "-") for r in rows), p.stdout


@pytest.fixture(scope="module")
def log_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("readers") / "log.mcap"
    scans = [make_scan(0), make_scan(1), make_scan(2, raytable=True, pose=False),
             make_scan(3)]
    cfg = Config(alpha=0.02)
    with McapRecorder(path, config=cfg) as rec:
        for i, s in enumerate(scans):
            r = make_result(s, i)
            rec.on_scan(s, cfg)
            if i == 2:  # the robot reports on earlier scans while this one is in progress
                rec.record_outcome(1, 0, ok=False, reason="slipped")
                rec.record_outcome(0, 1, ok=True)
            feed(rec, s, r, cfg, start=False)
    return path


def test_doctor_passes(log_path: Path) -> None:
    doctor(log_path)


def test_rerun_mcap_check_passes(log_path: Path) -> None:
    rerun_check(log_path)


class _JsonDecoders(McapDecoderFactory):
    def decoder_for(self, message_encoding: str, schema):  # type: ignore[no-untyped-def]
        return json.loads if message_encoding == "json" else None


def test_foxglove_channels_decode_with_mcap_protobuf_support(log_path: Path) -> None:
    scans = {r.index: r.scan for r in open_log(log_path)}
    seen: dict[str, int] = {}
    with open(log_path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory(), _JsonDecoders()])
        for schema, channel, message, proto in reader.iter_decoded_messages():
            assert schema is not None
            if channel.message_encoding == "json":
                assert proto["schema"].startswith("boxloc.Locate/")
                continue
            assert proto.DESCRIPTOR.full_name == schema.name
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            scan = scans.get(message.sequence)
            if channel.topic == C.SCAN_RANGE:  # a boxloc record (schema 1.4), any reader
                assert proto.schema.startswith("boxloc.ScanRange/") and len(proto.arrays) == 1
                a = proto.arrays[0]
                assert (a.name, a.dtype, list(a.shape)) == ("range", "<f4",
                                                              list(scan.range.shape))
                assert E.msg_to_array(a).tobytes() == scan.range.astype("<f4").tobytes()
            elif channel.topic == C.SCAN_PREVIEW:
                assert proto.format == "jpeg"
                assert proto.timestamp.ToNanoseconds() == message.log_time
                img = cv2.imdecode(np.frombuffer(proto.data, np.uint8), cv2.IMREAD_UNCHANGED)
                k = -(-scan.range.shape[1] // E.PREVIEW_MAX_WIDTH)
                assert img.shape == scan.range[::k, ::k].shape and img.dtype == np.uint8
            elif channel.topic == C.SCAN_CALIBRATION:
                assert list(proto.K) == scan.sensor.K.reshape(-1).tolist()
                assert (proto.width, proto.height) == (scan.sensor.width, scan.sensor.height)
            elif channel.topic == C.SCAN_POSE:
                assert proto.parent_frame_id == "base" and proto.child_frame_id == "sensor"
                T = scan.sensor_to_base
                t = [proto.translation.x, proto.translation.y, proto.translation.z]
                assert np.allclose(t, T[:3, 3])
                q = np.array([proto.rotation.x, proto.rotation.y, proto.rotation.z,
                              proto.rotation.w])
                assert np.isclose(np.linalg.norm(q), 1.0)
            elif channel.topic == C.SCAN_POINTS:
                assert proto.point_stride == 12 and len(proto.data) % 12 == 0
                P = np.frombuffer(proto.data, "<f4").reshape(-1, 3)
                assert np.isfinite(P).all() and len(P) > 0
            elif channel.topic == C.EDGE_MAP:
                assert proto.encoding == "mono8" and len(proto.data) == proto.width * proto.height
            elif channel.topic == C.SCENE:
                ids = {e.id for e in proto.entities}
                assert {"lines", "vertices", "hypotheses"} <= ids
                assert proto.deletions[0].type == 1  # ALL: nothing lingers from the last scan
    # Every protobuf channel decoded, the Foxglove ones on every scan.
    assert seen[C.SCAN_RANGE] == seen[C.SCAN_PREVIEW] == seen[C.SCENE] == 4
    assert seen[C.SCAN_POINTS] == 4
    assert seen[C.SCAN_CALIBRATION] == 3 and seen[C.SCAN_POSE] == 3
    assert seen[C.TESTS] == 4 and seen[C.PICK_OUTCOME] == 2


def test_every_channel_is_declared_in_the_table(log_path: Path) -> None:
    log = open_log(log_path)
    for ch in log.channels():
        spec = C.spec(ch.topic)
        assert ch.schema_name == spec.schema_name
        assert ch.message_encoding == spec.message_encoding
        assert ch.record == spec.record_schema
    with open(log_path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    assert len(summary.chunk_indexes) == 4  # one chunk per scan


def test_locate_json_view(log_path: Path) -> None:
    log = open_log(log_path)
    docs = [json.loads(m.data) for m in log.messages({C.LOCATE})]
    recs = list(log)
    assert [d["scan_index"] for d in docs] == [r.index for r in recs]
    for d, r in zip(docs, recs):
        s = r.surfaces
        assert [x["pick_order"] for x in d["surfaces"]] == s.pick_order.tolist()
        assert [x["width"] for x in d["surfaces"]] == s.width.tolist()


def test_provenance_metadata_and_attachments(log_path: Path) -> None:
    log = open_log(log_path)
    run = log.run
    for key in ("boxloc_version", "git_commit", "git_dirty", "config", "config_hash",
                "sensor", "sensor_hash", "host", "layout_version", "schema_version"):
        assert run.get(key), key
    assert run["git_dirty"] in ("true", "false", "unknown")
    assert run["kernels"] in ("aot", "jit") and run["numba"]
    assert log.config == Config(alpha=0.02)
    assert run["config_hash"] == Config(alpha=0.02).hash
    assert json.loads(run["sensor"]) == make_scan(0).sensor.to_dict()
    names = {a.name for a in log.attachments()}
    assert {C.CONFIG_ATTACHMENT, C.CALIBRATION_ATTACHMENT} <= names
    cfg = Config.from_dict(tomllib.loads(log.attachment(C.CONFIG_ATTACHMENT).decode()))
    assert cfg == Config(alpha=0.02)
    calib = json.loads(log.attachment(C.CALIBRATION_ATTACHMENT))
    assert calib["K"] == make_scan(0).sensor.K.tolist()


def test_a_ray_table_is_attached(tmp_path: Path) -> None:
    scan = make_scan(5, raytable=True)
    with McapRecorder(tmp_path / "rt.mcap") as rec:
        feed(rec, scan, make_result(scan, 0))
    log = open_log(tmp_path / "rt.mcap")
    import io

    table = np.load(io.BytesIO(log.attachment(C.RAYTABLE_ATTACHMENT)), allow_pickle=False)
    assert table.tobytes() == scan.sensor.table.tobytes()
    doctor(tmp_path / "rt.mcap")


def test_rotation_by_size_makes_files_that_each_pass(tmp_path: Path) -> None:
    scans = [make_scan(i) for i in range(5)]
    with McapRecorder(tmp_path / "rot", rotate_bytes=60_000, session="s") as rec:
        for i, s in enumerate(scans):
            feed(rec, s, make_result(s, i))
    paths = sorted((tmp_path / "rot").glob("*.mcap"))
    assert paths == rec.paths and len(paths) >= 3
    assert [p.name for p in paths[:2]] == ["s-000.mcap", "s-001.mcap"]
    got = []
    for p in paths:
        doctor(p)
        rerun_check(p)
        log = open_log(p)
        assert log.run["session"] == "s" and log.config == Config()
        assert C.CONFIG_ATTACHMENT in {a.name for a in log.attachments()}
        got += [r.index for r in log]
    assert got == [s.index for s in scans]


def test_rotation_by_duration_and_on_a_new_config(tmp_path: Path) -> None:
    scans = [make_scan(i) for i in range(5)]  # 0.1 s apart
    with McapRecorder(tmp_path / "d.mcap", rotate_seconds=0.25) as rec:
        for i, s in enumerate(scans):
            cfg = Config() if i < 4 else Config(alpha=0.05)
            feed(rec, s, make_result(s, i), cfg)
    names = [p.name for p in rec.paths]
    assert names == ["d.mcap", "d-001.mcap", "d-002.mcap"]
    per_file = [[r.index for r in open_log(p)] for p in rec.paths]
    assert per_file == [[0, 1, 2], [3], [4]]
    assert open_log(rec.paths[2]).config == Config(alpha=0.05)
