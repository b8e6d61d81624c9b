"""Replay of recorded logs with the current code: determinism, inputs untouched, config
overrides, a crashing stage, bad logs, and the ``boxloc replay`` verb."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner
from replay_support import make_log, product_differences, snapshot

from boxloc.cli import cli
from boxloc.config import Config
from boxloc.errors import InputError
from recorder.mcap import encode as E
from recorder.mcap.channels import scan_log_time
from recorder.mcap.log import open_log
from recorder.mcap.sink import McapRecorder, git_info
from replay.replay import (
    REPLAY_METADATA,
    ReplayOutcome,
    collect_logs,
    iter_input_scans,
    plan_outputs,
    replay_log,
)


@pytest.fixture(scope="module")
def logs(replay_logs: list[Path]) -> list[Path]:
    """Three recorded logs of two scans each (read-only for the tests; tests/conftest.py)."""
    return replay_logs


def _run(*args: str) -> object:
    return CliRunner().invoke(cli, list(args), catch_exceptions=False)


# --- determinism -----------------------------------------------------------------------------


def test_replay_reproduces_every_product_bit_for_bit(logs: list[Path], tmp_path: Path) -> None:
    before = snapshot(logs)
    n_surfaces = 0
    for log in logs:
        o = replay_log(log, out_dir=tmp_path)
        assert o.status == "ok" and o.error is None, o
        assert o.output == str(tmp_path / log.name)
        assert o.n_scans == 2 and [s.index for s in o.scans] == [0, 1]
        assert all(s.ok and s.error is None for s in o.scans)
        n_surfaces += sum(s.n_surfaces for s in o.scans)
        recs = list(open_log(o.output).scans())
        assert all(len(r.products["lines"]) > 0 and len(r.products["vertices"]) > 0
                   for r in recs)
        # the Hough trials were seeded from the scan content, not from the clock
        assert all(r.products["lines"].seed == r.scan.seed for r in recs)
        # same products, same seeds, same config hash, same log times (from capture times)
        assert product_differences(log, Path(o.output)) == []
    assert n_surfaces >= 1  # the scans found something: the comparison is not vacuous
    # the inputs were only read
    assert snapshot(logs) == before


def test_a_log_of_another_draw_replays_with_that_draw(tmp_path: Path) -> None:
    # the recorded config carries trial_seed, so the replay draws the same trials
    log = make_log(tmp_path / "draw2.mcap", [5], config=Config(trial_seed=2))
    o = replay_log(log, out_dir=tmp_path / "out")
    assert o.status == "ok", o
    recs = list(open_log(o.output).scans())
    assert recs[0].products["lines"].seed == Config(trial_seed=2).seed_for(recs[0].scan.seed)
    assert product_differences(log, Path(o.output)) == []
    # replayed with the scan's own draw, the trials (so the lines) differ
    o0 = replay_log(log, out_dir=tmp_path / "out0", overrides=["trial_seed=0"])
    assert any("lines" in d for d in product_differences(log, Path(o0.output)))


def test_replayed_log_carries_its_own_version_metadata(logs: list[Path],
                                                        tmp_path: Path) -> None:
    o = replay_log(logs[0], out_dir=tmp_path)
    new = open_log(o.output)
    commit, dirty = git_info()
    assert new.run["git_commit"] == commit and new.run["git_dirty"] == dirty
    assert new.run["config_hash"] == open_log(logs[0]).run["config_hash"] == o.config_hash
    md = new.metadata[REPLAY_METADATA]
    assert md["input"] == str(logs[0].resolve())
    assert md["input_sha256"] == snapshot([logs[0]])[str(logs[0])][0]
    assert md["config_source"] == "log" and json.loads(md["overrides"]) == []
    assert json.loads(md["replay_version"])["kind"] == "current"
    assert o.version["kind"] == "current" and o.version["git_commit"] == commit
    # JSON round trip of the outcome (what a revision's subprocess sends back)
    assert ReplayOutcome.from_dict(json.loads(json.dumps(o.to_dict()))) == o


def test_config_override_changes_the_results(logs: list[Path], tmp_path: Path) -> None:
    # A huge per-model MDL cost: no surface is worth its parameters any more.
    o = replay_log(logs[0], out_dir=tmp_path, overrides=["mdl_k3=1000000.0"])
    assert o.status == "ok"
    assert all(s.ok and s.n_surfaces == 0 for s in o.scans)
    diffs = product_differences(logs[0], Path(o.output))
    assert any("selection" in d for d in diffs) and any("surfaces" in d for d in diffs)
    assert not any("edges" in d or "lines" in d for d in diffs)  # earlier stages unchanged
    new = open_log(o.output)
    assert new.config.mdl_k3 == 1000000.0 and o.config_hash == new.config.hash
    assert json.loads(new.metadata[REPLAY_METADATA]["overrides"]) == ["mdl_k3=1000000.0"]


def test_given_config_replaces_the_recorded_one(logs: list[Path], tmp_path: Path) -> None:
    cfg = Config().with_overrides(["mdl_k3=1000000.0"])
    o = replay_log(logs[0], out_dir=tmp_path, config=cfg)
    assert o.config_hash == cfg.hash and all(s.n_surfaces == 0 for s in o.scans)
    assert open_log(o.output).metadata[REPLAY_METADATA]["config_source"] == "given"


def test_bad_override_is_the_outcome_error(logs: list[Path], tmp_path: Path) -> None:
    o = replay_log(logs[0], out_dir=tmp_path, overrides=["no_such_key=1"])
    assert o.status == "error" and "unknown config key" in o.error
    assert str(logs[0]) in o.error
    assert list(tmp_path.iterdir()) == []


def test_a_crashing_stage_is_that_scans_result(logs: list[Path], tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    import boxloc.pipeline as pipeline

    real = pipeline.find_vertices

    def flaky(lines, *, config, up=None):  # type: ignore[no-untyped-def]
        if flaky.calls == 1:  # the second scan
            flaky.calls += 1
            raise RuntimeError("vertex stage exploded")
        flaky.calls += 1
        return real(lines, config=config, up=up)

    flaky.calls = 0  # type: ignore[attr-defined]
    monkeypatch.setattr(pipeline, "find_vertices", flaky)
    o = replay_log(logs[0], out_dir=tmp_path)
    assert o.status == "ok" and o.n_scans == 2 and o.n_failed == 1
    ok, bad = o.scans
    assert ok.ok and not bad.ok
    assert "RuntimeError: vertex stage exploded" in bad.error
    recs = list(open_log(o.output).scans())
    assert recs[0].error is None and recs[0].complete
    assert recs[1].error["stage"] == "vertices"
    assert recs[1].error["error_type"] == "RuntimeError"
    assert set(recs[1].products) == {"noise", "edges", "lines"}  # what ran before the crash


# --- outputs are never overwritten -----------------------------------------------------------


def test_existing_output_is_never_overwritten(logs: list[Path], tmp_path: Path) -> None:
    first = replay_log(logs[0], out_dir=tmp_path)
    kept = snapshot([Path(first.output)])
    again = replay_log(logs[0], out_dir=tmp_path)
    assert again.status == "error" and "refusing to overwrite" in again.error
    assert snapshot([Path(first.output)]) == kept
    assert sorted(p.name for p in tmp_path.iterdir()) == [logs[0].name]  # no leftovers
    with pytest.raises(InputError, match="exists; refusing to overwrite"):
        plan_outputs([logs[0]], tmp_path)


def test_output_names_are_unique_and_never_an_input(logs: list[Path], tmp_path: Path) -> None:
    other = tmp_path / "other"
    other.mkdir()
    twin = shutil.copy(logs[0], other / logs[0].name)
    assert plan_outputs([logs[0], Path(twin)], tmp_path / "out") == ["log0.mcap", "log0-1.mcap"]
    with pytest.raises(InputError, match="over an input log"):
        plan_outputs([logs[0]], logs[0].parent)


def test_collect_logs(logs: list[Path], tmp_path: Path) -> None:
    assert collect_logs([logs[0].parent]) == sorted(logs)
    assert collect_logs([logs[1], logs[1].parent]) == [logs[1], logs[0], logs[2]]
    with pytest.raises(InputError, match="log not found"):
        collect_logs([tmp_path / "nope.mcap"])
    with pytest.raises(InputError, match="no .mcap logs"):
        collect_logs([tmp_path])


# --- bad logs --------------------------------------------------------------------------------


@pytest.fixture()
def bad_logs(logs: list[Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A directory with a good log and one of each kind of bad log."""
    d = tmp_path / "in"
    d.mkdir()
    shutil.copy(logs[0], d / "a_good.mcap")
    data = logs[1].read_bytes()
    (d / "b_truncated.mcap").write_bytes(data[: len(data) // 2])
    chunk = open_log(logs[1]).summary.chunk_indexes[0]
    broken = bytearray(data)
    at = chunk.chunk_start_offset + chunk.chunk_length // 2
    broken[at : at + 64] = bytes(64)  # zeros inside the compressed records of scan 0
    (d / "c_corrupt.mcap").write_bytes(bytes(broken))
    (d / "d_not_mcap.mcap").write_text("this is not a log\n")
    McapRecorder(d / "e_empty.mcap", config=Config(), fsync=False).finish()
    # A log from a future boxloc: every record and the metadata say schema 2.0.
    monkeypatch.setattr(E, "SCHEMA_MAJOR", 2)
    monkeypatch.setattr(E, "SCHEMA_VERSION", "2.0")
    make_log(d / "f_future.mcap", [7])
    monkeypatch.undo()
    return d


def test_bad_logs_are_reported_and_the_others_replayed(bad_logs: Path, tmp_path: Path) -> None:
    ins = sorted(bad_logs.iterdir())
    before = snapshot(ins)
    out = tmp_path / "out"
    res = _run("replay", str(bad_logs), "--out", str(out), "--jobs", "1", "-q", "--no-diff")
    err = res.stderr
    assert res.exit_code == 2, err
    assert "Traceback" not in err
    lines = err.splitlines()

    def line_of(name: str) -> str:
        hits = [ln for ln in lines if name in ln]
        assert hits, f"{name} not reported in:\n{err}"
        return hits[0]

    assert "error" in line_of("b_truncated.mcap") and "truncated log" in line_of("b_truncated")
    assert "boxloc recover" in line_of("b_truncated.mcap")
    assert "damaged" in line_of("c_corrupt.mcap")
    assert "not an MCAP file" in line_of("d_not_mcap.mcap")
    assert line_of("e_empty.mcap").startswith("warning:") and "no scans" in line_of("e_empty")
    assert "schema version 2.0" in line_of("f_future.mcap")
    assert "reads version 1" in line_of("f_future.mcap")
    assert "a_good.mcap" not in "\n".join(ln for ln in lines if "error" in ln)
    # only the good log was published; no temporary files left; inputs untouched
    assert sorted(p.name for p in out.iterdir()) == ["a_good.mcap", "replay.json"]
    assert product_differences(bad_logs / "a_good.mcap", out / "a_good.mcap") == []
    assert snapshot(ins) == before
    doc = json.loads((out / "replay.json").read_text())
    status = {Path(d["input"]).name: ReplayOutcome.from_dict(d).status for d in doc["logs"]}
    assert status == {"a_good.mcap": "ok", "b_truncated.mcap": "error",
                      "c_corrupt.mcap": "error", "d_not_mcap.mcap": "error",
                      "e_empty.mcap": "skipped", "f_future.mcap": "error"}


def test_empty_log_alone_is_a_warning_not_an_error(bad_logs: Path, tmp_path: Path) -> None:
    res = _run("replay", str(bad_logs / "e_empty.mcap"), "--out", str(tmp_path / "o"), "-q")
    assert res.exit_code == 0, res.stderr
    assert "warning:" in res.stderr and "no scans" in res.stderr


# --- the verb --------------------------------------------------------------------------------


def test_cli_replay_same_code_exits_0(logs: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "out"
    res = _run("replay", *map(str, logs), "--out", str(out), "--jobs", "1", "-q")
    assert res.exit_code == 0, res.stderr + res.stdout
    for log in logs:
        assert product_differences(log, out / log.name) == []
    assert (out / "replay.json").is_file()


def test_cli_override_regression_exits_1(logs: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "out"
    res = _run("replay", str(logs[0]), "--out", str(out), "--jobs", "1", "-q",
               "--set", "mdl_k3=1000000.0")
    assert res.exit_code == 1, res.stderr + res.stdout
    assert open_log(out / logs[0].name).config.mdl_k3 == 1000000.0


@pytest.mark.parametrize(("args", "message"), [
    (["nope.mcap"], "log not found"),
    (["{log}", "--set", "nonsense=1"], "unknown config key"),
    (["{log}", "--set", "alpha"], "override must be key=value"),
    (["{log}", "--config", "missing.toml"], "config file not found"),
    (["{log}", "--jobs", "0"], "--jobs must be >= 1"),
    (["{log}", "--scheduler", "localhost"], "--scheduler must be an address"),
    (["{log}", "--rerun", "sideways"], "--rerun must be one of"),
])
def test_cli_bad_input_is_one_line_before_any_work(logs: list[Path], tmp_path: Path,
                                                   args: list[str], message: str) -> None:
    out = tmp_path / "out"
    argv = [a.format(log=logs[0]) for a in args]
    res = _run("replay", *argv, "--out", str(out), "-q")
    assert res.exit_code == 2
    assert message in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert not out.exists() or list(out.iterdir()) == []


def test_cli_refuses_an_existing_output_before_any_work(logs: list[Path],
                                                        tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / logs[1].name).write_text("precious")
    res = _run("replay", *map(str, logs), "--out", str(out), "-q")
    assert res.exit_code == 2 and "refusing to overwrite" in res.stderr
    assert sorted(p.name for p in out.iterdir()) == [logs[1].name]
    assert (out / logs[1].name).read_text() == "precious"


def test_cli_rerun_saves_the_side_by_side_view(logs: list[Path], tmp_path: Path) -> None:
    rrd = tmp_path / "side.rrd"
    res = _run("replay", str(logs[0]), "--out", str(tmp_path / "out"), "--jobs", "1", "-q",
               "--rerun", "save", str(rrd))
    assert res.exit_code == 0, res.stderr
    assert rrd.is_file() and rrd.stat().st_size > 1000
    assert "side by side" in res.stderr


SAMPLE_LOGS = sorted((Path(__file__).resolve().parent.parent / "logs").glob("*.mcap"))


def test_the_sample_logs_are_in_the_repository() -> None:
    # they are committed (logs/README.md); an empty list would leave the test below nothing
    assert {p.name for p in SAMPLE_LOGS} >= {"mixed-640x480.mcap", "pallet-320x240.mcap"}


@pytest.mark.parametrize("sample", SAMPLE_LOGS, ids=[p.name for p in SAMPLE_LOGS])
def test_sample_logs_replay_bit_for_bit(sample: Path, tmp_path: Path) -> None:
    """On the repository's sample logs: a log recorded by this code (the replay of the
    sample) replays to the same products, bit for bit; the sample itself too when this
    clean checkout is the commit that recorded it. The sample is never modified."""
    before = snapshot([sample])
    first = replay_log(sample, out_dir=tmp_path / "a")
    assert first.status == "ok", first.error
    assert first.n_scans == len(open_log(sample).index()) >= 1
    second = replay_log(first.output, out_dir=tmp_path / "b")
    assert second.status == "ok", second.error
    assert product_differences(Path(first.output), Path(second.output)) == []
    commit, dirty = git_info()
    if open_log(sample).run.get("git_commit") == commit and dirty == "false" \
            and open_log(sample).run.get("git_dirty") == "false":
        assert product_differences(sample, Path(first.output)) == []
    # the scans (the inputs: the sample's products may be of an older schema) are the
    # recorded ones, bit for bit, at the same log times
    ins = list(iter_input_scans(open_log(sample)))
    outs = list(open_log(first.output).scans())
    assert len(ins) == len(outs)
    for a, b in zip(ins, outs):
        assert a.range.tobytes() == b.scan.range.tobytes() and a.seed == b.scan.seed
        assert a.sensor.rays().tobytes() == b.scan.sensor.rays().tobytes()
        assert scan_log_time(a.capture_time_ns, a.index) == b.log_time_ns
    assert snapshot([sample]) == before
