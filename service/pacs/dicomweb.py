"""DICOMweb (QIDO-RS / WADO-RS / STOW-RS) for registrations requested by reference.

* The request names a PACS by URL; only URLs listed in the server's settings
  (``DSAREG_DICOMWEB_SERVERS``) are accepted, and the credentials come from that entry,
  never from the request (no server-side request forgery, no credential injection).
* UIDs are checked against the DICOM UID syntax before they go into a URL path.
* Every HTTP call has a timeout; connection errors, timeouts and 429/502/503/504 are retried
  a bounded number of times with exponential back-off; anything else fails at once. All the
  calls of one job share a :class:`PacsBudget` (``DSAREG_PACS_DEADLINE_SECONDS``): a PACS that
  answers slowly, or trickles its answers, holds the job's worker at most that long in all.
  A failure raises :class:`PacsError` naming the server, the step and the HTTP status,
  which the worker turns into a failed job (``type .../pacs-error``).

Plain httpx is used (already a dependency) rather than a DICOMweb client library: the three
calls we need are short and we want exact control of timeouts, retries and error text.
"""

from __future__ import annotations

import json
import re
import time
import uuid
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import httpx
from pydantic import BaseModel, ConfigDict, Field, field_validator

if TYPE_CHECKING:
    from ..settings import ServiceSettings

UID_REGEX = r"^(0|[1-9][0-9]*)(\.(0|[1-9][0-9]*))*$"
UID_PATTERN = re.compile(UID_REGEX)
RETRIABLE_STATUS = {408, 429, 502, 503, 504}
TOTAL_TIME_FACTOR = 10  # one answer may take at most this many request timeouts in all
DICOM_JSON = "application/dicom+json"


def _uid(value: str) -> str:
    value = value.strip()
    if len(value) > 64 or not UID_PATTERN.match(value):
        raise ValueError("must be a DICOM UID (digits and dots, at most 64 characters)")
    return value


def normalize_url(url: str) -> str:
    return url.strip().rstrip("/")


# ---- request model ----------------------------------------------------------------------------


class ImageRef(BaseModel):
    model_config = ConfigDict(extra="forbid")
    series_uid: str = Field(description="Series Instance UID of the XA (or other image) series.",
                            min_length=1, max_length=64, pattern=UID_REGEX)
    sop_instance_uid: str | None = Field(None, description="The instance; default the series' first (by Instance Number).",
                                         min_length=1, max_length=64, pattern=UID_REGEX)
    frame: int | Literal["minip"] | None = Field(
        None, description="Multi-frame XA: 0-based frame, 'minip', or null for maximum opacification (per view: "
        "the two references may name different frames; options.frames, if it names one too, must agree).")

    @field_validator("series_uid", "sop_instance_uid")
    @classmethod
    def check_uid(cls, value):
        return value if value is None else _uid(value)

    @field_validator("frame")
    @classmethod
    def _frame(cls, value):
        if isinstance(value, int) and value < 0:
            raise ValueError("frame must be 0 or more")
        return value


class VolumeRef(BaseModel):
    model_config = ConfigDict(extra="forbid")
    series_uid: str = Field(description="Series Instance UID of the 3D volume (3D-RA / CTA) series.",
                            min_length=1, max_length=64, pattern=UID_REGEX)
    study_uid: str | None = Field(None, description="Its study, when it is not the XA study.",
                                  min_length=1, max_length=64, pattern=UID_REGEX)

    @field_validator("series_uid", "study_uid")
    @classmethod
    def check_uid(cls, value):
        return value if value is None else _uid(value)


class StudyReference(BaseModel):
    """What a by-reference request names in the PACS, whichever protocol reaches it: the study, the two
    XA images and the volume series (subclasses add where the PACS is: a DICOMweb URL or a DIMSE peer)."""

    model_config = ConfigDict(extra="forbid")
    study_uid: str = Field(description="Study Instance UID of the biplane XA study (results are stored into it).",
                           min_length=1, max_length=64, pattern=UID_REGEX)
    ap: ImageRef
    lat: ImageRef
    volume: VolumeRef

    @field_validator("study_uid")
    @classmethod
    def check_uid(cls, value):
        return _uid(value)

    @property
    def frames(self) -> tuple[int | str | None, int | str | None]:
        """The (ap, lat) frame choices (per view)."""
        return self.ap.frame, self.lat.frame


class DicomwebSource(StudyReference):
    url: str = Field(description="DICOMweb base URL; must be one of the server's configured DICOMweb servers.",
                     examples=["http://pacs.example:8042/dicom-web"])


