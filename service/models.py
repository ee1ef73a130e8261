"""Response models of the HTTP API (they make the OpenAPI document)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from .problems import ProblemDetails
from .store import JobRecord

Status = Literal["queued", "running", "succeeded", "failed", "canceled"]

EXAMPLE_ID = "0b5a6f3c9d2e4f1a8b7c6d5e4f3a2b1c"


class Progress(BaseModel):
    stage: str = Field(description="Current stage of the registration ('queued', 'load', 'ap', ...).")
    iteration: int = Field(0, description="Iteration within the stage.")
    loss: float | None = Field(None, description="Latest loss value.")
    fraction: float = Field(0.0, ge=0.0, le=1.0, description="Estimated fraction of the whole job done.")


class JobLinks(BaseModel):
    self: str
    cancel: str
    result: str
    overlay_ap: str
    overlay_lat: str
    mask_ap: str
    mask_lat: str
    animation: str


class JobStatus(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{
        "id": EXAMPLE_ID, "status": "running", "created_at": "2026-01-01T10:00:00Z",
        "started_at": "2026-01-01T10:00:01Z", "finished_at": None, "attempts": 1, "cancel_requested": False,
        "progress": {"stage": "simultaneous", "iteration": 120, "loss": 0.083, "fraction": 0.4},
        "result": None, "error": None, "warnings": [],
        "links": {"self": f"/v1/registrations/{EXAMPLE_ID}", "cancel": f"/v1/registrations/{EXAMPLE_ID}/cancel",
                  "result": f"/v1/registrations/{EXAMPLE_ID}/result",
                  "overlay_ap": f"/v1/registrations/{EXAMPLE_ID}/overlays/ap.png",
                  "overlay_lat": f"/v1/registrations/{EXAMPLE_ID}/overlays/lat.png",
                  "mask_ap": f"/v1/registrations/{EXAMPLE_ID}/masks/ap.png",
                  "mask_lat": f"/v1/registrations/{EXAMPLE_ID}/masks/lat.png",
                  "animation": f"/v1/registrations/{EXAMPLE_ID}/animation.gif"},
    }]})

    id: str
    status: Status
    created_at: str
    started_at: str | None = None
    finished_at: str | None = None
    attempts: int = Field(description="Times a worker claimed the job (retries after a lost worker count).")
    cancel_requested: bool = False
    progress: Progress | None = None
    result: dict[str, Any] | None = Field(None, description="The registration result when succeeded.")
    error: ProblemDetails | None = Field(None, description="Why the job failed (problem details).")
    warnings: list[str] = Field(default_factory=list, description="Notes from reading the inputs.")
    links: JobLinks


class JobList(BaseModel):
    items: list[JobStatus]
    next_cursor: str | None = Field(None, description="Pass as ?cursor= for the next page; null on the last page.")
    links: dict[str, str | None] = Field(default_factory=dict)


class Health(BaseModel):
    status: Literal["ok", "unavailable"]
    checks: dict[str, Any] = Field(default_factory=dict)


def iso(ts: float | None) -> str | None:
    if ts is None:
        return None
    return datetime.fromtimestamp(ts, tz=UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def job_links(job_id: str) -> JobLinks:
    base = f"/v1/registrations/{job_id}"
    return JobLinks(
        self=base, cancel=f"{base}/cancel", result=f"{base}/result",
        overlay_ap=f"{base}/overlays/ap.png", overlay_lat=f"{base}/overlays/lat.png",
        mask_ap=f"{base}/masks/ap.png", mask_lat=f"{base}/masks/lat.png", animation=f"{base}/animation.gif",
    )


def job_status(job: JobRecord) -> JobStatus:
    progress = job.progress
    if job.status == "queued":
        progress = {"stage": "queued", "iteration": 0, "loss": None, "fraction": 0.0}
    elif job.status == "succeeded":
        progress = {**(progress or {"stage": "done", "iteration": 0, "loss": None}), "fraction": 1.0}
    return JobStatus(
        id=job.id, status=job.status, created_at=iso(job.created_at) or "", started_at=iso(job.started_at),
        finished_at=iso(job.finished_at), attempts=job.attempts, cancel_requested=job.cancel_requested,
        progress=Progress(**progress) if progress else None,
        result=job.result if job.status == "succeeded" else None,
        error=ProblemDetails(**job.error) if job.error and job.status == "failed" else None,
        warnings=job.warnings, links=job_links(job.id),
    )
