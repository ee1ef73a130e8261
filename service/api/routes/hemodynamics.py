"""A job's hemodynamics outputs (``options.hemodynamics``): the per-vertex JSON, the coloured model, the parametric maps."""

from __future__ import annotations

from typing import Literal

from fastapi.responses import Response

from ...engine_adapter import engine
from ...problems import problem_responses
from ..deps import Ctx, OwnedJob, Principal, owned_job
from ..openapi import resource_router
from ..schemas.hemodynamics import HemodynamicsDocument
from .artifacts import PNG_RESPONSE, artifact_file

router = resource_router("hemodynamics")

BINARY = {"schema": {"type": "string", "format": "binary"}}


@router.get("/v1/registrations/{job_id}/hemodynamics.json", summary="Arrival and peak times per vertex of the model",
            responses={200: {"model": HemodynamicsDocument, "description": "Per vertex of the model file as given "
                             "(null where not measurable); present when the job asked for options.hemodynamics."},
                       **problem_responses(401, 403, 404)})
def get_hemodynamics(ctx: Ctx, job: OwnedJob) -> Response:
    return artifact_file(ctx, job, engine.HEMODYNAMICS_JSON, engine.ARTIFACTS[engine.HEMODYNAMICS_JSON])


@router.get("/v1/registrations/{job_id}/hemodynamics.{kind}", summary="The model coloured by arrival time (PLY, VTK)",
            response_class=Response,
            responses={200: {"content": {"application/octet-stream": BINARY},
                             "description": "hemodynamics.ply (vertex colours, the colour scale in its comments) or "
                                            "hemodynamics.vtk (point-data arrays, for 3D Slicer / ParaView)."},
                       **problem_responses(401, 403, 404, 422)})
def get_hemodynamics_model(ctx: Ctx, job_id: str, kind: Literal["ply", "vtk"], who: Principal) -> Response:
    name = f"hemodynamics.{kind}"
    return artifact_file(ctx, owned_job(ctx.jobs, job_id, who), name, engine.ARTIFACTS[name], filename=name)


@router.get("/v1/registrations/{job_id}/parametric/{view}.png", summary="A run colour-coded by arrival time",
            response_class=Response, responses={**PNG_RESPONSE, **problem_responses(401, 403, 404, 422)})
def get_parametric(ctx: Ctx, job_id: str, view: Literal["ap", "lat"], who: Principal) -> Response:
    name = engine.parametric_png(view)
    return artifact_file(ctx, owned_job(ctx.jobs, job_id, who), name, engine.ARTIFACTS[name])
