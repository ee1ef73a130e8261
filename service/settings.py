"""Service settings, grouped: ``settings.<group>.<name>`` (e.g. ``settings.jobs.workers``).

Every setting keeps its flat environment variable ``DSAREG_<NAME>`` (``DSAREG_WORKERS``): the groups
are for reading the code and the reference, not for the deployment. A config file (JSON or TOML,
named by ``DSAREG_CONFIG`` or ``--config``) gives the same flat keys without the prefix, in lower
case; environment variables win over the file, explicit keyword arguments (the CLI) win over both.
Keyword arguments and ``model_validate`` take the flat names too (``ServiceSettings(workers=2)``).

API keys are never kept in clear: ``api_keys`` (plain, for convenience) are hashed
with SHA-256 at load time and merged into ``api_key_hashes``.

A new setting goes into the group it belongs to (one field, with a ``description=``); its name
must be unique across all groups (``DSAREG_<NAME>`` is flat). Then regenerate ``docs/settings.md``.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, EnvSettingsSource, NoDecode, PydanticBaseSettingsSource, SettingsConfigDict
from pydantic_settings.exceptions import SettingsError

ENV_PREFIX = "DSAREG_"


class SettingError(ValueError):
    """A setting that cannot be used, found when the settings load or a component starts: which variable, what
    was wrong, what is accepted (one line on the command line, exit status 2; never a traceback)."""

    def __init__(self, name: str, problem: str, accepted: str | None = None):
        self.name, self.problem, self.accepted = name, problem, accepted
        super().__init__(f"invalid setting {env_name(name)}: {problem}" + (f" (accepted: {accepted})" if accepted else ""))

    def cli_explanation(self) -> tuple[bool, str]:
        """For :func:`dsareg_engine.commands.failures.explain`: the operator's fault, one line."""
        return True, str(self)


def hash_api_key(key: str) -> str:
    """The at-rest form of an API key: lower-case hex SHA-256 of its UTF-8 bytes."""
    return hashlib.sha256(key.strip().encode("utf-8")).hexdigest()


def _split_list(value: Any) -> Any:
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):
            return json.loads(text)
        return [part.strip() for part in text.split(",") if part.strip()]
    return value


class _Group(BaseModel):
    model_config = ConfigDict(extra="ignore", validate_default=True)


class ServerSettings(_Group):
    """The API process: where it listens, how much it logs."""

    host: str = Field("127.0.0.1", description="Address the API binds; anything but loopback needs API keys "
                      "(without keys the service binds 127.0.0.1 whatever is asked).")
    port: int = Field(8000, description="TCP port of the API.")
    log_level: str = Field("info", description="Log level of the API and its workers (debug, info, warning, error).")
    http_header_timeout_seconds: float = Field(
        10.0, gt=0.0, description="A request's line and headers must arrive within this long of the connection (or "
                                  "of the previous answer on it): otherwise 408 and the connection is closed.")
    http_body_idle_timeout_seconds: float = Field(
        30.0, gt=0.0, description="A request body that stops arriving for this long is answered 408 (problem+json) "
                                  "and its connection closed.")
    http_max_connections: int = Field(
        1000, ge=1, description="Open HTTP connections at most; a request past it is answered 503 at once.")


class StorageSettings(_Group):
    """Where inputs and artifacts live, and the disk space kept free."""

    data_dir: Path = Field(Path("./dsareg-data"), description="Inputs, artifacts and the default SQLite database.")
    blob_backend: Literal["auto", "files", "database"] = Field(
        "auto", description="Inputs/artifacts: files in data_dir, or a table of the job database "
                            "(auto: database with executor=celery, else files).")
    min_free_bytes: int = Field(
        512 * 1024 * 1024, ge=0,
        description="Free disk space the data directory keeps: a submission that would leave less is refused "
                    "(507 + Retry-After) before anything is written, a worker does not claim jobs below it, and new "
                    "DICOM associations are refused (C-STORE answers 'out of resources'); 0: no floor (a full disk "
                    "is still a 507, never a 500).")
    model_cache_entries: int = Field(
        16, ge=0, description="Vessel models read from volumes kept in <data_dir>/models for the next job on the same "
                              "volume (same files, same volume options): the submission's check reads the volume, "
                              "the worker and later jobs take the model (a whole-head CTA: about a minute of CPU "
                              "each time otherwise). The least recently used go first; 0: off.")

    @property
    def model_dir(self) -> Path | None:
        """Where the volume models are kept, or None when the cache is off."""
        return self.data_dir / "models" if self.model_cache_entries > 0 else None


