"""Simulated bolus runs (:mod:`.bolus_run`) as DICOM XA multi-frame files, three layouts that differ:

* ``recipe``: native, LIN pixels (photon counts, 12 bits), a Mask Subtraction Sequence (``AVG_SUB`` of the
  frames before contrast), timing in Frame Time (0018,1063);
* ``no-recipe``: native, LOG pixels (``4000 − 800 · attenuation``: higher = brighter, sign +1), no recipe and no viewing mode (the reader finds the masks), timing in
  Frame Time Vector (0018,1065);
* ``subtracted``: the frames already subtracted (Image Type SUBTRACTION, vessels dark), timing in Cine Rate;
* ``enhanced``: native, Enhanced XA (per-frame functional groups), LOG pixels with sign −1 in MONOCHROME1, no
  recipe, timing in each frame's Frame Acquisition DateTime (the frames' own, possibly irregular, times).

Each carries its plane's C-arm geometry (classic XA tags) and Acquisition Date/Time (the LAT plane
``lat_delay_s`` later). No patient data: a fixed phantom name.
"""

from __future__ import annotations

from datetime import datetime, timedelta

import numpy as np

from .native_run import ENHANCED_XA_SOP, XA_SOP, Plane, base_dataset, classic_geometry, to_bytes
from .native_run_texture import _frame_groups

LAYOUTS = ("recipe", "no-recipe", "subtracted", "enhanced")
LOG_TOP, LOG_SCALE, LOG_BASE = 4000.0, 800.0, 100.0
SUB_OFFSET, SUB_SCALE = 2048.0, 2500.0
START = datetime(2024, 1, 2, 10, 15, 0)


def _timing(ds, layout: str, fps: float, n_frames: int, start: datetime) -> None:
    if layout == "recipe":
        ds.FrameTime = round(1000.0 / fps, 4)
    elif layout == "no-recipe":
        ds.FrameTimeVector = [0.0] + [round(1000.0 / fps, 4)] * (n_frames - 1)
    else:
        ds.CineRate = int(round(fps)) if float(fps).is_integer() else round(fps, 2)
        ds.FrameTime = round(1000.0 / fps, 4)  # Cine Rate is an integer: the exact interval too
    ds.AcquisitionDate = start.strftime("%Y%m%d")
    ds.AcquisitionTime = start.strftime("%H%M%S.%f")


def _recipe(ds, mask_frames: int, n_frames: int) -> None:
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    item = Dataset()
    item.MaskOperation = "AVG_SUB"
    item.MaskFrameNumbers = list(range(1, mask_frames + 1))
    item.ApplicableFrameRange = [mask_frames + 1, n_frames]
    ds.MaskSubtractionSequence = Sequence([item])


def _pixels(log_frames: np.ndarray, layout: str, photons: float) -> np.ndarray:
    if layout == "recipe":
        return np.clip(np.round(photons / 8.0 * np.exp(-log_frames)), 0, 4095).astype(np.uint16)
    if layout == "no-recipe":
        return np.clip(np.round(LOG_TOP - LOG_SCALE * log_frames), 0, 4095).astype(np.uint16)  # sign +1: ∝ log intensity
    subtracted = log_frames[0] - log_frames  # the first frame as the mask: vessels dark (negative)
    return np.clip(np.round(SUB_OFFSET + SUB_SCALE * subtracted), 0, 4095).astype(np.uint16)


def enhanced_xa(log_frames: np.ndarray, plane: Plane, name: str, times_s: np.ndarray, start: datetime) -> bytes:
    """The ``enhanced`` layout: per-frame Frame Acquisition DateTimes at ``start + times_s``."""
    n_frames, rows, cols = log_frames.shape
    ds = base_dataset(ENHANCED_XA_SOP, rows, cols, n_frames, "A" if name == "ap" else "B")
    ds.ImageType = ["ORIGINAL", "PRIMARY", "SINGLE PLANE", "NONE"]
    ds.PhotometricInterpretation = "MONOCHROME1"
    ds.PerFrameFunctionalGroupsSequence, ds.SharedFunctionalGroupsSequence = _frame_groups(plane, n_frames, 0, 0.0, rows)
    for group, seconds in zip(ds.PerFrameFunctionalGroupsSequence, times_s):
        group.FrameContentSequence[0].FrameAcquisitionDateTime = (start + timedelta(seconds=float(seconds))).strftime(
            "%Y%m%d%H%M%S.%f")
    ds.PixelData = np.clip(np.round(LOG_BASE + LOG_SCALE * log_frames), 0, 4095).astype(np.uint16).tobytes()
    return to_bytes(ds)


def bolus_xa(log_frames: np.ndarray, plane: Plane, name: str, layout: str, fps: float, *, mask_frames: int = 3,
             photons: float = 2.0e4, lat_delay_s: float = 0.0, times_s: np.ndarray | None = None) -> bytes:
    """One view's run as a DICOM XA multi-frame file (see the module docstring); ``times_s``: the frames' times
    from the run's first frame (the ``enhanced`` layout writes them; the others are regular at ``fps``)."""
    n_frames, rows, cols = log_frames.shape
    if layout == "enhanced":
        times = times_s if times_s is not None else np.arange(n_frames) / fps
        return enhanced_xa(log_frames, plane, name, times, START + timedelta(seconds=lat_delay_s if name == "lat" else 0.0))
    ds = base_dataset(XA_SOP, rows, cols, n_frames, "A" if name == "ap" else "B")
    ds.PhotometricInterpretation = "MONOCHROME2"
    if layout == "subtracted":
        ds.ImageType = ["DERIVED", "PRIMARY", "SINGLE PLANE", "SUBTRACTION"]
        ds.PixelIntensityRelationship, ds.PixelIntensityRelationshipSign = "LOG", 1
    else:
        ds.ImageType = ["ORIGINAL", "PRIMARY", "BIPLANE A" if name == "ap" else "BIPLANE B"]
        ds.PixelIntensityRelationship = "LIN" if layout == "recipe" else "LOG"
        ds.PixelIntensityRelationshipSign = 1
    if layout == "recipe":
        _recipe(ds, mask_frames, n_frames)
    _timing(ds, layout, fps, n_frames, START + timedelta(seconds=lat_delay_s if name == "lat" else 0.0))
    classic_geometry(ds, plane, rows)
    ds.PixelData = _pixels(log_frames, layout, photons).tobytes()
    return to_bytes(ds)
