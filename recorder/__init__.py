"""Recording: MCAP logs (the record of truth) and Rerun views of every scan and product."""
