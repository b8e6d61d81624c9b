"""`boxloc run SOURCE... --workers N`: several inputs in order, scans run in worker processes
with the log identical (bit for bit, in scan order) to a serial run's, bad inputs among
good ones, a worker that dies, the bound on scans in flight, and Ctrl-C.

The stream machinery itself (:mod:`recorder.stream`) is tested on small simulated scans;
no test here depends on how fast anything is.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from cli_run import invoke

from boxloc import io
from boxloc import simulate as sim
from boxloc.config import Config
from boxloc.errors import InputError
from boxloc.scan import Scan
from recorder.mcap import channels as C
from recorder.mcap.log import open_log
from recorder.stream import (
    Encoding,
    Job,
    RemoteError,
    ScanRun,
    SimScan,
    WorkerLost,
    _portable,
    ordered_runs,
    run_job,
)

ROOT = Path(__file__).resolve().parents[1]
SPEC = "pallet:width=120,height=90,f=100"


def _scan(seed: int) -> Scan:
    return sim.simulate(SPEC, seed=seed).scan


@pytest.fixture(scope="module")
def scans_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four small simulated pallets (a few boxes each) as .npz files, s0 .. s3."""
    d = tmp_path_factory.mktemp("scans")
    for k in range(4):
        io.write_npz(_scan(k + 1), d / f"s{k}.npz")
    return d


def _messages(path: Path) -> list[tuple[str, int, int, bytes]]:
    """Every message of a log as stored, but the wall-clock timing (the one thing a run
    on other processes may change)."""
    return [(m.topic, m.log_time, m.sequence, m.data) for m in open_log(path).messages()
            if m.topic != C.TIMING]


def _ranges(path: Path) -> list[bytes]:
    return [r.scan.range.tobytes() for r in open_log(path).scans()]


# --- the command line ------------------------------------------------------------------------


def test_several_sources_run_in_the_order_given(scans_dir: Path, tmp_path: Path) -> None:
    files = sorted(scans_dir.glob("*.npz"))
    sub = tmp_path / "sub"
    sub.mkdir()
    for f in files[:2]:  # a directory: its files in name order
        (sub / f.name).write_bytes(f.read_bytes())
    log = tmp_path / "run.mcap"
    r = invoke("run", str(files[3]), str(sub), str(files[2]), "--record", str(log), "-q")
    assert r.returncode == 0, r.stderr
    order = [files[3], files[0], files[1], files[2]]
    assert _ranges(log) == [io.read_scan(f).range.tobytes() for f in order]
    # numbered across the sources, as `boxloc import` numbers them
    assert [rec.index for rec in open_log(log).scans()] == [0, 1, 2, 3]
    assert all(rec.complete for rec in open_log(log).scans())


def test_several_simulator_specs_are_numbered_across(tmp_path: Path) -> None:
    log = tmp_path / "sim.mcap"
    r = invoke("run", "sim:single:width=96,height=72,f=80", "sim:" + SPEC, "--count", "2",
               "--record", str(log), "-q")
    assert r.returncode == 0, r.stderr
    recs = list(open_log(log).scans())
    assert [x.index for x in recs] == [0, 1, 2, 3]
    assert [x.scan.shape for x in recs] == [(72, 96)] * 2 + [(90, 120)] * 2


def test_workers_write_the_serial_log_bit_for_bit(scans_dir: Path, tmp_path: Path) -> None:
    serial, parallel = tmp_path / "serial.mcap", tmp_path / "parallel.mcap"
    r = invoke("run", str(scans_dir), "--record", str(serial), "-q", "--workers", "1")
    assert r.returncode == 0, r.stderr
    r = invoke("run", str(scans_dir), "--record", str(parallel), "-q", "--workers", "2")
    assert r.returncode == 0, r.stderr
    a, b = _messages(serial), _messages(parallel)
    assert [m[:3] for m in a] == [m[:3] for m in b]  # the same messages in the same order
    assert a == b  # and the same bytes
    assert open_log(serial).config == open_log(parallel).config
    recs = list(open_log(parallel).scans())
    assert [x.index for x in recs] == [0, 1, 2, 3] and all(x.complete for x in recs)
    assert sum(len(x.result.surfaces) for x in recs if x.result is not None) > 0


