"""Which code a replay runs: the current code, or a git revision in an isolated worktree.

:data:`CURRENT` runs :func:`replay.replay.replay_log` in this process, with this code.

:class:`GitRevision` names another version. :meth:`GitRevision.prepare` resolves the ref
(``git rev-parse --verify REF^{commit}``), checks it out with ``git worktree add --detach``
into a temporary directory, checks that it can run, and yields a :class:`Worktree`; on exit
the worktree is removed. Everything fails with a one-line :class:`InputError` *before* any
replay starts.

A :class:`Worktree` runs each log in a subprocess of the current interpreter (so with the
current environment: the same Python and installed packages), with ``PYTHONPATH`` pointing
at the revision, started as ``python -P -m replay.worker --serve`` and kept alive between
logs (one per executor process and thread), speaking JSON lines (:mod:`replay.worker`).

Two layouts, decided by what the revision contains:

``own``
    The revision has ``replay/worker.py``: its own replay, recorder and algorithm run,
    ``PYTHONPATH=<worktree>``.
``compat``
    An older revision without it: the revision's ``boxloc`` (the algorithm under test)
    runs under *this* checkout's ``replay`` and ``recorder`` (the infrastructure), through
    a directory of symlinks (``boxloc -> <worktree>/boxloc``, ``recorder``, ``replay`` ->
    here) on ``PYTHONPATH``. The new log is then written in the current log layout. If the
    revision's ``boxloc`` is too old for this recorder, the check fails before any work.

In both, the new log's ``boxloc.run`` metadata records the revision's commit (the recorder
asks git in the worktree), and ``boxloc.replay`` says how it was made.

Config keys the revision does not know
--------------------------------------
A log records every config key of the code that wrote it, and a revision's ``Config``
refuses keys it does not know. The start-up check therefore asks the revision for its
config keys (:attr:`Worktree.config_keys`), and :meth:`Worktree.adapt_config` gives it the
config without the keys it predates. A key at its value in
:data:`boxloc.config.UNRECORDED_KEYS` (what runs did before the key existed) is dropped
silently: the revision runs exactly that. Any other value (a carton list for a revision
before ``box_sizes``) cannot be honoured: it is dropped, named in a one-line warning, and
recorded in the new log by :func:`replay.replay.replay_log`.

Logs newer than the revision
----------------------------
From log schema 1.6 the range is stored in image filter 5, which code of schema 1.4 and
1.5 does not read; from 1.7 float64 arrays of float32 values are stored as float32, which
code before 1.7 does not read. The start-up check reports the schema the revision's
recorder writes (``schema_version``, from 1.6 on; ``compat`` revisions run this recorder);
for a revision
that reports an older one or none, :func:`replay.replay.replay_log` gives the worker a
copy of each newer log made by :func:`recorder.mcap.sink.copy_log_for_older_readers`
(:meth:`Worktree.needs_older_log`), never the original.

Notes
-----
numba caches compiled kernels next to the sources, so a fresh worktree compiles them once
(about a minute for all of them, once per worker process at most) before its first scan.
Where the revision's ``boxloc`` is the running code's, file for file, the worktree gets the
running code's compiled kernels instead (:func:`seed_kernels`): the same sources compile to
the same code, so nothing is compiled again (``replay --rev HEAD`` on a clean checkout, or a
revision that changed only the recorder, replay, tests or docs).

With a Dask cluster the workers must see the worktree, the logs and the output directory
at the same paths (a shared file system, or a ``LocalCluster``).
"""

from __future__ import annotations

import atexit
import base64
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from boxloc.errors import InputError

if TYPE_CHECKING:
    from boxloc.config import Config
    from replay.replay import ReplayOutcome

