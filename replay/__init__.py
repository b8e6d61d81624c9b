"""Replay and diff: re-run the pipeline on the scans stored in logs, compare, report.

``replay_log`` (one log, a plain function) runs the current code or a git revision;
``executors`` run it over many logs on local processes or a Dask cluster.
"""
