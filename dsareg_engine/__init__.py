"""dsareg engine: geometry, silhouette rendering and two-view 3D/2D registration (no web code)."""

from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _distribution_version

try:  # the one source of the version: pyproject.toml's [project] version, as installed
    __version__ = _distribution_version("dsareg")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0.0.0+unknown"
