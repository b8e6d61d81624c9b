"""The suite's rules, and the recorded logs many test files share.

A skip hides breakage: a moved module or a renamed function once turned 52 tests into three
"SKIPPED" lines in a green run. So here a skipped test is a failure, unless it is marked
``real_data``: those read the external mOSD frames (tests/real_data.py), are skipped when
these are absent, and the skip names the missing files. Every other condition a test
needs (root for a tmpfs, Vulkan for the viewer, a git checkout) is one CI provides, and a
test that cannot run where it is run fails, saying why.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

#: tests/test_suite_rules.py runs the rules below on small suites of its own
pytest_plugins = ["pytester"]

#: the one marker whose tests may skip
REAL_DATA = "real_data"


def pytest_runtest_setup(item: pytest.Item) -> None:
    mark = item.get_closest_marker(REAL_DATA)
    if mark is None:
        return
    from real_data import MOSD, missing

    absent = missing(tuple(mark.args))
    if absent:
        pytest.skip(f"real data absent: {', '.join(absent)} not found in {MOSD}")


# --- a skip outside the real-data set fails the run -----------------------------------------


def _reason(report: pytest.CollectReport | pytest.TestReport) -> str:
    lr = report.longrepr
    if isinstance(lr, tuple) and len(lr) == 3:  # (path, line, "Skipped: why")
        return str(lr[2]).removeprefix("Skipped: ")
    return str(lr).strip().splitlines()[-1] if lr else ""


class SkipGuard:
    """Collects the skips outside the real-data set; any turns the exit status into 1."""

    def __init__(self) -> None:
        self.skips: list[tuple[str, str]] = []

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        # on the xdist controller the workers' reports arrive here, keywords included
        if report.skipped and not hasattr(report, "wasxfail") \
                and REAL_DATA not in report.keywords:
            self.skips.append((report.nodeid, _reason(report)))

    def pytest_collectreport(self, report: pytest.CollectReport) -> None:
        # a module that skips itself while it is collected (importorskip at module level)
        if report.skipped:
            self.skips.append((report.nodeid or "<collection>", _reason(report)))

    def pytest_sessionfinish(self, session: pytest.Session) -> None:
        if self.skips and session.exitstatus in (pytest.ExitCode.OK,
                                                 pytest.ExitCode.NO_TESTS_COLLECTED):
            session.exitstatus = pytest.ExitCode.TESTS_FAILED

    def pytest_terminal_summary(self, terminalreporter: Any) -> None:
        if not self.skips:
            return
        terminalreporter.section("skipped outside the real-data set: the run fails", red=True)
        for nodeid, why in self.skips:
            terminalreporter.line(f"SKIPPED (not allowed) {nodeid}: {why}", red=True)
        terminalreporter.line(f"only tests marked {REAL_DATA} may skip (tests/conftest.py)",
                              red=True)


def pytest_configure(config: pytest.Config) -> None:
    if not hasattr(config, "workerinput"):  # on an xdist worker, the controller decides
        config.pluginmanager.register(SkipGuard(), "boxloc-skip-guard")


# --- recorded logs shared by several test files (once per xdist worker) ----------------------


@pytest.fixture(scope="session")
def recorded_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The real pipeline on replay_helpers' six small scenes, default config: test_diff's
    baseline and the log test_explain explains. Read-only: copy it before annotating."""
    import replay_helpers

    return replay_helpers.record(tmp_path_factory.mktemp("recorded") / "base.mcap")


@pytest.fixture(scope="session")
def replay_logs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three logs of two scans each (replay_support.make_logs), for test_replay and
    test_replay_versions. Read-only."""
    from replay_support import make_logs

    return make_logs(tmp_path_factory.mktemp("replay-logs"), n_logs=3, scans_per_log=2)