class Source(BaseModel):
    model_config = ConfigDict(extra="forbid")
    dicomweb: DicomwebSource


class ReferenceRequestFields(BaseModel):
    """What every by-reference JSON body carries besides its ``source`` (DICOMweb here, DIMSE in pacs/dimse)."""

    model_config = ConfigDict(extra="forbid")
    options: dict[str, Any] = Field(default_factory=dict, description="RegistrationOptions, as in the multipart form.")
    callback_url: str | None = Field(
        None, max_length=2048, description="POSTed the job summary once the job ends (see docs/api/callbacks.md); "
                                           "must start with one of the server's DSAREG_CALLBACK_ALLOWED prefixes.")


class DicomwebRegistrationRequest(ReferenceRequestFields):
    """``POST /v1/registrations`` with ``Content-Type: application/json``: inputs by reference."""

    source: Source
    store_results: bool = Field(True, description="STOW-RS the REG and the overlays back into the study.")


# ---- errors --------------------------------------------------------------------------------------


class PacsError(Exception):
    """A DICOMweb call failed for good: which server, which step, which HTTP status."""

    def __init__(self, server: str, step: str, detail: str, status: int | None = None, attempts: int = 1):
        self.server, self.step, self.detail, self.status, self.attempts = server, step, detail, status, attempts
        where = f" (HTTP {status})" if status is not None else ""
        tries = f" after {attempts} attempts" if attempts > 1 else ""
        super().__init__(f"PACS {server}: {step} failed{where}{tries}: {detail}")

    def problem_extra(self) -> dict[str, Any]:
        return {"server": self.server, "step": self.step, "http_status": self.status, "attempts": self.attempts}


# ---- server settings -------------------------------------------------------------------------------


@dataclass(frozen=True)
class PacsServer:
    url: str
    username: str | None = None
    password: str | None = None
    token: str | None = None

    @property
    def auth(self) -> httpx.Auth | None:
        if self.username is not None:
            return httpx.BasicAuth(self.username, self.password or "")
        return None

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"} if self.token else {}


def configured_servers(settings: ServiceSettings) -> dict[str, PacsServer]:
    """``{normalized url: PacsServer}`` from ``settings.dicomweb.dicomweb_servers`` (dicts, or plain URLs)."""
    servers: dict[str, PacsServer] = {}
    for entry in settings.dicomweb.dicomweb_servers:
        if isinstance(entry, str):
            entry = {"url": entry}
        url = normalize_url(str(entry["url"]))
        servers[url] = PacsServer(url, entry.get("username"), entry.get("password"), entry.get("token"))
    return servers


def resolve_server(settings: ServiceSettings, url: str) -> PacsServer | None:
    return configured_servers(settings).get(normalize_url(url))


# ---- the client --------------------------------------------------------------------------------------


def _multipart_parts(response: httpx.Response) -> list[bytes]:
    """The bodies of a ``multipart/related`` response (split on the boundary; no copies of headers)."""
    content_type = response.headers.get("content-type", "")
    if not content_type.lower().startswith("multipart/"):
        return [response.content] if response.content else []
    match = re.search(r'boundary="?([^";]+)"?', content_type, flags=re.IGNORECASE)
    if match is None:
        raise ValueError("multipart answer without a boundary")
    delimiter = b"--" + match.group(1).strip().encode("latin-1")
    body = response.content
    parts = []
    for chunk in body.split(delimiter)[1:]:
        if chunk.startswith(b"--"):  # the closing delimiter
            break
        head_end = chunk.find(b"\r\n\r\n")
        if head_end < 0:
            continue
        payload = chunk[head_end + 4:]
        if payload.endswith(b"\r\n"):
            payload = payload[:-2]
        parts.append(payload)
    return parts


class PacsBudget:
    """The PACS time one job may spend in all, across its clients and requests (seconds)."""

    def __init__(self, seconds: float):
        self.seconds, self.spent = float(seconds), 0.0

    def remaining(self) -> float:
        return self.seconds - self.spent


