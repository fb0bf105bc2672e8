"""surgtrack: CAD-free 6-DoF tracking and 3D reconstruction of surgical instruments from RGB-D video."""

__version__ = "0.1.0"

import os as _os

# Multi-threaded BLAS on the small matrices of RANSAC and the posture graph is many times slower on few cores.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
