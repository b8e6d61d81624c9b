"""Have the real Rerun viewer render a recording to a PNG, headless, bound to 127.0.0.1.

The viewer runs as ``rerun --headless --bind 127.0.0.1`` (it needs a Vulkan driver; Mesa's
lavapipe does on a machine without a GPU) and is driven through Rerun's viewer-control API:
open the file, wait until it is loaded, put the time cursor on a scan, save a screenshot.
This is what the tests use to check that our recordings and blueprint render, and what
regenerates the README's picture::

    python -m recorder.rerun.screenshot FILE.rrd OUT.png [--scan N] [--size 1280x800]
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from boxloc.errors import BoxlocError
from recorder.rerun.sink import TIMELINE_SCAN, free_port, rerun_executable


@dataclass
class ViewerReport:
    """What the viewer said about a recording it rendered."""

    png: Path
    views: dict[str, str] = field(default_factory=dict)  #: view name -> class
    problems: list[str] = field(default_factory=list)  #: per-view warnings and errors
    errors: list[str] = field(default_factory=list)  #: the viewer's own ERROR log lines
    timelines: dict[str, tuple[int | None, int | None]] = field(default_factory=dict)


def _wait_port(port: int, proc: subprocess.Popen[bytes], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise BoxlocError(f"the headless Rerun viewer exited with code {proc.returncode}")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise BoxlocError(f"the headless Rerun viewer did not listen within {timeout_s:.0f} s")


def screenshot_rrd(
    rrd: str | os.PathLike[str], png: str | os.PathLike[str], *, scan: int | None = None,
    size: tuple[int, int] = (1280, 800), settle_s: float = 3.0, timeout_s: float = 60.0,
) -> ViewerReport:
    """Render ``rrd`` with its own blueprint in a headless viewer and save a PNG.

    Parameters
    ----------
    scan : int, optional
        Put the time cursor on this scan index (default: the last one).
    size : (width, height)
        Window size, logical points (the PNG has the same size in pixels).
    settle_s : float
        Wait after loading, for the views to fill and the start-up notifications to fade.
    timeout_s : float
        Bound on the whole session; the viewer is stopped in any case.

    Raises
    ------
    BoxlocError
        When the viewer cannot start (e.g. no Vulkan driver) or does not load the file.
    """
    from rerun.experimental import ViewerClient

    rrd, png = Path(rrd).resolve(), Path(png).resolve()
    port = free_port()
    cmd = [rerun_executable(), "--headless", "--bind", "127.0.0.1", "--port", str(port),
           "--window-size", f"{size[0]}x{size[1]}", "--hide-welcome-screen"]
    env = {**os.environ, "RERUN_APP_ONLY": "true"}
    # stderr to a file, not a pipe: nobody drains a pipe while the viewer runs
    errfile = tempfile.TemporaryFile()
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=errfile, env=env)
    deadline = time.monotonic() + timeout_s
    try:
        try:
            _wait_port(port, proc, min(timeout_s, 30.0))
        except BoxlocError as e:
            errfile.seek(0)
            err = errfile.read()[-2000:]
            raise BoxlocError(f"{e}: {err.decode(errors='replace').strip()}") from None
        client = ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy")
        client.open(str(rrd))
        state = client.get_state()
        while (state.loading or not state.recordings
               or not state.recordings[0].timelines) and time.monotonic() < deadline:
            time.sleep(0.1)
            state = client.get_state()
        if not state.recordings:
            raise BoxlocError(f"the viewer did not load {rrd}")
        rec = state.recordings[0]
        report = ViewerReport(png=png, timelines={t.name: (t.start, t.end)
                                                  for t in rec.timelines})
        end = report.timelines.get(TIMELINE_SCAN, (None, None))[1]
        target = scan if scan is not None else end
        if target is not None:
            client.set_time(TIMELINE_SCAN, sequence=int(target), play_state="paused")
        time.sleep(max(0.0, min(settle_s, deadline - time.monotonic())))
        png.parent.mkdir(parents=True, exist_ok=True)
        client.save_screenshot(str(png))
        state = client.get_state()
        report.views = {v.name: v.view_class for v in state.views}
        report.problems = [f"{v.name}: {r.severity}: {r.summary}"
                           for v in state.views for r in v.reports]
        report.errors = [e.message for e in client.get_logs() if e.level == "ERROR"]
        return report
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
        errfile.close()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rrd")
    ap.add_argument("png")
    ap.add_argument("--scan", type=int, default=None)
    ap.add_argument("--size", default="1280x800")
    a = ap.parse_args(argv)
    w, h = (int(v) for v in a.size.lower().split("x"))
    rep = screenshot_rrd(a.rrd, a.png, scan=a.scan, size=(w, h))
    print(f"{rep.png}: views {sorted(rep.views)}; problems {rep.problems or 'none'}")


if __name__ == "__main__":
    main()