def test_simulated_scans_made_in_the_workers_give_the_serial_log(tmp_path: Path) -> None:
    """With --workers 2 a sim: source's scans are simulated (and encoded) in the workers:
    the log is the serial one's, bit for bit, the timing's fields too but its wall times."""
    logs = {}
    for w in ("1", "2"):
        logs[w] = tmp_path / f"sim{w}.mcap"
        r = invoke("run", "sim:" + SPEC, "--count", "3", "--seed", "5", "--record",
                   str(logs[w]), "-q", "--workers", w)
        assert r.returncode == 0, r.stderr
    assert _messages(logs["1"]) == _messages(logs["2"])
    timing = [[m.topic for m in open_log(x).messages() if m.topic == C.TIMING]
              for x in logs.values()]
    assert timing == [[C.TIMING] * 3] * 2
    assert _ranges(logs["2"]) == [
        sim.simulate(SPEC, seed=5 + k).scan.range.tobytes() for k in range(3)]


def test_other_observers_get_the_calls_while_the_recorder_gets_the_encoded_scan(
        tmp_path: Path) -> None:
    """With --publish-ros2 beside --record, the worker's calls are replayed onto the
    publisher and its encoded messages written by the recorder: both outputs are the
    serial run's."""
    from mcap.reader import make_reader

    def ros2(path: Path) -> list[tuple[str, int, bytes]]:
        with open(path, "rb") as f:
            return [(ch.topic, m.log_time, m.data)
                    for _, ch, m in make_reader(f).iter_messages()]

    out = {}
    for w in ("1", "2"):
        out[w] = (tmp_path / f"log{w}.mcap", tmp_path / f"ros{w}.mcap")
        r = invoke("run", "sim:" + SPEC, "--count", "3", "--record", str(out[w][0]),
                   "--publish-ros2", str(out[w][1]), "-q", "--workers", w)
        assert r.returncode == 0, r.stderr
    assert _messages(out["1"][0]) == _messages(out["2"][0])
    a, b = ros2(out["1"][1]), ros2(out["2"][1])
    assert len(a) >= 6 and a == b  # a PoseArray and a MarkerArray per scan


def test_a_simulated_scan_that_cannot_be_made_is_reported_and_the_rest_run(
        tmp_path: Path) -> None:
    """A SimScan whose spec the simulator refuses is an unreadable input, in the worker as
    in the parent; the scans after it run."""
    import copy

    good = sim.parse_spec(SPEC)
    bad = copy.copy(good)
    object.__setattr__(bad, "width", 0)  # past the spec's own check: simulate refuses it
    jobs = [Job(SimScan(good, 1, 0), Config()), Job(SimScan(bad, 1, 1), Config()),
            Job(SimScan(good, 2, 2), Config())]
    with pytest.raises(InputError, match="scene width"):
        jobs[1].make_scan()
    out = list(ordered_runs(jobs, 2, encoding=Encoding(100)))
    assert [r.unread is not None for _, r in out] == [False, True, False]  # type: ignore[union-attr]
    assert "scene width" in (out[1][1].unread or "")  # type: ignore[union-attr]
    for (_job, run), seed in zip(out[::2], (1, 2)):
        assert run is not None and run.scan is not None and run.result is not None
        assert run.scan.range.tobytes() == sim.simulate(good, seed=seed).scan.range.tobytes()


