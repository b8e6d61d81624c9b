"""A fuzz case is a function of its run's seed, its index and the corpus alone: the same
bytes whatever ``PYTHONHASHSEED`` is, whatever the process did before it and whenever it is
written.

The log-records cases used to differ: their logs were written by ``mcap``'s Writer at
whatever zstd level the process had, and importing ``recorder.mcap.sink`` used to set it for
the whole process (it no longer does; ``write_log_model`` uses the recorder's
``ZstdLevelWriter``). A fresh fuzz worker wrote them at level 3; one that had run a log case
before (``recover_log`` imports the sink) at level 1. Which worker ran which case after what
changed from run to run.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from recorder.fuzz import CATEGORIES
from recorder.fuzz.cases import Case, Job
from recorder.fuzz.cli import main
from recorder.fuzz.corpus import CORPUS_INDEX, corpus_at

#: Cases per run: two turns of the category cycle, so every category is there, and the
#: log-records cases include each kind of mutation (payload, metadata, attachment, topic,
#: message order) with seed 0.
N_CASES = 44


def _write_cases(out: Path, corpus: Path, hashseed: int, *, prelude: str = "",
                 n: int = N_CASES) -> list[dict[str, Any]]:
    """``python -m recorder.fuzz --write-cases OUT`` in a fresh interpreter, after running
    ``prelude`` in it."""
    code = f"{prelude}\nimport sys\nfrom recorder.fuzz.cli import main\nsys.exit(main())"
    p = subprocess.run([sys.executable, "-c", code, "--write-cases", str(out), "--n", str(n),
                        "--seed", "0", "--corpus", str(corpus)],
                       env={**os.environ, "PYTHONHASHSEED": str(hashseed)},
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    rows: list[dict[str, Any]] = json.loads((out / "cases.json").read_text())
    return rows


def _group(row: dict[str, Any]) -> str:
    """The kind of mutation of a log-records case (its kind without the details)."""
    kind = str(row["kind"])
    if ":" in kind:
        return "payload"  # "<topic>:<what was mutated>"
    return kind.split("-")[0]


@pytest.fixture(scope="module")
def corpus(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A corpus directory (with its index), shared by the runs that are compared."""
    d = tmp_path_factory.mktemp("fuzz") / "corpus"
    corpus_at(d)
    assert (d / CORPUS_INDEX).is_file()
    return d


def test_cases_are_the_same_bytes_whatever_the_hash_seed_and_history(tmp_path: Path,
                                                                     corpus: Path) -> None:
    # One interpreter fresh, as a worker's first case; the other as a worker that has
    # recovered a log before (which imports the recorder), with another hash seed.
    a = _write_cases(tmp_path / "a", corpus, 0)
    b = _write_cases(tmp_path / "b", corpus, 12345, prelude="import recorder.mcap.recover")

    assert len(a) == len(b) == N_CASES
    assert {r["category"] for r in a} == set(CATEGORIES)
    records = [r for r in a if r["category"] == "log-records"]
    assert {_group(r) for r in records} == {"payload", "metadata", "attachment", "topic",
                                            "order"}
    assert sum(len(r["files"]) for r in a) >= 30  # the cases did write their inputs
    differ = [(x["case"], x["category"], x["kind"]) for x, y in zip(a, b) if x != y]
    assert not differ
    for r in records:  # and the files themselves, beyond their listed digests
        f = f"case-{r['case']:05d}/fuzzed.mcap"
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes()


def test_an_npz_case_does_not_depend_on_the_clock(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    from recorder.fuzz.npz_files import _write_zip

    members = {"range.npy": b"\x93NUMPY" + bytes(20), "points.npy": b"x" * 7}
    out = []
    for t in (1_000_000_000.0, 1_700_000_000.0):  # 2001 and 2023
        monkeypatch.setattr(time, "time", lambda t=t: t)
        p = tmp_path / f"{int(t)}.npz"
        _write_zip(p, members)
        out.append(p.read_bytes())
    assert out[0] == out[1]
    with zipfile.ZipFile(tmp_path / "1000000000.npz") as z:
        assert z.namelist() == list(members)
        assert [z.read(k) for k in members] == list(members.values())


def test_a_corpus_index_that_is_not_one_is_refused(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    (corpus / CORPUS_INDEX).write_text("{not json")
    code = main(["--write-cases", str(tmp_path / "out"), "--n", "1", "--corpus", str(corpus)])
    err = capsys.readouterr().err
    assert code == 2
    assert "is not a fuzz corpus index" in err and err.count("\n") == 1
    (corpus / CORPUS_INDEX).write_text(json.dumps({"small_logs": [str(tmp_path / "gone")]}))
    assert main(["--write-cases", str(tmp_path / "out"), "--corpus", str(corpus)]) == 2
    assert "which is not a file" in capsys.readouterr().err
    assert main(["--n", "-1"]) == 2
    assert "--n must be >= 0" in capsys.readouterr().err


def test_long_doubles_are_written_without_their_padding() -> None:
    """An x87 ``longdouble`` fills 10 of its 16 bytes; the rest is whatever the memory held,
    so an npz case of such an array differed from run to run (case 303 of seed 0)."""
    from recorder.fuzz.scan_files import _zero_padding

    a = np.array([0.1, -2.5, np.nan, np.inf]).astype(np.longdouble)
    raw = a.reshape(-1).view(np.uint8).reshape(a.size, a.itemsize)
    raw[:, 10:] = 0xA5  # garbage where a cast may leave some
    kept = a.copy()
    b = _zero_padding(a)
    assert b.shape == kept.shape and np.array_equal(b, kept, equal_nan=True)
    if np.finfo(np.longdouble).nmant == 63:  # x87 extended precision: 6 padding bytes
        assert not b.view(np.uint8).reshape(b.size, b.itemsize)[:, 10:].any()
        assert b.tobytes() != kept.tobytes()
    else:  # every byte is the number's
        assert b.tobytes() == kept.tobytes()
    assert _zero_padding(np.longdouble(1.5) * np.ones((), np.longdouble)).shape == ()
    f = np.ones((2, 3), np.float32)
    assert _zero_padding(f) is f


def test_the_workers_warm_up_runs_a_case_of_every_category(
        tmp_path: Path, corpus: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A worker's warm-up generates and runs one case per category (its cases once had
    negative indexes, which numpy refuses as seed entropy: every one failed unseen)."""
    import recorder.fuzz.pool as pool

    ran: list[str] = []
    generate = pool.generate

    def spy(case: Case, corpus: dict[str, Any], d: Path) -> Job:
        job = generate(case, corpus, d)
        ran.append(case.category)
        return job

    monkeypatch.setattr(pool, "generate", spy)
    pool._warm_up(json.loads((corpus / CORPUS_INDEX).read_text()), tmp_path)
    assert ran == list(CATEGORIES)
