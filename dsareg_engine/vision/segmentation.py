"""DSA image → binary vessel mask ``(H, W)``.

Methods:

* ``"mask"``: the image already is a segmentation; it is thresholded halfway between
  its extreme values (anti-aliased or JPEG'd masks work too).
* ``"otsu"``: Gaussian blur, Otsu threshold, small objects removed (the seed paper).
* ``"vesselness"``: Sato tubeness over several scales, hysteresis threshold around
  the response's Otsu level; keeps thin branches connected to thick ones.
* ``"dsa"``: background flattening, hysteresis, and the border at a fixed fraction of the
  local centreline contrast (:mod:`.dsa_border`): borders land where the vessel's outline
  projects, for thin and thick vessels alike.
* ``"network"``: the U-Net trained on real X-ray angiograms (:mod:`.angiogram`): field of view, vessels dark by
  physics, background anatomy and the field's edge left out. ``"frangi"``: its classical fallback.
* ``"auto"``: ``"mask"`` when the image has at most two values, else ``"dsa"`` where the ``dsa`` and
  ``network`` masks agree (on the image as it is, or after a flat-field correction: :mod:`.flat_field`) and
  ``"network"`` where they do not (:mod:`.segmentation_choice`).

:func:`vessel_coverage` is what registration fits: for ``"dsa"`` a per-pixel vessel coverage in
[0, 1] with sub-pixel borders (:mod:`.dsa_coverage`), for every other method the binary mask.

Polarity is detected: DSA shows vessels dark on a bright background; exported masks
show them bright on dark. The side that covers most of the image is the background.
"""

from __future__ import annotations

import numpy as np

from ..errors import DsaregInputError
from ..geometry.rig import ViewGeometry
from .angiogram import ANGIOGRAM_METHODS, segment_angiogram
from .segmentation_choice import AutoChoice, choose, network_coverage

SEGMENTATION_METHODS = ("auto", "network", "frangi", "dsa", "otsu", "vesselness", "mask")


def vessels_are_dark(pixels: np.ndarray) -> bool:
    """True when the background is the bright side (DSA), false for bright vessels (masks)."""
    low, high = float(pixels.min()), float(pixels.max())
    if high <= low:
        return False
    return float(np.median(pixels)) > 0.5 * (low + high)


def _bright_vessels(pixels: np.ndarray) -> np.ndarray:
    low, high = float(pixels.min()), float(pixels.max())
    normalized = (pixels.astype(np.float32) - low) / (high - low)
    return 1.0 - normalized if vessels_are_dark(pixels) else normalized


def _checked(pixels: np.ndarray, method: str, field_name: str) -> np.ndarray:
    """``pixels`` as an array, after checking the method, the shape and the values."""
    if method not in SEGMENTATION_METHODS:
        raise DsaregInputError(
            f"unknown segmentation '{method}'", field="segmentation", accepted=", ".join(SEGMENTATION_METHODS)
        )
    pixels = np.asarray(pixels)
    if pixels.ndim != 2:
        raise DsaregInputError(f"needs a 2D image, got shape {list(pixels.shape)}", field=field_name)
    if not np.all(np.isfinite(pixels)):
        raise DsaregInputError("contains NaN or infinite pixels", field=field_name)
    return pixels


