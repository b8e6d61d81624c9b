"""Untrusted logs: names from a log never become paths, nothing from a log is executed or
unpickled, and decoded sizes are bounded by the declared shape and a configurable limit,
checked before anything is allocated."""

from __future__ import annotations

import io
import os
import re
import tracemalloc
import uuid
import zipfile
from pathlib import Path

import numpy as np
import pytest
from cli_run import invoke
from factories import feed, make_result, make_scan
from figures import record
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from boxloc.errors import InputError, LogError
from boxloc.io import read_scan
from recorder.fuzz import PICKLE_BOMB, LogModel, read_log_model, write_log_model
from recorder.mcap import encode as E
from recorder.mcap.log import open_log
from recorder.mcap.proto import message_class
from recorder.mcap.sink import McapRecorder

ROOT = Path(__file__).resolve().parents[1]
TAG = uuid.uuid4().hex[:10]
#: Attachment, metadata and topic names a hostile log may carry.
HOSTILE = [f"../../../escape-{TAG}", f"/tmp/boxloc-abs-{TAG}", f"nul\x00{TAG}", "x" * 5000,
           f"..\\..\\win-{TAG}", f"sub/../../up-{TAG}", "", ".", "..", f"~/home-{TAG}",
           "[/]", f"[link=file:///tmp/link-{TAG}]x[/link]", "[bold red]"]


@pytest.fixture(scope="module")
def clean_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("clean") / "clean.mcap"
    with McapRecorder(path, fsync=False) as rec:
        for i in range(2):
            s = make_scan(i, shape=(24, 32))
            feed(rec, s, make_result(s, i))
    return path


def _hostile_log(clean: Path, dst: Path) -> Path:
    m: LogModel = read_log_model(clean)
    for name in HOSTILE:
        m.attachments.append([0, 0, name, "text/plain", b"attachment data"])
        m.metadata.append((name, {name: name}))
    first = m.messages[0]
    for name in HOSTILE:  # channels whose topics are hostile names, with a message each
        m.messages.append({**first, "topic": name})
    run = dict(m.metadata[0][1])
    run.update(host="[/]", git_commit="[link=file:///etc/passwd]x[/link]", session="[bold]")
    m.metadata[0] = (m.metadata[0][0], run)
    write_log_model(m, dst)
    return dst


def _tree(root: Path) -> set[Path]:
    return {p for p in root.rglob("*")}


def _exists(p: Path) -> bool:
    try:
        return os.path.lexists(p)
    except (OSError, ValueError):  # a name no file system takes cannot have been written
        return False


def _escapes(bases: list[Path]) -> list[Path]:
    """Where a tool that used a hostile name as a path would have written."""
    out = []
    for name in HOSTILE:
        clean = name.replace("\x00", "")
        if not clean or clean in (".", ".."):
            continue
        for b in bases:
            for cand in (b / clean, Path(clean), Path(os.path.expanduser(clean))):
                out.append(cand)
    return out


TOOLS = {
    "recover": lambda log, out: ["recover", str(log), "-o", str(out / "recovered.mcap")],
    "view --save": lambda log, out: ["view", str(log), "--save", str(out / "view.rrd")],
    "run --record": lambda log, out: ["run", str(log), "--record", str(out / "runs"), "-q"],
    "replay": lambda log, out: ["replay", str(log), "--out", str(out / "replay"), "-q",
                                "-j", "1"],
    "info --json": lambda log, out: ["info", str(log), "--json"],
    "info": lambda log, out: ["info", str(log)],
}


@pytest.mark.parametrize("tool", sorted(TOOLS))
def test_no_tool_writes_outside_its_output_directory(tool: str, tmp_path: Path,
                                                     clean_log: Path) -> None:
    src = tmp_path / "in"
    out = tmp_path / "out"
    cwd = tmp_path / "cwd"
    for d in (src, out, cwd):
        d.mkdir()
    log = _hostile_log(clean_log, src / "hostile.mcap")
    before = _tree(tmp_path)
    # in this process (an exception the CLI lets out fails the test), in cwd
    p = invoke(*TOOLS[tool](log, out), cwd=cwd, env={"COLUMNS": "4000"})
    assert p.returncode in (0, 1, 2), p.stderr[-3000:]
    new = _tree(tmp_path) - before
    outside = sorted(str(q) for q in new if out not in q.parents)
    assert outside == [], outside
    assert not [str(q)[:200] for q in _escapes([src, out, cwd, out / "runs", out / "replay"])
                if _exists(q)]
    assert list(cwd.iterdir()) == []
    record("untrusted", f"tool {tool}", {"hostile_names": len(HOSTILE), "exit": p.returncode,
                                         "files_outside_output": len(outside)})
    if tool == "info":  # names are shown as text, never read as Rich markup
        assert p.returncode == 0, p.stderr[-2000:]
        assert "[/]" in p.stdout and "[bold red]" in p.stdout and "[link=file:/" in p.stdout
    if tool == "recover":  # the hostile names are kept as data, the log stays readable
        assert p.returncode == 0, p.stderr
        names = {a.name for a in open_log(out / "recovered.mcap").attachments()}
        assert set(HOSTILE) <= names