#: Version of the JSON-lines protocol between this module and ``replay.worker``.
PROTOCOL = 1
#: Run in the revision's environment by the start-up check: its config keys (``noise.*``
#: for the noise model's), as one JSON line. Only ``dataclasses.fields`` of its
#: ``boxloc.config.Config``: that has held for every revision that has a ``replay`` worker.
_CONFIG_KEYS_PROBE = """
import dataclasses, json, sys
from boxloc.config import Config
keys = [f.name for f in dataclasses.fields(Config)]
try:
    noise = ["noise." + f.name for f in dataclasses.fields(Config().noise)]
    keys = [k for k in keys if k != "noise"] + noise
except Exception:  # no default config or no noise model: the top-level keys say enough
    pass
sys.stdout.write(json.dumps(keys) + "\\n")
"""
#: The first log schema whose range older code cannot read (image filter 5, commit 412d90e).
#: A revision whose worker reports an older ``schema_version``, or none (workers report it
#: from 1.6 on), replays a copy of such a log with the range in filter 4
#: (:func:`recorder.mcap.sink.copy_log_for_older_readers`).
RANGE_FILTER_5_SCHEMA = (1, 6)
#: The first log schema whose products older code cannot read (float64 arrays stored as
#: float32, filters 6 and 7): a revision that reads an older schema replays a copy with
#: those arrays in filters 1 and 3.
FLOAT32_FILTER_SCHEMA = (1, 7)
#: Seconds allowed for the start-up check of a revision (imports only, no JIT).
CHECK_TIMEOUT_S = 300.0
_GIT_TIMEOUT_S = 120.0


@dataclass(frozen=True)
class CurrentVersion:
    """The code of this process."""

    def describe(self) -> str:
        return "current code"


#: The current code (the default version of :func:`replay.replay.replay_log`).
CURRENT = CurrentVersion()


def _git(repo: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    try:
        return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True,
                              timeout=_GIT_TIMEOUT_S, check=check)
    except FileNotFoundError:
        raise InputError("--rev needs git, which is not installed") from None
    except subprocess.CalledProcessError as e:
        msg = (e.stderr or e.stdout or "").strip().splitlines()
        raise InputError(f"git {args[0]} failed: {msg[-1] if msg else e.returncode}") from None
    except subprocess.TimeoutExpired:
        raise InputError(f"git {args[0]} did not finish in {_GIT_TIMEOUT_S:.0f} s") from None


def default_repo() -> Path:
    """The git checkout this code lives in, else the current directory."""
    here = Path(__file__).resolve().parent.parent
    return here if (here / ".git").exists() else Path.cwd()


@dataclass(frozen=True)
class GitRevision:
    """Another version of the code: a git ref (commit, branch, tag, ``HEAD~3``).

    Parameters
    ----------
    ref : str
        Anything ``git rev-parse`` resolves to a commit.
    repo : str, optional
        The repository; default the checkout this code lives in (else the current
        directory).
    """

    ref: str
    repo: str | None = None

    def describe(self) -> str:
        return f"git revision {self.ref}"

    @property
    def repo_path(self) -> Path:
        return Path(self.repo) if self.repo else default_repo()

    def resolve(self) -> str:
        """The full commit hash of ``ref``.

        Raises
        ------
        InputError
            No git, not a repository, or no such revision.
        """
        ref = self.ref.strip()
        if not ref or ref.startswith("-"):
            raise InputError(f"--rev {self.ref!r} is not a git revision")
        repo = self.repo_path
        top = _git(repo, "rev-parse", "--show-toplevel", check=False)
        if top.returncode != 0:
            raise InputError(f"--rev needs a git repository; {repo} is not one")
        r = _git(repo, "rev-parse", "--verify", "--quiet", f"{ref}^{{commit}}", check=False)
        sha = r.stdout.strip()
        if r.returncode != 0 or not sha:
            raise InputError(f"--rev {self.ref}: no such revision in {top.stdout.strip()}")
        return sha

    @contextlib.contextmanager
    def prepare(self) -> Iterator[Worktree]:
        """Check the revision out in a temporary worktree, check it runs, yield it, remove it.

        Raises
        ------
        InputError
            The revision does not exist, cannot be checked out, or cannot run (its
            ``boxloc`` is missing or does not import with this environment).
        """
        sha = self.resolve()
        repo = Path(_git(self.repo_path, "rev-parse", "--show-toplevel").stdout.strip())
        tmp = Path(tempfile.mkdtemp(prefix=f"boxloc-rev-{sha[:12]}-"))
        src = tmp / "src"
        added = False
        wt: Worktree | None = None
        try:
            # Hooks off: an isolated checkout must not run the user's post-checkout scripts.
            _git(repo, "-c", "core.hooksPath=/dev/null", "worktree", "add", "--detach",
                 "--quiet", str(src), sha)
            added = True
            seed_kernels(src)
            wt = _layout(self.ref, sha, src, tmp)
            wt = _check(wt)
            yield wt
        finally:
            if wt is not None:
                close_workers(wt.root)
            if added:
                _git(repo, "worktree", "remove", "--force", str(src), check=False)
            shutil.rmtree(tmp, ignore_errors=True)
            if added:
                _git(repo, "worktree", "prune", check=False)


