"""Job directories: run, checkpoint, resume, lock, signals and Slurm submission."""

import bgs_batch  # noqa: F401  (first: sets the OpenMP environment before torch and numba load)
