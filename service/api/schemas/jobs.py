"""Response models of the HTTP API (they make the OpenAPI document)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from ...engine_adapter import engine
from ...problems import ProblemDetails
from .closed import CLOSED
from .confidence import Verdict
from ...storage.store import JobRecord
from .case import CaseIdentity, case_model
from .review import ExportState, Review, export_model, review_model

Status = Literal["queued", "running", "succeeded", "failed", "canceled"]
STATUS_TEXT = ("The job's state. `succeeded` means the job ran to the end and has a result; whether to trust the pose "
               "is the `verdict` (ok / check / failed), never the status.")
VERDICT_TEXT = ("= result.metrics.confidence.verdict: ok (use the pose), check (look at the overlays first), failed "
                "(do not use the pose). Null until the job succeeded (and for results of versions before the verdict).")

EXAMPLE_ID = "0b5a6f3c9d2e4f1a8b7c6d5e4f3a2b1c"
CASE_TEXT = ("Whose case it is (patient, study, series of each input, source), from the inputs' DICOM headers; "
             "null until the inputs were read (jobs by PACS reference: once a worker fetched them).")


class Progress(BaseModel):
    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [
        {"stage": "ap+lat:1/2", "iteration": 15, "loss": 0.0152, "fraction": 0.21}]})

    stage: str = Field(description="Current stage: 'queued', 'start', an optimization stage named "
                                   "'<views>:1/<downscale>' (e.g. 'ap+lat:1/4', 'ap:1/2') or "
                                   "'<views>:1/1:refine' (the final L-BFGS), then the outputs: 'outputs' (PNGs, "
                                   "0.92–0.96), 'animation', 'hemodynamics' (with options.hemodynamics), 'dicom' "
                                   "(0.98) and 'saving' (0.99); the PACS export comes after the job (its `export`). "
                                   "A succeeded job reports its last optimization stage at 1.0.")
    iteration: int = Field(0, description="Iteration within the stage (L-BFGS: function evaluations).")
    loss: float | None = Field(None, description="Latest loss (mean squared silhouette error over the active views).")
    fraction: float = Field(0.0, ge=0.0, le=1.0,
                            description="Fraction of the expected work done, never decreasing: each stage's share is "
                                        "its expected iterations × pixels × starts; 1.0 when succeeded.")


def _link(description: str) -> Any:
    return Field(None, description=description)


class JobLinks(BaseModel):
    """Links of a job; only those that lead somewhere now are present."""

    model_config = CLOSED

    self: str = Field(description="The job's status.")
    cancel: str | None = _link("Cancel (POST); present while queued or running.")
    result: str | None = _link("Result JSON; present when succeeded.")
    overlay_ap: str | None = _link("AP overlay PNG; present when succeeded.")
    overlay_lat: str | None = _link("LAT overlay PNG; present when succeeded.")
    mask_ap: str | None = _link("AP vessel mask PNG used for the registration; present when succeeded.")
    mask_lat: str | None = _link("LAT vessel mask PNG; present when succeeded.")
    loss_plot: str | None = _link("Loss-per-iteration plot PNG; present when succeeded.")
    image_ap: str | None = _link("The AP image registered (frame or frames combined, subtracted), PNG.")
    image_lat: str | None = _link("The LAT image registered, PNG.")
    layers_ap: str | None = _link("AP outlines (initial, registered), mask and unfilled pixels as RGB layers, PNG.")
    layers_lat: str | None = _link("LAT layers, PNG.")
    model: str | None = _link("model.json: the model as given, both poses and the C-arm (the 3D scene).")
    animation: str | None = _link("Animated GIF; present only when the job asked for options.animation and succeeded.")
    dicom_reg: str | None = _link("DICOM Spatial Registration (reg.dcm); present when succeeded and written.")
    dicom_overlay_ap: str | None = _link("DICOM Secondary Capture of the AP overlay; present when succeeded and written.")
    dicom_overlay_lat: str | None = _link("DICOM Secondary Capture of the LAT overlay; present when succeeded and written.")
    dicom_loss: str | None = _link("DICOM Secondary Capture of the loss plot; present when succeeded and written.")
    hemodynamics: str | None = _link("Arrival and peak times per vertex (hemodynamics.json); present when the job "
                                     "asked for options.hemodynamics and succeeded.")
    hemodynamics_ply: str | None = _link("The model coloured by arrival time (PLY); with options.hemodynamics.")
    hemodynamics_vtk: str | None = _link("The model with arrival / peak point-data arrays (VTK); with options.hemodynamics.")
    parametric_ap: str | None = _link("The AP run colour-coded by arrival time (PNG); with options.hemodynamics.")
    parametric_lat: str | None = _link("The LAT run colour-coded by arrival time (PNG); with options.hemodynamics.")
    dicom_parametric_ap: str | None = _link("DICOM Secondary Capture of parametric_ap.png; when written.")
    dicom_parametric_lat: str | None = _link("DICOM Secondary Capture of parametric_lat.png; when written.")
    track: str | None = _link("POST new AP/LAT images here to re-register from this pose; present when succeeded.")
    previous: str | None = _link("The job this tracking job started from; present for tracking jobs.")


class CallbackState(BaseModel):
    """Delivery of the job's completion callback (``callback_url``; docs/api/callbacks.md)."""

    model_config = CLOSED

    url: str = Field(description="The callback_url of the submission.")
    state: Literal["pending", "delivering", "delivered", "failed"] = Field(
        description="pending: waits for the job to end or for the next attempt; delivering: an attempt is under way; "
                    "delivered: a 2xx answer; failed: out of attempts, or a 3xx/410 answer (redirects are not followed).")
    delivery_id: str = Field(description="The X-Dsareg-Delivery header of every attempt (the same on retries).")
    attempts: int = Field(0, description="Attempts made so far.")
    last_attempt_at: str | None = None
    next_attempt_at: str | None = Field(None, description="When the next attempt is due (state pending after a failure).")
    delivered_at: str | None = None
    last_response_status: int | None = Field(None, description="HTTP status of the last answer (null: no answer).")
    last_error: str | None = Field(None, description="Why the last attempt did not deliver.")


