"""The groups of how the service runs: server, storage, database, jobs, limits, retention, Celery."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from .base import _Group


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
                              "the worker and later jobs take the model (a whole-head CTA: 7–11 CPU s and ~1 GB "
                              "each time otherwise). With the database blob backend also in the job database "
                              "(table volume_models), shared by every node. The least recently used go first; "
                              "0: off.")

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
