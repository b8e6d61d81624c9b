"""Work budgets: a stage that would run for minutes stops at its budget, and the log and
``explain`` say so."""

from __future__ import annotations

from boxloc.config import Config
from boxloc.pipeline import find_graspable_surfaces
from boxloc.simulate import simulate

SCENE = "pallet:width=320,height=240,f=262.5,distance=1.5"


def test_an_exhausted_budget_is_recorded_and_explained(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from recorder.mcap.sink import McapRecorder
    from replay.explain import explain, format_explanation

    sim = simulate(SCENE, 3)
    cfg = Config(max_line_work=100, max_vertices=1)
    with McapRecorder(tmp_path / "b.mcap", config=cfg, fsync=False) as rec:
        find_graspable_surfaces(sim.scan, cfg, observer=rec)
    d = explain(tmp_path / "b.mcap", 0)
    assert "lines" in {b["stage"] for b in d["budgets"]}
    text = format_explanation(d)
    assert "budget exhausted: the lines stage stopped at 100 neighbour points" in text
