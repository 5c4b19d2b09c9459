"""logger: every tuning run to MCAP; list, replay, re-analyse, plot and recover runs."""