class JobStatus(BaseModel):
    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [{
        "id": EXAMPLE_ID, "status": "running", "created_at": "2026-01-01T10:00:00Z",
        "started_at": "2026-01-01T10:00:01Z", "finished_at": None, "attempts": 1, "cancel_requested": False,
        "progress": {"stage": "simultaneous", "iteration": 120, "loss": 0.083, "fraction": 0.4},
        "result": None, "error": None, "warnings": [],
        "links": {"self": f"/v1/registrations/{EXAMPLE_ID}", "cancel": f"/v1/registrations/{EXAMPLE_ID}/cancel"},
    }]})

    id: str
    status: Status = Field(description=STATUS_TEXT)
    verdict: Verdict | None = Field(None, description=VERDICT_TEXT)
    created_at: str
    started_at: str | None = None
    finished_at: str | None = None
    attempts: int = Field(description="Times a worker claimed the job (retries after a lost worker count).")
    cancel_requested: bool = False
    progress: Progress | None = None
    result: dict[str, Any] | None = Field(None, description="The registration result when succeeded.")
    error: ProblemDetails | None = Field(None, description="Why the job failed (problem details).")
    warnings: list[str] = Field(default_factory=list, description="Notes from reading the inputs.")
    callback: CallbackState | None = Field(None, description="The completion callback, when the job asked for one.")
    source: dict[str, Any] | None = Field(
        None, description='Only for a job made from a study received over DIMSE: {"dimse": {"calling_ae", '
                          '"study_uid", "pairing", "ap", "lat", "volume"}} (absent otherwise).')
    review: Review | None = Field(None, description="A person's latest review (POST /v1/registrations/{id}/review); "
                                                    "null until then.")
    case: CaseIdentity | None = Field(None, description=CASE_TEXT)
    export: ExportState | None = Field(
        None, description="The PACS export of the results (STOW-RS / C-STORE), sent after the job succeeded (held for "
                          "a review first with DSAREG_EXPORT_AFTER_REVIEW=true): its state, attempts and last error. "
                          "Absent when the job stores nothing into a PACS (and for jobs that ended before round 13, "
                          "which exported inside the job: result.dicom.stored / exported).")
    links: JobLinks


