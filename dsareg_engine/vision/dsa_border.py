"""Grey-level DSA → vessel mask with its border where the model's outline projects.

A global threshold (Otsu) puts the border where the contrast crosses one level; thin and
faint vessels then come out narrow and thick ones too, by different amounts (measured:
3–4 px of area per outline pixel too narrow on 800-px images). Here, per pixel:

1. **Contrast**: vessels made bright (polarity detected), the uneven background removed
   (iteratively clipped Gaussian averages, see :func:`_smooth_background`), noise σ from
   the MAD of the 3×3-median residual.
2. **Vessels found**: hysteresis threshold of the smoothed contrast (≥ 3 σ, seeded ≥ 6 σ, and
   ≥ 5 % / 10 % of the strongest contrast), small objects removed.
3. **Local peak**: the contrast on the vessel's centreline (skeleton), carried to every
   pixel from its nearest centreline pixel.
4. **Border**: a pixel is vessel where its contrast reaches a fraction of its local peak that
   depends on the local radius R (see ``BORDER_CONSTANT``). A projected cylinder's thickness
   ``2√(R² − x²)`` falls steeply only at the very edge, so half the peak (the usual "FWHM")
   lies ~0.13 R inside the outline; after pixel integration the edge pixel holds about
   ``(1/3)/√R`` of the peak. The law was measured against true silhouettes (README).

5. **Catheter** (``REMOVE_CATHETER``): an unbranched, long, uniform-width branch entering from
   the image border once and ending free or in a fork whose other branches stay inside is removed
   (:func:`catheter_pixels`), unless it feeds a fork and is about as wide as the image's widest
   vessel: the tree's trunk entering a small field (a catheter lies in a wider proximal vessel).
   A distal vessel leaving the field that looks just like a catheter (no side branch over 8 % of the
   image, width constant within 12 % away from its forks) is removed too.

The registration's border correction then removes what uniform width error remains.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

BORDER_CONSTANT = 0.3
BORDER_EXPONENT = 0.25
"""The border's contrast level is ``BORDER_CONSTANT / R**BORDER_EXPONENT`` of the local centreline
contrast, R the local radius in px. For an ideal cylinder sampled by pixels the edge pixel holds
``≈ (1/3) / √R`` of the centre value; detector blur and the smoothing needed against noise flatten
that dependence. Measured against true silhouettes of the paper's mesh (800 px, blur 0.5 px):
excess area per outline pixel −0.03 / +0.01 / −0.06 px for R = 2–4 / 4–8 / ≥ 8 px (with
``0.4 / √R``: −0.04 / +0.09 / +0.14)."""
MIN_FRACTION, MAX_FRACTION = 0.05, 0.5
NOISE_FLOOR_SIGMA = 2.0
"""Pixels below this many noise σ of contrast are never vessel."""


def _noise_sigma(contrast: np.ndarray) -> float:
    """Noise σ from the MAD of the 3×3-median residual (1.12: the residual's loss of variance)."""
    residual = contrast - cv2.medianBlur(contrast, 3)
    return max(1.4826 * float(np.median(np.abs(residual - np.median(residual)))) * 1.12, 1e-6)


BACKGROUND_SIGMA_PX = 16.0
"""Scale of the background average (px). Small enough that a smooth background's crests are
followed (a Gaussian average lowers a crest by ½ κ σ²), large enough to bridge most vessels."""


def _normalized_average(image: np.ndarray, keep: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian average of ``image`` over the pixels where ``keep`` (float 0/1) and the weight it had."""
    weight = cv2.GaussianBlur(keep, (0, 0), sigma_px)
    return cv2.GaussianBlur(image * keep, (0, 0), sigma_px) / np.maximum(weight, 1e-6), weight


QUADRATIC_SIGMA_PX = 24.0
"""Window (Gaussian σ, px) of the final local quadratic background fit (0: none, the Gaussian average
only). Measured on the paper's mesh at 800 px (grey-level ADD, 3 cases, coverage targets): smooth
field varying over a third of the image 0.0067 / 0.0160 / 0.0090 mm without → 0.0054 / 0.0138 /
0.0088 at 24 px (0.0047 / 0.0101 / 0.0076 at 48 px); a finer field (10 cells) 0.0100 / 0.0117 /
0.0098 → 0.0075 / 0.0048 / 0.0085 at 24 px, but 0.019–0.039 at 64 px: wider windows stop
following real background structure. Using the fit wherever ≥ 30 % of its window is kept (at first:
only ≥ 80 %, blended from 50 %) took the first case set to 0.0028 / 0.0074 / 0.0058 mm, the finer
field to 0.0047 / 0.0036 / 0.0063 mm and a ±25 % field from 0.0091 / 0.0239 / 0.0117 to 0.0031 /
0.0081 / 0.0059 mm: the wide vessels' surroundings are where the average was off. With the
clipping's curvature allowance (below) added last: 0.0051 / 0.0081 / 0.0035, finer field 0.0070 /
0.0050 / 0.0069, ±25 % field 0.0050 / 0.0086 / 0.0028 mm (the same within the cases' spread)."""
_QUADRATIC_TERMS = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))


def _local_quadratic(image: np.ndarray, keep: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the constant term of a quadratic fitted to ``image`` over the ``keep`` pixels (float
    0/1) in a Gaussian window, and the window's kept weight (0–1). ``(H, W)`` float64 each.

    A Gaussian average of a curved background is off by ½ κ σ² (crests read low, troughs high); a
    local quadratic is not, so the vessels' contrast beside them is not lifted or lowered.
    """
    half = int(np.ceil(3.0 * sigma_px))
    u = np.arange(-half, half + 1, dtype=np.float64) / sigma_px
    window = np.exp(-0.5 * u**2)
    kernels = [window * u**power for power in range(5)]
    weight, weighted = keep.astype(np.float64), keep * image.astype(np.float64)
    moments: dict[tuple[int, int], np.ndarray] = {}

    def moment(values: np.ndarray, px: int, py: int) -> np.ndarray:  # correlation: local coordinates
        return cv2.sepFilter2D(values, cv2.CV_64F, kernels[px], kernels[py], borderType=cv2.BORDER_REFLECT)

    n = len(_QUADRATIC_TERMS)
    normal, right = np.empty(image.shape + (n, n)), np.empty(image.shape + (n,))
    for i, (px, py) in enumerate(_QUADRATIC_TERMS):
        right[..., i] = moment(weighted, px, py)
        for j, (qx, qy) in enumerate(_QUADRATIC_TERMS):
            key = (px + qx, py + qy)
            if key not in moments:
                moments[key] = moment(weight, *key)
            normal[..., i, j] = moments[key]
    total = normal[..., 0, 0]
    normal += np.eye(n) * 1e-6 * np.maximum(total, 1e-12)[..., None, None]
    return np.linalg.solve(normal, right[..., None])[..., 0, 0], total / window.sum() ** 2


def _smooth_background(bright: np.ndarray, sigma: float, rounds: int = 8) -> np.ndarray:
    """Smooth background under the vessels by iteratively clipped Gaussian averages (2× shrunk grid).

    Each round averages only the pixels not brighter than the current background by more than
    2.5 noise σ plus the average's own curvature bias (½ σ² |∇²b|: without it, on a low-noise
    image with a curved background, each round clipped the crests the last one had lowered and
    most of the background ended as vessel), so vessels drop out ring by ring; where a wide
    vessel leaves too few pixels near, a 4× wider average fills in. The kept pixels then get a local quadratic fit
    (:func:`_local_quadratic`), used where at least 30 % of its window was kept (blended with the
    average below that).
    """
    size = (max(1, bright.shape[1] // 2), max(1, bright.shape[0] // 2))
    small = cv2.resize(bright, size, interpolation=cv2.INTER_AREA)
    scale = BACKGROUND_SIGMA_PX / 2.0
    keep = np.ones(small.shape, np.float32)
    background = small
    for _ in range(rounds):
        near, weight = _normalized_average(small, keep, scale)
        wide, _ = _normalized_average(small, keep, 4.0 * scale)
        blend = np.clip(weight / 0.2, 0.0, 1.0)
        background = (blend * near + (1.0 - blend) * wide).astype(np.float32)
        curvature_bias = 0.5 * scale**2 * np.abs(cv2.Laplacian(cv2.GaussianBlur(background, (0, 0), 1.0), cv2.CV_32F))
        keep = (small - background < 2.5 * sigma + curvature_bias).astype(np.float32)
    if QUADRATIC_SIGMA_PX <= 0:
        return cv2.resize(background, bright.shape[::-1], interpolation=cv2.INTER_LINEAR)
    quadratic, kept = _local_quadratic(small, keep, QUADRATIC_SIGMA_PX / 2.0)
    trust = np.clip(kept / 0.3, 0.0, 1.0)
    background = (trust * quadratic + (1.0 - trust) * background).astype(np.float32)
    return cv2.resize(background, bright.shape[::-1], interpolation=cv2.INTER_LINEAR)


def _find_vessels(contrast: np.ndarray, sigma: float, min_object_px: int) -> np.ndarray:
    """Hysteresis on the σ = 1 px smoothed contrast: ≥ 3 noise σ, seeded at ≥ 6 σ; small objects removed.

    With little noise the levels also stay above 5 % / 10 % of the densest vessels' contrast, so
    what the background model leaves (a few ‰ of full scale) is not read as vessel."""
    from skimage.filters import apply_hysteresis_threshold
    from skimage.morphology import remove_small_objects

    smooth = cv2.GaussianBlur(contrast, (0, 0), 1.0)
    smooth_sigma = sigma / (2.0 * np.sqrt(np.pi))  # white noise left after a σ = 1 px Gaussian
    strongest = float(np.percentile(smooth, 99.9))  # the densest vessels' contrast
    found = apply_hysteresis_threshold(smooth, max(3.0 * smooth_sigma, 0.05 * strongest),
                                       max(6.0 * smooth_sigma, 0.1 * strongest))
    return remove_small_objects(found, max_size=min_object_px)


MIN_NOISE_FRACTION = 5e-3
"""Noise σ is taken as at least this fraction of the vessels' contrast range (99.9th percentile −
median): with a noise-free image (MAD 0) the background's clipping keeps too little and background
wrinkles become vessel (paper mesh, 800 px: 1.6–5.4× the true area at 1e-3, right from 3e-3). Noise
of 1 % of full scale reads 1.3–3.4e-2 of that range (paper mesh and phantom), so noisy images are not
affected. (The phantom at 400 px, noise-free, LAT view still read 10× the true area with any floor
up to 1e-2 until the clipping allowed for the average's curvature bias, see _smooth_background.)"""


def dsa_contrast(bright: np.ndarray) -> tuple[np.ndarray, float]:
    """Vessel contrast ``(H, W)`` float32 above the smooth background, and the noise σ (steps 1 of the module docstring)."""
    bright = bright.astype(np.float32)
    spread = float(np.percentile(bright, 99.9) - np.percentile(bright, 50.0))
    sigma = max(_noise_sigma(bright), MIN_NOISE_FRACTION * spread)
    return bright - _smooth_background(bright, sigma), sigma


def dsa_vessel_mask(bright: np.ndarray, min_object_px: int, contrast: tuple[np.ndarray, float] | None = None) -> np.ndarray:
    """Binary vessel mask ``(H, W)`` of a bright-vessel float image (see the module docstring).

    ``contrast``: :func:`dsa_contrast` of ``bright`` when already computed."""
    from skimage.morphology import remove_small_objects, skeletonize

    contrast, sigma = contrast if contrast is not None else dsa_contrast(bright)
    found = _find_vessels(contrast, sigma, min_object_px)
    if not found.any():
        return found
    smooth = cv2.GaussianBlur(contrast, (0, 0), 1.0)
    skeleton = skeletonize(found)
    _, (rows, cols) = ndimage.distance_transform_edt(~skeleton, return_indices=True)
    peak = cv2.GaussianBlur(smooth, (0, 0), 0.7)[rows, cols]
    light = cv2.GaussianBlur(contrast, (0, 0), 0.7)
    reach = cv2.dilate(found.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    mask = found
    for _ in range(2):  # the border level depends on the radius, the radius on the border
        radius = (ndimage.distance_transform_edt(mask) * skeleton)[rows, cols] + 0.5
        fraction = np.clip(BORDER_CONSTANT / np.maximum(radius, 0.5) ** BORDER_EXPONENT, MIN_FRACTION, MAX_FRACTION)
        mask = reach & (light >= fraction * peak) & (light >= NOISE_FLOOR_SIGMA * sigma)
    if REMOVE_CATHETER:
        mask = mask & ~catheter_pixels(mask, skeleton, rows, cols)
    return remove_small_objects(mask, max_size=min_object_px)


REMOVE_CATHETER = True
"""A catheter as long as a small vessel tree (1.4 mm wide, from the image border) otherwise
dominates the masks and the pose search: measured on the phantom in a 512-px clinical rig with
no initial pose, 7 of 9 grey-level cases failed with it kept. Two straight vessels crossing the
field are protected by the crossing rule (:func:`_meets_a_crossing`)."""
CATHETER_MIN_LENGTH = 0.08
"""A catheter branch runs at least this fraction of the image's longer side."""
CATHETER_MAX_WIDTH_CV = 0.12
"""... with a width this uniform (standard deviation of the radius along it ≤ this × its mean + 0.25 px)."""


TRUNK_WIDTH_RATIO = 0.9
"""A branch from the border that ends in a junction (it feeds branches) and is at least this wide relative
to the widest other vessel in the image is the tree's trunk entering the field, not a catheter: a catheter
lies in a proximal vessel wider than itself. Measured (median radius away from forks): a 1.4-mm catheter
0.54× the widest vessel of its 512-px image (its tip in a distal branch, about as wide as the catheter);
trunks entering a small field 1.28× and 1.67× (0.08-mm pixels, phantom)."""


def _fork_clusters(forks: np.ndarray) -> np.ndarray:
    """Forks closer than ~8 px labelled as one junction (a crossing often skeletonizes into two 3-way forks)."""
    return ndimage.label(cv2.dilate(forks.astype(np.uint8), np.ones((9, 9), np.uint8)))[0]


def _junction_branches(branch: np.ndarray, fork_labels: np.ndarray, branches: np.ndarray) -> list[set[int]]:
    """Per junction the branch ends in, the labels of the other branches meeting there."""
    own = set(np.unique(branches[branch]))
    near = cv2.dilate(branch.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    meetings = []
    for index in set(np.unique(fork_labels[near & (fork_labels > 0)])):
        around = cv2.dilate((fork_labels == index).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        meetings.append(set(np.unique(branches[around & (branches > 0)])) - own)
    return meetings


def _meets_a_crossing(meetings: list[set[int]], reaching_edge: set[int]) -> bool:
    """True when, at a junction the branch ends in, another branch also runs to the image border: a
    vessel crossing the field (two straight vessels crossing), not a catheter ending in a tree."""
    return any(others & reaching_edge for others in meetings)


def _branch_radii(branches: np.ndarray, radius: np.ndarray, from_fork: np.ndarray) -> dict[int, float]:
    """Median radius (px) of each skeleton branch over its pixels away from forks (branches with fewer than
    three such pixels, pieces of a junction whose radius the junction inflates, are left out)."""
    away = from_fork > 2.0 * radius + 3.0
    radii = {}
    for index, sl in enumerate(ndimage.find_objects(branches), start=1):
        kept = radius[sl][(branches[sl] == index) & away[sl]] if sl is not None else ()
        if len(kept) >= 3:
            radii[index] = float(np.median(kept))
    return radii


def _is_trunk(meetings: list[set[int]], own_px: float, index: int, radii: dict[int, float]) -> bool:
    """True when the branch feeds a junction and is about as wide as the widest other vessel (TRUNK_WIDTH_RATIO)."""
    widest_px = max((width for other, width in radii.items() if other != index), default=0.0)
    return any(meetings) and own_px >= TRUNK_WIDTH_RATIO * widest_px


def catheter_pixels(mask: np.ndarray, skeleton: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Pixels of ``mask`` ``(H, W)`` explained by a catheter: an unbranched skeleton branch that
    enters from the image border once and ends inside (its tip, or where it meets the parent
    vessel, thinner than that vessel), is long and has a uniform width (vessels taper and branch).

    ``rows``, ``cols``: for each pixel, its nearest skeleton pixel.
    """
    from skimage.measure import label

    height, width = mask.shape
    skeleton = skeleton & mask
    neighbours = cv2.filter2D(skeleton.astype(np.uint8), -1, np.ones((3, 3), np.float32), borderType=cv2.BORDER_CONSTANT)
    forks = skeleton & (neighbours >= 4)
    junctions = cv2.dilate(forks.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    branches = label(skeleton & ~junctions, connectivity=2)
    radius = ndimage.distance_transform_edt(mask)
    from_fork = ndimage.distance_transform_edt(~forks) if forks.any() else np.full(mask.shape, np.inf)
    edge = np.zeros(mask.shape, bool)
    edge[:3], edge[-3:], edge[:, :3], edge[:, -3:] = True, True, True, True
    fork_labels, reaching_edge = _fork_clusters(forks), set(np.unique(branches[edge & (branches > 0)])) - {0}
    radii = _branch_radii(branches, radius, from_fork)
    catheter = np.zeros(mask.shape, bool)
    for index in sorted(reaching_edge):
        along = branches == index
        widths = radius[along & ~edge & (from_fork > 2.0 * radius + 3.0)]  # away from where it joins
        if along.sum() < CATHETER_MIN_LENGTH * max(height, width) or len(widths) < 10:
            continue
        if label(along & edge, connectivity=2).max() != 1:  # crosses the field: a vessel, not a catheter tip
            continue
        meetings = _junction_branches(along, fork_labels, branches)
        if _meets_a_crossing(meetings, reaching_edge) or _is_trunk(meetings, float(np.median(widths)), index, radii):
            continue
        if widths.std() <= CATHETER_MAX_WIDTH_CV * widths.mean() + 0.25:  # + the distance map's pixel steps
            catheter |= along
    return mask & catheter[rows, cols]