@dataclass(frozen=True)
class Worktree:
    """A prepared :class:`GitRevision`: a checkout that runs replays in a subprocess.

    Plain data (picklable), so executors can ship it to their workers; each worker process
    starts its own ``replay.worker`` subprocess on first use.

    Attributes
    ----------
    ref, commit : str
        The ref as given and the commit it resolved to.
    root : str
        The worktree.
    pythonpath : tuple of str
        Prepended to ``PYTHONPATH`` of the subprocess.
    mode : str
        ``own`` or ``compat`` (see the module docstring).
    info : dict
        What the start-up check reported (versions, where each package was imported from).
    tmp : str
        The temporary directory holding the worktree (and the subprocesses' stderr logs).
    """

    ref: str
    commit: str
    root: str
    pythonpath: tuple[str, ...]
    mode: str
    info: dict[str, Any] = field(default_factory=dict, compare=False)
    tmp: str = ""

    def describe(self) -> str:
        return f"git revision {self.ref} ({self.commit[:12]}, {self.mode} layout)"

    def version_info(self) -> dict[str, Any]:
        return {"kind": "git", "ref": self.ref, "commit": self.commit, "mode": self.mode}

    @property
    def config_keys(self) -> frozenset[str] | None:
        """The revision's config keys (``noise.*`` for the noise model's), or None when its
        start-up check could not tell."""
        keys = self.info.get("config_keys")
        return frozenset(keys) if isinstance(keys, list) else None

    @property
    def schema_version(self) -> str | None:
        """The log schema the revision's recorder writes (and its reader reads up to), as
        its start-up check reported it; None when it did not (a worker before 1.6)."""
        v = self.info.get("schema_version")
        return v if isinstance(v, str) else None

    def needs_older_log(self, log_schema: str | None) -> bool:
        """Whether a log of schema ``log_schema`` (its ``boxloc.run`` record) must reach
        this revision as a copy for older readers: the log is of schema 1.6 or later (the
        range in image filter 5, :data:`RANGE_FILTER_5_SCHEMA`; from 1.7 float32 arrays,
        :data:`FLOAT32_FILTER_SCHEMA`) and the revision reads an older schema or did not
        say (its worker predates the report)."""
        log_v = schema_tuple(log_schema)
        if log_v is None or log_v < RANGE_FILTER_5_SCHEMA:
            return False
        own = schema_tuple(self.schema_version)
        return own is None or own < min(log_v, FLOAT32_FILTER_SCHEMA)

    def adapt_config(self, cfg: Config, overrides: Sequence[str], *,
                     send_config: bool) -> AdaptedConfig | None:
        """The config for this revision when it lacks keys of ``cfg``, else None (send the
        config and overrides as they are).

        Parameters
        ----------
        cfg : Config
            The config to replay with, as this code resolves it (the log's or the given
            one, plus ``overrides``).
        overrides : sequence of str
            ``key=value`` overrides; those of keys the revision lacks are left out.
        send_config : bool
            Send ``cfg`` itself (without the keys the revision lacks). False when ``cfg``
            is this code's defaults (a bag, a log without provenance): the revision then
            runs with its own defaults, as it would have.
        """
        known = self.config_keys
        if known is None:
            return None
        from boxloc.config import EXECUTION_FIELDS, UNRECORDED_KEYS

        flat = _flatten(cfg.to_dict())
        lacking = [k for k in flat if k not in known]
        keys_of_overrides = [o.partition("=")[0].strip() for o in overrides]
        if not lacking and all(k in known for k in keys_of_overrides):
            return None
        not_applied = {k: flat[k] for k in lacking if k not in EXECUTION_FIELDS
                       and not (k in UNRECORDED_KEYS and _same(flat[k], UNRECORDED_KEYS[k]))}
        kept = tuple(o for o, k in zip(overrides, keys_of_overrides) if k in known)
        for o, k in zip(overrides, keys_of_overrides):
            if k not in known and k not in flat:  # not even this code knows it
                not_applied[k] = o.partition("=")[2].strip()
        config = None
        if send_config:
            d = cfg.to_dict()
            for k in lacking:
                head, _, tail = k.partition(".")
                (d[head] if tail else d).pop(tail or head, None)
            config = d
        return AdaptedConfig(config, kept, not_applied)

    def env(self) -> dict[str, str]:
        env = dict(os.environ)
        old = env.get("PYTHONPATH")
        env["PYTHONPATH"] = os.pathsep.join([*self.pythonpath, *([old] if old else [])])
        return env

    def command(self, *args: str) -> list[str]:
        # -P: never put the working directory first on sys.path (it may hold a boxloc/).
        return [sys.executable, "-P", "-m", "replay.worker", *args]

    def replay(self, path: Path, *, out_dir: Path, config: Config | dict[str, Any] | None,
               overrides: Sequence[str], out_name: str | None,
               attachments: dict[str, tuple[str, bytes]] | None = None) -> ReplayOutcome:
        """Replay one log with this revision (see :func:`replay.replay.replay_log`).

        ``config`` may be a dict already in the revision's keys
        (:attr:`AdaptedConfig.config`). ``attachments`` (base64 in the request) are
        written by revisions whose worker reads them; older workers ignore the key, and
        :func:`replay.replay.replay_log` adds what their logs lack."""
        from replay.replay import ReplayOutcome

        req: dict[str, Any] = {
            "protocol": PROTOCOL, "path": str(Path(path).resolve()),
            "out_dir": str(Path(out_dir).resolve()),
            "config": config if config is None or isinstance(config, dict)
            else config.to_dict(),
            "overrides": list(overrides), "out_name": out_name}
        if attachments is not None:
            req["attachments"] = {n: [m, base64.b64encode(d).decode("ascii")]
                                  for n, (m, d) in attachments.items()}
        try:
            resp = _worker_for(self).request(req)
        except _WorkerDied as e:
            return ReplayOutcome(input=str(path), error=f"{path}: {e}",
                                 version=self.version_info())
        if not resp.get("ok"):
            return ReplayOutcome(input=str(path), error=f"{path}: {resp.get('error')}",
                                 version=self.version_info())
        d = dict(resp["outcome"])
        d["input"] = str(path)  # the paths as given here, not as the subprocess saw them
        if d.get("output"):
            d["output"] = str(Path(out_dir) / Path(d["output"]).name)
        d["version"] = {**d.get("version", {}), **self.version_info()}
        return ReplayOutcome.from_dict(d)


