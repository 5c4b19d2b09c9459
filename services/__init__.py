"""The three services (plant_sim, autotuner, logger) and the `autotune` command."""

import os

# One BLAS thread per process: the numerics here are small matrices and records, where extra
# threads only spin, and on a small machine they take the cores that the plant, tuner and
# logger processes running in lockstep need. Set before numpy is first imported; an explicit
# setting in the environment wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
