"""Hemodynamics payloads: ``result.hemodynamics`` (the summary) and ``hemodynamics.json`` (per-vertex arrays).

What the fields mean, with the definitions of arrival and peak: docs/concepts/hemodynamics.md.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

from .closed import CLOSED


class RunTimingRecord(BaseModel):
    """The frame times of one run, as read from its header."""

    model_config = CLOSED

    times_s: list[float] = Field(description="Each frame's time, s from the run's own first frame.")
    source: str = Field(description="The attribute they came from: FrameAcquisitionDateTime, FrameReferenceDateTime, "
                                    "FrameTimeVector, FrameTime or CineRate.")
    frame_interval_s: float = Field(description="The median time between frames, s.")
    start: str | None = Field(None, description="When the run's first frame was acquired (ISO 8601, the header's "
                                                "local time), or null.")


class HemodynamicsView(BaseModel):
    """One view's part of the measurement."""

    model_config = CLOSED

    points: int = Field(description="Vessel points of the working mesh (one per vertex).")
    inside: int = Field(description="Points whose cross-section lies inside this view's image.")
    overlapped: int = Field(description="Points another model part overlaps in this view (the other view carries them).")
    filled: int = Field(description="Points whose curve in this view shows contrast (peak significant and a filled "
                                    "vessel's share of opacity).")
    median_footprint_px: float | None = Field(None, description="Median radius of the sampled cross-section, px.")
    unmixed: int = Field(0, description="Points no view sees clean, measured in this view by unmixing (their curve "
                                        "less the modelled contribution of the vessels crossing them).")
    unmixed_filled: int = Field(0, description="Of those, the points whose unmixed curve shows contrast.")
    frames: int = Field(description="Frames of the run.")
    timing: RunTimingRecord
    clean_vertices: int = Field(description="Vertices of the model file this view sees clear of other vessels.")
    notes: list[str] = Field(description="How the frames were made (subtraction, mask shift).")


class ColourScale(BaseModel):
    """The arrival-time colour scale of the coloured model and the parametric maps."""

    model_config = CLOSED

    low_s: float = Field(description="Earliest time of the scale (dark blue), s from the first AP frame.")
    high_s: float = Field(description="Latest time of the scale (dark red), s.")
    map: Literal["turbo"] = Field(description="The colour map (OpenCV Turbo).")
    null_rgb: list[int] = Field(description="The colour of a vertex without a value.")


class HemodynamicsSummary(BaseModel):
    """`result.hemodynamics` (with `options.hemodynamics`): contrast arrival and time to peak on the registered
    model from both runs; the per-vertex values are in `hemodynamics.json` (`links.hemodynamics`)."""

    model_config = CLOSED

    vertices: int = Field(description="Vertices the per-vertex arrays follow (the model file's, duplicates included).")
    vertex_order: str = Field(description="Which vertices: the model file as given, or for a volume input "
                                          "hemodynamics.ply (the mesh dsareg made).")
    mapped_fraction: float = Field(description="Share of those vertices with an arrival time (0..1).")
    never_arrived: int = Field(description="Vertices a clean view measured and found without contrast (null values).")
    views_disagree: int = Field(description="Vertices one clean view sees filled and the other empty (left null).")
    unmixed_vertices: int = Field(0, description="Vertices no view sees clean whose values come from unmixing "
                                                 "(`unmixed` in hemodynamics.json).")
    mtt_median_s: float | None = Field(None, description="Median mean transit time (gamma-variate fit) over the "
                                                         "vertices with one, s.")
    agreement_points: int = Field(description="Vertices both views measured.")
    agreement_median_s: float | None = Field(None, description="Median |arrival AP − arrival LAT| over those, s.")
    lat_minus_ap_median_s: float | None = Field(None, description="Median arrival LAT − AP, s (a bias: clock offset "
                                                                  "or pose error).")
    arrival_range_s: list[float | None] | None = Field(None, description="[earliest, latest] arrival, s.")
    offset_s: float | None = Field(None, description="How much later the LAT run started than the AP run, s.")
    offset_basis: str = Field(description="How the offset is known (the runs' start times, or assumed 0).")
    transfer_max_mm: float | None = Field(None, description="Largest distance from a file vertex to the working "
                                                            "vertex whose values it takes, mm.")
    colour_scale: ColourScale
    views: dict[str, HemodynamicsView] = Field(description="Per view (`ap`, `lat`).")
    files: list[str] | None = Field(None, description="The files written (hemodynamics.json/.ply/.vtk, "
                                                      "parametric_{ap,lat}.png); absent from hemodynamics.json's copy.")
    cpu_s: float | None = Field(None, description="CPU seconds the step took (user + sys, all threads); absent from "
                                                  "hemodynamics.json's copy (written before the step ends).")


NullableSeries = list[float | None]


class HemodynamicsDocument(BaseModel):
    """`hemodynamics.json`: per vertex of the model file as given (OBJ `v` lines / PLY vertex order, duplicates
    included; for a volume input, the vertices of hemodynamics.ply), null where not measurable. Times are s from
    the first AP frame."""

    model_config = CLOSED

    vertex_order: str | None = Field(None, description="Which vertices the arrays follow.")
    vertices: int = Field(description="Length of every array.")
    clock: str = Field(description="What t = 0 is.")
    frame_times_s: dict[str, list[float]] = Field(description="Per view, its frames' times on that clock.")
    arrival_s: NullableSeries = Field(description="Contrast arrival: the curve's rise through half its peak, s.")
    peak_s: NullableSeries = Field(description="Time to peak (sub-frame), s.")
    peak_opacity: NullableSeries = Field(description="Peak opacity (−log intensity above the background).")
    arrival_s_ap: NullableSeries = Field(description="Arrival measured in the AP run (null where overlapped there).")
    arrival_s_lat: NullableSeries = Field(description="Arrival measured in the LAT run.")
    agreement_s: NullableSeries = Field(description="|arrival_s_ap − arrival_s_lat| where both measured.")
    mtt_s: NullableSeries = Field(description="Mean transit time of the gamma-variate fit of the first pass, "
                                              "(α + 1) β: its mean time after its onset, s.")
    area: NullableSeries = Field(description="Area under the gamma-variate fit of the first pass, K β^(α+1) Γ(α+1) "
                                             "(opacity × s).")
    overlap_ap: list[bool] = Field(description="The AP view is not clean there (another vessel overlaps, or outside).")
    overlap_lat: list[bool] = Field(description="The LAT view is not clean there.")
    unmixed: list[bool] = Field(description="No view is clean there: the values come from unmixing the vessels "
                                            "crossing the point (docs/concepts/hemodynamics.md).")
    summary: HemodynamicsSummary
