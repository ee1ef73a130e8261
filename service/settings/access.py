"""The groups of who may reach the service and whom it reaches: API keys, DICOMweb, DIMSE peers, callbacks."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import Field, field_validator, model_validator
from pydantic_settings import NoDecode

from .base import _Group, _split_list, env_name, hash_api_key


class AuthSettings(_Group):
    """API keys (hashed at load) and who may read /metrics."""

    api_keys: Annotated[list[str], NoDecode] = Field(default_factory=list, description="Plain keys (hashed at load).")
    api_key_hashes: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="SHA-256 hex digests of accepted keys."
    )
    metrics_public: bool | None = Field(
        None, description="GET /metrics without an API key. Default: public only when no API keys are configured; "
                          "otherwise it needs a valid key (any). The metrics are service-wide aggregates (jobs by "
                          "state, queue depth, latency by route template): no key, job id or path appears in them.")

    pacs_access: Annotated[dict[str, Any], NoDecode] = Field(
        default_factory=dict, description='With API keys: which PACS studies each key may have fetched by reference, '
        'JSON {"<key SHA-256 hex>" or "*": {"peers": [URL or AE title, or "*"], "studies": [UID or UID root "1.2."]}}; '
        'a key without an entry (nor "*") may fetch none (service/intake/pacs_access.py).')

    @field_validator("api_keys", "api_key_hashes", mode="before")
    @classmethod
    def _lists(cls, value: Any) -> Any:
        return _split_list(value)

    @field_validator("pacs_access", mode="before")
    @classmethod
    def _pacs_access(cls, value: Any) -> Any:
        from ..intake.pacs_access import parse_pacs_access

        return parse_pacs_access(value)

    @field_validator("api_key_hashes")
    @classmethod
    def _hex(cls, value: list[str]) -> list[str]:
        out = []
        for item in value:
            item = item.strip().lower()
            if len(item) != 64 or any(c not in "0123456789abcdef" for c in item):
                raise ValueError("api_key_hashes must be SHA-256 hex digests (64 hex characters)")
            out.append(item)
        return out

    @model_validator(mode="after")
    def _hash_plain_keys(self) -> AuthSettings:
        hashes = list(dict.fromkeys([*self.api_key_hashes, *(hash_api_key(k) for k in self.api_keys if k.strip())]))
        object.__setattr__(self, "api_key_hashes", hashes)
        object.__setattr__(self, "api_keys", [])  # clear text is not kept
        return self

    @property
    def auth_enabled(self) -> bool:
        return bool(self.api_key_hashes)

    @property
    def metrics_open(self) -> bool:
        """Whether /metrics answers without an API key (``metrics_public``, else: no keys configured)."""
        return (not self.auth_enabled) if self.metrics_public is None else self.metrics_public


class DicomwebSettings(_Group):
    """DICOMweb (service/pacs/dicomweb.py): the only PACS a request may name, with their credentials."""

    dicomweb_servers: Annotated[list[Any], NoDecode] = Field(
        default_factory=list,
        description='DICOMweb servers jobs may read from / store to: JSON list of {"url", "username"?, "password"?, '
                    '"token"?} (or plain URLs); a request naming any other URL is refused (422).')
    dicomweb_timeout_seconds: float = Field(30.0, gt=0.0, description="Timeout of one DICOMweb HTTP request.")
    dicomweb_retries: int = Field(2, ge=0, le=10, description="Retries of a DICOMweb request on connection errors, "
                                                              "timeouts and 408/429/502/503/504.")
    dicomweb_retry_backoff_seconds: float = Field(0.5, ge=0.0, description="First retry delay (doubles each retry).")
    pacs_deadline_seconds: float = Field(
        600.0, gt=0.0, description="PACS I/O of one job's fetch, or of one export attempt, in all (every DICOMweb "
                                   "request, with retries): a slow or trickling PACS holds a worker (or the exporter) "
                                   "at most this long, then a pacs-error.")

    @field_validator("dicomweb_servers", mode="before")
    @classmethod
    def _lists(cls, value: Any) -> Any:
        return _split_list(value)


class DimseSettings(_Group):
    """The DICOM node (service/pacs/dimse): C-ECHO / C-STORE SCP, jobs from received studies, results by C-STORE."""

    dicom_port: int | None = Field(
        None, ge=1, le=65535, description="DICOM (DIMSE) listener port; unset: no DICOM node in `dsareg serve` "
                                          "(`dsareg dicom-listener` runs one on its own).")
    dicom_host: str = Field("127.0.0.1", description="Bind address of the DICOM listener.")
    dicom_ae_title: str = Field("DSAREG", min_length=1, max_length=16, description="AE title of the DICOM node.")
    dicom_peers: Annotated[list[Any], NoDecode] = Field(
        default_factory=list,
        description='DICOM peers allowed to associate and to receive results: JSON list of {"ae_title", "host", '
                    '"port"}; an association from any other calling AE title or host is rejected.')
    dicom_stable_seconds: float = Field(
        10.0, gt=0.0, description="A received study becomes jobs once no instance of it arrived for this long.")
    dicom_export: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="AE titles (of dicom_peers) that receive the REG and overlays by C-STORE; "
                                          "empty: the peer that sent the study.")
    dicom_query_peer: str | None = Field(
        None, description="AE title (of dicom_peers) asked by C-FIND / C-MOVE for the patient's latest CT / MR / 3D-RA "
                          "volume when a received study has biplane XA but no volume; unset: such a study waits for one.")
    dicom_query_retry_seconds: float = Field(
        60.0, gt=0.0, description="Wait before asking dicom_query_peer again after it found no volume or was down.")
    dicom_export_retries: int = Field(2, ge=0, le=10, description="Retries of a failed C-STORE of the results within "
                                                                  "one export attempt (EXPORT_MAX_ATTEMPTS in all).")
    dicom_export_backoff_seconds: float = Field(0.5, ge=0.0, description="First export retry delay (doubles each retry).")
    dicom_timeout_seconds: float = Field(20.0, gt=0.0, description="Timeout of DIMSE connections, associations and "
                                                                   "messages (SCU and SCP).")
    dicom_interrupted_wait_seconds: float = Field(
        300.0, gt=0.0, description="Instances answered Success in an association that ended without release (abort, "
                                   "dropped connection, listener killed) are kept; they join their study when the "
                                   "sender comes back, or after this long without it.")
    dicom_inbox_retention_hours: float = Field(
        72.0, gt=0.0, description="Received DICOM instances (their files and inbox rows) are removed this long after "
                                  "their study settled: every instance dispatched, its jobs finished (or refused); "
                                  "files a kept job still uses go with the job (DSAREG_RETENTION_HOURS).")
    dicom_job_owner_key_hash: str | None = Field(
        None, description="SHA-256 hex of the API key that owns jobs made from DICOM studies (it sees them in the "
                          "API); default the first configured key, or anonymous when auth is off.")
    dicom_job_options: dict[str, Any] = Field(
        default_factory=dict, description="RegistrationOptions (as in the multipart form) of jobs made from DICOM studies; "
                                        "checked when the DICOM node starts: an option the API would refuse stops "
                                        "the start (exit status 2, naming the option).")

    @field_validator("dicom_peers", "dicom_export", mode="before")
    @classmethod
    def _lists(cls, value: Any) -> Any:
        return _split_list(value)

    @field_validator("dicom_peers")
    @classmethod
    def _peers(cls, value: list[Any]) -> list[dict[str, Any]]:
        peers = []
        for index, item in enumerate(value):
            if not isinstance(item, dict) or not {"ae_title", "host", "port"} <= set(item):
                raise ValueError(f'dicom_peers[{index}] must be {{"ae_title", "host", "port"}}')
            title = str(item["ae_title"]).strip()
            if not 0 < len(title) <= 16 or "\\" in title:
                raise ValueError(f"dicom_peers[{index}].ae_title must be 1 to 16 characters")
            port = int(item["port"])
            if not 0 < port < 65536:
                raise ValueError(f"dicom_peers[{index}].port must be 1..65535")
            peers.append({"ae_title": title, "host": str(item["host"]).strip(), "port": port})
        return peers

    @model_validator(mode="after")
    def _named_peers(self) -> DimseSettings:
        """The query peer and the export destinations are peers (else every study would fail on them, later)."""
        known = {peer["ae_title"] for peer in self.dicom_peers}
        named = {"dicom_query_peer": [self.dicom_query_peer] if self.dicom_query_peer else [],
                 "dicom_export": list(self.dicom_export)}
        for name, titles in named.items():
            unknown = [title for title in titles if title not in known]
            if unknown:
                raise ValueError(f"{name} ({env_name(name)}) names {', '.join(map(repr, unknown))}, not one of "
                                 f"DSAREG_DICOM_PEERS (AE titles: {', '.join(sorted(known)) or 'none'})")
        return self


class CallbackSettings(_Group):
    """Completion callbacks (service/jobs/callbacks.py, docs/api/callbacks.md)."""

    callback_allowed: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="URL prefixes a job's callback_url must start with (JSON list or comma-separated), e.g. "
                    "https://ris.example.org/hooks/; empty: callbacks are refused (422). Scheme, host and port must "
                    "match exactly and the path at a '/' boundary.")
    callback_secret: str = Field(
        "", repr=False, description="Key of the X-Dsareg-Signature HMAC-SHA256 of every callback body; required "
                                    "when callback_allowed is set.")
    callback_timeout_seconds: float = Field(10.0, gt=0.0, description="Timeout of one callback POST.")
    callback_max_attempts: int = Field(10, ge=1, le=50, description="Delivery attempts of one callback before it "
                                                                    "is marked failed.")
    callback_retry_backoff_seconds: float = Field(
        1.0, ge=0.0, description="Delay before the second attempt; doubles each attempt, at most 300 s.")

    @field_validator("callback_allowed", mode="before")
    @classmethod
    def _lists(cls, value: Any) -> Any:
        return _split_list(value)

    @model_validator(mode="after")
    def _callback_secret(self) -> CallbackSettings:
        if self.callback_allowed and not self.callback_secret.strip():
            raise ValueError("callback_secret (DSAREG_CALLBACK_SECRET) is required when callback_allowed is set: "
                             "every callback is signed with it")
        return self
