"""The replay entry point of a revision: ``python -P -m replay.worker --check | --serve``.

:mod:`replay.versions` starts it in a git worktree of another revision (with
``PYTHONPATH`` at that revision) and talks to it in JSON lines.

``--check``
    Import the pipeline and the recorder, print one JSON line (``protocol``, versions,
    ``schema_version``: the log schema its recorder writes and its reader reads up to,
    where ``boxloc``, ``recorder`` and ``replay`` were imported from) and exit 0; on any
    failure print the error on stderr and exit 1. Workers before log schema 1.6 do not
    report ``schema_version``: the replay then gives them logs they can read
    (:func:`recorder.mcap.sink.copy_log_for_older_readers`).
``--serve``
    Read one request per line on stdin, ``{"protocol", "path", "out_dir", "config",
    "overrides", "out_name"}`` and optionally ``"attachments"`` (``{name: [media type,
    base64]}``, for the new log; older workers ignore the key), replay that log with
    *this* code and answer one line
    ``{"ok": true, "outcome": {...}}`` (a :class:`replay.replay.ReplayOutcome` dict) or
    ``{"ok": false, "error": "..."}``. Ends at end of input.

Anything the code prints goes to stderr: the protocol has stdout to itself.
"""

from __future__ import annotations

import base64
import json
import os
import sys
from typing import IO, Any

PROTOCOL = 1


def check() -> dict[str, Any]:
    """Import what a replay needs and say where it came from and which log schema it reads."""
    import boxloc
    import boxloc.pipeline  # noqa: F401 - the algorithm must import
    import recorder
    import recorder.mcap.encode
    import recorder.mcap.log  # noqa: F401
    import recorder.mcap.sink
    import replay
    import replay.replay  # noqa: F401

    commit, dirty = recorder.mcap.sink.git_info()
    return {"protocol": PROTOCOL, "boxloc_version": boxloc.__version__, "git_commit": commit,
            "git_dirty": dirty, "python": sys.version.split()[0],
            "schema_version": recorder.mcap.encode.SCHEMA_VERSION,
            "boxloc_file": boxloc.__file__, "recorder_file": recorder.__file__,
            "replay_file": replay.__file__}


def handle(req: dict[str, Any]) -> dict[str, Any]:
    """Replay the log of one request."""
    from boxloc.config import Config
    from replay.replay import replay_log

    if req.get("protocol") != PROTOCOL:
        return {"ok": False, "error": f"replay worker speaks protocol {PROTOCOL}, got "
                                      f"{req.get('protocol')}"}
    try:
        cfg = Config.from_dict(req["config"]) if req.get("config") is not None else None
    except Exception as e:  # noqa: BLE001 - e.g. a key this revision's Config does not have
        return {"ok": False, "error": f"config: {e}"}
    attachments = None
    if req.get("attachments") is not None:
        try:
            attachments = {str(n): (str(m), base64.b64decode(d, validate=True))
                           for n, (m, d) in dict(req["attachments"]).items()}
        except Exception as e:  # noqa: BLE001 - a malformed request is its answer
            return {"ok": False, "error": f"attachments: {type(e).__name__}: {e}"}
    outcome = replay_log(req["path"], out_dir=req["out_dir"], config=cfg,
                         overrides=tuple(req.get("overrides") or ()),
                         out_name=req.get("out_name"), attachments=attachments)
    return {"ok": True, "outcome": outcome.to_dict()}


def serve(stdin: IO[str], out: IO[str]) -> None:
    for line in stdin:
        if not line.strip():
            continue
        try:
            resp = handle(json.loads(line))
        except Exception as e:  # noqa: BLE001 - one bad request must not end the worker
            resp = {"ok": False, "error": f"{type(e).__name__}: {e}"}
        out.write(json.dumps(resp) + "\n")
        out.flush()


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    # Keep the protocol's stdout to ourselves: fd 1 (and print) now go to stderr.
    out = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)
    if args == ["--check"]:
        out.write(json.dumps(check()) + "\n")
        return 0
    if args == ["--serve"]:
        serve(sys.stdin, out)
        return 0
    print("usage: python -m replay.worker --check | --serve", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
