"""The three services (plant_sim, autotuner, logger) and the `autotune` command."""
