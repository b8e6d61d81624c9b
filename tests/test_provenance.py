"""Complete provenance: a log records every config value, defaults included, and a default
changed later changes neither what an old log says nor what its replay runs."""

from __future__ import annotations

import dataclasses
import inspect
import json
from pathlib import Path
from typing import Any

import pytest
from replay_support import make_log, product_differences

from boxloc.config import UNRECORDED_KEYS, Config
from boxloc.errors import InputError
from boxloc.scan import NoiseModel
from recorder.mcap.log import open_log
from replay.replay import replay_log


def _recorded(log: Path) -> dict[str, Any]:
    return json.loads(open_log(log).run["config"])


#: The keys a log recorded before full provenance (commit 16cb81b), which left the last
#: two and noise's last two out at their defaults.
_KEYS_THEN = ("alpha", "p_success", "min_edge", "max_edge", "max_tilt", "min_crease_angle",
              "support_fraction", "min_inlier_fraction", "flatness", "angle_tolerance",
              "mdl_k1", "mdl_k2", "mdl_k3", "workers", "max_pixels", "direction_granularity",
              "trial_seed", "end_tolerance")
_NOISE_THEN = ("sigma0", "k1", "k2", "sigma_angle", "min_cos", "edge_px", "row_corr")


def _writer_before_full_provenance(cfg: Config) -> dict[str, Any]:
    """``Config.to_dict`` as logs were written before every value was recorded."""
    d: dict[str, Any] = {k: getattr(cfg, k) for k in _KEYS_THEN}
    d["noise"] = {k: getattr(cfg.noise, k) for k in _NOISE_THEN
                  if not (k in ("edge_px", "row_corr") and getattr(cfg.noise, k) == 0.0)}
    if d["trial_seed"] == 0:
        del d["trial_seed"]
    if d["end_tolerance"] == 0.75:
        del d["end_tolerance"]
    return d


def _unwritten(d: dict[str, Any]) -> set[str]:
    """Config keys (``noise.x`` for the noise model's) that a recorded dict lacks."""
    top = {f.name for f in dataclasses.fields(Config)} - set(d)
    noise = {f"noise.{f.name}" for f in dataclasses.fields(NoiseModel)} - {
        f"noise.{k}" for k in d.get("noise", {})}
    return top | noise


def _set_defaults(monkeypatch: pytest.MonkeyPatch, cls: type, **values: Any) -> None:
    """Change dataclass ``cls``'s defaults, as a later version of the code would."""
    params = [p for p in inspect.signature(cls.__init__).parameters.values()
              if p.default is not inspect.Parameter.empty]
    defaults = list(cls.__init__.__defaults__)  # type: ignore[misc]
    for k, v in values.items():
        defaults[[p.name for p in params].index(k)] = v
        monkeypatch.setattr(cls, k, v)
    monkeypatch.setattr(cls.__init__, "__defaults__", tuple(defaults))


