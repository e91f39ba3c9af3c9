"""What users take away from a run: PLY maps, trajectories, uncertainty images, metrics, reports."""

import bgs_batch  # noqa: F401  (first: sets the OpenMP environment before torch and numba load)
