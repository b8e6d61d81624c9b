"""The recorder's verbs (`boxloc run`, `info`, `annotate`, `recover`), pick outcomes, and the
real pipeline end to end."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
from click.testing import CliRunner
from factories import feed, make_result, make_scan

from boxloc import io
from boxloc import simulate as sim
from boxloc.cli import cli
from boxloc.config import Config
from boxloc.errors import LogError
from boxloc.pipeline import find_graspable_surfaces
from boxloc.products import products_equal
from recorder import annotate as A
from recorder.mcap.encode import SCHEMA_VERSION
from recorder.mcap.log import open_log
from recorder.mcap.sink import McapRecorder
from recorder.overhead import measure_overhead

SIM = "sim:single:width=96,height=72,f=80"


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _invoke(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(cli, list(args))
    return res.exit_code, res.output


@pytest.fixture()
def log_path(tmp_path: Path) -> Path:
    path = tmp_path / "log.mcap"
    with McapRecorder(path) as rec:
        for i in range(3):
            s = make_scan(i)
            feed(rec, s, make_result(s, i))
    return path


# --- annotate and outcomes -----------------------------------------------------------------


def test_annotate_never_touches_the_log_and_info_shows_the_outcome(log_path: Path) -> None:
    before = _sha(log_path)
    code, out = _invoke("annotate", str(log_path), "--scan", "1", "--surface", "0",
                        "--pick", "failed", "--reason", "slipped off")
    assert code == 0, out
    code, out = _invoke("annotate", str(log_path), "--scan", "0", "--surface", "2",
                        "--pick", "ok")
    assert code == 0, out
    assert _sha(log_path) == before
    assert A.sidecar_path(log_path).is_file()

    code, out = _invoke("info", str(log_path), "--json")
    assert code == 0, out
    info = json.loads(out)
    latest = {(o["scan_index"], o["surface_id"]): o for o in info["outcomes"]["latest"]}
    assert latest[(1, 0)]["ok"] is False and latest[(1, 0)]["reason"] == "slipped off"
    assert latest[(0, 2)]["ok"] is True and latest[(0, 2)]["origin"] == "sidecar"
    assert info["outcomes"] == {**info["outcomes"], "reports": 2, "ok": 1, "failed": 1}

    code, text = _invoke("info", str(log_path))
    assert code == 0 and "slipped off" in text and "pick outcomes" in text
    assert _sha(log_path) == before


def test_a_later_outcome_replaces_an_earlier_one(log_path: Path) -> None:
    A.append_outcome(log_path, 1, 0, False, "first try")
    A.append_outcome(log_path, 1, 0, True, "second try")
    latest = open_log(log_path).latest_outcomes()
    assert latest[(1, 0)].ok and latest[(1, 0)].reason == "second try"
    assert len(open_log(log_path).outcomes()) == 2


@pytest.mark.parametrize("args,match", [
    (("--scan", "9", "--surface", "0", "--pick", "ok"), "no scan 9"),
    (("--scan", "1", "--surface", "99", "--pick", "ok"), "no surface 99"),
])
def test_annotate_refuses_what_is_not_in_the_log(log_path: Path, args: tuple[str, ...],
                                                 match: str) -> None:
    code, out = _invoke("annotate", str(log_path), *args)
    assert code == 2 and match in out and "Traceback" not in out
    assert not A.sidecar_path(log_path).exists()


def test_annotate_a_missing_log(tmp_path: Path) -> None:
    code, out = _invoke("annotate", str(tmp_path / "nope.mcap"), "--scan", "0", "--surface",
                        "0", "--pick", "ok")
    assert code == 2 and "not found" in out


def test_the_sidecar_survives_a_torn_last_line_and_refuses_garbage(log_path: Path) -> None:
    A.append_outcome(log_path, 1, 0, True)
    side = A.sidecar_path(log_path)
    with open(side, "a") as f:
        f.write('{"v": 1, "scan": 2, "surf')  # a writer killed mid-line
    assert [o.scan_index for o in A.read_sidecar(log_path)] == [1]
    side.write_text('{"v": 1, "scan": 2, "surface": 0, "ok": true}\nnot json\n')
    with pytest.raises(LogError, match=":2: bad outcome line"):
        A.read_sidecar(log_path)
    side.write_text('{"v": 2, "scan": 2, "surface": 0, "ok": true}\n')
    with pytest.raises(LogError, match="version"):
        A.read_sidecar(log_path)


def test_the_robot_reports_outcomes_through_the_recorder(tmp_path: Path) -> None:
    path = tmp_path / "robot.mcap"
    cfg = Config()
    with McapRecorder(path) as rec:
        s0, s1 = make_scan(0), make_scan(1)
        feed(rec, s0, make_result(s0, 0))
        rec.on_scan(s1, cfg)
        rec.record_outcome(0, 0, ok=True)  # while scan 1 runs: goes in with its chunk
        feed(rec, s1, make_result(s1, 1), cfg, start=False)
        rec.record_outcome(1, 1, ok=False, reason="dropped")  # between scans: the sidecar
        with pytest.raises(Exception, match="not recorded"):
            rec.record_outcome(7, 0, ok=True)
    log = open_log(path)
    got = {(o.scan_index, o.surface_id): o for o in log.outcomes()}
    assert got[(0, 0)].ok and got[(0, 0)].origin == "log" and got[(0, 0)].source == "robot"
    assert not got[(1, 1)].ok and got[(1, 1)].origin == "sidecar"


# --- info and recover ----------------------------------------------------------------------


def test_info_shows_scans_channels_versions_time_and_size(log_path: Path) -> None:
    code, out = _invoke("info", str(log_path), "--json")
    assert code == 0
    info = json.loads(out)
    assert info["complete"] and info["scans"]["count"] == 3
    assert [s["index"] for s in info["scans"]["items"]] == [0, 1, 2]
    assert info["versions"]["boxloc_version"] == "0.1.0"
    assert info["versions"]["git_commit"]
    assert info["size_bytes"] == log_path.stat().st_size
    assert info["time_span"]["duration_s"] == pytest.approx(0.2)
    topics = {c["topic"]: c for c in info["channels"]}
    assert topics["/scan/range"]["record"] == f"boxloc.ScanRange/{SCHEMA_VERSION}"
    assert topics["/scan/range/preview"]["schema"] == "foxglove.CompressedImage"
    assert topics["/boxloc/hypotheses"]["record"] == f"boxloc.HypothesisSet/{SCHEMA_VERSION}"
    assert topics["/scan/info"]["messages"] == 3
    code, text = _invoke("info", str(log_path))
    assert code == 0
    for needle in ("complete", "scans: 3", "/boxloc/tests", "boxloc 0.1.0", "config.toml"):
        assert needle in text, needle


def test_info_and_recover_on_a_truncated_log(log_path: Path, tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    data = log_path.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    code, out = _invoke("info", str(cut), "--json")
    assert code == 0
    info = json.loads(out)
    assert not info["complete"] and info["truncated"]
    n = info["scans"]["count"]
    assert 1 <= n < 3
    code, text = _invoke("info", str(cut))
    assert "TRUNCATED" in text
    code, out = _invoke("recover", str(cut))
    assert code == 0 and f"recovered {n} scan(s)" in out
    assert open_log(tmp_path / "cut.recovered.mcap").complete


def test_info_on_something_that_is_not_a_log(tmp_path: Path) -> None:
    p = tmp_path / "x.mcap"
    p.write_bytes(b"hello world, not mcap")
    code, out = _invoke("info", str(p))
    assert code == 2 and "not an MCAP file" in out


# --- run ----------------------------------------------------------------------------------


def test_run_records_a_simulated_session_and_replays_it_exactly(tmp_path: Path) -> None:
    code, out = _invoke("run", SIM, "--count", "2", "--record", str(tmp_path / "rec"),
                        "--rerun", "none", "--seed", "5")
    assert code == 0, out
    (first,) = sorted((tmp_path / "rec").glob("*.mcap"))
    recs = list(open_log(first))
    assert [r.index for r in recs] == [0, 1] and all(r.complete for r in recs)
    # Re-run the recorded scans from the log: the same products, bit for bit.
    code, out = _invoke("run", str(first), "--record", str(tmp_path / "again.mcap"), "-q")
    assert code == 0, out
    again = list(open_log(tmp_path / "again.mcap"))
    for a, b in zip(recs, again):
        assert a.scan.range.tobytes() == b.scan.range.tobytes()
        assert products_equal(a.result, b.result) == []
    assert open_log(tmp_path / "again.mcap").config == open_log(first).config


def test_run_on_scan_files_and_a_directory(tmp_path: Path) -> None:
    d = tmp_path / "scans"
    d.mkdir()
    for i in range(2):
        io.write_npz(make_scan(i, shape=(48, 64)), d / f"s{i}.npz")
    code, out = _invoke("run", str(d / "s0.npz"), "--record", str(tmp_path / "one.mcap"))
    assert code == 0, out
    assert [r.index for r in open_log(tmp_path / "one.mcap")] == [0]
    code, out = _invoke("run", str(d), "--record", str(tmp_path / "dir.mcap"))
    assert code == 0, out
    recs = list(open_log(tmp_path / "dir.mcap"))
    assert [r.index for r in recs] == [0, 1]
    assert recs[1].scan.range.tobytes() == make_scan(1, shape=(48, 64)).range.tobytes()


def test_run_refuses_to_overwrite_and_bad_rerun_targets(tmp_path: Path) -> None:
    p = tmp_path / "x.mcap"
    p.write_bytes(b"keep me")
    code, out = _invoke("run", SIM, "--record", str(p))
    assert code == 2 and "refusing to overwrite" in out
    assert p.read_bytes() == b"keep me"
    code, out = _invoke("run", SIM, "--rerun", "teleport")
    assert code == 2 and "--rerun" in out


def test_run_saves_to_rerun_with_the_target_as_the_next_word(tmp_path: Path) -> None:
    rrd = tmp_path / "out.rrd"
    code, out = _invoke("run", "--rerun", "save", str(rrd), SIM, "--record",
                        str(tmp_path / "r.mcap"), "-q")
    assert code == 0, out
    # the scan went to both: a whole scan in the log, and more than its range image
    # (96 x 72 float32, 27 kB) in the recording
    assert [(r.index, r.complete) for r in open_log(tmp_path / "r.mcap")] == [(0, True)]
    assert rrd.stat().st_size > 96 * 72 * 4


def test_the_real_pipeline_round_trips_through_the_log(tmp_path: Path) -> None:

    scan = sim.simulate("pallet:width=120,height=90,f=100", seed=2).scan
    with McapRecorder(tmp_path / "p.mcap") as rec:
        result = find_graspable_surfaces(scan, Config(), observer=rec)
    (got,) = list(open_log(tmp_path / "p.mcap"))
    assert products_equal(result, got.result) == []
    assert got.timing_ms == result.timing_ms
    assert products_equal(find_graspable_surfaces(got.scan, Config()), result) == []


def test_measure_overhead_reports_time_and_size() -> None:

    scans = [sim.simulate(f"single:width=96,height=72,f=80,seed={i}").scan for i in range(2)]
    r = measure_overhead(scans)
    assert r["scans"] == 2 and r["pixels"] == 96 * 72
    assert r["pipeline_s"] > 0 and r["recorder_s"] > 0 and r["log_bytes"] > 0
    assert 0 < r["max_scan_bytes"] <= r["log_bytes"]
    assert r["recorder_fraction"] == pytest.approx(r["recorder_s"] / r["pipeline_s"])


@pytest.mark.parametrize("argv,expected", [
    (["--rerun", "connect", "rerun+http://127.0.0.1:9876/proxy", "SRC"],
     "SRC|connect rerun+http://127.0.0.1:9876/proxy"),
    (["--rerun", "connect", "SRC"], "SRC|connect"),
    (["--rerun", "connect", "127.0.0.1:9876", "SRC"], "SRC|connect 127.0.0.1:9876"),
    (["SRC", "--rerun", "save", "out.rrd"], "SRC|save out.rrd"),
    (["--rerun", "save", "out.rrd", "SRC"], "SRC|save out.rrd"),
    (["--rerun", "save=out.rrd", "SRC"], "SRC|save out.rrd"),
    (["SRC", "--rerun", "spawn"], "SRC|spawn"),
    (["SRC"], "SRC|none"),
])
def test_the_rerun_option_takes_its_target_as_the_next_word(argv: list[str],
                                                            expected: str) -> None:
    import click

    from recorder.commands import _RerunOption, normalize_rerun

    @click.command()
    @click.argument("source")
    @click.option("--rerun", cls=_RerunOption, default="none")
    def cmd(source: str, rerun: str) -> None:
        click.echo(f"{source}|{normalize_rerun(rerun)}")

    res = CliRunner().invoke(cmd, argv)
    assert res.exit_code == 0, res.output
    assert res.output.strip() == expected
