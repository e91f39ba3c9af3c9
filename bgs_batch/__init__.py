"""bgs-batch: uncertainty-aware 3D Gaussian Splatting SLAM for RGB-D recordings, on CPU."""

__version__ = "0.1.0"
