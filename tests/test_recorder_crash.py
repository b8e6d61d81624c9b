"""Crash safety: SIGKILL leaves a recoverable log, SIGINT a complete one, a full disk a clear
error and readable earlier scans. Recovery never modifies its input."""

from __future__ import annotations

import hashlib
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from factories import FullDisk, feed, make_result, make_scan
from test_recorder_readers import doctor, rerun_check

from boxloc.errors import InputError, LogError
from boxloc.products import products_equal
from recorder.mcap.log import open_log
from recorder.mcap.recover import recover_log
from recorder.mcap.sink import McapRecorder, RecordingError

TESTS = Path(__file__).parent
ROOT = TESTS.parent

SHAPE = (96, 128)

_CHILD = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {tests!r})
    from factories import FullDisk, feed, make_result, make_scan
    from recorder.mcap.sink import McapRecorder
    rec = McapRecorder({path!r})
    i = 0
    while True:
        scan = make_scan(i, shape={shape!r})
        feed(rec, scan, make_result(scan, i))
        print("flushed", i, flush=True)
        i += 1
        time.sleep(0.05)
""")


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def test_sigkill_leaves_a_log_whose_flushed_scans_all_recover(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    code = _CHILD.format(tests=str(TESTS), path=str(path), shape=SHAPE)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            cwd=ROOT)
    flushed: list[int] = []
    try:
        deadline = time.monotonic() + 60
        while len(flushed) < 4 and time.monotonic() < deadline:
            line = proc.stdout.readline()  # type: ignore[union-attr]
            if not line:
                break
            flushed.append(int(line.split()[1]))
        assert len(flushed) >= 4, "the recorder child did not get going"
        assert path.stat().st_size > 0
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL

    # The killed log has no summary: strict readers refuse it with a pointer to recover.
    with pytest.raises(LogError, match="boxloc recover"):
        open_log(path)
    before = _sha(path)
    report = recover_log(path)
    assert _sha(path) == before  # never modifies its input
    assert not report.source_complete
    assert set(flushed) <= set(report.scan_indices)
    doctor(report.output)
    rerun_check(report.output)
    recovered = list(open_log(report.output))
    assert [r.index for r in recovered] == sorted(report.scan_indices)
    for rec in recovered:  # bit for bit what the child recorded
        scan = make_scan(rec.index, shape=SHAPE)
        assert rec.scan.range.tobytes() == scan.range.tobytes()
        assert products_equal(make_result(scan, rec.index), rec.result) == []


def test_sigint_finishes_the_log_cleanly(tmp_path: Path) -> None:
    path = tmp_path / "interrupted.mcap"
    cmd = [sys.executable, "-m", "boxloc.cli", "run", "sim:single:width=96,height=72,f=80",
           "--count", "500", "--record", str(path), "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=ROOT)
    try:
        deadline = time.monotonic() + 90
        # Wait until a few scans are on disk (the file grows by one chunk per scan).
        while time.monotonic() < deadline:
            if path.exists() and path.stat().st_size > 150_000:
                break
            if proc.poll() is not None:
                break
            time.sleep(0.1)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    log = open_log(path)  # complete: has its summary
    assert log.complete
    records = list(log)
    assert len(records) >= 2
    assert all(r.complete for r in records[:-1])
    last = records[-1]
    assert last.complete or last.error["error_type"] == "Interrupted"
    doctor(path)
    rerun_check(path)


def test_a_full_disk_fails_clearly_and_keeps_earlier_scans(tmp_path: Path) -> None:
    path = tmp_path / "full.mcap"
    rec = McapRecorder(path, opener=lambda p: FullDisk(p, 200_000))
    written = []
    with pytest.raises(RecordingError) as info:
        for i in range(50):
            scan = make_scan(i, shape=SHAPE)
            feed(rec, scan, make_result(scan, i))
            written.append(i)
    msg = str(info.value)
    assert "no space left on device" in msg and "boxloc recover" in msg
    assert "\n" not in msg
    assert 1 <= rec.n_scans == len(written) < 50
    rec.finish()  # after the error: closes, writes nothing, raises nothing
    rec.finish()
    with pytest.raises(RecordingError, match="stopped after an error"):
        rec.on_scan(make_scan(99, shape=SHAPE), None)  # type: ignore[arg-type]
    report = recover_log(path)
    # every scan written before the error; the failing scan too if its chunk was already
    # complete on disk when a later write (index, summary) ran out of space
    assert report.scan_indices in (written, written + [len(written)])
    recovered = list(open_log(report.output))
    for r, i in zip(recovered, report.scan_indices):
        assert products_equal(make_result(make_scan(i, shape=SHAPE), i), r.result) == []
    doctor(report.output)


def test_the_cli_reports_a_full_disk_in_one_line(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    from click.testing import CliRunner

    from boxloc.cli import cli

    monkeypatch.setattr(McapRecorder, "_open_stream", lambda self, p: FullDisk(p, 150_000))
    res = CliRunner().invoke(cli, ["run", "sim:single:width=96,height=72,f=80", "--count",
                                   "50", "--record", str(tmp_path / "x.mcap"), "-q"])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.startswith("boxloc: error")]
    assert len(lines) == 1 and "no space left on device" in lines[0]
    assert "Traceback" not in res.output
    assert recover_log(tmp_path / "x.mcap").scans >= 1


def test_recover_refuses_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / "a.mcap"
    scan = make_scan(0)
    with McapRecorder(path) as rec:
        feed(rec, scan, make_result(scan, 0))
    with pytest.raises(InputError, match="is the input"):
        recover_log(path, path)
    out = recover_log(path).output
    assert open_log(out).metadata["boxloc.recovery"]["source_complete"] == "true"
    with pytest.raises(InputError, match="exists"):
        recover_log(path)
    recover_log(path, overwrite=True)


def test_recover_skips_a_damaged_chunk_and_keeps_the_rest(tmp_path: Path) -> None:
    path = tmp_path / "bitrot.mcap"
    with McapRecorder(path) as rec:
        for i in range(3):
            scan = make_scan(i)
            feed(rec, scan, make_result(scan, i))
    log = open_log(path)
    chunks = sorted(log.summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    data = bytearray(path.read_bytes())
    mid = chunks[1].chunk_start_offset + chunks[1].chunk_length // 2
    data[mid] ^= 0xFF  # flip bits inside the second scan's compressed data
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(LogError, match="damaged"):
        list(open_log(bad).scans())
    report = recover_log(bad)
    assert report.scan_indices == [0, 2] and report.damage
    doctor(report.output)