class DatabaseSettings(_Group):
    """The job database and its deadlines (service/storage/dbtimeouts.py): a frozen database is a fast 503."""

    database_url: str | None = Field(None, description="Any SQLAlchemy URL; default sqlite:///<data_dir>/jobs.sqlite3.")
    sqlite_busy_timeout_seconds: float = Field(
        1.0, gt=0.0, description="SQLite: how long a write waits for the database lock (a writer frozen with "
                                 "the lock → 503 + Retry-After after this long).")
    db_connect_timeout_seconds: float = Field(1.0, gt=0.0, description="PostgreSQL: time to open a connection.")
    db_statement_timeout_seconds: float = Field(
        1.0, gt=0.0, description="PostgreSQL: statement_timeout of the session, and the client-side deadline "
                                 "(+0.25 s) of one statement when the server does not answer at all.")
    db_lock_timeout_seconds: float = Field(0.5, gt=0.0, description="PostgreSQL: lock_timeout of the session.")
    db_pool_timeout_seconds: float = Field(1.0, gt=0.0, description="Wait for a free pooled database connection.")


class JobSettings(_Group):
    """Who runs jobs and how: workers, leases, attempts, deadlines."""

    executor: Literal["embedded", "celery"] = Field(
        "embedded", description="Who runs jobs: embedded worker processes of the API, or Celery workers.")
    workers: int = Field(1, ge=0, le=64, description="Embedded worker processes (0: API only, jobs stay queued).")
    threads_per_worker: int = Field(
        0, ge=0, le=256,
        description="CPU threads (torch and the numba kernels) of each worker; 0 = the cores shared among the workers.",
    )
    lease_seconds: float = Field(30.0, gt=0.5, description="A claimed job is the worker's until this long after its last heartbeat.")
    heartbeat_seconds: float | None = Field(None, description="Default lease_seconds / 3.")
    max_attempts: int = Field(3, ge=1, le=20, description="Claims of one job before it fails for good.")
    poll_seconds: float = Field(0.5, gt=0.0, description="How often an idle worker looks for queued jobs.")
    progress_interval_seconds: float = Field(0.5, ge=0.0, description="Least time between two progress writes of a job.")
    warm_up_job: bool = Field(
        True, description="Before its first job a worker runs one tiny registration (loads what a first job would "
                          "load on first use; its kernels are loaded either way). Off only for test servers whose "
                          "first job is not timed: a worker is then ready that much sooner.")
    result_save_seconds: float = Field(
        120.0, ge=0.0, description="How long a worker retries saving a finished job while the job database is out "
                                   "(exponential backoff) before giving up the attempt.")
    job_timeout_seconds: float = Field(3600.0, gt=0.0, description="A running job is stopped and failed after this long.")
    # results to the PACS by the API process's exporter, never the worker; held for a review on request
    # (service/jobs/exports.py, docs/review.md)
    export_after_review: bool = Field(
        False, description="Hold the STOW-RS / C-STORE of a job's DICOM results until a person approves the job "
                           "(POST /v1/registrations/{id}/review); a rejected job is never exported. Off: the exporter "
                           "sends them as soon as the job succeeded (the worker goes on to the next job either way).")
    export_max_attempts: int = Field(5, ge=1, le=50, description="Export attempts of a job's results (each with the "
                                                                 "DICOMweb / DIMSE retries) before it is marked failed.")
    export_retry_backoff_seconds: float = Field(
        5.0, ge=0.0, description="Delay before the second export attempt; doubles each attempt, at most 300 s.")
    export_lease_seconds: float = Field(
        15.0, gt=0.0, le=300.0,
        description="An export attempt is its API process's until this long after its last renewal (renewed every "
                    "third of it): an API killed or frozen mid-export leaves the export to another one after this long.")

    @property
    def effective_heartbeat_seconds(self) -> float:
        return self.heartbeat_seconds or max(0.2, self.lease_seconds / 3.0)


