"""``--rev``: another version of the code, from an isolated git worktree.

Bad refs and revisions that cannot run fail before any work; ``--rev HEAD`` replays with the
committed code (a real worktree of this repository) and removes the worktree afterwards.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from click.testing import CliRunner
from replay_support import product_differences, snapshot

from boxloc.cli import cli
from boxloc.errors import InputError
from recorder.mcap.log import open_log
from replay.replay import REPLAY_METADATA
from replay.versions import GitRevision, default_repo, seed_kernels

REPO = default_repo()


@pytest.fixture(autouse=True)
def _a_git_checkout() -> None:
    """``--rev`` needs git and this repository's history: CI runs on a clone, so their
    absence is a broken set-up, not a reason to skip."""
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.fail(f"--rev needs git and the boxloc git checkout ({REPO / '.git'} absent)")


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c",
                           "user.email=t@example.com", *args], capture_output=True, text=True,
                          check=True).stdout.strip()


def _worktrees(repo: Path) -> list[str]:
    return [ln for ln in _git(repo, "worktree", "list", "--porcelain").splitlines()
            if ln.startswith("worktree ")]


def _rev_dirs(sha: str) -> set[str]:
    """Temporary directories of worktrees of commit ``sha`` (other tests may run at the same
    time with other commits)."""
    return {p.name for p in Path(tempfile.gettempdir()).glob(f"boxloc-rev-{sha[:12]}-*")}


def _worktrees_of(repo: Path, sha: str) -> list[str]:
    return [w for w in _worktrees(repo) if f"boxloc-rev-{sha[:12]}-" in w]


def _repo(tmp_path: Path, files: dict[str, str] | None = None,
          copy: tuple[str, ...] = ()) -> Path:
    """A git repository with ``files`` and copies of this checkout's packages ``copy``."""
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    for name, text in (files or {}).items():
        (repo / name).parent.mkdir(parents=True, exist_ok=True)
        (repo / name).write_text(text)
    for pkg in copy:
        shutil.copytree(REPO / pkg, repo / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    _git(repo, "add", "-A")
    _git(repo, "commit", "-q", "-m", "test revision")
    return repo


@pytest.fixture(scope="module")
def logs(replay_logs: list[Path]) -> list[Path]:
    return replay_logs[:1]  # a log of two scans (tests/conftest.py)


def test_missing_ref_fails_before_any_work(logs: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["replay", str(logs[0]), "--out", str(out), "--rev",
                                   "no-such-branch-7f3a", "-q"])
    assert res.exit_code == 2
    assert "--rev no-such-branch-7f3a: no such revision" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "Traceback" not in res.stderr
    assert not out.exists()  # not even the output directory was made


@pytest.mark.parametrize("ref", ["", "--output=x", "-h"])
def test_option_like_refs_are_refused(ref: str) -> None:
    with pytest.raises(InputError, match="is not a git revision"):
        GitRevision(ref).resolve()


def test_not_a_repository(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="is not one"):
        GitRevision("HEAD", repo=str(tmp_path)).resolve()


def test_revision_without_boxloc_cannot_run(tmp_path: Path) -> None:
    repo = _repo(tmp_path, {"README.md": "nothing here\n"})
    sha = _git(repo, "rev-parse", "HEAD")
    with pytest.raises(InputError, match=r"cannot run: it has no boxloc package"):
        with GitRevision("HEAD", repo=str(repo)).prepare():
            pytest.fail("prepare() must fail before yielding")
    assert len(_worktrees(repo)) == 1 and not _rev_dirs(sha)  # cleaned up


def test_revision_that_does_not_import_cannot_run(tmp_path: Path) -> None:
    repo = _repo(tmp_path, {"boxloc/__init__.py": "raise ImportError('this revision is "
                                                  "broken')\n"})
    sha = _git(repo, "rev-parse", "HEAD")
    with pytest.raises(InputError, match=r"--rev HEAD \([0-9a-f]{12}\) cannot run: "
                                         r"ImportError: this revision is broken"):
        with GitRevision("HEAD", repo=str(repo)).prepare():
            pytest.fail("prepare() must fail before yielding")
    assert len(_worktrees(repo)) == 1 and not _rev_dirs(sha)


def test_revision_with_its_own_replay_runs_its_own_code(tmp_path: Path) -> None:
    repo = _repo(tmp_path, copy=("boxloc", "recorder", "replay"))
    sha = _git(repo, "rev-parse", "HEAD")
    with GitRevision("HEAD", repo=str(repo)).prepare() as wt:
        assert wt.mode == "own" and wt.commit == sha
        root = Path(wt.root)
        assert Path(wt.info["boxloc_file"]).is_relative_to(root)
        assert Path(wt.info["replay_file"]).is_relative_to(root)
        assert Path(wt.info["recorder_file"]).is_relative_to(root)
        assert wt.info["git_commit"] == sha and wt.info["git_dirty"] == "false"
        assert root.is_dir()
    assert not root.exists() and len(_worktrees(repo)) == 1


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_rev_head_replays_with_the_committed_code(logs: list[Path], tmp_path: Path) -> None:
    # A real worktree of this repository. Its numba kernels are the running code's where
    # the committed boxloc is the working tree's (seed_kernels); else it compiles them once.
    sha = _git(REPO, "rev-parse", "HEAD")
    has_replay = bool(_git(REPO, "ls-tree", "HEAD", "replay/worker.py"))
    before, dirs, ins = _worktrees_of(REPO, sha), _rev_dirs(sha), snapshot(logs)
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["replay", str(logs[0]), "--out", str(out), "--rev", "HEAD",
                                   "--jobs", "1", "-q", "--no-diff"], catch_exceptions=False)
    assert res.exit_code == 0, res.stderr
    assert f"({sha[:12]}, {'own' if has_replay else 'compat'} layout)" in res.stderr
    doc = json.loads((out / "replay.json").read_text())
    (o,) = doc["logs"]
    assert o["error"] is None and o["n_scans"] == 2 and all(s["ok"] for s in o["scans"])
    assert o["version"]["kind"] == "git" and o["version"]["commit"] == sha
    new = open_log(out / logs[0].name)
    assert new.run["git_commit"] == sha and new.run["git_dirty"] == "false"
    assert json.loads(new.metadata[REPLAY_METADATA]["replay_version"])["git_commit"] == sha
    # the worktree is gone, the inputs untouched
    assert _worktrees_of(REPO, sha) == before and _rev_dirs(sha) == dirs
    assert snapshot(logs) == ins
    # When the committed algorithm is the working tree's, the replay is bit for bit the same.
    same_code = subprocess.run(["git", "-C", str(REPO), "diff", "--quiet", "HEAD", "--",
                                "boxloc"], check=False).returncode == 0
    if same_code:
        assert product_differences(logs[0], out / logs[0].name) == []


