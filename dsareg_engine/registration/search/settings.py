"""The one settings type of the pose searches: a grid over SO(3), scored in a window around the mask, hill-climbed.

The centroid search (:mod:`.initialization`), the coverage search (:mod:`.coverage_search`) and the branch search's
coarse and fine passes (:mod:`.branch_search`) are the same procedure at different sizes and with a different score;
each is one :class:`SearchSettings` value. A field a score does not read is ignored by it (the centroid score reads
``blur_px``; the coverage score ``beta``, ``model_reach``, ``chunk`` and ``past_edge_weight``).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SearchSettings:
    """Knobs of one pose search (defaults: the centroid search's, measured on the phantom and the paper's mesh).

    Attributes:
        rotations: size of the SO(3) grid (4096 → neighbours ~15° apart, any rotation within ~13°).
        window_px: side of the scoring window around the mask (the coverage search's canvas is twice as large).
        margin: window margin around the mask's bounding box, as a fraction of its size.
        points: surface points splatted per candidate (a search that samples its own points).
        refine_top: best candidates refined by the local hill-climb.
        refine_steps_deg: rotation steps of the hill-climb, one round each.
        distinct_deg: starts differ by at least this rotation.
        blur_px: centroid score: Gaussian blur of the mask in the window (px).
        beta: coverage score: recall weighs β² times precision in the F-score.
        model_reach: coverage score: the window's half side covers at least this many projected model RMS radii.
        chunk: coverage score: candidates scored per FFT batch (memory: chunk × C² floats).
        past_edge_weight: coverage score: a model pixel past the detector's edge counts this much against precision
            (one on the detector but off the vessels counts 1): the field of view may cut the model, but a pose must
            not win by hiding what it cannot explain past the edge.
    """

    rotations: int = 4096
    window_px: int = 64
    margin: float = 0.3
    points: int = 2500
    refine_top: int = 40
    refine_steps_deg: tuple[float, ...] = (8.0, 4.0, 2.0)
    distinct_deg: float = 30.0
    blur_px: float = 1.5
    beta: float = 2.0
    model_reach: float = 1.5
    chunk: int = 512
    past_edge_weight: float = 0.5


CENTROID = SearchSettings()
"""The centroid search (:mod:`.initialization`)."""
COVERAGE = SearchSettings(rotations=512, window_px=40, refine_top=16, refine_steps_deg=(12.0, 6.0, 3.0))
"""The coverage search (:mod:`.coverage_search`): a coarser grid (each candidate costs FFTs), one-sided ``F_2``."""