def test_a_scan_encoded_in_a_worker_is_written_as_the_recorder_writes_it(
        tmp_path: Path) -> None:
    """ScanEncoder is the recorder's own encoding: a scan encoded by run_job and written
    with write_encoded gives the bytes of the recorder as the pipeline's observer."""
    from boxloc.observer import NullObserver
    from boxloc.pipeline import find_graspable_surfaces
    from recorder.mcap.sink import McapRecorder

    jobs = _jobs(2)
    cfg = jobs[0].config
    direct, written = tmp_path / "direct.mcap", tmp_path / "written.mcap"
    with McapRecorder(direct, config=cfg, session="s", max_points=300) as rec:
        for job in jobs:
            find_graspable_surfaces(job.make_scan(), job.config, observer=rec)
    with McapRecorder(written, config=cfg, session="s", max_points=300) as rec:
        for job in jobs:
            run = run_job(job, Encoding(rec.max_points, rec.config))
            assert len(run.encoded) == 1 and run.encoded[0].messages[-1][0] == C.RESULT
            assert run.encoded[0].n_surfaces == len(run.result.surfaces)  # type: ignore[union-attr]
            run.replay(job.make_scan(), NullObserver(), write=rec.write_encoded)
        assert rec.n_scans == 2
    assert _messages(direct) == _messages(written)
    assert open_log(direct).metadata["boxloc.run"]["config_hash"] == \
        open_log(written).metadata["boxloc.run"]["config_hash"]


def test_an_encoded_scan_is_refused_while_the_recorder_has_one_in_progress(
        tmp_path: Path) -> None:
    from recorder.mcap.sink import McapRecorder

    job = _jobs(1)[0]
    run = run_job(job, Encoding(100))
    with McapRecorder(tmp_path / "x.mcap", config=job.config) as rec:
        rec.on_scan(job.make_scan(), job.config)
        with pytest.raises(ValueError, match="in progress"):
            rec.write_encoded(run.encoded[0])


def _garbage(d: Path) -> Path:
    bad = d / "s1b.npz"  # between s1 and s2 in name order
    bad.write_bytes(b"not a zip file")
    return bad


@pytest.mark.parametrize("workers", ["1", "0"])
def test_a_bad_input_among_several_is_reported_and_the_rest_run(
        scans_dir: Path, tmp_path: Path, workers: str) -> None:
    d = tmp_path / "mixed"
    d.mkdir()
    for f in scans_dir.glob("*.npz"):
        (d / f.name).write_bytes(f.read_bytes())
    bad = _garbage(d)
    also_bad = tmp_path / "truncated.npz"
    also_bad.write_bytes((scans_dir / "s0.npz").read_bytes()[:500])
    log = tmp_path / f"mixed{workers}.mcap"
    r = invoke("run", str(d), str(also_bad), str(scans_dir / "s3.npz"), "--record", str(log),
               "-q", "--workers", workers)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    # each bad input named on its own line, the run's error the last line
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert any(str(bad) in ln for ln in lines[:-1])
    assert any(str(also_bad) in ln for ln in lines[:-1])
    assert lines[-1].startswith("boxloc: error: 2 input(s) could not be read")
    # every good scan recorded, in order, numbered without gaps
    good = [d / "s0.npz", d / "s1.npz", d / "s2.npz", d / "s3.npz", scans_dir / "s3.npz"]
    assert _ranges(log) == [io.read_scan(f).range.tobytes() for f in good]
    assert [x.index for x in open_log(log).scans()] == [0, 1, 2, 3, 4]


def test_a_bad_last_input_is_the_runs_one_line_error(scans_dir: Path, tmp_path: Path) -> None:
    bad = _garbage(tmp_path)
    log = tmp_path / "last.mcap"
    r = invoke("run", str(scans_dir / "s0.npz"), str(scans_dir / "s1.npz"), str(bad),
               "--record", str(log), "-q", "--workers", "2")
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    # the summary of what was recorded, then the error, said once
    assert lines[0].startswith("2 scan(s)") and str(log) in lines[0]
    assert len(lines) == 2 and lines[1].startswith(f"boxloc: error: {bad}: ")
    assert len(_ranges(log)) == 2


def test_a_missing_source_is_refused_before_anything_runs(scans_dir: Path,
                                                          tmp_path: Path) -> None:
    log = tmp_path / "never.mcap"
    r = invoke("run", str(scans_dir / "s0.npz"), str(tmp_path / "typo.npz"), "--record",
               str(log), "--workers", "2")
    assert r.returncode == 2
    assert "not found" in r.stderr and "typo.npz" in r.stderr and "Traceback" not in r.stderr
    assert not log.exists()