#: Any version :func:`replay.replay.replay_log` accepts.
Version = CurrentVersion | GitRevision | Worktree


@dataclass(frozen=True)
class AdaptedConfig:
    """A config in the keys of a revision that lacks some (:meth:`Worktree.adapt_config`).

    Attributes
    ----------
    config : dict or None
        The config to send (``Config.to_dict`` without the lacking keys), or None: the
        revision resolves its own (its defaults).
    overrides : tuple of str
        The overrides of keys the revision knows.
    not_applied : dict
        The keys the revision lacks whose value it cannot reproduce (not their
        :data:`boxloc.config.UNRECORDED_KEYS` value), ``noise.*`` dotted, with the value it
        runs without (JSON-able): the replay differs from the request by these.
    """

    config: dict[str, Any] | None
    overrides: tuple[str, ...]
    not_applied: dict[str, Any]


def schema_tuple(version: Any) -> tuple[int, int] | None:
    """A log schema version ``"MAJOR.MINOR"`` as ``(major, minor)``; None if it is not one.

    >>> schema_tuple("1.10") > schema_tuple("1.6")
    True
    >>> schema_tuple("1.x") is None
    True
    """
    if not isinstance(version, str):
        return None
    major, dot, minor = version.strip().partition(".")
    if not (dot and major.isdigit() and minor.isdigit()):
        return None
    return int(major), int(minor)


def _flatten(d: dict[str, Any]) -> dict[str, Any]:
    """``Config.to_dict`` with the noise model's keys dotted (``noise.k2``)."""
    out = {k: v for k, v in d.items() if k != "noise"}
    out.update({f"noise.{k}": v for k, v in dict(d.get("noise") or {}).items()})
    return out


def _same(a: Any, b: Any) -> bool:
    """Config values equal as recorded (lists and tuples alike)."""
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return bool(a == b)