class JobSummary(BaseModel):
    """One job in a list: state, verdict and times; the full result is behind ``links.result``."""

    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [{
        "id": EXAMPLE_ID, "status": "succeeded", "created_at": "2026-01-01T10:00:00Z",
        "started_at": "2026-01-01T10:00:01Z", "finished_at": "2026-01-01T10:00:09Z", "seconds": 8.2,
        "progress": {"stage": "ap+lat:1/1:refine", "iteration": 11, "loss": 0.0019, "fraction": 1.0},
        "converged": True, "verdict": "ok", "dice": {"ap": 0.997, "lat": 0.998}, "error": None,
        "links": {"self": f"/v1/registrations/{EXAMPLE_ID}", "result": f"/v1/registrations/{EXAMPLE_ID}/result"},
    }]})

    id: str
    status: Status = Field(description=STATUS_TEXT)
    created_at: str
    started_at: str | None = None
    finished_at: str | None = None
    seconds: float | None = Field(None, description="Run time (started → finished), seconds.")
    progress: Progress | None = None
    converged: bool | None = Field(None, description="metrics.converged of the result (succeeded jobs).")
    verdict: Verdict | None = Field(None, description=VERDICT_TEXT)
    reasons: list[str] | None = Field(None, description="metrics.confidence.reasons: why the verdict is check or "
                                                        "failed, in plain words (empty when ok).")
    dice: dict[str, float] | None = Field(None, description="Dice per view of the registered silhouette.")
    error: str | None = Field(None, description="Title and detail of the problem, for failed jobs.")
    review: Review | None = Field(None, description="A person's latest review; null until then.")
    case: CaseIdentity | None = Field(None, description=CASE_TEXT)
    links: JobLinks


class JobList(BaseModel):
    model_config = CLOSED

    items: list[JobSummary] = Field(description="Newest first; each a summary (GET links.self for the job, "
                                                "links.result for its result).")
    next_cursor: str | None = Field(None, description="Pass as ?cursor= for the next page; null on the last page.")
    links: dict[str, str | None] = Field(default_factory=dict)


class Health(BaseModel):
    model_config = CLOSED

    status: Literal["ok", "unavailable"]
    checks: dict[str, Any] = Field(default_factory=dict)