def test_a_failing_scan_is_recorded_as_in_a_serial_run(scans_dir: Path,
                                                       tmp_path: Path) -> None:
    """A scan the pipeline refuses (no valid range) is that scan's error, the same in both
    logs, and the scans after it run."""
    d = tmp_path / "with_empty"
    d.mkdir()
    s = io.read_scan(scans_dir / "s0.npz")
    empty = Scan(range=np.full(s.shape, np.nan, np.float32), sensor=s.sensor)
    io.write_npz(empty, d / "a_empty.npz")
    (d / "b.npz").write_bytes((scans_dir / "s1.npz").read_bytes())
    logs = {}
    for w in ("1", "2"):
        logs[w] = tmp_path / f"w{w}.mcap"
        r = invoke("run", str(d), "--record", str(logs[w]), "-q", "--workers", w)
        assert r.returncode == 0, r.stderr
        assert "scan 0: failed: InputError: scan has no valid range" in r.stderr
    assert _messages(logs["1"]) == _messages(logs["2"])
    first, second = list(open_log(logs["2"]).scans())
    assert first.error is not None and first.error["error_type"] == "InputError"
    assert second.complete and second.result is not None


@pytest.mark.parametrize("how", ["ctrl-c", "sigterm"])
def test_an_interrupt_leaves_a_complete_log_with_every_scan_started(tmp_path: Path,
                                                                    how: str) -> None:
    """Ctrl-C reaches the whole process group, SIGTERM (a service stopped) the parent: the
    workers ignore both and finish the scans they have, and the parent records them and
    closes the log (exit 130)."""
    log = tmp_path / "interrupted.mcap"
    cmd = [sys.executable, "-m", "boxloc.cli", "run", "sim:single:width=96,height=72,f=80",
           "--count", "2000", "--record", str(log), "--quiet", "--workers", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=ROOT, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            if log.exists() and log.stat().st_size > 150_000:  # a few scans on disk
                break
            time.sleep(0.1)
        assert proc.poll() is None, proc.communicate()
        if how == "ctrl-c":
            os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C does
        else:
            proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    lg = open_log(log)
    assert lg.complete
    recs = list(lg.scans())
    assert 2 <= len(recs) < 2000
    assert [x.index for x in recs] == list(range(len(recs)))  # no gap: in order, all kept
    assert all(x.complete for x in recs)


# --- recorder.stream ------------------------------------------------------------------------


def _jobs(n: int) -> list[Job]:
    return [Job(_scan(k + 1), Config()) for k in range(n)]


def test_a_scan_run_replays_the_pipelines_calls_in_order() -> None:
    from boxloc.pipeline import find_graspable_surfaces
    from boxloc.products import products_equal

    job = _jobs(1)[0]
    run = run_job(job)
    assert run.error is None and run.result is not None
    names = [c[0] for c in run.calls]
    assert names == ["on_scan", "on_noise", "on_edges", "on_lines", "on_vertices",
                     "on_hypotheses", "on_verification", "on_selection", "on_surfaces",
                     "on_result"]

    class Seen:
        def __init__(self) -> None:
            self.calls: list[tuple[str, Scan]] = []

        def __getattr__(self, name: str) -> object:
            return lambda scan, *a: self.calls.append((name, scan))

    seen = Seen()
    result = run.replay(job.scan, seen)  # type: ignore[arg-type]
    assert [c[0] for c in seen.calls] == names and all(c[1] is job.scan for c in seen.calls)
    assert products_equal(result, find_graspable_surfaces(job.scan, Config())) == []


def test_an_error_that_does_not_pickle_keeps_its_name_and_message() -> None:
    class Odd(Exception):
        def __init__(self, a: int, b: int) -> None:  # pickle cannot rebuild it from args
            super().__init__(f"odd {a} {b}")

    e = _portable(Odd(1, 2))
    run = ScanRun((), None, e)
    with pytest.raises(RemoteError, match="odd 1 2") as info:
        run.replay(_scan(1), None)  # type: ignore[arg-type]
    assert type(info.value).__name__ == "Odd"
    assert _portable(InputError("x")).__class__ is InputError  # picklable: itself


def test_results_come_in_item_order_within_the_window() -> None:
    """Items that are not jobs pass through in their place; never more than the window
    is read ahead of what was yielded."""
    jobs = _jobs(5)
    items: list[object] = [jobs[0], "a read error", *jobs[1:3], "another", *jobs[3:]]
    read = 0

    def source() -> object:
        nonlocal read
        for it in items:
            read += 1
            yield it

    got = []
    for item, run in ordered_runs(source(), 2, window=3):
        assert read - len(got) <= 3
        got.append(item)
        assert (run is None) == isinstance(item, str)
        if run is not None:
            assert run.error is None and run.result is not None
            assert run.result.scan_index == item.scan.index  # type: ignore[attr-defined]
    assert got == items


class _ExitOnUnpickle:
    """Kills the worker process that unpickles it (as the OOM killer would)."""

    def __reduce__(self) -> tuple[object, tuple[int]]:
        return (os._exit, (3,))


def test_a_scan_that_kills_its_worker_is_failed_and_the_others_run() -> None:
    a, b, c = _jobs(3)
    deadly = Job(Scan(range=b.scan.range, sensor=b.scan.sensor, index=b.scan.index,
                      meta={"x": _ExitOnUnpickle()}), b.config)
    out = list(ordered_runs([a, deadly, c], 2))
    assert [job.scan.index for job, _ in out] == [a.scan.index, b.scan.index, c.scan.index]
    (_, ra), (_, rb), (_, rc) = out
    assert ra is not None and ra.result is not None and rc is not None and rc.result is not None
    assert rb is not None and isinstance(rb.error, WorkerLost)
    assert "died 2 time(s)" in str(rb.error) and "exit code 3" in str(rb.error)
    assert [c[0] for c in rb.calls] == ["on_scan"]  # recorded as a scan with its error


def test_a_scan_goes_to_its_worker_without_its_caches() -> None:
    """The points and a ray table's search tree are recomputed in the worker (the same):
    they are not pickled; the parent's scan keeps them."""
    import pickle

    from factories import make_scan

    from recorder.stream import _lean

    s = make_scan(0, shape=(48, 64), raytable=True)
    _ = s.points, s.sensor._tree  # type: ignore[attr-defined]
    lean = _lean(s)
    assert "points" not in vars(lean) and "_tree" not in vars(lean.sensor)
    assert "points" in vars(s) and "_tree" in vars(s.sensor)
    assert len(pickle.dumps(lean)) < len(pickle.dumps(s)) / 2
    assert lean.range is s.range and lean.points.tobytes() == s.points.tobytes()


def test_an_encoded_scan_comes_back_without_its_sensors_caches() -> None:
    """What the pipeline cached on a ray table in the worker (its search tree, its pixel
    angle) does not travel back with the encoded scan; the sensor record is the same."""
    from factories import make_scan

    from recorder.mcap import encode as E

    s = make_scan(0, shape=(48, 64), raytable=True)
    run = run_job(Job(s, Config()), Encoding(100))
    cached = {"_tree", "pixel_angle"} & set(vars(s.sensor))
    assert cached  # the pipeline used them
    (enc,) = run.encoded
    assert not cached & set(vars(enc.sensor))
    assert E.encode_sensor(enc.sensor, 0, 0) == E.encode_sensor(s.sensor, 0, 0)


def test_a_full_disk_with_workers_fails_in_one_line_and_keeps_earlier_scans(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The parent writes the log: its write error ends the run as in a serial run (the
    workers are stopped), and the scans written before it are recoverable."""
    from click.testing import CliRunner
    from factories import FullDisk

    from boxloc.cli import cli
    from recorder.mcap.recover import recover_log
    from recorder.mcap.sink import McapRecorder

    monkeypatch.setattr(McapRecorder, "_open_stream", lambda self, p: FullDisk(p, 150_000))
    res = CliRunner().invoke(cli, ["run", "sim:single:width=96,height=72,f=80", "--count",
                                   "50", "--record", str(tmp_path / "x.mcap"), "-q",
                                   "--workers", "2"])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.startswith("boxloc: error")]
    assert len(lines) == 1 and "no space left on device" in lines[0]
    assert "Traceback" not in res.output
    assert recover_log(tmp_path / "x.mcap").scans >= 1
