"""The recorder compresses its chunks at its own zstd level (``ZSTD_LEVEL``) in its own
writer, and nowhere else: importing ``recorder.mcap.sink`` leaves every other mcap Writer of
the process as the library made it.

Before, the import replaced ``mcap.writer.zstandard`` for the whole process, so a plain
Writer wrote level 3 or level 1 depending on what had been imported before (this made fuzz
cases depend on their worker's history).
"""

from __future__ import annotations

import inspect
import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import zstandard
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from recorder.fuzz.log_records import LogModel, write_log_model
from recorder.mcap.sink import ZSTD_LEVEL, ZstdLevelWriter

ROOT = Path(__file__).resolve().parents[1]


def _payload() -> bytes:
    """200 kB that zstd levels 1 and 3 compress to other bytes (nibbles, some repeats)."""
    rng = np.random.default_rng(7)
    return (rng.integers(0, 16, 200_000, dtype=np.uint8) * 17).tobytes()


def _write(cls: type[Writer]) -> bytes:
    """One chunk of two messages, written by ``cls`` to memory."""
    buf = io.BytesIO()
    w = cls(buf, compression=CompressionType.ZSTD)
    w.start(library="test")
    cid = w.register_channel("/x", "raw", 0)
    data = _payload()
    w.add_message(cid, 1, data[:100_000], 1)
    w.add_message(cid, 2, data[100_000:], 2)
    w.finish()
    return buf.getvalue()


def _chunks(mcap: bytes) -> list[tuple[bytes, bytes]]:
    """(uncompressed, as stored) of each zstd chunk of an MCAP file."""
    out = []
    for r in StreamReader(io.BytesIO(mcap), emit_chunks=True).records:
        if isinstance(r, Chunk):
            assert r.compression == "zstd"
            raw = zstandard.ZstdDecompressor().decompress(
                r.data, max_output_size=r.uncompressed_size)
            out.append((raw, r.data))
    return out


def _at_level(chunks: list[tuple[bytes, bytes]], level: int) -> bool:
    return all(zstandard.ZstdCompressor(level=level).compress(raw) == packed
               for raw, packed in chunks)


def test_the_payload_tells_the_levels_apart() -> None:
    # the premise of the tests below: level 1 and level 3 are other bytes for this payload
    raw = _payload()
    assert (zstandard.ZstdCompressor(level=1).compress(raw)
            != zstandard.ZstdCompressor(level=3).compress(raw))


def test_importing_the_recorder_does_not_change_a_plain_writer() -> None:
    """In a fresh interpreter: a plain mcap Writer's bytes before and after importing the
    recorder's sink (and the modules that import it) are the same, at the library's level."""
    # the helpers' own source, so that nothing of the recorder is imported before `before`
    code = "\n".join([
        "import io, json, sys",
        "import numpy as np",
        "from mcap.writer import CompressionType, Writer",
        inspect.getsource(_payload),
        inspect.getsource(_write),
        "assert not any(m.startswith('recorder') for m in sys.modules), sorted(sys.modules)",
        "before = _write(Writer)",
        "import recorder.mcap.sink, recorder.mcap.recover, recorder.fuzz.log_records",
        "after = _write(Writer)",
        "print(json.dumps({'before': before.hex(), 'after': after.hex(),",
        "                  'sink_loaded': 'recorder.mcap.sink' in sys.modules}))",
    ])
    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    out = json.loads(p.stdout)
    assert out["sink_loaded"]
    before, after = bytes.fromhex(out["before"]), bytes.fromhex(out["after"])
    assert before == after
    assert _at_level(_chunks(before), 3)  # mcap's own default, untouched


def test_the_recorders_writer_compresses_at_its_level() -> None:
    assert ZSTD_LEVEL != 3  # else the test could not tell the writers apart
    ours, plain = _write(ZstdLevelWriter), _write(Writer)
    chunks = _chunks(ours)
    assert len(chunks) == 1 and _at_level(chunks, ZSTD_LEVEL)
    # the same file but for the chunk's compressed bytes: the layout is the library's
    assert [raw for raw, _ in chunks] == [raw for raw, _ in _chunks(plain)]
    assert ours != plain
    # the plain Writer in this process (where the sink is imported) is still at level 3
    assert _at_level(_chunks(plain), 3)


def test_a_recorded_log_is_at_the_recorders_level(recorded_log: Path) -> None:
    chunks = _chunks(recorded_log.read_bytes())
    assert len(chunks) >= 6  # one per scan
    assert _at_level(chunks, ZSTD_LEVEL)


def test_fuzzed_logs_are_at_the_recorders_level(tmp_path: Path) -> None:
    data = _payload()
    msg = {"topic": "/x", "encoding": "raw", "schema": ("", "", b""), "ch_meta": {},
           "log_time": 1, "publish_time": 1, "sequence": 0, "data": data}
    m = LogModel("fuzz", [("m", {"k": "v"})], [[0, 0, "a.txt", "text/plain", b"a"]], [msg])
    write_log_model(m, tmp_path / "f.mcap")
    chunks = _chunks((tmp_path / "f.mcap").read_bytes())
    assert len(chunks) == 1 and _at_level(chunks, ZSTD_LEVEL)
