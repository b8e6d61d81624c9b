"""``replay --rev`` with carton sizes (issue #21): the run at the other revision gets the same
sizes, the new log keeps the ``box_sizes.csv`` attachment, and a revision that predates
carton lists runs without them, says so in one line and records it in the new log.

The scene is the packed-layer one of ``tests/test_packed.py`` at 160 x 120 pixels: two
touching 0.3 x 0.4 m cartons, sharp edges, no gap. With the carton list it gives two
surfaces; without it, one ambiguous region and no surface. So a replay that lost the sizes
shows at once.

The fast tests run "the other revision" in this process (:class:`_InProcess`, a worktree
whose recorder writes no carton file and whose config keys are chosen); the slow ones check
out real revisions (an older revision's fresh worktree compiles its numba kernels once, most
of a minute; this code's reuses the running code's, :func:`replay.versions.seed_kernels`).
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner
from mcap.reader import make_reader
from replay_support import product_differences, snapshot
from scenes import box, scene

from boxloc.config import Config
from boxloc.io.box_sizes import read_box_sizes
from boxloc.pipeline import find_graspable_surfaces
from recorder.mcap import channels as C
from recorder.mcap import encode as E
from recorder.mcap.log import open_log
from recorder.mcap.proto import message_class
from recorder.mcap.sink import McapRecorder, box_sizes_attachment, copy_log_adding
from replay.replay import (
    REPLAY_CARRIED_METADATA,
    STAGING_SUFFIX,
    ReplayOutcome,
    _replay_here,
    box_sizes_override,
    remove_partials,
    replay_log,
)
from replay.versions import GitRevision, Worktree, default_repo, schema_tuple

REPO = default_repo()
SITE: dict[str, Any] = {"min_edge": 0.15, "max_edge": 0.5}
TWO = [box(-0.15, 0.0, 0.3, 0.4, 0.25), box(0.15, 0.0, 0.3, 0.4, 0.25)]
#: the file as a user writes it (length first: read_box_sizes sorts each row)
SIZES_CSV = "width,length,height\n0.4,0.3,0.25\n"
#: every config key of this code, dotted for the noise model's
KEYS = [*(k for k in Config().to_dict() if k != "noise"),
        *(f"noise.{k}" for k in Config().noise.to_dict())]


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``sizes``: the scene recorded with the carton list and its file attached; ``plain``:
    without; ``csv``: the file."""
    d = tmp_path_factory.mktemp("rev-sizes")
    csv = d / "cartons.csv"
    csv.write_text(SIZES_CSV)
    scan = scene(TWO, distance=1.5, tilt=0.08, bevel=0.0, width=160, height=120,
                 f=131.25).scan
    out = {"csv": csv}
    for name, cfg, att in (
            ("sizes", Config(**SITE, box_sizes=read_box_sizes(csv)), box_sizes_attachment(csv)),
            ("plain", Config(**SITE), None)):
        out[name] = d / f"{name}.mcap"
        with McapRecorder(out[name], config=cfg, fsync=False, attachments=att) as rec:
            find_graspable_surfaces(scan, cfg, observer=rec)
    # the scene's premise: the sizes make two surfaces of one ambiguous region
    (s,) = open_log(out["sizes"]).scans()
    (p,) = open_log(out["plain"]).scans()
    assert len(s.products["surfaces"].width) == 2 and len(s.products["ambiguous"]) == 0
    assert len(p.products["surfaces"].width) == 0 and len(p.products["ambiguous"]) == 1
    return out


def _surfaces(path: Path) -> tuple[int, int]:
    (rec,) = open_log(path).scans()
    return len(rec.products["surfaces"].width), len(rec.products["ambiguous"])


def _sizes_of(path: Path) -> tuple[tuple[float, float, float], ...]:
    cfg = open_log(path).config
    assert cfg is not None
    return cfg.box_sizes


