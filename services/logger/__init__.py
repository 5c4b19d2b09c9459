"""logger: writes every tuning run to MCAP, replays and re-analyses it (issue 4; not yet built)."""
