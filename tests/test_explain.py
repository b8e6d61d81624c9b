"""``replay.explain`` / ``boxloc explain``: the decision chain of a surface, read from a log.

The chain is checked against the products of the log itself (every id and test in an
explanation must be the log's), on small simulated scans (tests/replay_helpers.py).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import replay_helpers as helpers
from click.testing import CliRunner

from boxloc.cli import cli
from boxloc.errors import InputError, LogError
from boxloc.products import DimensionSource
from boxloc.stats import TestKind
from recorder.annotate import append_outcome
from recorder.mcap.log import open_log
from replay.explain import explain, format_explanation

VERTEX_TESTS = {"LINES_MEET", "LINES_ORTHOGONAL", "AT_SEGMENT_ENDS"}
DIAGONAL_TESTS = {"COPLANAR", "PARALLEL", "FIRST_QUADRANT"}
STOPS = {"scan", "edges", "lines", "vertices", "dimensions", "verification", "selection",
         "ambiguous"}


@pytest.fixture(scope="module")
def log(recorded_log: Path) -> Path:
    return recorded_log  # replay_helpers' scenes, default config (tests/conftest.py)


@pytest.fixture(scope="module")
def records(log: Path) -> dict[int, Any]:
    recs = {r.index: r for r in open_log(log).scans()}
    assert sum(len(r.surfaces) for r in recs.values()) >= 1, "no surface found in the scenes"
    return recs


def _surfaces(records: dict[int, Any]) -> list[tuple[int, int]]:
    return [(i, k) for i, r in sorted(records.items()) for k in range(len(r.surfaces))]


def test_chosen_surface_chain_matches_the_log(log: Path, records: dict[int, Any]) -> None:
    sources = set()
    for i, k in _surfaces(records):
        r = records[i]
        H, V, L, S = (r.products[s] for s in ("hypotheses", "vertices", "lines", "surfaces"))
        sel = r.products["selection"]
        d = explain(log, i, surface=k)
        assert d["mode"] == "surface" and len(d["surfaces"]) == 1
        e = d["surfaces"][0]
        h, j = int(S.hypothesis[k]), int(S.attempt[k])
        assert e["hypothesis"]["id"] == h and e["attempt"] == j
        # the generating vertex and its two lines, with support, trial and votes
        v = e["hypothesis"]["vertex"]
        assert v["id"] == int(H.vertex[h])
        assert v["parent"] == int(V.parent[v["id"]])
        if v["parent"] >= 0:  # a neighbour's corner: its parent's seam side, no lines
            assert v["lines"] == [] and v["parent_side"] in range(4)
            assert {t["kind"] for t in v["tests"]} == {"NEIGHBOUR_CORNER"}
            assert all(t["a"] == v["parent"] for t in v["tests"])
            continue
        assert {ln["id"] for ln in v["lines"]} == {int(V.line_a[v["id"]]),
                                                  int(V.line_b[v["id"]])}
        for ln in v["lines"]:
            assert ln["n_support"] == int(L.n_support[ln["id"]]) > 0
            assert ln["trial"] == int(L.trial[ln["id"]])
            assert ln["direction_votes"] == pytest.approx(float(L.direction_votes[ln["id"]]))
        # the vertex tests: all three kinds, on this pair, all accepted (it is a vertex)
        assert {t["kind"] for t in v["tests"]} == VERTEX_TESTS
        assert all(t["accepted"] for t in v["tests"])
        assert all({t["a"], t["b"]} == {v["line_a"], v["line_b"]} for t in v["tests"])
        # where the dimensions came from
        dims = e["hypothesis"]["dimensions"]
        src = DimensionSource(int(H.att_source[j])).name
        sources.add(src)
        assert dims["source"] == src
        if src == "VERTICES":
            g = dims["diagonal"]
            assert g["vertex"] == int(H.att_diagonal[j])
            assert {t["kind"] for t in g["tests"]} == DIAGONAL_TESTS
            assert all(t["accepted"] for t in g["tests"])
        elif src == "EDGES":
            used = [t for t in dims["edges"]["edge_support"] if t.get("used")]
            assert len(used) == 1 and used[0]["accepted"]
            assert used[0]["statistic"] > used[0]["critical"]  # |P_f| > p
            assert dims["edges"]["peaks_x"] and dims["edges"]["peaks_y"]
        else:  # a far side from a seam or from the plane's extent: the tests that gave it
            key = {"SEAMS": "seams", "EXTENT": "extent"}[src]
            assert dims["edges"][key]
            if src == "SEAMS":  # the text names each seam's axis and its test
                text = format_explanation(d)
                for t in dims["edges"]["seams"]:
                    assert f"SEAM_PEAK {t['a']},{t['b']}:" in text
                assert "seam along " in text
            assert not any(t.get("used") for t in dims["edges"]["edge_support"])
        # every attempt of the hypothesis, the surface's own one accepted with its tests
        atts = {a["id"]: a for a in e["hypothesis"]["attempts"]}
        assert set(atts) == set(np.flatnonzero(H.att_hypothesis == h).tolist())
        mine = atts[j]["verification"]
        assert mine["accepted"] and mine["reason"] == "ACCEPTED"
        kinds = {t["kind"] for t in mine["tests"]}
        assert {"VERIFY_INLIERS", "VERIFY_MEAN", "VERIFY_BOUNDARY"} <= kinds
        for t in mine["tests"]:
            assert t["a"] == j and TestKind[t["kind"]] >= TestKind.VERIFY_INLIERS
        for a in atts.values():
            if not a["verified"]:
                assert a["verification"]["reason"] != "ACCEPTED"
        # the MDL: q_ii and the competition, as in the log's Selection
        s = e["selection"]
        c = int(np.flatnonzero(sel.candidates == j)[0])
        assert s["chosen"] and s["q_ii"] == pytest.approx(float(sel.Q[c, c]))
        for o in s["overlapping"]:
            assert o["q_ij"] == pytest.approx(float(sel.Q[c, o["candidate"]])) != 0.0
            assert o["beaten_by_this"] == (int(sel.beaten_by[o["candidate"]]) == c)
        # and the text says all of it
        text = format_explanation(d)
        assert f"generating vertex V{v['id']}" in text
        assert all(f"L{ln['id']}" in text for ln in v["lines"])
        assert f"dimensions from {src}" in text and "MDL selection" in text
        assert "LINES_ORTHOGONAL" in text and "VERIFY_INLIERS" in text
    assert sources  # at least one source covered (both, with the current scenes)


def test_every_surface_by_default(log: Path, records: dict[int, Any]) -> None:
    i = next(i for i, r in records.items() if len(r.surfaces))
    d = explain(log, i)
    assert [e["surface"] for e in d["surfaces"]] == list(range(len(records[i].surfaces)))


def test_at_a_missed_box_says_where_the_chain_stopped(log: Path) -> None:
    missed = helpers.missed_faces(log)
    assert missed, "every exposed face was found: the test needs a missed one"
    stops = set()
    for i, f, sim in missed[:6]:
        uv = sim.scan.sensor.project(sim.truth.centers[f][None])[0]
        d = explain(log, i, at=f"{uv[0]:.1f},{uv[1]:.1f}")
        a = d["at"]
        assert a["where"]["pixel"] == [int(round(uv[0])), int(round(uv[1]))]
        assert a["stopped_at"] in STOPS | {"chosen"} and a["why"]
        stops.add(a["stopped_at"])
        text = format_explanation(d)
        assert f"the chain stopped at: {a['stopped_at'].upper()}" in text
        assert a["why"][:40] in text
        if a["stopped_at"] == "verification":
            assert all(not at["verified"] for at in a["attempts"])
            assert "failed verification" in a["why"]
        if a["stopped_at"] == "vertices":
            assert a["lines"] and "form no vertex" in a["why"]
        if a["stopped_at"] == "selection":
            assert "lost the MDL selection" in a["why"]
        # the same place given as a point in the sensor frame: the same answer
        P = sim.truth.centers[f]
        d3 = explain(log, i, at=tuple(float(x) for x in P))
        assert d3["at"]["stopped_at"] == a["stopped_at"]
    assert stops - {"chosen"}, "no missed face was explained as missed"


def test_at_a_chosen_surface(log: Path, records: dict[int, Any]) -> None:
    i, k = _surfaces(records)[0]
    r = records[i]
    c = r.surfaces.centers[k]
    uv = r.scan.sensor.project(c[None])[0]
    d = explain(log, i, at=(float(uv[0]), float(uv[1])))
    assert d["at"]["stopped_at"] == "chosen" and d["at"]["surface"] == k
    assert d["at"]["explanation"]["surface"] == k


def test_json_output_is_valid(log: Path, records: dict[int, Any]) -> None:
    i, k = _surfaces(records)[0]
    run = CliRunner().invoke
    r = run(cli, ["explain", str(log), "--scan", str(i), "--surface", str(k), "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert d["surfaces"][0]["surface"] == k
    missed = helpers.missed_faces(log)[0]
    r = run(cli, ["explain", str(log), "--scan", str(missed[0]), "--at", "80,60", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["at"]["stopped_at"]
    r = run(cli, ["explain", str(log), "--scan", str(i), "--surface", str(k)])
    assert r.exit_code == 0 and "generating vertex" in r.stdout


def test_failed_picks(log: Path, records: dict[int, Any], tmp_path: Path) -> None:
    i, k = _surfaces(records)[0]
    lg = tmp_path / "picked.mcap"
    shutil.copyfile(log, lg)
    d = explain(lg, i, failed_picks=True)
    assert d["surfaces"] == []
    assert "no failed pick" in format_explanation(d)
    append_outcome(lg, i, k, False, "suction lost")
    d = explain(lg, i, failed_picks=True)
    assert [e["surface"] for e in d["surfaces"]] == [k]
    assert d["surfaces"][0]["pick"]["reason"] == "suction lost"
    assert "pick FAILED: suction lost" in format_explanation(d)


def test_bad_requests(log: Path, records: dict[int, Any]) -> None:
    i = next(iter(records))
    n = len(records[i].surfaces)
    with pytest.raises(InputError, match=f"has {n} surface"):
        explain(log, i, surface=n)
    with pytest.raises(InputError, match="only one of"):
        explain(log, i, surface=0, at="1,2")
    with pytest.raises(InputError, match="outside"):
        explain(log, i, at="1000,1000")
    with pytest.raises(InputError, match="X,Y"):
        explain(log, i, at="1,2,3,4")
    with pytest.raises(InputError, match="not seen"):
        explain(log, i, at=(0.0, 0.0, -1.0))  # behind the sensor
    with pytest.raises(LogError, match="no scan 99"):
        explain(log, 99)


@pytest.mark.parametrize("args", [
    ["--scan", "0", "--surface", "50"],
    ["--scan", "0", "--at", "nope"],
    ["--scan", "0", "--surface", "0", "--failed-picks"],
    ["--scan", "99"],
])
def test_cli_errors_are_one_line(log: Path, args: list[str]) -> None:
    r = CliRunner().invoke(cli, ["explain", str(log), *args])
    assert r.exit_code == 2
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.output


def test_cli_missing_log(tmp_path: Path) -> None:
    r = CliRunner().invoke(cli, ["explain", str(tmp_path / "x.mcap"), "--scan", "0"])
    assert r.exit_code == 2 and "not found" in r.stderr


def test_a_surface_says_where_its_centre_is_and_why(log: Path, records: dict[int, Any]) -> None:
    i, k = _surfaces(records)[0]
    S = records[i].surfaces
    d = explain(log, i, surface=k)["surfaces"][0]
    assert d["bulge_mm"] == pytest.approx(S.bulge[k] * 1e3, abs=0.01)
    (t,) = d["tests"]
    assert t["a"] == int(S.attempt[k]) and t["dof"] == 1
    text = format_explanation(explain(log, i, surface=k))
    assert "lid bulge" in text and "SURFACE_BULGE" in text


def test_a_split_parts_corner_is_named_as_such() -> None:
    """A vertex made for a part of a flat region split at a listed size reads as that, not
    as a neighbour's corner (``VertexSet.parent_side`` SIZE_PART)."""
    from boxloc.stages.hypotheses import SIZE_PART
    from replay.explain import _vertex_lines

    v = {"id": 7, "point": [0.1, 0.2, 1.5], "normal": [0.0, 0.0, -1.0], "parent": 2}
    part = "\n".join(_vertex_lines({**v, "parent_side": SIZE_PART}, ""))
    seam = "\n".join(_vertex_lines({**v, "parent_side": 1}, ""))
    assert "a part's corner: vertex V2's flat region" in part and "neighbour" not in part
    assert "a neighbour's corner, on side 1 of vertex V2" in seam