def _attachments(path: Path) -> dict[str, bytes]:
    log = open_log(path)
    return {a.name: log.attachment(a.name) for a in log.attachments()}


# --- the other revision in this process ------------------------------------------------------


class _InProcess(Worktree):
    """A "revision" that is this code, run here: its config keys are ``info['config_keys']``
    (a config it is sent holds only those; the rest take this code's defaults, as in a
    revision without them), and its recorder writes no carton file."""

    def replay(self, path: Path, *, out_dir: Path, config: Any, overrides: Any,
               out_name: str | None, attachments: Any = None) -> ReplayOutcome:
        # like a worker from before the "attachments" key: it ignores them
        if isinstance(config, dict):
            assert set(config) | {f"noise.{k}" for k in config.get("noise", {})} \
                <= set(self.info["config_keys"]) | {"noise"}
            config = Config.from_dict(config)
        return _replay_here(Path(path), Path(out_dir), config, tuple(overrides), out_name, {})


def _rev(keys: list[str], schema: str | None = E.SCHEMA_VERSION) -> _InProcess:
    """A revision with config keys ``keys`` whose worker reports log schema ``schema`` (None:
    a worker before 1.6, which did not say)."""
    info: dict[str, Any] = {"config_keys": keys}
    if schema is not None:
        info["schema_version"] = schema
    return _InProcess("old", "0" * 40, "", (), "own", info)


def test_a_revision_without_carton_lists_runs_without_them_says_so_and_keeps_the_file(
        logs: dict[str, Path], tmp_path: Path) -> None:
    old = _rev([k for k in KEYS if k not in ("box_sizes", "size_tolerance")])
    o = replay_log(logs["sizes"], out_dir=tmp_path, version=old)
    assert o.status == "ok" and o.output == str(tmp_path / "sizes.mcap")
    (w,) = o.warnings
    assert "--rev old (000000000000) predates box_sizes: replayed without box_sizes=" \
           "[[0.3,0.4,0.25]]" in w and "\n" not in w
    new = Path(o.output)
    assert _surfaces(new) == (0, 1)  # it really ran without the sizes
    # the file is kept, bit for bit, and the log says what was not applied and why
    assert _attachments(new)[C.BOX_SIZES_ATTACHMENT] == SIZES_CSV.encode()
    md = open_log(new).metadata[REPLAY_CARRIED_METADATA]
    assert json.loads(md["attachments"]) == [C.BOX_SIZES_ATTACHMENT]
    assert json.loads(md["not_applied"]) == {"box_sizes": [[0.3, 0.4, 0.25]]}
    assert json.loads(md["warnings"]) == [w]
    # only the finished log is left: no staging directory, no partial file
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sizes.mcap"]


def test_keys_at_their_old_value_are_dropped_silently(logs: dict[str, Path],
                                                      tmp_path: Path) -> None:
    # no carton list: box_sizes = () and size_tolerance = 0.01 are what runs did before them
    old = _rev([k for k in KEYS if k not in ("box_sizes", "size_tolerance")])
    o = replay_log(logs["plain"], out_dir=tmp_path, version=old)
    assert o.status == "ok" and o.warnings == ()
    assert product_differences(logs["plain"], Path(str(o.output))) == []
    assert REPLAY_CARRIED_METADATA not in open_log(Path(str(o.output))).metadata