def _layout(ref: str, sha: str, src: Path, tmp: Path) -> Worktree:
    """Decide how the checkout runs: its own replay, or its boxloc under this replay."""
    if not (src / "boxloc" / "__init__.py").is_file():
        raise InputError(f"--rev {ref} ({sha[:12]}) cannot run: it has no boxloc package")
    if (src / "replay" / "worker.py").is_file():
        return Worktree(ref, sha, str(src), (str(src),), "own", tmp=str(tmp))
    here = Path(__file__).resolve().parent.parent
    shim = tmp / "path"
    shim.mkdir()
    (shim / "boxloc").symlink_to(src / "boxloc", target_is_directory=True)
    for pkg in ("recorder", "replay"):
        (shim / pkg).symlink_to(here / pkg, target_is_directory=True)
    return Worktree(ref, sha, str(src), (str(shim),), "compat", tmp=str(tmp))


#: numba's cache files (:mod:`numba.core.caching`): the index of a function's compiled
#: overloads, and one file of machine code per overload.
_KERNEL_SUFFIXES = (".nbi", ".nbc")


def seed_kernels(src: Path, here: Path | None = None) -> int:
    """Give the worktree ``src`` the compiled numba kernels of the running code, if its
    ``boxloc`` package is the running code's, file for file.

    numba keeps a function's compiled code in ``__pycache__`` beside its source, valid while
    the source's modification time and size are those it was compiled from; a kernel that
    calls a kernel or reads a constant of another module is not checked against that
    module. So the kernels are copied only when every ``.py`` file of the package is the
    same (the same files, byte for byte), and each copied source gets the running source's
    modification time. The cache's key also holds the CPU and numba's version, so a kernel
    that does not apply here is compiled as before, never run.

    Parameters
    ----------
    src : Path
        The worktree (its ``boxloc`` package).
    here : Path, optional
        The running code's checkout (default: the one this module is in).

    Returns
    -------
    int
        Cache files copied (0: the packages differ, the running code has no compiled kernels
        beside its sources, or ``NUMBA_CACHE_DIR`` puts every cache elsewhere).
    """
    if os.environ.get("NUMBA_CACHE_DIR"):
        return 0  # a cache directory keyed by each source's path: nothing to share
    mine = (here or Path(__file__).resolve().parent.parent) / "boxloc"
    theirs = src / "boxloc"
    if not mine.is_dir() or not theirs.is_dir():
        return 0
    files = sorted(p.relative_to(mine) for p in mine.rglob("*.py"))
    if files != sorted(p.relative_to(theirs) for p in theirs.rglob("*.py")):
        return 0
    if any((mine / f).read_bytes() != (theirs / f).read_bytes() for f in files):
        return 0
    n = 0
    for cache in sorted(mine.rglob("__pycache__")):
        kernels = [f for f in sorted(cache.iterdir()) if f.suffix in _KERNEL_SUFFIXES]
        if not kernels:
            continue
        dest = theirs / cache.relative_to(mine)
        dest.mkdir(exist_ok=True)
        for f in kernels:
            shutil.copyfile(f, dest / f.name)
            n += 1
    if n:
        for f in files:  # the stamp numba checks a cached kernel against
            st = (mine / f).stat()
            os.utime(theirs / f, ns=(st.st_atime_ns, st.st_mtime_ns))
    return n


def _last_line(text: str) -> str:
    lines = [ln.strip() for ln in (text or "").strip().splitlines() if ln.strip()]
    return lines[-1][:500] if lines else ""


