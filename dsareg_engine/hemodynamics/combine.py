"""The two views of one vessel point, combined.

Per view a point is *clean* when it is measurable there (inside the image, a footprint) and no other model part
overlaps it (:mod:`.overlap`); a point no view sees clean is measured in each view where it is measurable by
unmixing (:mod:`.unmixing`). A view is *usable* for a point where it is clean or unmixed. Its per-view values
(``arrival_s_ap`` ...) are given where it is usable and filled. The combined value is the mean of the usable
views' values, given only when every usable view saw contrast there: a point one usable view sees filled and the
other sees empty is left unmeasured (``views_disagree``),
so that a vessel contrast never reached is never given a time. ``agreement_s`` = ``|arrival_s_ap −
arrival_s_lat|`` where both views measured the point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .parameters import CurveParameters


@dataclass(frozen=True)
class ViewMeasure:
    """One view's measurement of the points ``(N,)``: curve ``parameters`` and ``measurable`` / ``overlapped``;
    ``unmixed`` ``(N,)`` bool: points no view sees clean whose ``parameters`` come from unmixing (:mod:`.unmixing`)."""

    parameters: CurveParameters
    measurable: np.ndarray
    overlapped: np.ndarray
    unmixed: np.ndarray | None = None

    @property
    def clean(self) -> np.ndarray:
        return self.measurable & ~self.overlapped

    @property
    def usable(self) -> np.ndarray:
        """Clean, or measured by unmixing."""
        return self.clean if self.unmixed is None else self.clean | self.unmixed

    def value(self, name: str) -> np.ndarray:
        """A parameter where the point is usable (NaN elsewhere)."""
        return np.where(self.usable, getattr(self.parameters, name), np.nan)

    def with_unmixed(self, rows: np.ndarray, found: CurveParameters) -> ViewMeasure:
        """This measure with the points ``rows`` (indices) taking the unmixed parameters ``found``."""
        merged = {}
        for name in ("arrival_s", "peak_s", "peak_opacity", "filled", "noise", "mtt_s", "area"):
            values = getattr(self.parameters, name).copy()
            values[rows] = getattr(found, name)
            merged[name] = values
        unmixed = np.zeros(len(self.measurable), bool)
        unmixed[rows] = True
        return ViewMeasure(CurveParameters(**merged), self.measurable, self.overlapped, unmixed)


def _mean(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(a) & np.isfinite(b), 0.5 * (a + b), np.where(np.isfinite(a), a, b))


def combine(ap: ViewMeasure, lat: ViewMeasure) -> dict[str, np.ndarray]:
    """Per point arrays: ``arrival_s``, ``peak_s``, ``peak_opacity``, ``mtt_s``, ``area`` (combined), ``arrival_s_ap``,
    ``arrival_s_lat``, ``peak_s_ap``, ``peak_s_lat``, ``agreement_s`` (NaN = null), and the bool arrays
    ``clean_ap``, ``clean_lat``, ``unmixed_ap``, ``unmixed_lat``, ``never_arrived``, ``views_disagree``."""
    views = {"ap": ap, "lat": lat}
    empty_clean = {name: v.usable & ~v.parameters.filled for name, v in views.items()}
    filled_clean = {name: v.usable & v.parameters.filled for name, v in views.items()}
    disagree = (filled_clean["ap"] & empty_clean["lat"]) | (filled_clean["lat"] & empty_clean["ap"])
    never = (empty_clean["ap"] | empty_clean["lat"]) & ~filled_clean["ap"] & ~filled_clean["lat"]
    out: dict[str, np.ndarray] = {}
    for name in ("arrival_s", "peak_s", "peak_opacity", "mtt_s", "area"):
        combined = _mean(ap.value(name), lat.value(name))
        out[name] = np.where(disagree, np.nan, combined)
    for view_name, view in views.items():
        out[f"arrival_s_{view_name}"] = view.value("arrival_s")
        out[f"peak_s_{view_name}"] = view.value("peak_s")
        out[f"clean_{view_name}"] = view.clean
        out[f"unmixed_{view_name}"] = view.usable & ~view.clean
    out["agreement_s"] = np.abs(out["arrival_s_ap"] - out["arrival_s_lat"])
    out["never_arrived"] = never
    out["views_disagree"] = disagree
    return out
