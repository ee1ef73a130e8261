"""The PACS side of a job submitted by DICOMweb reference, run by the worker.

A job by reference (``source.dicomweb``) fetches its inputs with QIDO-RS / WADO-RS before the
engine runs (:meth:`PacsJob.fetch`); with ``store_results``, the REG and the overlays are stored
back into the study with STOW-RS after the job, by the exporter (:mod:`service.jobs.exports`), not
the worker; ``result.dicom`` lists what was fetched and written, the job's ``export`` what was stored. The DICOM results themselves (``reg.dcm``,
``overlay_{ap,lat}.dcm``, ``loss.dcm``, served under ``/v1/registrations/{id}/dicom/...``) are
written by the engine for every job (``engine.run_case``).
"""

from __future__ import annotations

from typing import Any

from ..engine_adapter import engine, fetched_case_files
from ..settings import ServiceSettings
from ..storage.store import JobRecord
from .dicomweb import (
    DicomwebClient,
    DicomwebRegistrationRequest,
    PacsBudget,
    PacsError,
    fetch_inputs,
    parse_reference,
    resolve_server,
)
from .dimse.pull import pull_job
from .instance_check import InstanceLimits, InstanceRefused, check_file

REFERENCE_ROLE = "dicomweb"
STORED_FILES = (engine.REG_DCM, engine.overlay_dcm("ap"), engine.overlay_dcm("lat"))


def pacs_job(job: JobRecord, read: Any, settings: ServiceSettings) -> Any:
    """The job's DICOMweb (:class:`PacsJob`) or DIMSE reference (``None`` for a job whose inputs were uploaded)."""
    refs = [item for item in job.inputs if item.role == REFERENCE_ROLE]
    if refs:
        return PacsJob(parse_reference(read(refs[0].sha256)), settings)
    return pull_job(job, read, settings)  # by DIMSE reference (C-GET), or None


class PacsJob:
    """Fetch the inputs of a job by reference and store its DICOM results back."""

    def __init__(self, reference: DicomwebRegistrationRequest, settings: ServiceSettings):
        self.reference, self.settings = reference, settings
        self.source_info: dict[str, Any] = {}
        self.budget = PacsBudget(settings.dicomweb.pacs_deadline_seconds)  # the fetch and the store together

    def _client(self) -> DicomwebClient:
        source = self.reference.source.dicomweb
        server = resolve_server(self.settings, source.url)
        if server is None:  # accepted earlier, since removed from the settings
            raise PacsError(source.url, "configuration", "no longer one of this server's DICOMweb servers")
        return DicomwebClient(server, timeout=self.settings.dicomweb.dicomweb_timeout_seconds,
                              retries=self.settings.dicomweb.dicomweb_retries,
                              backoff=self.settings.dicomweb.dicomweb_retry_backoff_seconds,
                              max_bytes=self.settings.limits.max_upload_bytes, budget=self.budget)

    def fetch(self) -> Any:
        """The study's AP, LAT and volume instances as ``engine.CaseFiles`` (geometry from the XA headers)."""
        source = self.reference.source.dicomweb
        with self._client() as client:
            fetched = fetch_inputs(client, source)
        self._check(client.server.url, {"ap": [fetched.ap], "lat": [fetched.lat], "volume": fetched.volume})
        self.source_info = {"server": client.server.url, "study_uid": source.study_uid,
                            "fetch_seconds": round(fetched.seconds, 3), "requests": fetched.calls}
        return fetched_case_files(fetched.ap, fetched.lat, fetched.volume, source.frames, fetched.warnings)

    def _check(self, server: str, instances: dict[str, list[bytes]]) -> None:
        """Each fetched instance's sizes as the DICOM node checks a received one (inflated, pixels, truncation)."""
        limits = InstanceLimits.of(self.settings)
        for name, items in instances.items():
            for data in items:
                try:
                    check_file(data, limits)
                except InstanceRefused as exc:
                    raise PacsError(server, f"check {name} instance", f"refused: {exc.reason}") from None


def pacs_problem(exc: PacsError) -> dict[str, Any]:
    """The ``extra`` members of the failed job's problem."""
    extra = exc.problem_extra()
    if getattr(exc, "mesh_to_world", None) is not None:
        extra["mesh_to_world"] = exc.mesh_to_world
    return extra
