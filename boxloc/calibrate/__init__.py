"""Estimating sensor parameters from scans: range noise, edge blur, squareness."""