def test_a_revision_with_carton_lists_gets_the_sizes_and_the_file_is_added(
        logs: dict[str, Path], tmp_path: Path) -> None:
    new_rev = _rev(KEYS)
    # the log's own sizes: the same surfaces as the original, the file kept
    o = replay_log(logs["sizes"], out_dir=tmp_path / "a", version=new_rev)
    assert o.status == "ok" and o.warnings == ()
    assert product_differences(logs["sizes"], Path(str(o.output))) == []
    assert _attachments(Path(str(o.output)))[C.BOX_SIZES_ATTACHMENT] == SIZES_CSV.encode()
    # --box-sizes on a log without: the revision runs with them, the new log has the file
    sizes = read_box_sizes(logs["csv"])
    o = replay_log(logs["plain"], out_dir=tmp_path / "b", version=new_rev,
                   overrides=(box_sizes_override(sizes),),
                   attachments=box_sizes_attachment(logs["csv"]))
    assert o.status == "ok" and o.warnings == ()
    new = Path(str(o.output))
    assert _surfaces(new) == (2, 0) and _sizes_of(new) == sizes
    assert product_differences(logs["sizes"], new) == []  # as if recorded with the sizes
    assert _attachments(new)[C.BOX_SIZES_ATTACHMENT] == SIZES_CSV.encode()
    md = open_log(new).metadata[REPLAY_CARRIED_METADATA]
    assert json.loads(md["attachments"]) == [C.BOX_SIZES_ATTACHMENT]
    assert json.loads(md["not_applied"]) == {}


def test_an_existing_output_is_never_replaced(logs: dict[str, Path], tmp_path: Path) -> None:
    (tmp_path / "sizes.mcap").write_bytes(b"mine")
    o = replay_log(logs["sizes"], out_dir=tmp_path, version=_rev(KEYS))
    assert o.status == "error" and "exists; refusing to overwrite it" in str(o.error)
    assert (tmp_path / "sizes.mcap").read_bytes() == b"mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sizes.mcap"]


def test_the_worker_writes_the_attachments_it_is_sent(logs: dict[str, Path],
                                                     tmp_path: Path) -> None:
    import base64

    from replay.worker import PROTOCOL, handle

    data = SIZES_CSV.encode()
    req = {"protocol": PROTOCOL, "path": str(logs["plain"]), "out_dir": str(tmp_path),
           "config": None, "overrides": [box_sizes_override(read_box_sizes(logs["csv"]))],
           "out_name": None,
           "attachments": {C.BOX_SIZES_ATTACHMENT: ["text/csv", base64.b64encode(data)
                                                    .decode()]}}
    resp = handle(json.loads(json.dumps(req)))
    assert resp["ok"], resp
    new = Path(resp["outcome"]["output"])
    assert _attachments(new)[C.BOX_SIZES_ATTACHMENT] == data and _surfaces(new) == (2, 0)
    bad = handle({**req, "out_name": "bad.mcap",
                  "attachments": {"x": ["text/plain", "not base64!"]}})
    assert not bad["ok"] and bad["error"].startswith("attachments: ")
    assert not (tmp_path / "bad.mcap").exists()


