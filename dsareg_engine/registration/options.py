"""Options of one registration job (pydantic: the CLI and the HTTP service share them)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..errors import DsaregInputError

Configuration = Literal["ap", "lat", "simultaneous", "ap_then_lat", "lat_then_ap"]
CONFIGURATIONS: tuple[str, ...] = ("ap", "lat", "simultaneous", "ap_then_lat", "lat_then_ap")
Matrix4 = list[list[float]]
FrameIndex = Annotated[int, Field(ge=0, le=100000)] | Literal["minip"] | None


class FrameChoice(BaseModel):
    """Which frame of a multi-frame XA run each view uses (0-based frame indices)."""

    model_config = ConfigDict(extra="forbid")

    ap: FrameIndex = Field(None, description="AP: a 0-based frame index, 'minip' (native runs: the MinIP of the "
                           "subtracted arterial phase; subtracted runs: of all frames), or null: native runs the "
                           "per-pixel maximum opacity over the arterial phase, subtracted runs the frame of "
                           "maximum vessel opacification.")
    lat: FrameIndex = Field(None, description="LAT: as ap.")


FiniteMm = Annotated[float, Field(allow_inf_nan=False)]
Point3 = Annotated[list[FiniteMm], Field(min_length=3, max_length=3)]


class SphereRegion(BaseModel):
    """A sphere in the model frame."""

    model_config = ConfigDict(extra="forbid")

    centre_mm: Point3 = Field(description="Centre [x, y, z] (model frame, mm).")
    radius_mm: FiniteMm = Field(gt=0, description="Radius (mm).")


class ModelRegion(BaseModel):
    """The part of the model a run injected (model frame, mm): exactly one of a box, a sphere or the
    branch nearest a point (that branch and everything downstream of it, from the model's inflow)."""

    model_config = ConfigDict(extra="forbid")

    box_mm: Annotated[list[Point3], Field(min_length=2, max_length=2)] | None = Field(
        None, description="Opposite corners [[x0, y0, z0], [x1, y1, z1]] of an axis-aligned box.")
    sphere: SphereRegion | None = Field(None, description="A sphere.")
    branch_near_mm: Point3 | None = Field(None, description="A point [x, y, z] near the injected branch: the branch "
                                          "nearest it and what lies downstream of it (the inflow is guessed: the "
                                          "thickest vessel's far end from the model's centre).")

    @model_validator(mode="after")
    def _exactly_one(self) -> ModelRegion:
        given = [name for name in ("box_mm", "sphere", "branch_near_mm") if getattr(self, name) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of box_mm, sphere, branch_near_mm")
        return self


class RegistrationOptions(BaseModel):
    """What a caller may choose; every field has a default that works."""

    model_config = ConfigDict(extra="forbid")

    configuration: Configuration = Field(
        "simultaneous", description="Views and their order (the paper's Table 1 rows)."
    )
    starts: int = Field(4, ge=1, le=64, description="Initial poses optimized in parallel; the best is kept.")
    start_spread_deg: float = Field(
        5.0, ge=0.0, le=45.0, description="Rotation spread of the extra starts around the initial pose (degrees)."
    )
    start_spread_mm: float = Field(
        5.0, ge=0.0, le=100.0, description="Translation spread of the extra starts (mm)."
    )
    max_iterations: int = Field(300, ge=1, le=5000, description="Cap on gradient iterations per stage.")
    working_size_px: int = Field(
        0, ge=0, le=4096, description="Longest image side of the final stage in pixels; 0 = the images' own size."
    )
    seed: int = Field(0, ge=0, le=2**63 - 1, description="Seed for the extra starts; the same seed gives the same result.")
    coarse_to_fine: bool = Field(True, description="Image pyramid from ~100 px up (off: full size only).")
    refine: bool = Field(True, description="Final stage at full size with a pose-change stop rule (L-BFGS; Levenberg–Marquardt after a two-view pyramid on the CPU).")
    mode: Literal["full", "track"] = Field(
        "full",
        description="full: multi-start coarse-to-fine registration. track: re-registration after a small motion "
        "(≤ ~3 mm / 3°) from the initial pose (the previous result): one start, a short blurred stage at ~200 px, "
        "then L-BFGS at full size; metrics.motion reports the motion from the initial pose.",
    )
    thin_vessel_weighting: bool = Field(
        False, description="Weight pixels so thin branches count as much as thick ones."
    )
    border_correction: bool = Field(
        True,
        description="Before the fine stages, measure per view how much wider (px) the vessel mask is than the "
        "model's silhouette and move the target's border by that much (segmentation thresholds rarely put "
        "the border exactly on the model's surface); reported as metrics.border_shift_px.",
    )
    initial_mesh_to_world: Matrix4 | None = Field(None, description="Overrides the geometry's initial pose.")
    reference_mesh_to_world: Matrix4 | None = Field(
        None, description="Tracking (mode track): the procedure's first pose, mesh mm → world mm; the result's "
        "metrics.tracking.since_reference is the motion since it (null: the initial pose is the reference). "
        "POST …/track sets it from the job it tracks from.")
    single_plane_depth: Literal["fit", "previous"] = Field(
        "fit", description="Tracking with one plane (configuration ap or lat): the model's depth along that plane's "
        "beam, which one view shows through perspective alone. 'fit': where the fit puts it (within 0.1 mm on "
        "synthetic images of an exact model, but a model 1 % too large moved it 1.4-1.6 mm: "
        "docs/benchmarks/tracking.md); 'previous': held at the previous pose's (no motion along the beam assumed). "
        "Either way metrics.tracking says it is not measured and the verdict is at most check.")
    region: ModelRegion | None = Field(
        None, description="Register only this part of the model (what the run injected, when the model holds more "
        "vessels than the images show); without it partial visibility is detected from the images.")
    initialization: Literal["auto", "given", "search"] = Field(
        "auto",
        description="Where the starts come from: 'given' = the initial pose (request, else geometry, else identity) "
        "and random perturbations of it; 'search' = triangulate the masks' centroids for the position and search "
        "all rotations for the best distinct starts (at least 8 of them); 'auto' = 'given' when an initial pose was "
        "given, else 'search'. "
        "Reported as metrics.initialization.",
    )
    ground_truth_mesh_to_world: Matrix4 | None = Field(
        None, description="Known pose (synthetic studies): adds error metrics to the result."
    )
    segmentation: Literal["auto", "dsa", "otsu", "vesselness", "mask"] = Field(
        "auto", description="How DSA images become vessel masks (inputs that are masks are used as they are; "
        "auto = 'dsa': flattened background, border at a fraction of the local vessel contrast)."
    )
    frames: FrameChoice = Field(default_factory=FrameChoice, description="Multi-frame XA runs: the frame each "
                                "view uses (the two views may differ); the result's image_reading says which were used.")
    subtraction: Literal["auto", "off"] = Field(
        "auto", description="Multi-frame XA runs: 'auto' subtracts native (unsubtracted) runs in the log domain, by "
        "their Mask Subtraction Sequence or, without one, with the frames before contrast arrives as the mask; "
        "'off' reads every run as stored.")
    motion_correction: bool = Field(
        True, description="Native XA runs: move the mask onto the contrast frame by the patient motion measured on "
        "the background (a sub-pixel translation; reported in image_reading.*.mask_shift_px).")
    volume_kind: Literal["auto", "cta", "mra", "3d-dsa"] = Field(
        "auto", description="What a volume input is: cta (CT in HU: vessels in a HU window, bone removed), mra "
        "(TOF-MRA: bright vessels, scalp fat and skull excluded), 3d-dsa (already subtracted: Otsu threshold); "
        "auto = from the DICOM tags (Modality, Image Type, Contrast/Bolus Agent) and the values. Reported as "
        "result volume.kind.")
    volume_vessel_min: float | None = Field(
        None, description="Lowest vessel value in the volume (HU for CTA, intensity for MRA / 3D-DSA); null = "
        "estimated halfway between tissue and vessels.")
    volume_vessel_max: float | None = Field(
        None, description="CTA: HU from which a voxel is bone (default 700); ignored for other kinds.")
    volume_labels: list[Annotated[int, Field(ge=1)]] | None = Field(
        None, min_length=1, description="A label map's labels that are vessels (e.g. [1, 2, 3]); null = every label "
        "above 0. A volume whose values are a few whole numbers with a background of 0 (a label map, a 0/1 mask) is "
        "read as labels, all its pieces but specks kept; with this option the volume must be one. Reported as "
        "result volume.labels and input_decisions (vessel labels, vessel pieces).")
    mesh_units: Literal["mm", "cm", "m"] | None = Field(
        None, description="The mesh file's length unit; null = the format's own (glTF/GLB: metres) or else "
        "millimetres. A model whose size is implausible for head arteries in that unit is refused at submission. "
        "Reported in result input_decisions (what: units).")
    animation: bool = Field(False, description="Also write an animated GIF of the optimization.")
    hemodynamics: bool = Field(
        False, description="Also map contrast arrival and time to peak from both runs onto the registered model "
        "(result.hemodynamics, hemodynamics.json / .ply / .vtk, parametric_{ap,lat}.png); needs multi-frame DICOM XA "
        "runs with frame timing. The registration itself is unchanged.")
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="Where to run; auto = CUDA when available (tracking: the CPU, faster there).")
    mirror_check: bool = Field(
        True, description="When the kept pose fits poorly (some view's Dice below 0.7), also register the model's mirror "
        "image to tell a mirrored model (result confidence.signals.mirror), and, on a failed fit of images no header names "
        "(PNG, TIFF, masks), the two images exchanged (a reason then says they look swapped). Off: neither fit (the "
        "mirror's cost is a pose search), for a caller that knows the model's handedness or a fit meant to be rough (a worker's warm-up job).")


def image_reading(options: RegistrationOptions):
    """The options' image reading (:class:`dsareg_engine.io.xa_run.ImageReading`)."""
    from ..io.xa_run import ImageReading

    return ImageReading(ap_frame=options.frames.ap, lat_frame=options.frames.lat, subtraction=options.subtraction,
                        motion_correction=options.motion_correction)


def _is_union_tag(part) -> bool:
    """Pydantic names the member of a union it tried (``constrained-int``, ``literal['minip']``); not a field."""
    text = str(part)
    return any(c in text for c in "-[('") or text in ("int", "str", "float", "bool", "none")


def parse_options(data: dict | str | bytes | None) -> RegistrationOptions:
    """Validate options given as a dict or JSON text.

    Raises:
        DsaregInputError: naming the offending field, e.g. ``options.starts``.
    """
    try:
        if data is None:
            return RegistrationOptions()
        if isinstance(data, (str, bytes)):
            return RegistrationOptions.model_validate_json(data)
        return RegistrationOptions.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        location = ".".join(str(part) for part in first["loc"] if not _is_union_tag(part))
        raise DsaregInputError(
            first["msg"],
            field=f"options.{location}" if location else "options",
            accepted="a JSON object with fields " + ", ".join(RegistrationOptions.model_fields),
        ) from None
