"""The same replay on local processes and on a Dask cluster: the same results, in the same
order, and a worker lost mid-task is retried with an identical result."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner
from replay_support import KillAlways, KillOnce, make_logs, product_differences

from boxloc.cli import cli
from boxloc.errors import InputError
from replay.executors import run_dask, run_local, run_serial
from replay.replay import ReplayJob, ReplayOutcome

# The scheduler always serves HTTP (health, metrics; no dashboard here) on 127.0.0.1, trying
# port 8787 first; when another cluster has it, it takes a free port and says so.
pytestmark = pytest.mark.filterwarnings("ignore:Port 8787 is already in use")


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return make_logs(tmp_path_factory.mktemp("logs"), n_logs=4, scans_per_log=1)


def _job(out: Path) -> ReplayJob:
    return ReplayJob(out_dir=str(out))


def _same(outcomes: list[ReplayOutcome], logs: list[Path], out: Path) -> None:
    """Outcomes in input order, all fine, and every new log equal to its input."""
    assert [o.input for o in outcomes] == [str(p) for p in logs]
    for o, log in zip(outcomes, logs):
        assert o.status == "ok", o.error
        assert o.output == str(out / log.name)
        assert product_differences(log, out / log.name) == []
    assert not list(out.glob(".*")), "temporary files left behind"


def _summary(outcomes: list[ReplayOutcome]) -> list[tuple]:
    return [(Path(o.input).name, o.status, o.scans, o.config_hash) for o in outcomes]


def test_two_local_jobs_give_the_serial_results(logs: list[Path], tmp_path: Path) -> None:
    serial = run_serial(logs, _job(tmp_path / "s"))
    two = run_local(logs, _job(tmp_path / "p"), 2)
    _same(serial, logs, tmp_path / "s")
    _same(two, logs, tmp_path / "p")
    assert _summary(two) == _summary(serial)
    for log in logs:
        assert product_differences(tmp_path / "s" / log.name, tmp_path / "p" / log.name) == []


@pytest.mark.timeout(120)
def test_a_killed_local_worker_is_retried(logs: list[Path], tmp_path: Path) -> None:
    marks = tmp_path / "marks"
    marks.mkdir()
    out = tmp_path / "out"
    fn = KillOnce(_job(out), victim=logs[1].name, marker_dir=str(marks))
    outcomes = run_local(logs, fn, 2)
    assert (marks / f"{logs[1].name}.killed").exists()  # the worker really died once
    _same(outcomes, logs, out)


@pytest.mark.timeout(120)
def test_a_log_that_keeps_killing_workers_is_an_error(logs: list[Path],
                                                      tmp_path: Path) -> None:
    out = tmp_path / "out"
    fn = KillAlways(_job(out), victim=logs[2].name)
    outcomes = run_local(logs, fn, 2, retries=1)
    bad = outcomes[2]
    assert bad.status == "error" and "worker process died 2 times" in bad.error
    assert str(logs[2]) in bad.error
    rest = [o for i, o in enumerate(outcomes) if i != 2]
    _same(rest, [p for i, p in enumerate(logs) if i != 2], out)


# --- Dask ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cluster() -> Iterator[str]:
    """A two-process Dask cluster on 127.0.0.1, closed after the tests."""
    from distributed import LocalCluster

    lc = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None, silence_logs=40)
    try:
        yield lc.scheduler_address
    finally:
        lc.close(timeout=30)


@pytest.mark.timeout(180)
def test_dask_gives_the_local_results(cluster: str, logs: list[Path], tmp_path: Path) -> None:
    assert cluster.startswith("tcp://127.0.0.1:")
    local = run_local(logs, _job(tmp_path / "l"), 1)
    dask = run_dask(logs, _job(tmp_path / "d"), cluster)
    _same(dask, logs, tmp_path / "d")
    assert _summary(dask) == _summary(local)


@pytest.mark.timeout(180)
def test_a_lost_dask_worker_is_retried(cluster: str, logs: list[Path], tmp_path: Path) -> None:
    marks = tmp_path / "marks"
    marks.mkdir()
    out = tmp_path / "out"
    fn = KillOnce(_job(out), victim=logs[0].name, marker_dir=str(marks))
    outcomes = run_dask(logs, fn, cluster)
    assert (marks / f"{logs[0].name}.killed").exists()
    _same(outcomes, logs, out)


@pytest.mark.timeout(180)
def test_cli_on_a_dask_scheduler(cluster: str, logs: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["replay", str(logs[0].parent), "--out", str(out),
                                   "--scheduler", cluster, "-q"], catch_exceptions=False)
    assert res.exit_code == 0, res.stderr + res.stdout
    for log in logs:
        assert product_differences(log, out / log.name) == []


def test_unreachable_scheduler_is_a_clear_error(logs: list[Path], tmp_path: Path) -> None:
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(InputError, match="cannot connect to the Dask scheduler"):
        run_dask(logs, _job(tmp_path), f"tcp://127.0.0.1:{port}", timeout_s=2)
    assert not (tmp_path / logs[0].name).exists()
