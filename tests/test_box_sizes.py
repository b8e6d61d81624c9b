"""The carton list (issue #21, point 2): the CSV reader, the config fields, and how a
rectangle's size is tested against the list."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from boxloc.config import UNRECORDED_KEYS, Config
from boxloc.errors import InputError
from boxloc.io.box_sizes import read_box_sizes


def _csv(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "sizes.csv"
    p.write_text(text)
    return p


def test_reads_rows_in_order_width_below_length_and_an_empty_height_as_nan(
        tmp_path: Path) -> None:
    sizes = read_box_sizes(_csv(tmp_path, "width,length,height\n0.40,0.30,0.25\n0.2,0.3,\n"))
    assert sizes[0] == (0.30, 0.40, 0.25)
    assert sizes[1][:2] == (0.2, 0.3) and math.isnan(sizes[1][2])


@pytest.mark.parametrize("text, match", [
    ("w,l,h\n0.3,0.4,0.2\n", r"row 1: header must be width,length,height"),
    ("width,length,height\n0.3,abc,0.2\n", r"row 2: length is not a number"),
    ("width,length,height\n0.3,0.4,0.2\n0.3,-0.4,0.2\n", r"row 3: length must be a positive"),
    ("width,length,height\n0.3,0.4\n", r"row 2: expected 3 fields"),
    ("width,length,height\n0.3,nan,0.2\n", r"row 2: length must be a positive finite"),
    ("width,length,height\n0,0.4,0.2\n", r"row 2: width must be a positive"),
    ("width,length,height\n", r"no carton sizes after the header"),
    ("", r"empty file"),
])
def test_every_problem_is_one_line_naming_file_row_and_problem(
        tmp_path: Path, text: str, match: str) -> None:
    p = _csv(tmp_path, text)
    with pytest.raises(InputError, match=match) as e:
        read_box_sizes(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


def test_a_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="box sizes file not found: .*nope.csv"):
        read_box_sizes(tmp_path / "nope.csv")


def test_config_round_trips_the_list_through_toml_and_json_unknown_heights_included() -> None:
    c = Config(box_sizes=((0.4, 0.3, math.nan), (0.2, 0.3, 0.25)), size_tolerance=0.008)
    assert c.box_sizes[0][:2] == (0.3, 0.4)  # width <= length
    assert Config.from_toml(c.to_toml()) == c
    assert Config.from_dict(json.loads(json.dumps(c.to_dict(), allow_nan=False))) == c
    assert Config.from_recorded(c.to_dict()) == c
    assert c.hash != Config().hash


def test_old_logs_ran_without_a_list_and_the_default_hash_is_unchanged() -> None:
    assert UNRECORDED_KEYS["box_sizes"] == () and "size_tolerance" in UNRECORDED_KEYS
    d = Config().to_dict()
    del d["box_sizes"], d["size_tolerance"]
    assert Config.from_recorded(d) == Config()
    # the default list and tolerance hash as before they existed
    assert Config(max_edge_work=0, max_line_work=0, max_vertices=0, max_hypothesis_work=0,
                  noise_auto=False, mdl_face_points=0.0,
                  min_return_fraction=0.0, hole_weight=1.0).hash == "6931a5b73eb71291"


@pytest.mark.parametrize("rows", [((0.3,),), ((0.3, 0.4, -1.0),), "0.3,0.4", ((0.3, True),)])
def test_config_refuses_a_bad_list(rows: object) -> None:
    with pytest.raises(InputError, match="box_sizes"):
        Config(box_sizes=rows)  # type: ignore[arg-type]


def test_locate_reads_the_list_and_refuses_a_bad_one(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from boxloc.cli import cli

    bad = _csv(tmp_path, "width,length\n0.3,0.4\n")
    r = CliRunner().invoke(cli, ["locate", str(tmp_path / "scan.npz"), "--box-sizes", str(bad)])
    # the scan is missing too, but the carton list is read first: its problem is named
    assert r.exit_code == 2 and "header must be width,length,height" in r.output
