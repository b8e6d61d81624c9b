"""Scoring the localizer: metrics, the open3d baseline, real-data truth and the benches."""
