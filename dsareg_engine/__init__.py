"""dsareg engine: geometry, silhouette rendering and two-view 3D/2D registration (no web code)."""

__version__ = "0.1.0"
