"""The DICOM side of a job, run by the worker: inputs by DICOMweb reference, DICOM results.

Every job writes ``reg.dcm`` (Spatial Registration) and ``overlay_{ap,lat}.dcm`` /
``loss.dcm`` (Secondary Capture) next to its PNGs (served under
``/v1/registrations/{id}/dicom/...``); the patient/study attributes come from the DICOM inputs
when there are any. A job submitted by reference (``source.dicomweb``) fetches its inputs with
QIDO-RS / WADO-RS first and, with ``store_results``, stores the REG and the overlays back into
the study with STOW-RS; ``result.dicom`` lists what was written and stored.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from .dicomweb import DicomwebClient, PacsError, fetch_inputs, parse_reference, resolve_server
from .engine_adapter import engine, input_limits, load_job_case

log = logging.getLogger("dsareg.service.dicom")

REFERENCE_ROLE = "dicomweb"
STORED_FILES = (engine.REG_DCM, engine.overlay_dcm("ap"), engine.overlay_dcm("lat"))


class DicomJob:
    def __init__(self, job, read, settings):
        self.job, self.read, self.settings = job, read, settings
        refs = [item for item in job.inputs if item.role == REFERENCE_ROLE]
        self.reference = parse_reference(read(refs[0].sha256)) if refs else None
        self.sources = None
        self.info: dict[str, Any] = {}

    @property
    def by_reference(self) -> bool:
        return self.reference is not None

    def _client(self) -> DicomwebClient:
        source = self.reference.source.dicomweb
        server = resolve_server(self.settings, source.url)
        if server is None:  # accepted earlier, since removed from the settings
            raise PacsError(source.url, "configuration", "no longer one of this server's DICOMweb servers")
        return DicomwebClient(server, timeout=self.settings.dicomweb_timeout_seconds,
                              retries=self.settings.dicomweb_retries,
                              backoff=self.settings.dicomweb_retry_backoff_seconds,
                              max_bytes=self.settings.max_upload_bytes)

    def load_case(self, segmentation: str, limits: dict | None):
        if not self.by_reference:
            case = load_job_case(self.job.inputs, self.job.geometry, segmentation, self.read, limits)
            try:
                self.sources = engine.read_sources(*self._uploaded("ap"), *self._uploaded("lat"), *self._uploaded("volume", True))
            except Exception:  # noqa: BLE001 - DICOM context is optional for uploads
                log.warning("job %s: could not read DICOM headers of the uploads", self.job.id)
            return case
        source = self.reference.source.dicomweb
        with self._client() as client:
            fetched = fetch_inputs(client, source)
        self.info["source"] = {"server": client.server.url, "study_uid": source.study_uid,
                               "fetch_seconds": round(fetched.seconds, 3), "requests": fetched.calls}
        case = engine.load_case(volume=fetched.volume, volume_name="volume.dcm", ap=fetched.ap, ap_name="ap.dcm",
                         lat=fetched.lat, lat_name="lat.dcm", geometry=self.job.geometry, segmentation=segmentation,
                         limits=input_limits(limits), frame=source.frame)
        case.warnings = [*fetched.warnings, *case.warnings]
        self.sources = engine.read_sources(fetched.ap, fetched.lat, fetched.volume)
        return case

    def _uploaded(self, role: str, many: bool = False) -> tuple:
        items = [item for item in self.job.inputs if item.role == role]
        if not items:
            return (None,)
        if many:
            return ([self.read(item.sha256) for item in items],)
        return (self.read(items[0].sha256),) if len(items) == 1 else (None,)

    def finish(self, result: dict, out_dir: Path) -> dict:
        """Write the DICOM results into ``out_dir`` (and STOW them when asked); adds ``result['dicom']``."""
        out_dir = Path(out_dir)
        try:
            written = engine.write_dicom_outputs(out_dir, result["mesh_to_world"], self.sources or engine.DicomSources(),
                                                out_dir)
        except Exception as exc:
            if self.by_reference:
                raise
            log.warning("job %s: DICOM outputs not written (%s)", self.job.id, exc)
            result.setdefault("warnings", []).append("DICOM outputs could not be written")
            return result
        dicom: dict[str, Any] = {"instances": written, **self.info}
        if self.by_reference and self.reference.store_results:
            source = self.reference.source.dicomweb
            started = time.perf_counter()
            try:
                with self._client() as client:
                    stored = client.store(source.study_uid, [(out_dir / name).read_bytes() for name in STORED_FILES])
            except PacsError as exc:
                exc.mesh_to_world = result["mesh_to_world"]  # the registration itself succeeded
                raise
            expected = {written[name]["sop_instance_uid"] for name in STORED_FILES}
            dicom["stored"] = {"server": client.server.url, "study_uid": source.study_uid,
                               "sop_instance_uids": [written[name]["sop_instance_uid"] for name in STORED_FILES],
                               "confirmed": sorted(expected & set(stored)) == sorted(expected),
                               "store_seconds": round(time.perf_counter() - started, 3)}
        result["dicom"] = dicom
        return result


def pacs_problem(exc: PacsError) -> dict[str, Any]:
    """The ``extra`` members of the failed job's problem."""
    extra = exc.problem_extra()
    if getattr(exc, "mesh_to_world", None) is not None:
        extra["mesh_to_world"] = exc.mesh_to_world
    return extra