def iso(ts: float | None) -> str | None:
    if ts is None:
        return None
    return datetime.fromtimestamp(ts, tz=UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def job_links(job_id: str, job: JobRecord | None = None) -> JobLinks:
    """Links for a job; with ``job``, only those that exist now (artifacts it has, cancel while active)."""
    base = f"/v1/registrations/{job_id}"
    every = dict(
        cancel=f"{base}/cancel", result=f"{base}/result",
        overlay_ap=f"{base}/overlays/ap.png", overlay_lat=f"{base}/overlays/lat.png",
        mask_ap=f"{base}/masks/ap.png", mask_lat=f"{base}/masks/lat.png", loss_plot=f"{base}/loss.png",
        image_ap=f"{base}/images/ap.png", image_lat=f"{base}/images/lat.png", layers_ap=f"{base}/layers/ap.png",
        layers_lat=f"{base}/layers/lat.png", model=f"{base}/model.json",
        animation=f"{base}/animation.gif", track=f"{base}/track",
        hemodynamics=f"{base}/hemodynamics.json", hemodynamics_ply=f"{base}/hemodynamics.ply",
        hemodynamics_vtk=f"{base}/hemodynamics.vtk", parametric_ap=f"{base}/parametric/ap.png",
        parametric_lat=f"{base}/parametric/lat.png",
        **{key: f"{base}/dicom/{name}" for key, name in LINKED_DICOM.items()},
    )
    if job is None:
        return JobLinks(self=base, **every)
    links: dict[str, str] = {}
    if job.status in ("queued", "running"):
        links["cancel"] = every["cancel"]
    if job.status == "succeeded":
        if job.result is not None:
            links["result"] = every["result"]
        artifacts = job.artifacts or {}
        for key, name in {**LINKED_ARTIFACTS, **LINKED_DICOM}.items():
            if name in artifacts:
                links[key] = every[key]
        if job.result is not None and "mesh_to_world" in job.result:
            links["track"] = every["track"]
    if job.previous_id:
        links["previous"] = f"/v1/registrations/{job.previous_id}"
    return JobLinks(self=base, **links)


LINKED_ARTIFACTS = {"overlay_ap": engine.overlay_png("ap"), "overlay_lat": engine.overlay_png("lat"),
                    "mask_ap": engine.mask_png("ap"), "mask_lat": engine.mask_png("lat"), "loss_plot": engine.LOSS_PNG,
                    "animation": engine.ANIMATION_GIF, "hemodynamics": engine.HEMODYNAMICS_JSON,
                    "hemodynamics_ply": engine.HEMODYNAMICS_PLY, "hemodynamics_vtk": engine.HEMODYNAMICS_VTK,
                    "parametric_ap": engine.parametric_png("ap"), "parametric_lat": engine.parametric_png("lat"),
                    "image_ap": engine.image_png("ap"),
                    "image_lat": engine.image_png("lat"), "layers_ap": engine.layers_png("ap"),
                    "layers_lat": engine.layers_png("lat"), "model": engine.MODEL_JSON}
LINKED_DICOM = {"dicom_reg": engine.REG_DCM, "dicom_overlay_ap": engine.overlay_dcm("ap"),
                "dicom_overlay_lat": engine.overlay_dcm("lat"), "dicom_loss": engine.LOSS_DCM,
                "dicom_parametric_ap": engine.parametric_dcm("ap"), "dicom_parametric_lat": engine.parametric_dcm("lat")}


def previous_link_header(job: JobRecord) -> dict[str, str]:
    """``Link: </v1/registrations/{previous}>; rel="previous"`` for a tracking job, else nothing."""
    return {"Link": f'</v1/registrations/{job.previous_id}>; rel="previous"'} if job.previous_id else {}


def _final_progress(job: JobRecord) -> dict[str, Any]:
    """A succeeded job: its last optimization stage (from the result) at fraction 1.0."""
    metrics = (job.result or {}).get("metrics") or {}
    iterations = metrics.get("iterations") if isinstance(metrics.get("iterations"), dict) else {}
    if iterations:
        stage, count = list(iterations.items())[-1]
        loss = metrics.get("loss")
        return {"stage": str(stage), "iteration": int(count) if isinstance(count, (int, float)) else 0,
                "loss": float(loss) if isinstance(loss, (int, float)) else None, "fraction": 1.0}
    return {**(job.progress or {"stage": "done", "iteration": 0, "loss": None}), "fraction": 1.0}


def _progress(job: JobRecord) -> Progress | None:
    progress = job.progress
    if job.status == "queued":
        progress = {"stage": "queued", "iteration": 0, "loss": None, "fraction": 0.0}
    elif job.status == "succeeded":
        progress = _final_progress(job)
    return Progress(**progress) if progress else None


def succeeded_result(job: JobRecord) -> dict[str, Any] | None:
    """The result of a succeeded job, with ``verdict`` filled from ``metrics.confidence`` (older rows lack it)."""
    if job.status != "succeeded" or not isinstance(job.result, dict):
        return None
    verdict = _verdict(job.result)
    return {**job.result, "verdict": verdict} if verdict and "verdict" not in job.result else job.result


def _callback_state(job: JobRecord) -> CallbackState | None:
    row = job.callback
    if not row:
        return None
    retry_at = row.get("next_attempt_at") if row.get("state") == "pending" and row.get("attempts") else None
    return CallbackState(
        url=row["url"], state=row["state"], delivery_id=row["delivery_id"], attempts=row.get("attempts") or 0,
        last_attempt_at=iso(row.get("last_attempt_at")), next_attempt_at=iso(retry_at),
        delivered_at=iso(row.get("delivered_at")), last_response_status=row.get("last_status"),
        last_error=row.get("last_error"))


def job_status(job: JobRecord) -> JobStatus:
    result = succeeded_result(job)
    return JobStatus(
        id=job.id, status=job.status, verdict=_verdict(result) if result else None, created_at=iso(job.created_at) or "",
        started_at=iso(job.started_at), finished_at=iso(job.finished_at), attempts=job.attempts,
        cancel_requested=job.cancel_requested, progress=_progress(job), result=result,
        error=ProblemDetails(**job.error) if job.error and job.status == "failed" else None,
        warnings=job.warnings, callback=_callback_state(job), review=review_model(job.review),
        export=export_model(job.export), case=case_model(job.case), links=job_links(job.id, job),
    )


def status_body(job: JobRecord) -> dict[str, Any]:
    """The JSON of :func:`job_status`, with absent links left out (not null)."""
    return _drop_absent_links(job_status(job).model_dump(mode="json"))


def _drop_absent_links(body: dict[str, Any]) -> dict[str, Any]:
    body["links"] = {k: v for k, v in body["links"].items() if v is not None}
    for optional in ("source", "export"):
        if optional in body and body[optional] is None:
            del body[optional]
    return body


def _verdict(result: dict[str, Any]) -> str | None:
    """``metrics.confidence.verdict`` (ok / check / failed); None for results without one."""
    verdict = ((result.get("metrics") or {}).get("confidence") or {}).get("verdict")
    return verdict if verdict in ("ok", "check", "failed") else None


def _reasons(result: dict[str, Any]) -> list[str] | None:
    reasons = ((result.get("metrics") or {}).get("confidence") or {}).get("reasons")
    return [str(reason) for reason in reasons] if isinstance(reasons, list) else None


def job_summary(job: JobRecord) -> JobSummary:
    result = job.result if job.status == "succeeded" and isinstance(job.result, dict) else {}
    metrics = result.get("metrics") or {}
    views = result.get("views") or {}
    dice = {name: float(v["dice"]) for name, v in views.items()
            if isinstance(v, dict) and isinstance(v.get("dice"), (int, float))}
    error = None
    if job.status == "failed" and job.error:
        error = ": ".join(str(x) for x in (job.error.get("title"), job.error.get("detail")) if x)
    seconds = None
    if job.started_at is not None and job.finished_at is not None:
        seconds = round(job.finished_at - job.started_at, 3)
    full = job_links(job.id, job)
    links = JobLinks(self=full.self, cancel=full.cancel, result=full.result, previous=full.previous)
    return JobSummary(
        id=job.id, status=job.status, created_at=iso(job.created_at) or "", started_at=iso(job.started_at),
        finished_at=iso(job.finished_at), seconds=seconds, progress=_progress(job),
        converged=metrics.get("converged") if isinstance(metrics.get("converged"), bool) else None,
        verdict=_verdict(result) if result else None, reasons=_reasons(result) if result else None,
        dice=dice or None, error=error, review=review_model(job.review), case=case_model(job.case), links=links,
    )


def summary_body(job: JobRecord) -> dict[str, Any]:
    return _drop_absent_links(job_summary(job).model_dump(mode="json"))


class JobProgressEvent(BaseModel):
    """The data of a ``progress`` event of ``GET /v1/registrations/{id}/events`` (JSON, one line)."""

    model_config = ConfigDict(CLOSED, json_schema_extra={"examples": [{
        "id": EXAMPLE_ID, "status": "running",
        "progress": {"stage": "ap+lat:1/2", "iteration": 15, "loss": 0.0152, "fraction": 0.21}}]})

    id: str
    status: Status = Field(description="queued or running (a final state ends the stream with an `end` event).")
    progress: Progress | None = None


def progress_event(job: JobRecord) -> dict[str, Any]:
    """The JSON of a ``progress`` event for ``job``."""
    return JobProgressEvent(id=job.id, status=job.status, progress=_progress(job)).model_dump(mode="json")
