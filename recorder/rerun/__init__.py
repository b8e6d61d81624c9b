"""The Rerun view: one ``log_*`` per product, the blueprint, the viewer."""