class DicomwebClient:
    """QIDO-RS / WADO-RS / STOW-RS against one configured server, with bounded retries (and a job's budget)."""

    def __init__(self, server: PacsServer, *, timeout: float = 30.0, retries: int = 2, backoff: float = 0.5,
                 max_bytes: int = 512 * 1024 * 1024, transport: httpx.BaseTransport | None = None,
                 budget: PacsBudget | None = None):
        self.server = server
        self.retries = max(0, int(retries))
        self.backoff = backoff
        self.max_bytes = max_bytes
        self.timeout = timeout
        self.deadline = TOTAL_TIME_FACTOR * timeout  # whole answer, so a trickling server cannot hold a job
        self.budget = budget
        self.opened = time.monotonic()
        self.deadline_at = self.opened + (budget.remaining() if budget is not None else float("inf"))
        self.client = httpx.Client(base_url=server.url, auth=server.auth, headers=server.headers,
                                   timeout=httpx.Timeout(timeout, connect=min(timeout, 10.0)), transport=transport,
                                   follow_redirects=False)
        self.calls = 0

    def close(self) -> None:
        self.client.close()
        if self.budget is not None:
            self.budget.spent += time.monotonic() - self.opened
            self.budget = None

    def _left(self, step: str, attempts: int, error: str | None = None) -> float:
        """Seconds left of the job's PACS budget; :class:`PacsError` when it is spent."""
        left = self.deadline_at - time.monotonic()
        if left <= 0:
            spent = f"{self.budget.seconds:g}" if self.budget is not None else "its"
            raise PacsError(self.server.url, step, f"the PACS did not answer within the job's {spent} s "
                                                   f"(DSAREG_PACS_DEADLINE_SECONDS){'; last: ' + error if error else ''}",
                            None, attempts)
        return left

    def __enter__(self) -> DicomwebClient:  # noqa: PYI034
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _request(self, method: str, path: str, step: str, ok=(200,), **kwargs) -> httpx.Response:
        attempts, error = 0, None
        while True:
            left = self._left(step, attempts, error)
            attempts += 1
            self.calls += 1
            try:
                response = self._fetch(method, path, step, timeout=httpx.Timeout(
                    min(self.timeout, left), connect=min(self.timeout, 10.0, left)), **kwargs)
            except httpx.TimeoutException as exc:
                error, status = f"no answer within the timeout ({type(exc).__name__})", None
            except httpx.TransportError as exc:
                error, status = f"cannot connect ({type(exc).__name__}: {str(exc)[:120]})", None
            else:
                if response.status_code in ok:
                    return response
                status = response.status_code
                error = _error_text(response)
                if status not in RETRIABLE_STATUS:
                    raise PacsError(self.server.url, step, error, status, attempts)
            if attempts > self.retries:
                raise PacsError(self.server.url, step, error, status, attempts)
            time.sleep(min(self.backoff * 2 ** (attempts - 1), max(0.0, self.deadline_at - time.monotonic())))

    def _fetch(self, method: str, path: str, step: str, **kwargs) -> httpx.Response:
        """One request, its answer read in chunks under a byte cap and a total time limit."""
        started = time.monotonic()
        limit = min(self.deadline, self.deadline_at - started)
        with self.client.stream(method, path, **kwargs) as response:
            chunks, total = [], 0
            for chunk in response.iter_bytes():  # decoded (Content-Encoding)
                total += len(chunk)
                if total > self.max_bytes:
                    raise PacsError(self.server.url, step, f"the answer exceeds {self.max_bytes} bytes "
                                                           "(DSAREG_MAX_UPLOAD_BYTES)", response.status_code)
                if time.monotonic() - started > limit:
                    raise httpx.ReadTimeout(f"the answer took over {limit:g} s")
                chunks.append(chunk)
        headers = [(k, v) for k, v in response.headers.multi_items()
                   if k.lower() not in ("content-encoding", "content-length", "transfer-encoding")]
        return httpx.Response(response.status_code, headers=headers, content=b"".join(chunks),
                              request=response.request)

    def _parts(self, response: httpx.Response, step: str) -> list[bytes]:
        try:
            return _multipart_parts(response)
        except ValueError as exc:
            raise PacsError(self.server.url, step, str(exc), response.status_code) from None

    # QIDO-RS
    def search_instances(self, study: str, series: str) -> list[dict]:
        response = self._request("GET", f"/studies/{study}/series/{series}/instances", "search instances (QIDO-RS)",
                                 ok=(200, 204), headers={"Accept": DICOM_JSON})
        if response.status_code == 204 or not response.content:
            return []
        try:
            return list(response.json())
        except ValueError:
            raise PacsError(self.server.url, "search instances (QIDO-RS)", "the answer is not DICOM JSON") from None

    # WADO-RS
    def retrieve_instance(self, study: str, series: str, instance: str) -> bytes:
        step = "retrieve instance (WADO-RS)"
        response = self._request("GET", f"/studies/{study}/series/{series}/instances/{instance}", step,
                                 headers={"Accept": 'multipart/related; type="application/dicom"'})
        parts = self._parts(response, step)
        if len(parts) != 1:
            raise PacsError(self.server.url, step, f"expected one instance, got {len(parts)}")
        return parts[0]

    def retrieve_series(self, study: str, series: str) -> list[bytes]:
        step = "retrieve series (WADO-RS)"
        response = self._request("GET", f"/studies/{study}/series/{series}", step,
                                 headers={"Accept": 'multipart/related; type="application/dicom"'})
        parts = self._parts(response, step)
        if not parts:
            raise PacsError(self.server.url, step, "the series has no instances", response.status_code)
        return parts

    # STOW-RS
    def store(self, study: str, instances: list[bytes]) -> list[str]:
        """Store ``instances`` into ``study``; the SOP Instance UIDs the server reports as stored."""
        step = "store results (STOW-RS)"
        boundary = uuid.uuid4().hex
        body = b"".join(b"--" + boundary.encode() + b"\r\nContent-Type: application/dicom\r\n\r\n" + data + b"\r\n"
                        for data in instances) + b"--" + boundary.encode() + b"--\r\n"
        response = self._request(
            "POST", f"/studies/{study}", step, ok=(200, 202),
            content=body, headers={"Content-Type": f'multipart/related; type="application/dicom"; boundary={boundary}',
                                   "Accept": DICOM_JSON})
        try:
            answer = response.json() if response.content else {}
        except ValueError:
            answer = {}
        failed = (answer.get("00081198") or {}).get("Value") or []
        if failed:
            reasons = sorted({str((item.get("00081197") or {}).get("Value", ["?"])[0]) for item in failed})
            raise PacsError(self.server.url, step, f"{len(failed)} instance(s) refused (failure reasons {reasons})",
                            response.status_code)
        stored = []
        for item in (answer.get("00081199") or {}).get("Value") or []:
            uid = (item.get("00081155") or {}).get("Value") or []
            if uid:
                stored.append(str(uid[0]))
        return stored


