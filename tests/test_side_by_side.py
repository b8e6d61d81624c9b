"""``replay.side_by_side``: baseline and candidate in one Rerun recording, differences marked.

The ``.rrd`` files are read back by the real ``rerun`` CLI (``rrd verify``, ``rrd print``).
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest
import replay_helpers as helpers
import rerun.blueprint as rrb
from click.testing import CliRunner

from boxloc.cli import cli
from boxloc.config import Config
from boxloc.errors import InputError
from recorder.rerun.sink import rerun_executable
from replay.diff import diff_logs
from replay.side_by_side import (
    BASELINE,
    CANDIDATE,
    DIFF_LOG,
    DIFF_MARKERS,
    log_side_by_side,
    side_by_side_blueprint,
)

ENV = {**os.environ, "RERUN_APP_ONLY": "true"}


def _rerun(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([rerun_executable(), *args], capture_output=True, text=True,
                          timeout=120, env=ENV)


def verify(path: Path) -> None:
    out = _rerun("rrd", "verify", str(path))
    assert out.returncode == 0, (out.stdout + out.stderr)[-2000:]


def entities(path: Path) -> set[str]:
    out = _rerun("rrd", "print", str(path))
    assert out.returncode == 0, out.stderr[-2000:]
    return set(re.findall(r"Chunk\(\S+\) with \d+ rows \([^)]*\) - (\S+) - ", out.stdout))


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("sbs")
    scenes = (0, 3)  # a single box and a small pile; both give surfaces
    return {"base": helpers.record(d / "base.mcap", scenes=scenes),
            # no hypothesis pays for itself: every surface is removed
            "cand": helpers.record(d / "cand.mcap", Config(mdl_k3=1e7), scenes=scenes)}


def test_side_by_side_rrd(logs: dict[str, Path], tmp_path: Path) -> None:
    ld = diff_logs(logs["base"], logs["cand"])
    removed = sum(len(s.surfaces.removed) for s in ld.scans)
    assert removed >= 1, "the scenes no longer give a surface to remove"
    rrd = tmp_path / "sbs.rrd"
    sink = log_side_by_side(logs["base"], logs["cand"], f"save:{rrd}", ld)
    assert sink.urls == {"file": str(rrd)}
    verify(rrd)
    ents = entities(rrd)
    for prefix in (BASELINE, CANDIDATE):
        for path in ("world/points", "world/lines", "world/vertices", "world/surfaces",
                     "scan/range", "scan/edges"):
            assert f"/{prefix}/{path}" in ents, (prefix, path, sorted(ents)[:40])
    # markers on what differs: the removed surfaces, on the baseline's side
    assert f"/{BASELINE}/{DIFF_MARKERS}/outlines" in ents
    assert f"/{BASELINE}/{DIFF_MARKERS}/centers" in ents
    assert DIFF_LOG in ents
    # the blueprint travels with the recording (its own store, in the same file)
    assert "/viewport" in ents and any(e.startswith("/container/") for e in ents)
    # the data: nothing outside the two runs and the differences
    blueprint = ("view", "container", "viewport", "blueprint_panel", "selection_panel",
                 "time_panel")
    assert all(e.split("/")[1] in (BASELINE, CANDIDATE, "diff", "__properties", *blueprint)
               for e in ents if e != "/"), sorted(ents)


def test_diff_is_computed_when_not_given(logs: dict[str, Path], tmp_path: Path) -> None:
    rrd = tmp_path / "b.rrd"
    log_side_by_side(logs["base"], logs["base"], target=None, rerun=f"save {rrd}")
    verify(rrd)
    ents = entities(rrd)
    assert f"/{CANDIDATE}/world/surfaces" in ents
    assert f"/{BASELINE}/{DIFF_MARKERS}/outlines" not in ents  # identical: nothing marked


def test_bad_target_fails_before_reading(tmp_path: Path) -> None:
    missing = tmp_path / "not-read.mcap"  # never opened: the target is refused first
    with pytest.raises(InputError, match=r"\.rrd"):
        log_side_by_side(missing, missing, "save:out.txt")
    with pytest.raises(InputError, match="unknown Rerun target"):
        log_side_by_side(missing, missing, "teleport")
    with pytest.raises(InputError, match="no Rerun target"):
        log_side_by_side(missing, missing)


def _views(node: object) -> list[object]:
    if isinstance(node, rrb.Container):
        return [v for k in node.contents for v in _views(k)]
    return [node]


def test_blueprint_has_both_columns() -> None:
    bp = side_by_side_blueprint()
    left, right = bp.root_container.contents[0].contents  # the two columns, side by side
    for col, prefix in ((left, BASELINE), (right, CANDIDATE)):
        views = _views(col)
        assert {str(v.name).split(":")[0] for v in views} == {prefix}
        assert any(str(v.origin) == f"/{prefix}/scan" for v in views)  # image + markers
    assert [v.name for v in _views(bp.root_container.contents[1])] == ["differences"]


def test_cli_diff_rerun_save(logs: dict[str, Path], tmp_path: Path) -> None:
    rrd = tmp_path / "cli.rrd"
    r = CliRunner().invoke(cli, ["diff", str(logs["base"]), str(logs["cand"]),
                                 "--rerun", "save", str(rrd)])
    assert r.exit_code == 1, r.output  # the surfaces are gone: a regression
    verify(rrd)
    assert f"/{CANDIDATE}/world/surfaces" in entities(rrd)
