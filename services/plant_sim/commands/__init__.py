"""plant_sim's own commands that work on plant files without the bus (``autotune model``)."""