def segment_vessels(
    pixels: np.ndarray,
    method: str = "auto",
    *,
    blur_sigma_px: float = 1.5,
    min_object_fraction: float = 2e-4,
    field_name: str = "image",
    field_of_view: np.ndarray | None = None,
) -> np.ndarray:
    """Binary vessel mask (``bool``, same shape as ``pixels``). ``field_of_view``: the file's shutter (True
    inside), used by the ``network`` / ``frangi`` / ``auto`` methods.

    Raises:
        DsaregInputError: unknown method, constant image, or no vessel found.
    """
    pixels = _checked(pixels, method, field_name)
    if pixels.dtype == bool:
        mask = pixels.copy()
        if mask.mean() > 0.5:
            mask = ~mask
        return _non_empty(mask, field_name)
    if float(pixels.max()) <= float(pixels.min()):
        raise DsaregInputError("is constant: no vessels to segment", field=field_name)
    n_values = len(np.unique(pixels[:: max(1, pixels.shape[0] // 256), :: max(1, pixels.shape[1] // 256)]))
    auto = method == "auto"
    if auto:
        method = "mask" if n_values <= 2 and len(np.unique(pixels)) <= 2 else "dsa"
    bright = _bright_vessels(pixels)
    min_size = max(16, int(min_object_fraction * pixels.size))
    if method in ANGIOGRAM_METHODS:
        return _non_empty(segment_angiogram(pixels, field_of_view, method=method).mask, field_name)
    if method == "dsa" and auto:
        choice = choose(pixels, bright, min_size, field_of_view)
        return _non_empty(choice.dsa_mask if choice.method == "dsa" else choice.angiogram.mask, field_name)
    if method == "mask":
        mask = bright > 0.5
    elif method == "dsa":
        from .dsa_border import dsa_vessel_mask

        mask = dsa_vessel_mask(bright, min_size)
    elif method == "otsu":
        from skimage.filters import gaussian, threshold_otsu
        from skimage.morphology import remove_small_objects

        smooth = gaussian(bright, sigma=blur_sigma_px, preserve_range=True)
        mask = smooth > threshold_otsu(smooth)
        mask = remove_small_objects(mask, max_size=min_size)
    else:  # sato (its import pulls in skimage.feature and scipy.stats: ~0.7 CPU s, only here)
        from skimage.filters import apply_hysteresis_threshold, sato, threshold_otsu
        from skimage.morphology import remove_small_objects

        response = sato(bright, sigmas=(1.0, 2.0, 3.0, 4.0), black_ridges=False)
        high = threshold_otsu(response)
        mask = apply_hysteresis_threshold(response, 0.5 * high, high)
        mask = remove_small_objects(mask, max_size=min_size)
    return _non_empty(mask, field_name)


def segment_vessels_and_choice(pixels: np.ndarray, method: str = "auto", *, field_name: str = "image",
                               field_of_view: np.ndarray | None = None) -> tuple[np.ndarray, AutoChoice | None]:
    """:func:`segment_vessels` and, where ``auto`` chose between ``dsa`` and the network, its choice."""
    pixels = _checked(pixels, method, field_name)
    if method != "auto" or resolved_method(pixels, method) != "dsa" or float(pixels.max()) <= float(pixels.min()):
        return segment_vessels(pixels, method, field_name=field_name, field_of_view=field_of_view), None
    choice = choose(pixels, _bright_vessels(pixels), max(16, int(2e-4 * pixels.size)), field_of_view)
    mask = choice.dsa_mask if choice.method == "dsa" else choice.angiogram.mask
    return _non_empty(mask, field_name), choice


def resolved_method(pixels: np.ndarray, method: str) -> str:
    """The method ``segment_vessels`` applies: ``"auto"`` → ``"mask"`` for at most two values, else ``"dsa"``."""
    if method != "auto":
        return method
    pixels = np.asarray(pixels)
    if pixels.dtype == bool:
        return "mask"
    sample = pixels[:: max(1, pixels.shape[0] // 256), :: max(1, pixels.shape[1] // 256)]
    return "mask" if len(np.unique(sample)) <= 2 and len(np.unique(pixels)) <= 2 else "dsa"


def vessel_coverage(
    pixels: np.ndarray, method: str = "auto", *, min_object_fraction: float = 2e-4, field_name: str = "image",
    field_of_view: np.ndarray | None = None,
) -> np.ndarray:
    """The registration target ``(H, W)``: float32 vessel coverage in [0, 1] where the method resolves
    to ``"dsa"`` (sub-pixel borders, :func:`~.dsa_coverage.dsa_vessel_coverage`), else the bool mask
    of :func:`segment_vessels`, unchanged; for ``"network"`` (and ``"auto"`` where it picks the network) the
    network's probability near its mask (:func:`~.segmentation_choice.network_coverage`).

    Raises:
        DsaregInputError: as :func:`segment_vessels`.
    """
    return vessel_coverage_and_choice(pixels, method, min_object_fraction=min_object_fraction,
                                      field_name=field_name, field_of_view=field_of_view)[0]


def vessel_coverage_and_choice(
    pixels: np.ndarray, method: str = "auto", *, min_object_fraction: float = 2e-4, field_name: str = "image",
    field_of_view: np.ndarray | None = None,
) -> tuple[np.ndarray, AutoChoice | None]:
    """:func:`vessel_coverage` and, where ``auto`` chose between ``dsa`` and the network, its choice."""
    pixels = _checked(pixels, method, field_name)
    constant = pixels.dtype != bool and float(pixels.max()) <= float(pixels.min())
    if method == "network" and not constant:
        angiogram = segment_angiogram(pixels, field_of_view, method="network")
        _non_empty(angiogram.mask, field_name)
        return network_coverage(angiogram), None
    if pixels.dtype == bool or resolved_method(pixels, method) != "dsa" or constant:
        return segment_vessels(pixels, method, min_object_fraction=min_object_fraction, field_name=field_name,
                               field_of_view=field_of_view), None
    from .dsa_coverage import dsa_vessel_coverage

    bright, min_size = _bright_vessels(pixels), max(16, int(min_object_fraction * pixels.size))
    choice = choose(pixels, bright, min_size, field_of_view) if method == "auto" else None
    if choice is not None and choice.method != "dsa":
        _non_empty(choice.angiogram.mask, field_name)
        return network_coverage(choice.angiogram), choice
    coverage = dsa_vessel_coverage(bright, min_size, found=None if choice is None else choice.dsa_found)
    if choice is not None and choice.inside is not None:
        coverage = np.where(choice.inside, coverage, 0.0).astype(np.float32)
    _non_empty(coverage >= 0.5, field_name)
    return coverage, choice


def _non_empty(mask: np.ndarray, field_name: str) -> np.ndarray:
    if not mask.any():
        raise DsaregInputError("no vessel found in the image", field=field_name)
    if mask.all():
        raise DsaregInputError("the whole image segments as vessel", field=field_name)
    return mask


def resample_mask(
    mask: np.ndarray, geometry: ViewGeometry | None, working_size_px: int
) -> tuple[np.ndarray, ViewGeometry | None]:
    """Resize a mask so its longest side is ``working_size_px`` (0 = unchanged), geometry rescaled to match.

    Downsampling uses area averaging then a 0.5 threshold, so a vessel thinner than a
    working pixel stays visible when it covers at least half of it.
    """
    import cv2

    height, width = mask.shape
    if working_size_px <= 0 or working_size_px == max(height, width):
        return mask, geometry
    scale = working_size_px / max(height, width)
    new_w, new_h = max(1, round(width * scale)), max(1, round(height * scale))
    interpolation = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    resized = cv2.resize(mask.astype(np.float32), (new_w, new_h), interpolation=interpolation) >= 0.5
    if geometry is not None:
        geometry = geometry.resized(new_w, new_h)
    return resized, geometry
