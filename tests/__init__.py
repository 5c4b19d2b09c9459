import services  # noqa: F401  (first: one BLAS thread per process, before numpy loads)
