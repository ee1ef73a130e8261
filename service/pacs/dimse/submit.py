"""Jobs from studies received over DIMSE, through the intake like every submission (:mod:`service.intake`).

:class:`DimseIntake` is what :class:`service.pacs.dimse.dispatcher.StudyDispatcher` calls for
each planned job of a stable study: back-pressure (queue limits), the input validator, one row
in the job table and the executor's ``submit`` — as ``POST /v1/registrations`` does. A job
refused raises the intake's :mod:`~service.intake.refusals`.

A job's inputs are the received instances themselves (roles ``ap``, ``lat``, ``volume``: the
blobs the C-STORE wrote) and a small JSON input of role ``dimse`` (:func:`source_document`):
where the study came from and where the results go. Its Idempotency-Key is derived from the
study and the instances, so planning a study again (after a restart, or when more instances
arrive) never makes a second job for the same pair.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
from typing import Any

from ...engine_adapter import job_case
from ...intake.context import ANONYMOUS, IntakeContext
from ...intake.refusals import Refusal
from ...intake.submission import check_queue, create_job, fingerprint, new_job, validate_inputs
from ...storage.records import StoredInstance
from ...storage.store import InputFile
from .grouping import PlannedJob
from .job_options import dicom_job_options

log = logging.getLogger("dsareg.dimse")

ROLE = "dimse"


def job_owner(settings: Any) -> str:
    hashes = settings.auth.api_key_hashes
    chosen = settings.dimse.dicom_job_owner_key_hash or (hashes[0] if hashes else None)
    return "key:" + chosen.strip().lower()[:16] if chosen and settings.auth.auth_enabled else ANONYMOUS


def source_document(study_uid: str, job: PlannedJob, by_uid: dict[str, StoredInstance], settings: Any) -> dict:
    """The job's ``dimse`` input: the study's origin and the export destinations (deterministic JSON)."""
    calling = by_uid[job.ap].calling_ae
    volume_series = sorted({by_uid[uid].series_uid for uid in job.volume})
    volume = {"series_uid": volume_series[0], "instances": len(job.volume)}
    if job.volume_origin:  # not in the study: the patient's latest volume, retrieved by C-MOVE
        volume["retrieved"] = dict(job.volume_origin)
    return {"source": {"dimse": {
        "calling_ae": calling, "study_uid": study_uid, "pairing": job.rule,
        "ap": {"series_uid": by_uid[job.ap].series_uid, "sop_instance_uid": job.ap},
        "lat": {"series_uid": by_uid[job.lat].series_uid, "sop_instance_uid": job.lat},
        "volume": volume}},
        "export": list(settings.dimse.dicom_export) or [calling]}


def idempotency_key(study_uid: str, job: PlannedJob) -> str:
    text = "|".join([study_uid, job.ap, job.lat, *sorted(job.volume)])
    return "dimse:" + hashlib.sha256(text.encode()).hexdigest()


async def _planned_inputs(ctx: IntakeContext, study_uid: str, job: PlannedJob,
                          by_uid: dict[str, StoredInstance]) -> tuple[list[InputFile], Any]:
    """The job's inputs (the received instances and its ``dimse`` document) and its parsed options."""
    document = json.dumps(source_document(study_uid, job, by_uid, ctx.settings), sort_keys=True).encode()
    digest, size = await asyncio.to_thread(ctx.blobs.put_bytes, document)

    def item(role: str, uid: str) -> InputFile:
        return InputFile(role=role, sha256=by_uid[uid].sha256, size=by_uid[uid].size, suffix=".dcm")

    inputs = [item("ap", job.ap), item("lat", job.lat), *(item("volume", uid) for uid in job.volume),
              InputFile(role=ROLE, sha256=digest, size=size, suffix=".json")]
    return inputs, dicom_job_options(ctx.settings)  # checked when the node started


async def prevalidate(ctx: IntakeContext, study_uid: str, job: PlannedJob, by_uid: dict[str, StoredInstance]) -> None:
    """Parse a planned job's inputs ahead of time (when its association is released, before the study is
    stable): the validator keeps successful outcomes by content, so the submission then costs no parse."""
    inputs, options = await _planned_inputs(ctx, study_uid, job, by_uid)
    try:
        await validate_inputs(ctx, inputs, None, options)
    except Refusal:
        pass  # reported by the submission itself


async def submit_planned(ctx: IntakeContext, study_uid: str, job: PlannedJob,
                         by_uid: dict[str, StoredInstance]) -> tuple[str, bool]:
    """One planned job → ``(job id, created)``; raises a :class:`~service.intake.refusals.Refusal` like the HTTP
    submission."""
    owner, key = job_owner(ctx.settings), idempotency_key(study_uid, job)
    existing = await asyncio.to_thread(ctx.jobs.find_idempotent, owner, key)
    if existing is not None:
        return existing.id, False
    inputs, options = await _planned_inputs(ctx, study_uid, job, by_uid)
    options_json = options.model_dump(mode="json")
    await check_queue(ctx, owner)
    warnings, identity = await validate_inputs(ctx, inputs, None, options)
    record = new_job(ctx, owner, key, options_json=options_json, geometry=None, inputs=inputs, warnings=warnings,
                     request_hash=fingerprint(inputs, None, options_json), input_bytes=sum(i.size for i in inputs),
                     case=job_case(identity, "dimse"))
    submitted = await create_job(ctx, record)
    if submitted.created:  # else an equal request won the race
        await asyncio.to_thread(ctx.executor.submit, submitted.job.id)
    return submitted.job.id, submitted.created


class DimseIntake:
    """What the DICOM node's dispatcher submits through (coroutines, on the loop it is given: the API's in
    ``dsareg serve``, its own in ``dsareg dicom-listener``)."""

    def __init__(self, ctx: IntakeContext):
        self.ctx = ctx

    async def submit(self, study_uid: str, job: PlannedJob, by_uid: dict[str, StoredInstance]) -> tuple[str, bool]:
        return await submit_planned(self.ctx, study_uid, job, by_uid)

    async def prevalidate(self, study_uid: str, job: PlannedJob, by_uid: dict[str, StoredInstance]) -> None:
        await prevalidate(self.ctx, study_uid, job, by_uid)