class LimitSettings(_Group):
    """What one request, one input and the queue may cost."""

    max_upload_bytes: int = Field(512 * 1024 * 1024, ge=1024, description="Whole request body, enforced while streaming.")
    queue_limit: int = Field(1000, ge=1, description="Queued jobs at most; more → 503 with Retry-After.")
    queue_limit_per_key: int = Field(200, ge=1, description="Queued jobs of one API key at most; more → 429.")
    validation_timeout_seconds: float = Field(60.0, gt=0.0, description="Input parsing time at most before a 422.")
    validation_processes: int = Field(1, ge=1, le=16, description="Processes that parse inputs for the API.")
    validation_memory_mb: int = Field(
        512, ge=0, description="Extra address space for one input parse (RLIMIT_AS of the validator; 0: unlimited).")
    validation_volume_memory_mb: int = Field(
        4096, ge=0, description="The most extra address space one submission's volume may be given for its first read, "
                                "sized from the volume's header (voxel count -> measured cost); a volume expected to "
                                "need more is refused at once. 0: volumes get validation_memory_mb like any input.")
    validation_volume_timeout_seconds: float = Field(
        600.0, ge=0.0, description="The most time one submission's volume may be given for its first read: its "
                                   "validator's CPU seconds are sized from the header (3 x the measured cost) up to "
                                   "this, and its wall-clock is bounded by this (a loaded machine slows the read, not "
                                   "the input). 0: no more than validation_timeout_seconds.")
    max_mesh_faces: int | None = Field(None, ge=1, description="Refuse meshes with more faces (engine default 500k).")
    max_image_pixels: int | None = Field(None, ge=1, description="Refuse larger images, from the header (engine default 64 MP).")
    max_image_bytes: int = Field(
        64 * 1024 * 1024, ge=1024,
        description="Refuse images whose decoded pixels (width × height × channels × bytes per sample × frames, "
                    "from the header) need more bytes: a small compressed file must not decode to gigabytes.")
    max_job_cost: float = Field(
        5e10, ge=0.0, description="Refuse jobs estimated above this many pixel-iterations "
                                  "(starts × max_iterations × final-stage pixels of the views); 0: no limit.")
    max_volume_bytes: int | None = Field(None, ge=1, description="Refuse larger decoded volumes (engine default 1 GiB).")
    # DICOM instances, wherever they come from (service/pacs/instance_check.py): checked before they cost
    max_dicom_instance_bytes: int = Field(
        1088 * 1024 * 1024, ge=1024,
        description="One DICOM instance at most this many bytes as received and, for a deflated transfer syntax, as "
                    "inflated (bounded while streaming); more: C-STORE 0xA700, nothing kept.")
    max_dicom_pixel_bytes: int = Field(
        1024 * 1024 * 1024, ge=1024,
        description="Rows × Columns × Number of Frames × Samples per Pixel × Bits Allocated / 8 of one DICOM instance "
                    "(from its header) at most; more: C-STORE 0xA700.")

    @property
    def input_limits(self) -> dict[str, int]:
        """Keyword arguments of the engine's ``InputLimits`` (only those configured)."""
        chosen = {"max_faces": self.max_mesh_faces, "max_image_pixels": self.max_image_pixels,
                  "max_volume_bytes": self.max_volume_bytes, "max_image_bytes": self.max_image_bytes}
        return {k: v for k, v in chosen.items() if v}


class RetentionSettings(_Group):
    """How long finished jobs are kept."""

    retention_hours: float = Field(168.0, gt=0.0, description="Finished jobs and their files are removed after this.")
    sweep_interval_seconds: float = Field(300.0, gt=0.0, description="Period of the retention sweep and lease recovery.")


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
        from .intake.pacs_access import parse_pacs_access

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


class CelerySettings(_Group):
    """Scale-out with Celery (executor=celery; service/README.md, "Scale-out with Celery")."""

    broker_url: str = Field("redis://127.0.0.1:6379/0", description="Celery broker (executor=celery).")
    celery_queue: str = Field("dsareg", description="Celery queue of registration jobs.")
    broker_visibility_timeout_seconds: float = Field(
        0.0, ge=0.0, description="Redis visibility timeout; 0: job_timeout_seconds * 2 + 600 (longer than any job).")
    redispatch_after_seconds: float = Field(
        60.0, gt=0.0, description="A queued job not picked up this long is sent to the broker again (executor=celery).")
    task_max_retries: int = Field(5, ge=0, le=50, description="Retries of a Celery task on a transient store error.")
    broker_publish_timeout_seconds: float = Field(
        0.5, gt=0.0, description="Longest a submission waits for the broker (executor=celery): a down or frozen "
                                 "broker leaves the job queued in the table and the sweeper re-sends it.")


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