def _check(wt: Worktree) -> Worktree:
    """Start the revision's worker once with ``--check``: it imports the pipeline and the
    recorder and says where they came from. Fails before any work if it cannot run."""
    what = f"--rev {wt.ref} ({wt.commit[:12]})"
    try:
        r = subprocess.run(wt.command("--check"), capture_output=True, text=True,
                           env=wt.env(), cwd=wt.tmp, timeout=CHECK_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise InputError(f"{what} cannot run: its start-up check took over "
                         f"{CHECK_TIMEOUT_S:.0f} s") from None
    if r.returncode != 0:
        raise InputError(f"{what} cannot run: {_last_line(r.stderr) or r.returncode}")
    try:
        info = json.loads(_last_line(r.stdout))
    except ValueError:
        raise InputError(f"{what} cannot run: its replay worker answered "
                         f"{_last_line(r.stdout)[:80]!r}") from None
    if info.get("protocol") != PROTOCOL:
        raise InputError(f"{what} cannot run: its replay worker speaks protocol "
                         f"{info.get('protocol')}, this replay speaks {PROTOCOL}")
    # The point of a worktree is to run *its* algorithm: make sure that is what imported.
    roots = [Path(p).resolve() for p in (wt.root, *wt.pythonpath)]
    got = Path(str(info.get("boxloc_file", ""))).resolve()
    if not any(got.is_relative_to(r) for r in roots):
        raise InputError(f"{what} cannot run: boxloc was imported from {got}, not from the "
                         "worktree")
    info["config_keys"] = _config_keys(wt)
    return Worktree(wt.ref, wt.commit, wt.root, wt.pythonpath, wt.mode, info, wt.tmp)


def _config_keys(wt: Worktree) -> list[str] | None:
    """The revision's config keys (:data:`_CONFIG_KEYS_PROBE`), or None if it cannot say
    (then every config goes to it as it is, as before the probe existed)."""
    try:
        r = subprocess.run([sys.executable, "-P", "-c", _CONFIG_KEYS_PROBE],
                           capture_output=True, text=True, env=wt.env(), cwd=wt.tmp or None,
                           timeout=CHECK_TIMEOUT_S)
        lines = r.stdout.strip().splitlines()  # (_last_line cuts at 500 characters)
        keys = json.loads(lines[-1]) if r.returncode == 0 and lines else None
    except (subprocess.TimeoutExpired, ValueError, OSError):
        return None
    if not isinstance(keys, list) or not all(isinstance(k, str) for k in keys):
        return None
    return keys


# --- the worker subprocesses -----------------------------------------------------------------


class _WorkerDied(Exception):
    """The revision's worker subprocess ended while replaying a log."""


class _Worker:
    """One ``replay.worker --serve`` subprocess of a worktree."""

    def __init__(self, wt: Worktree) -> None:
        self.wt = wt
        fd, err = tempfile.mkstemp(prefix=f"worker-{os.getpid()}-", suffix=".log",
                                   dir=wt.tmp if wt.tmp and Path(wt.tmp).is_dir() else None)
        self.err_path = Path(err)
        self._err = os.fdopen(fd, "wb")
        self.proc = subprocess.Popen(wt.command("--serve"), stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=self._err, env=wt.env(),
                                     cwd=wt.tmp or None, text=True, bufsize=1)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def request(self, req: dict[str, Any]) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        try:
            self.proc.stdin.write(json.dumps(req) + "\n")
            self.proc.stdin.flush()
            line = self.proc.stdout.readline()
        except (BrokenPipeError, OSError):
            line = ""
        if not line:
            rc = self.proc.wait(timeout=30)
            self.close()
            tail = ""
            with contextlib.suppress(OSError):
                tail = _last_line(self.err_path.read_text(errors="replace"))
            raise _WorkerDied(f"the replay process of --rev {self.wt.ref} died (exit code {rc})"
                              + (f": {tail}" if tail else ""))
        try:
            return dict(json.loads(line))
        except ValueError:
            return {"ok": False, "error": f"bad answer from the replay process: {line[:80]!r}"}

    def close(self) -> None:
        with contextlib.suppress(Exception):
            if self.proc.stdin is not None:
                self.proc.stdin.close()  # EOF: the worker's loop ends
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        with contextlib.suppress(Exception):
            if self.proc.stdout is not None:
                self.proc.stdout.close()
        with contextlib.suppress(Exception):
            self._err.close()


_WORKERS: dict[tuple[str, int], _Worker] = {}
_LOCK = threading.Lock()


def _worker_for(wt: Worktree) -> _Worker:
    """This thread's live worker for ``wt`` (one per process and thread: requests on one
    pipe are sequential)."""
    key = (wt.root, threading.get_ident())
    with _LOCK:
        w = _WORKERS.get(key)
        if w is None or not w.alive():
            w = _Worker(wt)
            _WORKERS[key] = w
    return w


def close_workers(root: str | None = None) -> None:
    """Stop this process's worker subprocesses (of worktree ``root``, or all)."""
    with _LOCK:
        keys = [k for k in _WORKERS if root is None or k[0] == root]
        workers = [_WORKERS.pop(k) for k in keys]
    for w in workers:
        w.close()


atexit.register(close_workers)
