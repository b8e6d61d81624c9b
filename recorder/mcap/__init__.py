"""The MCAP log, the record of truth: schemas, encoding, writing, reading, recovery."""