def test_exposed_says_when_its_counts_are_effective() -> None:
    """Where the noise's correlation weighed VERIFY_EXPOSED's counts, the attempt says so and
    by how much; with white noise (effective = raw) it says nothing."""
    from replay.explain import _exposed_note

    def v(b: int) -> dict[str, Any]:
        rows = [{"kind": "VERIFY_EXPOSED", "a": 3, "b": b, "statistic": 19, "critical": 20,
                 "accepted": True}]
        return {"n_front": 205, "n_behind": 102, "tests": rows}

    note = _exposed_note(v(28))
    assert "307 points beyond k as 28 independent ones" in note and "11.0" in note
    assert _exposed_note(v(307)) == ""
    assert _exposed_note({"n_front": 0, "n_behind": 0, "tests": []}) == ""


def test_a_test_reads_as_its_numbers_show() -> None:
    """The relation printed is the one between the recorded statistic and critical value,
    never one inferred from the decision; a decision its numbers alone would not make names
    the kind's further condition (a continuing plane beyond a seam side)."""
    from replay.explain import _test_text

    row = {"kind": "VERIFY_CONTINUATION", "a": 18, "b": 2, "statistic": 0.8388,
           "critical": 0.8, "accepted": True}
    text = _test_text(row)
    assert "0.8388 >= 0.8: accepted: the side is a seam or a gap" in text
    assert "< 0.8" not in text
    assert _test_text({**row, "statistic": 0.1}).endswith("0.1 < 0.8: accepted")
    # a detection is a statistic above its critical value
    jump = {"kind": "JUMP", "a": 1, "b": 5, "statistic": 39.0, "critical": 6.635,
            "dof": 1.0, "accepted": True}
    assert "39 > 6.635 (chi2 1 dof): accepted" in _test_text(jump)
    # a summary count is not compared with its critical value
    pop = {"kind": "POINT_ON_PLANE", "a": 3, "b": 400, "statistic": 361, "critical": 6.635,
           "dof": 1.0, "accepted": True}
    assert "361 (critical 6.635)" in _test_text(pop)
    # rejected against the numbers: the boundary line is not significant
    side = {"kind": "VERIFY_BOUNDARY", "a": 1, "b": -1, "statistic": 8, "critical": 6,
            "p_value": 0.2, "accepted": False}
    assert "8 >= 6 (p = 0.2): REJECTED: the line is not significant" in _test_text(side)


def test_every_printed_relation_holds_for_its_numbers(log: Path,
                                                      records: dict[int, Any]) -> None:
    """Over every surface of the log, each ``s REL c`` printed is true of s and c."""
    import operator
    import re

    ops = {"<=": operator.le, "<": operator.lt, ">": operator.gt, ">=": operator.ge}
    pat = re.compile(r": (-?[\d.e+-]+) (<=|>=|<|>) (-?[\d.e+-]+)[ :(]")
    n = 0
    for i, k in _surfaces(records):
        for line in format_explanation(explain(log, i, surface=k)).splitlines():
            for s, rel, c in pat.findall(line):
                assert ops[rel](float(s), float(c)), line
                n += 1
    assert n > 20
