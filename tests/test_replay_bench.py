"""The ``replay`` section of ``boxloc bench`` (and ``boxloc bench --replay``), scaled down:
the real section replays 50 logs twice, which is a benchmark, not a test."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

import replay.replay_bench as rb
from boxloc.cli import cli


@pytest.fixture()
def small(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(rb, "N_LOGS", 3)
    monkeypatch.setattr(rb, "SCANS_PER_LOG", 1)
    monkeypatch.setattr(rb, "WIDTH", 160)
    monkeypatch.setattr(rb, "HEIGHT", 120)


@pytest.mark.timeout(300)
def test_bench_replay_runs_only_the_replay_section(small: None, tmp_path: Path) -> None:
    res = CliRunner().invoke(cli, ["bench", "--replay", "--seed", "3", "--out", str(tmp_path)],
                             catch_exceptions=False)
    assert res.exit_code == 0, res.stderr
    report = json.loads((tmp_path / "bench.json").read_text())
    assert report["errors"]["total"] == 0, report["errors"]
    assert "summary" not in report  # no scenes were scored
    sec = report["sections"]["replay"]
    assert sec["n_logs"] == 3 and sec["resolution"] == "160x120"
    for run, jobs in (("jobs_1", 1), ("jobs_2", 2)):
        r = sec[run]
        assert r["jobs"] == jobs and r["errors"] == 0 and r["failed_scans"] == 0
        assert r["wall_s"] > 0 and r["logs_per_s"] == pytest.approx(3 / r["wall_s"], rel=0.01)
        assert 0 < r["core_share"] <= 2.0  # (1 per worker process, plus timer noise)
    assert sec["speedup_2_over_1"] == pytest.approx(
        sec["jobs_1"]["wall_s"] / sec["jobs_2"]["wall_s"], rel=0.01)
    assert sec["pass"] == (sec["speedup_2_over_1"] >= 1.8)
    assert "section: replay" in res.stderr
    assert not list(tmp_path.glob("replay-bench*"))  # its scratch logs are gone