# The groups in reference order: attribute of ServiceSettings → its model.
GROUPS: dict[str, type[_Group]] = {
    "server": ServerSettings, "storage": StorageSettings, "database": DatabaseSettings, "jobs": JobSettings,
    "limits": LimitSettings, "retention": RetentionSettings, "auth": AuthSettings, "celery": CelerySettings,
    "dicomweb": DicomwebSettings, "dimse": DimseSettings, "callbacks": CallbackSettings,
}
# Every setting's flat name → its group (a name is unique across groups: its env variable is flat).
GROUP_OF: dict[str, str] = {name: group for group, model in GROUPS.items() for name in model.model_fields}
assert len(GROUP_OF) == sum(len(model.model_fields) for model in GROUPS.values()), "a setting name is in two groups"
assert not set(GROUPS) & set(GROUP_OF), "a group has the name of a setting"


def env_name(name: str) -> str:
    """The environment variable of the setting ``name`` (flat, whatever its group)."""
    return f"{ENV_PREFIX}{name.upper()}"


class FlatEnvSource(PydanticBaseSettingsSource):
    """Reads ``DSAREG_<NAME>`` for every setting of every group, parsed as pydantic-settings parses env values.

    pydantic-settings reads env variables only for the top-level fields (or ``GROUP__NAME`` forms with a
    nested delimiter); this source runs its own env reader over each group model instead, so the names
    stay flat. It returns flat names; ``ServiceSettings`` files them into their groups.
    """

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:  # pragma: no cover - unused
        return None, field_name, False

    def __call__(self) -> dict[str, Any]:
        values: dict[str, Any] = {}
        for model in GROUPS.values():
            values.update(EnvSettingsSource(model, case_sensitive=False, env_prefix=ENV_PREFIX)())  # type: ignore[arg-type]
        return values


def _nest(data: Any) -> Any:
    """Flat input (``{"workers": 2}``) filed into groups (``{"jobs": {"workers": 2}}``); a flat key wins."""
    if not isinstance(data, dict):
        return data
    nested: dict[str, Any] = {group: dict(data.get(group) or {}) for group in GROUPS}
    for key, value in data.items():
        if key in GROUP_OF:
            nested[GROUP_OF[key]][key] = value
    return nested


def _env_error_location(loc: tuple[Any, ...]) -> tuple[Any, ...]:
    """``("jobs", "workers", …)`` → ``("DSAREG_WORKERS", …)``: the name an operator sets."""
    if len(loc) >= 2 and loc[0] in GROUPS and loc[1] in GROUP_OF:
        return (env_name(str(loc[1])), *loc[2:])
    return loc


