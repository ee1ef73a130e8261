"""``result.hemodynamics``: what was measured, how much of the model, how well the two views agree, which timing."""

from __future__ import annotations

import numpy as np

from .colours import TimeScale


def _rounded(value: float | None, digits: int = 4) -> float | None:
    return None if value is None or not np.isfinite(value) else round(float(value), digits)


def summarize(per_vertex: dict[str, np.ndarray], found, runs: dict, offset_s: float, basis: str, order: str,
              moved, scale: TimeScale) -> dict:
    """The summary of a measurement, per file vertex (``per_vertex``) and per view."""
    arrival = per_vertex["arrival_s"]
    both = np.isfinite(per_vertex["arrival_s_ap"]) & np.isfinite(per_vertex["arrival_s_lat"])
    difference = per_vertex["arrival_s_lat"][both] - per_vertex["arrival_s_ap"][both]
    views = {}
    for name, run in runs.items():
        counts = dict(found.views[name])
        counts.update({"frames": int(len(run.timing.times_s)), "timing": run.timing.to_dict(),
                       "clean_vertices": int(per_vertex[f"clean_{name}"].sum()), "notes": list(run.notes)})
        views[name] = counts
    return {
        "vertices": int(len(arrival)),
        "vertex_order": order,
        "mapped_fraction": _rounded(float(np.isfinite(arrival).mean()) if len(arrival) else 0.0),
        "never_arrived": int(per_vertex["never_arrived"].sum()),
        "views_disagree": int(per_vertex["views_disagree"].sum()),
        "unmixed_vertices": int((per_vertex["unmixed_ap"] | per_vertex["unmixed_lat"]).sum()),
        "mtt_median_s": _rounded(float(np.nanmedian(per_vertex["mtt_s"])) if np.isfinite(per_vertex["mtt_s"]).any()
                                 else None),
        "agreement_points": int(both.sum()),
        "agreement_median_s": _rounded(float(np.median(np.abs(difference))) if both.any() else None),
        "lat_minus_ap_median_s": _rounded(float(np.median(difference)) if both.any() else None),
        "arrival_range_s": [_rounded(float(np.nanmin(arrival))), _rounded(float(np.nanmax(arrival)))]
        if np.isfinite(arrival).any() else None,
        "offset_s": _rounded(offset_s),
        "offset_basis": basis,
        "transfer_max_mm": _rounded(float(moved.distance_mm.max()) if len(moved.distance_mm) else 0.0),
        "colour_scale": {"low_s": _rounded(scale.low_s), "high_s": _rounded(scale.high_s), "map": "turbo",
                         "null_rgb": [128, 128, 128]},
        "views": views,
    }