def test_the_reader_keeps_hostile_names_as_data(tmp_path: Path, clean_log: Path) -> None:
    log = open_log(_hostile_log(clean_log, tmp_path / "h.mcap"))
    assert {a.name for a in log.attachments()} >= set(HOSTILE)
    assert log.attachment(HOSTILE[0]) == b"attachment data"
    assert len(list(log.scans())) == 2  # foreign topics are ignored
    with pytest.raises(LogError, match="no attachment"):
        log.attachment("../clean.mcap")


# --- sizes -----------------------------------------------------------------------------------


def _replace(clean: Path, dst: Path, topic: str, data: bytes) -> Path:
    m = read_log_model(clean)
    for x in m.messages:
        if x["topic"] == topic:
            x["data"] = data
    write_log_model(m, dst)
    return dst


def _huge_range(width: int, height: int) -> bytes:
    msg = RawImage(frame_id="sensor", width=width, height=height, encoding="32FC1",
                   step=(width * 4) % 2**32, data=b"\0" * 64)
    return msg.SerializeToString()


def _peak_mb(fn: object) -> tuple[BaseException | None, float]:
    tracemalloc.start()
    err: BaseException | None = None
    try:
        fn()  # type: ignore[operator]
    except Exception as e:  # noqa: BLE001 - returned to the test
        err = e
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    return err, peak / 2**20


@pytest.mark.parametrize("wh", [(100_000, 100_000), (2**32 - 1, 2**32 - 1), (65_536, 65_536),
                                (4097, 4096)])
def test_a_log_claiming_a_huge_scan_is_refused_before_allocating(tmp_path: Path,
                                                                 clean_log: Path,
                                                                 wh: tuple[int, int]) -> None:
    p = _replace(clean_log, tmp_path / "huge.mcap", "/scan/range", _huge_range(*wh))
    err, peak = _peak_mb(lambda: list(open_log(p).scans()))
    assert isinstance(err, LogError), err
    assert "\n" not in str(err) and "range image" in str(err)
    assert peak < 32  # MB: the claimed image would be up to 64 GB
    record("untrusted", f"range {wh[0]}x{wh[1]}", {"refused": True,
                                                    "traced_peak_mb": round(peak, 2)})


def test_a_huge_sensor_and_scan_info_are_refused(tmp_path: Path, clean_log: Path) -> None:
    Product = message_class("Product")
    for topic, key in (("/scan/sensor", "size"), ("/scan/info", "shape")):
        data = next(x["data"] for x in read_log_model(clean_log).messages
                    if x["topic"] == topic)
        msg = Product()
        msg.ParseFromString(data)
        arr = next(a for a in msg.arrays if a.name == key)
        arr.data = np.array([100_000, 100_000], "<i8").tobytes()
        p = _replace(clean_log, tmp_path / f"{key}.mcap", topic, msg.SerializeToString())
        err, peak = _peak_mb(lambda p=p: list(open_log(p).scans()))
        assert isinstance(err, LogError), err
        assert peak < 32


def _product_with(clean: Path, topic: str, edit: object) -> bytes:
    data = next(x["data"] for x in read_log_model(clean).messages if x["topic"] == topic)
    msg = message_class("Product")()
    msg.ParseFromString(data)
    edit(msg)  # type: ignore[operator]
    return msg.SerializeToString()


@pytest.mark.parametrize("shape", [[2**32, 2**32], [2**63, 2**63], [2**64 - 1, 2],
                                   [0, 2**64 - 1], [2**63, 0, 3]])
