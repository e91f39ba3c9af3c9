"""bgs-batch: uncertainty-aware 3D Gaussian Splatting SLAM for RGB-D recordings, on CPU."""

import os

# Idle OpenMP threads must sleep, not spin: torch and numba each run an OpenMP pool on the same
# two cores, and with the default active wait the idle pool slows the other one several-fold
# (measured: projection 52 ms -> 9.5 ms). Pools read this when they start, so it is set here,
# before anything imports torch or numba; an explicit user setting is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# numba tries TBB first and warns on every run when the installed TBB is too old (Debian's);
# it then uses OpenMP anyway. Asking for OpenMP first keeps that choice without the warning.
os.environ.setdefault("NUMBA_THREADING_LAYER_PRIORITY", "omp tbb workqueue")

__version__ = "0.1.0"