def test_a_log_that_cannot_be_completed_is_published_as_written_with_a_warning(
        logs: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import recorder.mcap.sink

    def full_disk(*args: Any, **kwargs: Any) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(recorder.mcap.sink, "copy_log_adding", full_disk)
    o = replay_log(logs["sizes"], out_dir=tmp_path, version=_rev(KEYS))
    assert o.status == "ok" and len(o.warnings) == 1
    assert "without box_sizes.csv" in o.warnings[0] and "No space left" in o.warnings[0]
    assert _surfaces(Path(str(o.output))) == (2, 0)  # the revision's replay is kept
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sizes.mcap"]


# --- a revision that cannot read the range of a 1.6 log --------------------------------------


def _filters(path: Path, topics: set[str]) -> set[int]:
    """The array filters of the ``boxloc.v1.Product`` records on ``topics`` of a log."""
    with open(path, "rb") as f:
        datas = [m.data for _, c, m in make_reader(f).iter_messages(log_time_order=False)
                 if c.topic in topics]
    filters = set()
    for d in datas:
        msg = message_class("Product")()
        msg.ParseFromString(d)
        filters |= {a.filter for a in msg.arrays}
    return filters


def _range_filters(path: Path) -> set[int]:
    """The image filters of the ``/scan/range`` records of a log."""
    filters = _filters(path, {C.SCAN_RANGE})
    assert filters
    return filters


def _product_filters(path: Path) -> set[int]:
    """The array filters of every ``boxloc.v1.Product`` record of a log but the range."""
    products = {c.topic for c in C.CHANNELS if c.schema_name.endswith(".Product")}
    return _filters(path, products - {C.SCAN_RANGE})


class _OldReader(_InProcess):
    """A revision whose reader stops at the log schema it reports (before 1.6 when it
    reports none): a range in image filter 5 (1.6) or an array in filter 6 or 7 (1.7) that
    it cannot read fails as it does there. It notes what it is given in ``info['seen']``:
    the path, the range's filters and the other records' filters."""

    def replay(self, path: Path, *, out_dir: Path, config: Any, overrides: Any,
               out_name: str | None, attachments: Any = None) -> ReplayOutcome:
        ranges, others = _range_filters(Path(path)), _product_filters(Path(path))
        self.info.setdefault("seen", []).append((Path(path), ranges, others))
        reads = schema_tuple(self.schema_version) or (1, 5)
        if 5 in ranges and reads < (1, 6):
            return ReplayOutcome(input=str(path), error=f"{path}: array 'range': 42446 bytes "
                                                        "(76800 expected)")
        if others & {6, 7} and reads < (1, 7):
            return ReplayOutcome(input=str(path), error=f"{path}: array 'points': unknown "
                                                        "filter 6")
        return super().replay(path, out_dir=out_dir, config=config, overrides=overrides,
                              out_name=out_name, attachments=attachments)


def _old_reader(schema: str | None) -> _OldReader:
    return _OldReader("old", "0" * 40, "", (), "own", {"config_keys": KEYS}
                      | ({"schema_version": schema} if schema else {}))


def test_the_worker_reports_the_log_schema_it_reads() -> None:
    from replay.worker import check

    assert check()["schema_version"] == E.SCHEMA_VERSION
    assert _rev(KEYS).schema_version == E.SCHEMA_VERSION
    assert _rev(KEYS, None).schema_version is None


@pytest.mark.parametrize("schema", [None, "1.5", "1.4"])
def test_a_revision_before_schema_1_6_replays_a_copy_it_reads_and_the_input_is_untouched(
        logs: dict[str, Path], tmp_path: Path, schema: str | None) -> None:
    assert _range_filters(logs["sizes"]) == {5}  # the premise: a 1.6 log
    ins = snapshot([logs["sizes"]])
    old = _old_reader(schema)
    o = replay_log(logs["sizes"], out_dir=tmp_path, version=old)
    assert o.status == "ok" and o.warnings == (), o
    assert o.input == str(logs["sizes"]) and o.output == str(tmp_path / "sizes.mcap")
    # it read a copy with the range in filter 4 (what 1.4 and 1.5 read) and no float32
    # arrays, never the input
    ((seen, filters, others),) = old.info["seen"]
    assert seen != logs["sizes"] and seen.name == "sizes.mcap" and filters == {4}
    assert 6 in _product_filters(logs["sizes"]) and not others & {6, 7}
    assert snapshot([logs["sizes"]]) == ins
    # the same range, so the same products; the carton file kept; the original recorded
    new = Path(o.output)
    assert product_differences(logs["sizes"], new) == []
    assert _attachments(new)[C.BOX_SIZES_ATTACHMENT] == SIZES_CSV.encode()
    md = open_log(new).metadata[REPLAY_CARRIED_METADATA]
    copy = json.loads(md["input_copy"])
    assert copy["input"] == str(logs["sizes"].resolve())
    assert copy["input_sha256"] == ins[str(logs["sizes"])][0]
    assert json.loads(md["not_applied"]) == {} and json.loads(md["warnings"]) == []
    # the copy went with the staging directory
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sizes.mcap"]


def test_a_revision_that_reads_schema_1_6_replays_a_copy_with_float64_arrays(
        logs: dict[str, Path], tmp_path: Path) -> None:
    old = _old_reader("1.6")
    o = replay_log(logs["sizes"], out_dir=tmp_path, version=old)
    assert o.status == "ok" and o.warnings == (), o
    ((seen, filters, others),) = old.info["seen"]
    # the range as it is (1.6 reads filter 5); the edge points and covariances, stored as
    # float32 (filters 6 and 7, schema 1.7), as float64 (1 and 3): the same bits
    assert seen != logs["sizes"] and filters == {5} and not others & {6, 7} and {1, 3} <= others
    new = Path(str(o.output))
    assert product_differences(logs["sizes"], new) == []
    assert "input_copy" in open_log(new).metadata[REPLAY_CARRIED_METADATA]


@pytest.mark.parametrize("schema", ["1.7", "2.0"])
def test_a_revision_that_reads_schema_1_7_gets_the_input_itself(
        logs: dict[str, Path], tmp_path: Path, schema: str) -> None:
    old = _old_reader(schema)
    o = replay_log(logs["plain"], out_dir=tmp_path, version=old)
    ((seen, filters, others),) = old.info["seen"]
    assert seen == logs["plain"] and filters == {5} and 6 in others
    assert o.status == "ok" and o.warnings == (), o
    assert REPLAY_CARRIED_METADATA not in open_log(Path(str(o.output))).metadata


def test_an_error_of_a_revision_that_read_a_copy_names_the_input(
        logs: dict[str, Path], tmp_path: Path) -> None:
    class Failing(_OldReader):
        def replay(self, path: Path, **kw: Any) -> ReplayOutcome:
            self.info["seen"] = path
            return ReplayOutcome(input=str(path), error=f"{path}: scan 0: boom",
                                 warnings=(f"{Path(path).resolve()}: odd",))

    bad = Failing("old", "0" * 40, "", (), "own", {"config_keys": KEYS})
    o = replay_log(logs["plain"], out_dir=tmp_path, version=bad)
    assert bad.info["seen"] != logs["plain"]
    assert o.input == str(logs["plain"]) and o.error == f"{logs['plain']}: scan 0: boom"
    assert o.warnings == (f"{logs['plain']}: odd",)
    assert list(tmp_path.iterdir()) == []  # nothing published, no staging left


def test_a_copy_that_cannot_be_made_is_the_logs_error(
        logs: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import recorder.mcap.sink

    def full_disk(src: Any, dst: Any, reader: Any = None) -> None:
        Path(dst).write_bytes(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(recorder.mcap.sink, "copy_log_for_older_readers", full_disk)
    old = _old_reader(None)
    o = replay_log(logs["plain"], out_dir=tmp_path, version=old)
    assert o.status == "error" and "seen" not in old.info  # the revision never ran
    assert str(o.error).startswith(f"{logs['plain']}: cannot copy it for --rev old, which "
                                   "reads log schema before 1.6: OSError")
    assert "No space left" in str(o.error) and "\n" not in str(o.error)
    assert list(tmp_path.iterdir()) == []


def test_a_log_before_schema_1_6_goes_to_an_old_revision_as_it_is() -> None:
    old = _old_reader(None)
    assert not old.needs_older_log("1.5") and not old.needs_older_log(None)
    assert not old.needs_older_log("garbage") and old.needs_older_log("1.6")
    assert not _old_reader("1.6").needs_older_log("1.6")
    assert _old_reader("1.6").needs_older_log("1.7") and old.needs_older_log("1.7")
    assert not _old_reader("1.7").needs_older_log("1.7")
    assert not _old_reader("1.7").needs_older_log("1.8")  # nothing newer to rewrite yet


# --- adapting a config to a revision's keys --------------------------------------------------


def test_adapt_config() -> None:
    cfg = Config(**SITE, box_sizes=((0.3, 0.4, 0.25),), max_vertices=50)
    ov = ("alpha=0.05", "box_sizes=[[0.3, 0.4, 0.25]]")
    assert _rev(KEYS).adapt_config(cfg, ov, send_config=True) is None  # knows every key
    unknown = Worktree("r", "0" * 40, "", (), "own", {})  # its check could not tell
    assert unknown.adapt_config(cfg, ov, send_config=True) is None
    lacking = ("box_sizes", "size_tolerance", "max_vertices", "noise.corr_px_rows")
    a = _rev([k for k in KEYS if k not in lacking]).adapt_config(cfg, ov, send_config=True)
    assert a is not None and a.config is not None
    # what the revision cannot reproduce; corr_px_rows and size_tolerance are at their old
    # values (boxloc.config.UNRECORDED_KEYS), so they go silently
    assert a.not_applied == {"box_sizes": [[0.3, 0.4, 0.25]], "max_vertices": 50}
    assert a.overrides == ("alpha=0.05",)
    assert not set(lacking[:3]) & set(a.config) and "corr_px_rows" not in a.config["noise"]
    assert a.config["min_edge"] == 0.15 and a.config["noise"]["k2"] == cfg.noise.k2
    # the defaults (a bag, a log without provenance): the revision keeps its own
    d = _rev([k for k in KEYS if k not in lacking]).adapt_config(Config(), ov,
                                                                 send_config=False)
    assert d is not None and d.config is None and d.overrides == ("alpha=0.05",)


# --- the log copy that adds what a revision could not write -----------------------------------


def test_copy_log_adding_keeps_every_record(logs: dict[str, Path], tmp_path: Path) -> None:
    src, dst = logs["sizes"], tmp_path / "copy.mcap"
    copy_log_adding(src, dst, attachments={C.BOX_SIZES_ATTACHMENT: ("text/csv", b"new"),
                                           "notes.txt": ("text/plain", b"n")},
                    metadata={"boxloc.test": {"k": "v"}})
    assert product_differences(src, dst) == []
    a, b = open_log(src), open_log(dst)
    assert b.metadata == {**a.metadata, "boxloc.test": {"k": "v"}}
    got = _attachments(dst)
    assert got == {**_attachments(src), C.BOX_SIZES_ATTACHMENT: b"new", "notes.txt": b"n"}
    assert len(b.attachments()) == len(got)  # the old carton file was replaced, not doubled

    def summary(p: Path) -> tuple[int, int, list[int]]:
        with open(p, "rb") as f:
            s = make_reader(f).get_summary()
        assert s is not None and s.statistics is not None
        return (len(s.chunk_indexes), s.statistics.message_count,
                sorted(i.message_end_time for i in s.chunk_indexes))

    assert summary(src) == summary(dst)  # one chunk per scan, as recorded
    with pytest.raises(FileExistsError):
        copy_log_adding(src, dst)
    trunc = tmp_path / "trunc.mcap"
    trunc.write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    with pytest.raises(Exception):  # noqa: B017 - whatever the reader says; nothing left
        copy_log_adding(trunc, tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists()


def test_remove_partials_removes_staging_directories(tmp_path: Path) -> None:
    stage = tmp_path / f".run.123-abcd{STAGING_SUFFIX}"
    stage.mkdir()
    (stage / "run.mcap").write_bytes(b"x")
    other = tmp_path / f".other.1-ab{STAGING_SUFFIX}"
    other.mkdir()
    assert remove_partials(tmp_path, ["run.mcap"]) == 1
    assert not stage.exists() and other.exists()


# --- real revisions --------------------------------------------------------------------------


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c",
                           "user.email=t@example.com", *args], capture_output=True, text=True,
                          check=True).stdout.strip()


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_rev_of_this_code_keeps_sizes_and_surfaces(logs: dict[str, Path],
                                                   tmp_path: Path) -> None:
    # a revision that is this working tree's code, committed in a repository of its own
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    for pkg in ("boxloc", "recorder", "replay"):
        shutil.copytree(REPO / pkg, repo / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    _git(repo, "add", "-A")
    _git(repo, "commit", "-q", "-m", "this code")
    sizes = read_box_sizes(logs["csv"])
    with GitRevision("HEAD", repo=str(repo)).prepare() as wt:
        assert wt.mode == "own" and wt.config_keys == frozenset(KEYS)
        o = replay_log(logs["sizes"], out_dir=tmp_path / "a", version=wt)
        b = replay_log(logs["plain"], out_dir=tmp_path / "b", version=wt,
                       overrides=(box_sizes_override(sizes),),
                       attachments=box_sizes_attachment(logs["csv"]))
    for out in (o, b):
        assert out.status == "ok" and out.warnings == (), out
        new = Path(str(out.output))
        assert open_log(new).run["git_commit"] == wt.commit
        assert _sizes_of(new) == sizes
        assert _attachments(new)[C.BOX_SIZES_ATTACHMENT] == SIZES_CSV.encode()
        assert product_differences(logs["sizes"], new) == []  # the original's surfaces


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_rev_before_carton_lists_warns_records_and_keeps_the_file(
        logs: dict[str, Path], tmp_path: Path) -> None:
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.fail(f"--rev needs git and the boxloc git checkout ({REPO / '.git'} absent)")
    # the commit that added the carton list to the config, and its parent
    added = _git(REPO, "log", "--format=%H", "--reverse", "-S", "size_tolerance", "--",
                 "boxloc/config.py").splitlines()
    assert added, "no commit added size_tolerance to boxloc/config.py"
    old = f"{added[0]}^"
    out = tmp_path / "out"
    ins = snapshot([logs["sizes"], logs["plain"]])
    res = CliRunner().invoke(__import__("boxloc.cli").cli.cli,
                             ["replay", str(logs["sizes"]), str(logs["plain"]), "--out",
                              str(out), "--rev", old, "-j", "1", "-q", "--no-diff"],
                             catch_exceptions=False)
    # it reads the 1.6 logs (a copy with the range in filter 4); the logs are untouched
    assert res.exit_code == 0, res.stderr
    assert snapshot([logs["sizes"], logs["plain"]]) == ins
    # One warning per log that records a key the revision predates at a value it cannot
    # run: box_sizes for sizes.mcap only; keys added later (max_hypothesis_work, recorded
    # at its default while the revision runs without a budget) for both.
    warn = [ln for ln in res.stderr.splitlines() if ln.startswith("warning:")]
    assert all("predates " in w and ": replayed without " in w for w in warn)
    (sized,) = [w for w in warn if "box_sizes" in w]
    assert "box_sizes=[[0.3,0.4,0.25]]" in sized and f"{logs['sizes']}:" in sized
    doc = json.loads((out / "replay.json").read_text())
    by_name = {Path(o["input"]): o for o in doc["logs"]}
    assert set(by_name) == {logs["sizes"], logs["plain"]}  # the inputs, not their copies
    assert not any("box_sizes" in w for w in by_name[logs["plain"]]["warnings"])
    assert [w for w in by_name[logs["sizes"]]["warnings"] if "box_sizes" in w] == [
        sized.removeprefix("warning: ")]
    new = out / "sizes.mcap"
    log = open_log(new)
    assert log.run["git_commit"] == _git(REPO, "rev-parse", old)
    assert _attachments(new)[C.BOX_SIZES_ATTACHMENT] == SIZES_CSV.encode()
    md = log.metadata[REPLAY_CARRIED_METADATA]
    not_applied = json.loads(md["not_applied"])
    assert not_applied["box_sizes"] == [[0.3, 0.4, 0.25]]
    assert set(not_applied) <= set(KEYS)  # any others are keys of this code it predates
    assert json.loads(md["input_copy"])["input"] == str(logs["sizes"].resolve())
    assert C.BOX_SIZES_ATTACHMENT not in _attachments(out / "plain.mcap")
    assert sorted(p.name for p in out.iterdir()) == ["plain.mcap", "replay.json", "sizes.mcap"]
