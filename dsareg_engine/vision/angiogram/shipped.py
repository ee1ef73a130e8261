"""Where the shipped weights are, and whether they are installed (no torch import: deciding costs nothing)."""

from __future__ import annotations

from pathlib import Path

WEIGHTS_PATH = Path(__file__).resolve().parent / "weights" / "vessel_unet.pt"
"""The shipped weights (trained by ``python -m benchmarks.engine segmentation-train``)."""


def weights_available(path: Path = WEIGHTS_PATH) -> bool:
    """Whether the weights file is installed."""
    return Path(path).is_file()