def _error_text(response: httpx.Response) -> str:
    text = response.text[:300].strip().replace("\n", " ") if response.content else ""
    reason = response.reason_phrase or "error"
    return f"{reason}{': ' + text if text else ''}"


def _dicom_json_value(item: dict, tag: str):
    value = (item.get(tag) or {}).get("Value") or []
    return value[0] if value else None


# ---- the job's side ------------------------------------------------------------------------------------


@dataclass
class FetchedStudy:
    ap: bytes
    lat: bytes
    volume: list[bytes]
    warnings: list[str]
    seconds: float
    calls: int


def fetch_inputs(client: DicomwebClient, source: DicomwebSource) -> FetchedStudy:
    """The AP and LAT instances and every instance of the volume series."""
    started = time.perf_counter()
    warnings: list[str] = []
    images: dict[str, bytes] = {}
    for name in ("ap", "lat"):
        ref: ImageRef = getattr(source, name)
        instance = ref.sop_instance_uid
        if instance is None:
            found = client.search_instances(source.study_uid, ref.series_uid)
            if not found:
                raise PacsError(client.server.url, "search instances (QIDO-RS)",
                                f"{name}: series {ref.series_uid} has no instances in study {source.study_uid}", 404)

            def number(item: dict) -> float:
                value = _dicom_json_value(item, "00200013")
                try:
                    return float(value)
                except (TypeError, ValueError):
                    return float("inf")

            found.sort(key=number)
            instance = _dicom_json_value(found[0], "00080018")
            if not instance:
                raise PacsError(client.server.url, "search instances (QIDO-RS)", f"{name}: no SOPInstanceUID in the answer")
            if len(found) > 1:
                warnings.append(f"{name}: series has {len(found)} instances; the first by Instance Number was used "
                                "(give sop_instance_uid to choose)")
        images[name] = client.retrieve_instance(source.study_uid, ref.series_uid, _uid(str(instance)))
    volume = client.retrieve_series(source.volume.study_uid or source.study_uid, source.volume.series_uid)
    return FetchedStudy(images["ap"], images["lat"], volume, warnings, time.perf_counter() - started, client.calls)


def parse_reference(data: bytes) -> DicomwebRegistrationRequest:
    return DicomwebRegistrationRequest.model_validate(json.loads(data))