def test_an_array_whose_shape_overflows_is_refused(tmp_path: Path, clean_log: Path,
                                                   shape: list[int]) -> None:
    def edit(msg: object) -> None:
        a = msg.arrays[0]  # type: ignore[attr-defined]
        del a.shape[:]
        a.shape.extend(shape)
        a.data, a.filter = b"", 0

    p = _replace(clean_log, tmp_path / "o.mcap", "/boxloc/edges",
                 _product_with(clean_log, "/boxloc/edges", edit))
    err, peak = _peak_mb(lambda: list(open_log(p).scans()))
    assert isinstance(err, LogError) and "\n" not in str(err), err
    assert peak < 32
    record("untrusted", f"array shape {shape}", {"refused": True,
                                                 "traced_peak_mb": round(peak, 2)})


def test_the_limit_is_configurable(clean_log: Path) -> None:
    assert len(list(open_log(clean_log).scans())) == 2
    with pytest.raises(LogError, match="out of bounds"):
        list(open_log(clean_log, limits=E.DecodeLimits(max_pixels=100)).scans())
    with pytest.raises(LogError, match="exceed the limit"):
        list(open_log(clean_log, limits=E.DecodeLimits(max_array_bytes=256)).scans())


def test_an_unknown_schema_major_version_is_refused(tmp_path: Path, clean_log: Path) -> None:
    def edit(msg: object) -> None:
        msg.schema = msg.schema.replace("/1.", "/2.")  # type: ignore[attr-defined]

    p = _replace(clean_log, tmp_path / "v2.mcap", "/boxloc/edges",
                 _product_with(clean_log, "/boxloc/edges", edit))
    with pytest.raises(LogError, match="major version 2"):
        list(open_log(p).scans())


@pytest.mark.parametrize("topic", ["/scan/info", "/scan/range", "/scan/sensor",
                                   "/boxloc/edges", "/boxloc/tests", "/boxloc/result",
                                   "/boxloc/timing"])
def test_protobuf_garbage_is_a_clean_error(tmp_path: Path, clean_log: Path, topic: str) -> None:
    rng = np.random.default_rng(len(topic))
    for k in range(5):
        junk = rng.integers(0, 256, int(rng.integers(1, 400)), dtype=np.uint8).tobytes()
        p = _replace(clean_log, tmp_path / f"g{k}.mcap", topic, junk)
        # refused, every one of these draws (a reader that skipped the topic, or took any
        # bytes for a message, would read them)
        with pytest.raises(LogError) as e:
            list(open_log(p).scans())
        assert "\n" not in str(e.value)


# --- nothing is executed or unpickled --------------------------------------------------------


def test_an_object_array_is_never_unpickled(tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # the payload would create ./PWNED
    f = io.BytesIO()
    np.lib.format.write_array_header_1_0(f, {"descr": "|O", "fortran_order": False,
                                             "shape": (4, 4)})
    p = tmp_path / "bomb.npz"
    with zipfile.ZipFile(p, "w") as zf:
        zf.writestr("range.npy", f.getvalue() + PICKLE_BOMB)
        zf.writestr("points.npy", f.getvalue() + PICKLE_BOMB)
    with pytest.raises(InputError, match="must be"):
        read_scan(p, intrinsics="10,10,2,2")
    assert not (tmp_path / "PWNED").exists()


#: Ways to run code from data. ``eval(``/``exec(`` as calls (not ``.eval(`` methods).
_FORBIDDEN = [
    (re.compile(r"^\s*(import|from)\s+(c?pickle|dill|cloudpickle|marshal|shelve)\b", re.M),
     "imports a deserializer that runs code"),
    (re.compile(r"\b(c?pickle|dill|cloudpickle|marshal)\.loads?\("), "unpickles"),
    (re.compile(r"allow_pickle\s*=\s*True"), "allows pickles"),
    (re.compile(r"(?<![\w.])(eval|exec)\("), "evaluates text"),
    (re.compile(r"\byaml\.(load|unsafe_load)\("), "loads YAML with tags"),
    (re.compile(r"\bnp\.load\((?![^)]*allow_pickle\s*=\s*False)"), "np.load without "
     "allow_pickle=False"),
]


def test_no_code_path_unpickles_or_evaluates() -> None:
    found = []
    for pkg in ("boxloc", "recorder", "replay"):
        for f in sorted((ROOT / pkg).rglob("*.py")):
            text = f.read_text()
            for rx, why in _FORBIDDEN:
                for m in rx.finditer(text):
                    line = text.count("\n", 0, m.start()) + 1
                    found.append(f"{f.relative_to(ROOT)}:{line}: {why}: {m.group(0)!r}")
    assert found == [], "\n".join(found)