class ServiceSettings(BaseSettings):
    """Every knob of ``dsareg serve``, in groups; each setting is still the env variable ``DSAREG_<NAME>``."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore", validate_default=True)

    server: ServerSettings = Field(default_factory=ServerSettings)
    storage: StorageSettings = Field(default_factory=StorageSettings)
    database: DatabaseSettings = Field(default_factory=DatabaseSettings)
    jobs: JobSettings = Field(default_factory=JobSettings)
    limits: LimitSettings = Field(default_factory=LimitSettings)
    retention: RetentionSettings = Field(default_factory=RetentionSettings)
    auth: AuthSettings = Field(default_factory=AuthSettings)
    celery: CelerySettings = Field(default_factory=CelerySettings)
    dicomweb: DicomwebSettings = Field(default_factory=DicomwebSettings)
    dimse: DimseSettings = Field(default_factory=DimseSettings)
    callbacks: CallbackSettings = Field(default_factory=CallbackSettings)

    @classmethod
    def settings_customise_sources(cls, settings_cls: type[BaseSettings], init_settings: PydanticBaseSettingsSource,
                                   env_settings: PydanticBaseSettingsSource, dotenv_settings: PydanticBaseSettingsSource,
                                   file_secret_settings: PydanticBaseSettingsSource,
                                   ) -> tuple[PydanticBaseSettingsSource, ...]:
        """Keyword arguments, then the flat ``DSAREG_<NAME>`` variables; nothing else (no ``DSAREG_JOBS`` JSON)."""
        return init_settings, FlatEnvSource(settings_cls)

    @model_validator(mode="wrap")
    @classmethod
    def _flat_names(cls, data: Any, handler: Any) -> Any:
        """Files flat names into groups; a bad value's error names its env variable (``DSAREG_WORKERS``)."""
        try:
            return handler(_nest(data))
        except ValidationError as exc:
            details = [{"type": e["type"], "loc": _env_error_location(tuple(e["loc"])), "input": e.get("input"),
                        "ctx": e.get("ctx", {})} for e in exc.errors()]
            raise ValidationError.from_exception_data(cls.__name__, details) from None  # type: ignore[arg-type]

    def __getattr__(self, name: str) -> Any:
        if name in GROUP_OF:  # a merge from before the grouping: say where the setting went
            raise AttributeError(f"ServiceSettings.{name} is now ServiceSettings.{GROUP_OF[name]}.{name}")
        return super().__getattr__(name)  # type: ignore[misc]

    # ---- derived (across groups) ------------------------------------------------------
    @property
    def effective_database_url(self) -> str:
        return self.database.database_url or f"sqlite:///{(self.storage.data_dir / 'jobs.sqlite3').resolve()}"

    @property
    def effective_blob_backend(self) -> str:
        if self.storage.blob_backend != "auto":
            return self.storage.blob_backend
        return "database" if self.jobs.executor == "celery" else "files"

    @property
    def effective_visibility_timeout(self) -> float:
        return self.celery.broker_visibility_timeout_seconds or self.jobs.job_timeout_seconds * 2.0 + 600.0

    @property
    def effective_host(self) -> str:
        """No keys → loopback only, whatever was asked for."""
        return self.server.host if self.auth.auth_enabled else "127.0.0.1"

    def flat(self) -> dict[str, Any]:
        """Every setting by its flat name (the keys of a config file)."""
        return {name: getattr(getattr(self, group), name) for name, group in GROUP_OF.items()}


def load_config_file(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    if not isinstance(data, dict):
        raise TypeError(f"config file {path} must hold an object")
    return {key.lower(): value for key, value in data.items()}


def _from_environment() -> ServiceSettings:
    """The settings of the environment (and defaults); a variable that is not valid JSON where JSON is expected
    (pydantic-settings' ``SettingsError``) is a :class:`SettingError` naming it."""
    try:
        return ServiceSettings()
    except SettingsError as exc:
        named = re.search(r'field "(\w+)"', str(exc))
        cause = exc.__cause__
        raise SettingError(named.group(1) if named else "?", f"not valid JSON ({cause})" if cause else str(exc),
                           "JSON text: an object {...} or a list [...] as the setting's reference says "
                           "(docs/settings.md)") from None


def load_settings(config_file: str | Path | None = None, **overrides: Any) -> ServiceSettings:
    """Settings from (lowest first) the config file, the environment, then ``overrides`` (flat names).

    Keyword overrides whose value is ``None`` are ignored (unset CLI flags).
    """
    file_values: dict[str, Any] = {}
    config_file = config_file or os.environ.get("DSAREG_CONFIG")
    if config_file:
        file_values = load_config_file(config_file)
    env_only = _from_environment()
    env_set = {name for name in GROUP_OF if env_name(name) in os.environ}
    env_values = env_only.flat()
    merged: dict[str, Any] = dict(file_values)
    for name in env_set:
        merged[name] = env_values[name]
    if "api_key_hashes" in env_set or "api_keys" in env_set:
        merged["api_key_hashes"] = env_only.auth.api_key_hashes + list(file_values.get("api_key_hashes", []))
        merged["api_keys"] = file_values.get("api_keys", [])
    merged.update({k: v for k, v in overrides.items() if v is not None})
    return ServiceSettings.model_validate(merged) if merged else env_only


def settings_to_env(settings: ServiceSettings) -> dict[str, str]:
    """Environment that recreates ``settings`` in a child process (hashes only, never clear keys)."""
    env: dict[str, str] = {}
    for name, value in settings.flat().items():
        if name == "api_keys" or value is None:
            continue
        if isinstance(value, (list, dict)):
            env[env_name(name)] = json.dumps(value)
        else:
            env[env_name(name)] = str(value)
    return env
