"""Typed payloads of the OpenAPI document: geometry, options, result (and the multipart parts).

These models declare the payloads with descriptions, units, examples and enums, and
:func:`document` puts them into ``/openapi.json``:

* ``components.schemas``: ``RegistrationOptions``, ``ViewSpec`` and ``LatFromAp`` (the engine's own
  models, so the fields cannot drift), ``GeometryFile`` (the engine's ``RigSpec``, its view names spelled
  out), ``RegistrationResult`` /
  ``ViewResult`` / ``ResultMetrics`` / ``GroundTruthErrors``;
* the ``POST /v1/registrations`` multipart parts, each with its schema and encoding;
* ``JobStatus.result`` and ``GET …/result`` point at ``RegistrationResult``.

The result contract is closed: every model here refuses undeclared fields (``CLOSED``, published as
``additionalProperties: false``), so every field the engine writes into ``result.json`` must be
declared here, with a description (docs/api/result-contract.md); the tests validate every result they
produce against :class:`RegistrationResult` (tests/support/result_contract.py).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from ...engine_adapter import engine
from .closed import CLOSED
from .confidence import Verdict
from .dicom_result import DicomResult
from .hemodynamics import HemodynamicsSummary
from .input_records import Acquisition, ImageReadingRecord, InputDecisionRecord, VolumeRead
from .result_metrics import Matrix4, ResultMetrics

Matrix34 = list[list[float]]
IDENTITY = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
REF = "#/components/schemas/{model}"


# ---- geometry file ---------------------------------------------------------------------------


class GeometryFile(engine.RigSpec):
    """The C-arm geometry (the `geometry` part): two views in world millimetres and the initial pose.
    Instead of JSON, the part may be a preset name (`paper`), or be left out when both images are
    DICOM XA (or `.rad`) files whose headers carry the geometry."""

    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [{
        "views": {"ap": {"image_size": [800, 800], "pixel_spacing_mm": [0.3, 0.3], "sid_mm": 1200.0,
                         "world_to_view": [[0, 0, -1, 0], [0, 1, 0, 0], [1, 0, 0, 750], [0, 0, 0, 1]]}},
        "lat_from_ap": {"angle_deg": 90.0}, "initial_mesh_to_world": IDENTITY}]})

    views: dict[Literal["ap", "lat"], engine.ViewSpec] = Field(description="The views by name: `ap` and `lat`.")


# ---- result ---------------------------------------------------------------------------------


class DetectorGeometry(BaseModel):
    """The C-arm of one view as it stood, world mm (the rig's convention: source at the view frame's origin, the
    image plane at z = sid_mm)."""

    model_config = ConfigDict(extra="forbid")

    source_mm: list[float] = Field(min_length=3, max_length=3, description="X-ray source position, world mm.")
    corners_mm: list[list[float]] = Field(min_length=4, max_length=4, description=(
        "World mm of the image's outer corners on the detector: top-left, top-right, bottom-right, bottom-left of "
        "the stored image (pixel edges, (u, v) = (-0.5, -0.5) … (W-0.5, H-0.5))."))
    image_size_px: list[int] = Field(min_length=2, max_length=2, description="(W, H) of the image registered.")
    sid_mm: float = Field(description="Source-to-detector distance, mm.")
    pixel_spacing_mm: list[float] = Field(min_length=2, max_length=2, description="(du, dv) at the detector, mm.")
    mm_per_px_at_model: float | None = Field(None, description="A pixel's size at the depth of the model's centre "
                                                               "(registered pose), mm: one mm scale for both views.")


class ViewResult(BaseModel):
    """Per-view outcome."""

    model_config = CLOSED

    world_to_view: Matrix4 = Field(description="4x4 world mm → view frame (the geometry's, unchanged).")
    mesh_to_view: Matrix4 = Field(description="4x4 = world_to_view · mesh_to_world.")
    projection_matrix: Matrix34 = Field(description="3x4 homogeneous mesh-frame mm → homogeneous pixels.")
    dice: float = Field(ge=0, le=1, description="Dice of the registered hard silhouette with the vessel mask.")
    iou: float = Field(ge=0, le=1, description="Intersection over union of the same.")
    detector: DetectorGeometry | None = Field(None, description="Where the source and the detector stood "
                                                                "(the review page's 3D scene; model.json repeats it).")
    image_from_job: str | None = Field(
        None, description="A tracking job sent one plane only (POST …/track): this view's image is not from this job's "
                          "run but an earlier one's, carried along: the id of the job it was sent with. The view was "
                          "not fitted (metrics.tracking.views); its overlay and Dice show the new pose on that earlier "
                          "image. Null: the image came with this job.")


# ---- result ----------------------------------------------------------------------------------------


class RegistrationResult(BaseModel):
    """The registration result (`result.json`). `verdict` says whether to trust `mesh_to_world`; a job that
    `succeeded` only ran to the end. Every field is declared (none undeclared is written); a later version may
    declare more, so clients should ignore fields they do not know."""

    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [{
        "mesh_to_world": IDENTITY, "initial_mesh_to_world": IDENTITY, "verdict": "ok",
        "views": {"ap": {"world_to_view": IDENTITY, "mesh_to_view": IDENTITY,
                         "projection_matrix": [[692.8, 0, 399.5, 0], [0, 692.8, 399.5, 0], [0, 0, 1, 0]],
                         "dice": 0.997, "iou": 0.994}},
        "metrics": {"loss": 0.0019, "converged": True, "reason": "pose change below tolerance in the final stage",
                    "confidence": {"verdict": "ok", "reasons": [], "signals": {}}}}]})

    mesh_to_world: Matrix4 = Field(description="4x4 rigid estimated pose, mesh mm → world mm: the answer.")
    initial_mesh_to_world: Matrix4 | None = Field(None, description="4x4 pose the registration started from.")
    views: dict[str, ViewResult] = Field(description="Per view (`ap`, `lat`).")
    metrics: ResultMetrics
    warnings: list[str] | None = Field(None, description="Notes from reading the inputs (decimation, resizing...).")
    image_reading: dict[str, ImageReadingRecord] | None = Field(
        None, description="Per view, what was read from a multi-frame XA run (frames, mask frames, recipe, shift).")
    verdict: Verdict | None = Field(
        None, description="= metrics.confidence.verdict: ok (use the pose), check (look at the overlays first), "
                          "failed (do not use it). Null only for results of versions before the verdict.")
    dicom: DicomResult | None = Field(None, description="The DICOM objects written (and fetched/stored in a PACS).")
    volume: VolumeRead | None = Field(None, description="For a volume input: what was read from it.")
    input_decisions: list[InputDecisionRecord] | None = Field(
        None, description="The decisions taken about the inputs (run kind, mask frames, frames combined, volume kind "
                          "and window, units, handedness), each with its measure and margin.")
    hemodynamics: HemodynamicsSummary | None = Field(
        None, description="With options.hemodynamics: contrast arrival and time to peak on the model from both runs "
                          "(per-vertex values: links.hemodynamics).")
    acquisition: Acquisition | None = Field(
        None, description="DICOM XA runs: whether they were acquired together; sequential runs add a pose per run and "
                          "the motion between them (null without DICOM headers saying either).")


# ---- putting them into the OpenAPI document -----------------------------------------------


def _components(*models: type[BaseModel]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for model in models:
        schema = model.model_json_schema(ref_template=REF, mode="serialization")
        out.update(schema.pop("$defs", {}))
        out[model.__name__] = schema
    return out


def options_model() -> type[BaseModel]:
    from ...engine_adapter import engine

    return engine.RegistrationOptions


def multipart_schema(presets: list[str]) -> dict[str, Any]:
    """The multipart/form-data body of ``POST /v1/registrations``."""
    return {
        "type": "object",
        "required": ["ap", "lat"],
        "description": "Give `mesh` or `volume`, both images, and optionally `geometry` and `options`.",
        "properties": {
            "mesh": {"type": "string", "format": "binary",
                     "description": "Vessel surface mesh in mm: OBJ, STL (ASCII/binary), PLY, OFF, GLB, VTP or legacy "
                                    "VTK polydata."},
            "volume": {"type": "array", "items": {"type": "string", "format": "binary"},
                       "description": "Vessel volume instead of a mesh: NIfTI, NRRD (`.nhdr` + its data file as two "
                                      "parts), MetaImage (`.mha`, or `.mhd` + its data file), legacy VTK structured "
                                      "points, a DICOM series (one part per file) or `.rad` + `.raw`; its vessels read "
                                      "by kind (CTA, TOF-MRA, 3D-DSA) or as a label map, and meshed (marching cubes)."},
            "ap": {"type": "string", "format": "binary",
                   "description": "AP view: DSA image or binary vessel mask (PNG, TIFF, JPEG, DICOM XA single/"
                                  "multi-frame); a `.rad` + `.raw` pair as two parts."},
            "lat": {"type": "string", "format": "binary", "description": "LAT view, as `ap`."},
            "geometry": {
                "description": "The C-arm geometry: a preset name, GeometryFile JSON (text or a file part), or "
                               "nothing when DICOM XA / .rad headers carry it.",
                "anyOf": [
                    {"type": "string", "enum": presets, "description": "A preset name."},
                    {"type": "string", "contentMediaType": "application/json",
                     "contentSchema": {"$ref": REF.format(model="GeometryFile")}},
                ],
                "examples": [presets[0] if presets else "paper"],
            },
            "options": {
                "type": "string", "contentMediaType": "application/json",
                "contentSchema": {"$ref": REF.format(model="RegistrationOptions")},
                "description": "RegistrationOptions as JSON text; every field is optional.",
                "examples": ['{"starts": 2, "max_iterations": 300}'],
            },
            "callback_url": {
                "type": "string", "maxLength": 2048,
                "description": "POSTed the job summary (JobSummary JSON, signed) once the job ends; must start with "
                               "one of the server's DSAREG_CALLBACK_ALLOWED prefixes, else 422.",
                "examples": ["https://ris.example.org/dsareg-hooks/job-done"],
            },
        },
    }


def reference_model() -> type[BaseModel]:
    from ...pacs.dicomweb import DicomwebRegistrationRequest

    return DicomwebRegistrationRequest


def dimse_reference_model() -> type[BaseModel]:
    from ...pacs.dimse.pull import DimseRegistrationRequest

    return DimseRegistrationRequest


def json_body_schema() -> dict[str, Any]:
    """The ``application/json`` body: inputs by DICOMweb or by DIMSE reference, told apart by the key of ``source``."""
    return {"oneOf": [{"$ref": REF.format(model=reference_model().__name__)},
                      {"$ref": REF.format(model=dimse_reference_model().__name__)}],
            "description": 'Inputs by reference: `{"source": {"dicomweb": ...}}` (QIDO/WADO-RS) or '
                           '`{"source": {"dimse": ...}}` (C-MOVE / C-GET from a DSAREG_DICOM_PEERS peer); '
                           "the single key of `source` says which."}


def document(schema: dict[str, Any]) -> dict[str, Any]:
    """Add the payload schemas to an OpenAPI document (in place; returned for convenience)."""
    from ...engine_adapter import engine

    PRESETS = engine.PRESETS

    schemas = schema.setdefault("components", {}).setdefault("schemas", {})
    schemas.update(_components(options_model(), GeometryFile, RegistrationResult, reference_model(),
                               dimse_reference_model()))
    result_ref = {"$ref": REF.format(model="RegistrationResult")}
    for name in ("JobStatus", "JobStatus-Output"):
        props = schemas.get(name, {}).get("properties", {})
        if "result" in props:
            props["result"] = {"anyOf": [result_ref, {"type": "null"}],
                               "description": "The registration result when succeeded, else null."}
    paths = schema.get("paths", {})
    post = paths.get("/v1/registrations", {}).get("post")
    if post is not None:
        post["requestBody"] = {"required": True, "content": {
            "multipart/form-data": {
                "schema": multipart_schema(sorted(PRESETS)),
                "encoding": {"options": {"contentType": "application/json, text/plain"},
                             "geometry": {"contentType": "text/plain, application/json"},
                             "volume": {"contentType": "application/octet-stream"}},
            },
            # inputs by DICOMweb or DIMSE reference (service/intake/reference.py)
            "application/json": {"schema": json_body_schema()},
        }}
    get_result = paths.get("/v1/registrations/{job_id}/result", {}).get("get")
    if get_result is not None:
        ok = get_result.setdefault("responses", {}).setdefault("200", {})
        ok["description"] = "The registration result."
        ok["content"] = {"application/json": {"schema": result_ref}}
    return schema
