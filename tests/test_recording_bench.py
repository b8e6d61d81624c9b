"""The ``recording`` section's throughput figure: ``boxloc run --workers 1`` and ``2`` on the
same scans, each a process tree of its own, with wall and CPU time and the logs compared.

No test here depends on how fast anything is: the figures are checked for what they are
made of, not for their values.
"""

from __future__ import annotations

import sys
from typing import Any

import pytest

from boxloc import simulate as sim
from boxloc.config import Config
from recorder.recording_bench import measure_throughput, run_measured

SPEC = "pallet:width=120,height=90,f=100"


def test_throughput_runs_both_worker_counts_on_the_same_scans_and_compares_the_logs() -> None:
    scans = [sim.simulate(SPEC, seed=k).scan for k in (1, 2, 3)]
    tp = measure_throughput(scans, Config(), rounds=2)
    assert tp["scans"] == 3 and len(tp["rounds"]) == 2
    # the figures are the rounds' medians (of two: their mean), the runs shown the lower one's
    for key in ("speedup", "steady_speedup", "cpu_bound_speedup"):
        vals = [r[key] for r in tp["rounds"] if r[key] is not None]
        if vals:
            assert tp[key] == pytest.approx(sum(vals) / len(vals), abs=1e-3)
    assert tp["speedup_range"] == sorted(r["speedup"] for r in tp["rounds"])
    low = min(tp["rounds"], key=lambda r: r["speedup"])
    assert tp["runs"] == low["runs"]
    for rnd in tp["rounds"]:
        check_round(rnd)
    assert tp["same_log"] is True
    with pytest.raises(ValueError, match="rounds must be >= 1"):
        measure_throughput(scans, Config(), rounds=0)


def check_round(tp: dict[str, Any]) -> None:
    """One round's runs: serial then parallel, each made of what it says."""
    one, two = tp["runs"]
    assert (one["workers"], two["workers"]) == (1, 2)
    # serial: one process; parallel: the parent, the forkserver and its workers at least
    assert one["processes"] == 1 and two["processes"] >= 3
    for r in (one, two):
        assert r["wall_s"] > 0 and r["cpu_s"] > 0
        assert r["scans_per_s"] == pytest.approx(3 / r["wall_s"], rel=1e-2)
        assert r["core_share"] == pytest.approx(
            r["cpu_s"] / (r["wall_s"] * r["workers"]), rel=1e-2)
        # a run of the first W scans: start-up and one scan per worker
        assert 0 < r["first_scans_wall_s"]
        if r["steady_scans_per_s"] is not None:  # None if the difference is not positive
            # from the unrounded times; both reported to the millisecond, so their
            # difference (a few ms on a free machine) is known to +-1 ms only
            diff = r["wall_s"] - r["first_scans_wall_s"]
            n = 3 - r["workers"]
            assert (0.99 * n / (diff + 0.001) <= r["steady_scans_per_s"]
                    <= 1.01 * n / max(diff - 0.001, 1e-9))
    assert tp["speedup"] == pytest.approx(two["scans_per_s"] / one["scans_per_s"], rel=1e-2)
    if tp["steady_speedup"] is not None:
        assert tp["steady_speedup"] == pytest.approx(
            two["steady_scans_per_s"] / one["steady_scans_per_s"], rel=1e-2)
    assert tp["cpu_bound_speedup"] == pytest.approx(2 * one["cpu_s"] / two["cpu_s"], rel=1e-2)


def test_a_run_that_fails_is_an_error_with_its_message() -> None:
    with pytest.raises(RuntimeError, match="no scan files"):
        measure_throughput([], Config())


def test_run_measured_counts_the_cpu_of_processes_the_command_leaves_running() -> None:
    """A grandchild that the command does not wait for (as the workers' forkserver) is
    counted from its own CPU times."""
    # The burner says when it has burnt its 0.4 s of CPU, and the command exits then,
    # leaving it asleep: a busy machine delays the burn, not what is counted.
    burn = ("import sys, time; t = time.process_time()\n"
            "while time.process_time() - t < 0.4: pass\n"
            "print('burnt', flush=True); time.sleep(1.0)")
    start = ("import subprocess, sys; p = subprocess.Popen([sys.executable, '-c', "
             f"{burn!r}], stdout=subprocess.PIPE); p.stdout.readline()")
    r = run_measured([sys.executable, "-c", start])
    assert r["returncode"] == 0 and r["processes"] == 2
    assert r["cpu_s"] >= 0.38


def test_the_matrix_footprint_records_matrix_scenes_at_640x480_and_splits_by_sensor() -> None:
    from recorder.recording_bench import matrix_footprint

    fp = matrix_footprint(n=4)
    assert fp["scans"] == 4 and fp["seed"] == 0
    # the first four matrix scenes: one of each sensor, each a scan's chunk of the log
    assert sorted(fp["by_sensor"]) == ["active-stereo", "laser", "structured-light", "tof"]
    assert fp["median_scan_bytes"] <= fp["max_scan_bytes"] < 4 * fp["bytes_per_scan"]
    assert min(fp["by_sensor"].values()) <= fp["max_scan_bytes"]
    ch = fp["kb_per_scan_by_channel"]
    assert "/scan/range" in ch and "/boxloc/edges" in ch and "/boxloc/tests" in ch
    # every intermediate product is in the log: the stage channels all have bytes
    assert all(ch[t] > 0 for t in ("/boxloc/lines", "/boxloc/vertices", "/boxloc/hypotheses",
                                   "/boxloc/verification", "/boxloc/surfaces"))
