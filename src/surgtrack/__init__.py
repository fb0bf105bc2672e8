"""surgtrack: CAD-free 6-DoF tracking and 3D reconstruction of surgical instruments from RGB-D video."""

__version__ = "0.1.0"
