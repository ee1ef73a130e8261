"""A job's results: the result JSON, its images (overlays, masks, animation, loss plot) and DICOM files."""

from __future__ import annotations

from typing import Literal

from fastapi.responses import FileResponse, JSONResponse, Response

from ...engine_adapter import engine
from ..schemas.jobs import previous_link_header, succeeded_result
from ...problems import Problem, problem_responses
from ...storage.store import JobRecord
from ..deps import Ctx, OwnedJob, Principal, ServiceContext, owned_job
from ..openapi import resource_router

router = resource_router("results")

# the engine names its output files (dsareg_engine.artifacts); these routes serve them
ARTIFACTS = {
    **{("overlays", view): (engine.overlay_png(view), engine.ARTIFACTS[engine.overlay_png(view)]) for view in ("ap", "lat")},
    **{("masks", view): (engine.mask_png(view), engine.ARTIFACTS[engine.mask_png(view)]) for view in ("ap", "lat")},
    **{("images", view): (engine.image_png(view), "image/png") for view in ("ap", "lat")},
    **{("layers", view): (engine.layers_png(view), "image/png") for view in ("ap", "lat")},
}
DicomName = Literal[tuple(engine.DICOM_FILES)]  # reg.dcm, overlay_ap.dcm, overlay_lat.dcm, loss.dcm

PNG_RESPONSE = {200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}},
                      "description": "The image."}}
CACHE = {"Cache-Control": "no-store"}  # PHI: never kept by a browser or proxy (secure_headers.py enforces it)


def artifact_file(ctx: ServiceContext, job: JobRecord, name: str, media: str, filename: str | None = None) -> Response:
    """The stored artifact ``name`` of a succeeded job (404 ``artifact-not-available`` otherwise)."""
    digest = job.artifacts.get(name)
    if job.status != "succeeded" or not digest:
        why = f"the job is {job.status}" if job.status != "succeeded" else "the job did not produce it"
        raise Problem(404, f"{name} is not available: {why}", kind="artifact-not-available",
                      extra={"job_status": job.status})
    path = ctx.blobs.local_path(digest)
    if path is None:
        raise Problem(404, f"{name} is no longer stored", kind="artifact-not-available")
    return FileResponse(path, media_type=media, filename=filename, headers=dict(CACHE))


@router.get("/v1/registrations/{job_id}/result", summary="Registration result (JSON)",
            responses={200: {"description": "mesh_to_world, per-view results and metrics",
                             "content": {"application/json": {"example": {
                                 "mesh_to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                                 "views": {"ap": {}, "lat": {}}, "metrics": {"dice": {"ap": 0.91, "lat": 0.9}}}}}},
                       **problem_responses(401, 404)})
def get_result(job: OwnedJob) -> Response:
    if job.status != "succeeded" or job.result is None:
        raise Problem(404, f"no result: the job is {job.status}", kind="result-not-available",
                      extra={"job_status": job.status})
    return JSONResponse(succeeded_result(job), headers=previous_link_header(job))


# the view (and DICOM name) is validated before the job is looked up: a bad one is a 422 for any job,
# so these routes call owned_job themselves instead of depending on OwnedJob


@router.get("/v1/registrations/{job_id}/overlays/{view}.png", summary="Overlay of the registered mesh",
            response_class=Response, responses={**PNG_RESPONSE, **problem_responses(401, 404, 422)})
def get_overlay(ctx: Ctx, job_id: str, view: Literal["ap", "lat"], who: Principal) -> Response:
    return artifact_file(ctx, owned_job(ctx.jobs, job_id, who), *ARTIFACTS[("overlays", view)])


@router.get("/v1/registrations/{job_id}/masks/{view}.png", summary="Vessel mask used for a view",
            response_class=Response, responses={**PNG_RESPONSE, **problem_responses(401, 404, 422)})
def get_mask(ctx: Ctx, job_id: str, view: Literal["ap", "lat"], who: Principal) -> Response:
    return artifact_file(ctx, owned_job(ctx.jobs, job_id, who), *ARTIFACTS[("masks", view)])


@router.get("/v1/registrations/{job_id}/images/{view}.png", summary="The image registered (8-bit grey)",
            description="The image the registration fitted: the frame, or the frames combined, subtracted; "
                        "at its own pixel grid, contrast stretched (0.5–99.5 percentiles).",
            response_class=Response, responses={**PNG_RESPONSE, **problem_responses(401, 403, 404, 422)})
def get_registered_image(ctx: Ctx, job_id: str, view: Literal["ap", "lat"], who: Principal) -> Response:
    return artifact_file(ctx, owned_job(ctx.jobs, job_id, who), *ARTIFACTS[("images", view)])


@router.get("/v1/registrations/{job_id}/layers/{view}.png", summary="Outlines and mask as RGB layers",
            description="Same grid as the image: R 255 = outline of the initial pose, G 255 = outline of the "
                        "registered pose, B bit 7 (128) = vessel mask, B bit 6 (64) = model pixels with no vessel "
                        "under them (unfilled). A page draws each as a toggle.",
            response_class=Response, responses={**PNG_RESPONSE, **problem_responses(401, 403, 404, 422)})
def get_layers(ctx: Ctx, job_id: str, view: Literal["ap", "lat"], who: Principal) -> Response:
    return artifact_file(ctx, owned_job(ctx.jobs, job_id, who), *ARTIFACTS[("layers", view)])


@router.get("/v1/registrations/{job_id}/model.json", summary="The model, both poses and the C-arm (3D scene)",
            description="vertices (flat x, y, z mm, the model file's vertex order as given: OBJ `v` lines in order, "
                        "duplicates kept), faces (flat, 0-based), poses.registered / poses.initial (4x4 mesh → "
                        "world) and per view the detector (source, image corners in world mm).",
            response_class=Response,
            responses={200: {"content": {"application/json": {}}, "description": "The model document."},
                       **problem_responses(401, 403, 404)})
def get_model(ctx: Ctx, job: OwnedJob) -> Response:
    return artifact_file(ctx, job, engine.MODEL_JSON, "application/json")


@router.get("/v1/registrations/{job_id}/animation.gif", summary="Animation of the optimization",
            response_class=Response,
            responses={200: {"content": {"image/gif": {"schema": {"type": "string", "format": "binary"}}},
                             "description": "Animated GIF (only with options.animation)."},
                       **problem_responses(401, 404)})
def get_animation(ctx: Ctx, job: OwnedJob) -> Response:
    return artifact_file(ctx, job, engine.ANIMATION_GIF, engine.ARTIFACTS[engine.ANIMATION_GIF])


@router.get("/v1/registrations/{job_id}/loss.png", summary="Plot of the loss per iteration",
            response_class=Response, responses={**PNG_RESPONSE, **problem_responses(401, 404)})
def get_loss_plot(ctx: Ctx, job: OwnedJob) -> Response:
    return artifact_file(ctx, job, engine.LOSS_PNG, engine.ARTIFACTS[engine.LOSS_PNG])


@router.get("/v1/registrations/{job_id}/dicom/{name}",
            summary="DICOM results: Spatial Registration (reg.dcm) and Secondary Capture overlays",
            response_class=Response,
            responses={200: {"content": {"application/dicom": {"schema": {"type": "string", "format": "binary"}}},
                             "description": "A DICOM Part 10 file."},
                       **problem_responses(401, 404, 422)})
def get_dicom(ctx: Ctx, job_id: str, name: DicomName, who: Principal) -> Response:
    return artifact_file(ctx, owned_job(ctx.jobs, job_id, who), name, engine.DICOM_FILES[name], filename=name)