_KERNEL = """import numba


@numba.njit(cache=True)
def f(x):
    return x + 1
"""
_CALL = ("import json; from boxloc.k import f; f(1); "
         "print(json.dumps([sum(f.stats.cache_hits.values()), "
         "sum(f.stats.cache_misses.values())]))")


def _cache_use(root: Path) -> list[int]:
    """[cache hits, cache misses] of one call of the kernel in a fresh process at ``root``."""
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["PYTHONPATH"] = str(root)
    p = subprocess.run([sys.executable, "-P", "-c", _CALL], capture_output=True, text=True,
                       env=env, cwd=root, timeout=300)
    assert p.returncode == 0, p.stderr
    return list(json.loads(p.stdout.splitlines()[-1]))


def _package(root: Path, text: str = _KERNEL) -> None:
    (root / "boxloc").mkdir(parents=True)
    (root / "boxloc" / "__init__.py").write_text("")
    (root / "boxloc" / "k.py").write_text(text)


def test_a_worktree_of_the_same_package_reuses_the_compiled_kernels(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    here, src = tmp_path / "here", tmp_path / "src"
    _package(here)
    assert _cache_use(here) == [0, 1]  # compiled and cached beside the source
    _package(src)  # a checkout: the same bytes, a later modification time
    os.utime(src / "boxloc" / "k.py", (1e9, 1e9))
    assert seed_kernels(src, here) >= 2  # the index and the overload's code
    assert (src / "boxloc" / "k.py").stat().st_mtime_ns == \
        (here / "boxloc" / "k.py").stat().st_mtime_ns
    assert _cache_use(src) == [1, 0]  # loaded, not compiled


def test_a_worktree_whose_package_differs_compiles_its_own_kernels(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    here = tmp_path / "here"
    _package(here)
    assert _cache_use(here) == [0, 1]
    # another kernel module's byte, or a module more: nothing is copied
    for k, (text, extra) in enumerate([(_KERNEL.replace("x + 1", "x + 2"), None),
                                       (_KERNEL, "other.py")]):
        src = tmp_path / f"src{k}"
        _package(src, text)
        if extra:
            (src / "boxloc" / extra).write_text("")
        assert seed_kernels(src, here) == 0 and not (src / "boxloc" / "__pycache__").exists()
        assert _cache_use(src) == [0, 1]
    # a cache directory of its own (keyed by each source's path): nothing is copied either
    src = tmp_path / "src-env"
    _package(src)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "nc"))
    assert seed_kernels(src, here) == 0