@pytest.fixture
def later_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every key old logs left out, and one they always recorded, get another default."""
    _set_defaults(monkeypatch, Config, end_tolerance=0.5, trial_seed=3, alpha=0.05,
                  noise_auto=True)
    _set_defaults(monkeypatch, NoiseModel, edge_px=0.7, row_corr=0.2)
    # the patch took: a fresh config is another config
    assert Config().end_tolerance == 0.5 and Config().trial_seed == 3
    assert Config().noise.edge_px == 0.7 and Config().alpha == 0.05 and Config().noise_auto


def test_a_log_records_every_value_defaults_included(tmp_path: Path) -> None:
    log = make_log(tmp_path / "new.mcap", [1])
    d = _recorded(log)
    assert set(d) == {f.name for f in dataclasses.fields(Config)}
    assert set(d["noise"]) == {f.name for f in dataclasses.fields(NoiseModel)}
    assert d["trial_seed"] == 0 and d["end_tolerance"] == Config().end_tolerance
    assert d["noise"]["edge_px"] == 0.0 and d["noise"]["row_corr"] == 0.0
    assert Config.from_dict(d) == Config()


def test_an_old_log_keeps_saying_what_it_ran_after_the_defaults_change(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with monkeypatch.context() as m:
        m.setattr(Config, "to_dict", _writer_before_full_provenance)
        # as the code of the time ran: the noise model pinned, no budgets, raw MDL points
        old = make_log(tmp_path / "old.mcap", [1, 2],
                       config=Config(noise_auto=False, max_edge_work=0, max_line_work=0,
                                     max_vertices=0, max_hypothesis_work=0,
                                     mdl_face_points=0.0, min_return_fraction=0.0,
                                     hole_weight=1.0))
    # every key an old log lacks has the value its run used in the frozen table (a key
    # added to the config without its entry there fails here)
    assert _unwritten(_recorded(old)) <= set(UNRECORDED_KEYS)
    assert "end_tolerance" not in _recorded(old)  # an old log indeed
    # what the old code ran: no budgets yet
    assert open_log(old).config == Config(max_edge_work=0, max_line_work=0, max_vertices=0,
                                          max_hypothesis_work=0, noise_auto=False,
                                          mdl_face_points=0.0, min_return_fraction=0.0,
                                          hole_weight=1.0)
    _set_defaults(monkeypatch, Config, end_tolerance=0.5, trial_seed=3, alpha=0.05,
                  noise_auto=True)
    _set_defaults(monkeypatch, NoiseModel, edge_px=0.7, row_corr=0.2)
    assert Config().end_tolerance == 0.5 and Config().noise.row_corr == 0.2
    said = open_log(old).config
    assert said is not None
    assert (said.end_tolerance, said.trial_seed, said.alpha) == (0.75, 0, 0.01)
    assert said.noise_auto is False
    assert (said.noise.edge_px, said.noise.row_corr) == (0.0, 0.0)
    # and its replay runs that config: the products bit for bit, every value recorded
    o = replay_log(old, out_dir=tmp_path / "out")
    assert o.status == "ok", o
    assert product_differences(old, Path(o.output)) == []
    d = _recorded(Path(o.output))
    assert (d["end_tolerance"], d["trial_seed"], d["alpha"]) == (0.75, 0, 0.01)
    assert d["noise_auto"] is False
    assert (d["noise"]["edge_px"], d["noise"]["row_corr"]) == (0.0, 0.0)


def test_a_new_log_replays_its_values_whatever_the_defaults_become(
        tmp_path: Path, later_defaults: None) -> None:
    cfg = Config(end_tolerance=0.75, trial_seed=0, alpha=0.01, noise_auto=False,
                 noise=NoiseModel(edge_px=0.0, row_corr=0.0))
    with pytest.MonkeyPatch.context() as m:  # recorded by today's code, before the change
        m.setattr(Config, "to_dict", lambda c: {**dataclasses.asdict(c),
                                                "noise": dataclasses.asdict(c.noise)})
        log = make_log(tmp_path / "new.mcap", [1], config=cfg)
    assert open_log(log).config == cfg
    o = replay_log(log, out_dir=tmp_path / "out")
    assert o.status == "ok" and product_differences(log, Path(o.output)) == []


def test_a_recorded_config_missing_another_key_is_refused() -> None:
    d = Config().to_dict()
    del d["alpha"]
    with pytest.raises(InputError, match="recorded config lacks alpha"):
        Config.from_recorded(d)
    del d["noise"]["k2"]
    with pytest.raises(InputError, match="alpha, noise.k2"):
        Config.from_recorded(d)


def test_the_hash_names_the_same_config_as_before_full_provenance() -> None:
    # the hash the recorder wrote for the default config before every value was recorded
    # (the budgets and the MDL's face units came later: a run without them is that config)
    assert Config(max_edge_work=0, max_line_work=0, max_vertices=0, max_hypothesis_work=0,
                  noise_auto=False, mdl_face_points=0.0,
                  min_return_fraction=0.0, hole_weight=1.0).hash == "6931a5b73eb71291"
    assert Config(trial_seed=2).hash != Config().hash
    assert Config(end_tolerance=0.5).hash != Config().hash
    assert Config(workers=2).hash == Config().hash
