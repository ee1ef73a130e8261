"""The two views of one vessel point, combined.

Per view a point is *clean* when it is measurable there (inside the image, a footprint) and no other model part
overlaps it (:mod:`.overlap`). Its per-view values (``arrival_s_ap`` ...) are given where it is clean and filled.
The combined value is the mean of the clean views' values, given only when every clean view saw contrast there:
a point one clean view sees filled and the other clean view sees empty is left unmeasured (``views_disagree``),
so that a vessel contrast never reached is never given a time. ``agreement_s`` = ``|arrival_s_ap −
arrival_s_lat|`` where both views measured the point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .parameters import CurveParameters


@dataclass(frozen=True)
class ViewMeasure:
    """One view's measurement of the points ``(N,)``: curve ``parameters`` and ``measurable`` / ``overlapped``."""

    parameters: CurveParameters
    measurable: np.ndarray
    overlapped: np.ndarray

    @property
    def clean(self) -> np.ndarray:
        return self.measurable & ~self.overlapped

    def value(self, name: str) -> np.ndarray:
        """A parameter where the point is clean (NaN elsewhere)."""
        return np.where(self.clean, getattr(self.parameters, name), np.nan)


def _mean(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(a) & np.isfinite(b), 0.5 * (a + b), np.where(np.isfinite(a), a, b))


def combine(ap: ViewMeasure, lat: ViewMeasure) -> dict[str, np.ndarray]:
    """Per point arrays: ``arrival_s``, ``peak_s``, ``peak_opacity`` (combined), ``arrival_s_ap``,
    ``arrival_s_lat``, ``peak_s_ap``, ``peak_s_lat``, ``agreement_s`` (NaN = null), and the bool arrays
    ``clean_ap``, ``clean_lat``, ``never_arrived``, ``views_disagree``."""
    views = {"ap": ap, "lat": lat}
    empty_clean = {name: v.clean & ~v.parameters.filled for name, v in views.items()}
    filled_clean = {name: v.clean & v.parameters.filled for name, v in views.items()}
    disagree = (filled_clean["ap"] & empty_clean["lat"]) | (filled_clean["lat"] & empty_clean["ap"])
    never = (empty_clean["ap"] | empty_clean["lat"]) & ~filled_clean["ap"] & ~filled_clean["lat"]
    out: dict[str, np.ndarray] = {}
    for name in ("arrival_s", "peak_s", "peak_opacity"):
        combined = _mean(ap.value(name), lat.value(name))
        out[name] = np.where(disagree, np.nan, combined)
    for view_name, view in views.items():
        out[f"arrival_s_{view_name}"] = view.value("arrival_s")
        out[f"peak_s_{view_name}"] = view.value("peak_s")
        out[f"clean_{view_name}"] = view.clean
    out["agreement_s"] = np.abs(out["arrival_s_ap"] - out["arrival_s_lat"])
    out["never_arrived"] = never
    out["views_disagree"] = disagree
    return out
