"""The HTTP API (FastAPI): long-running-operation pattern over the job store.

``create_app(settings)`` builds the app; its lifespan opens the store, starts the
input-validator processes, the executor (embedded worker processes) and the sweeper
(lease recovery, retention), and stops them again.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from fastapi import Depends, FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily, HistogramMetricFamily
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from .blobs import BlobStore, safe_suffix
from .dbblobs import make_blob_store
from .docs_offline import install_docs
from .executor import Executor, make_executor
from .httpfaults import allowed_methods
from .limits import check_job_cost, check_options, parse_json_part
from .middleware import BodyLimitMiddleware, MetricsMiddleware
from .models import EXAMPLE_ID, Health, JobList, JobStatus, status_body, summary_body
from .problems import PROBLEM_MEDIA_TYPE, Problem, ProblemDetails, problem_body, problem_responses
from .schemas import document as document_payloads
from .settings import ServiceSettings
from .store import (
    STATUSES,
    ConflictError,
    InputFile,
    JobRecord,
    JobStore,
    SqlJobStore,
    decode_cursor,
    new_job_id,
    store_outage_errors,
)
from .track import install_track_route
from .validation import ValidatorPool

log = logging.getLogger("dsareg.service")

ANONYMOUS = "anonymous"
MAX_GEOMETRY_BYTES = 1 << 20
MAX_OPTIONS_BYTES = 1 << 20
MAX_VOLUME_FILES = 4000
RETRY_AFTER_QUEUED = "2"
STORE_RETRY_AFTER = "5"
DURATION_BUCKETS = (1, 2, 5, 10, 20, 30, 60, 120, 300, 600, 1800, 3600)


# ---- context --------------------------------------------------------------------------------


@dataclass
class ServiceContext:
    settings: ServiceSettings
    store: JobStore
    blobs: BlobStore
    validator: ValidatorPool | None
    executor: Executor
    registry: CollectorRegistry
    uploads: Counter
    sweeper: Sweeper | None = None
    extra: dict[str, Any] = field(default_factory=dict)


class Sweeper:
    """Recovers expired leases (often) and enforces retention (every sweep interval).

    After the job store was unreachable, no lease is judged expired for one lease period: while
    the database was down no worker could renew its lease, so an expired lease is no sign of a
    dead worker, and requeuing would throw away a registration its worker is about to save.
    """

    def __init__(self, ctx: ServiceContext):
        self.ctx = ctx
        self._halt = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sweeper", daemon=True)
        self.last_retention = 0.0
        self.recover_after = 0.0  # monotonic time before which leases are not recovered (store outage grace)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._halt.set()
        self._thread.join(5)

    def _run(self) -> None:
        recovery_every = max(0.5, min(5.0, self.ctx.settings.lease_seconds / 3.0))
        while not self._halt.wait(recovery_every):
            try:
                self.sweep_once(recover=time.monotonic() >= self.recover_after)
            except store_outage_errors() as exc:
                log.warning("sweep skipped: job store unavailable (%s)", type(exc).__name__)
                self.recover_after = time.monotonic() + self.ctx.settings.lease_seconds
            except Exception:
                log.exception("sweep failed")

    def sweep_once(self, *, force_retention: bool = False, recover: bool = True) -> None:
        store, blobs, settings = self.ctx.store, self.ctx.blobs, self.ctx.settings
        requeued, failed = store.recover_expired() if recover else ([], [])
        for job_id in requeued:
            log.warning("job %s: lease expired, requeued", job_id)
        for job_id in failed:
            log.warning("job %s: lease expired, no attempts left (or canceled)", job_id)
        self.ctx.executor.requeued(requeued)
        self.ctx.executor.maintain(store)
        now = time.time()
        if force_retention or now - self.last_retention >= settings.sweep_interval_seconds:
            self.last_retention = now
            expired = store.expired_finished(now - settings.retention_hours * 3600.0)
            for job_id in expired:
                orphans = store.delete(job_id)
                blobs.delete(orphans, min_age_seconds=0.0)  # submit re-stores a blob it still needs
                blobs.remove_job_work(job_id)
            if expired:
                log.info("retention: removed %d jobs", len(expired))
            blobs.collect_garbage(store.referenced_blobs(), min_age_seconds=3600.0)
            blobs.clean_tmp()


class StoreCollector:
    """Job gauges and the job-duration histogram, read from the store at scrape time
    (the store is shared by API and workers, so every process sees the same numbers)."""

    def __init__(self, ctx_getter: Callable[[], ServiceContext | None]):
        self.ctx_getter = ctx_getter

    def collect(self):
        ctx = self.ctx_getter()
        if ctx is None:
            return
        counts = ctx.store.count_by_status()
        jobs = GaugeMetricFamily("dsareg_jobs", "Jobs in the store by state.", labels=["state"])
        for state in STATUSES:
            jobs.add_metric([state], counts.get(state, 0))
        yield jobs
        yield GaugeMetricFamily("dsareg_queue_depth", "Jobs waiting for a worker.", value=counts.get("queued", 0))
        yield GaugeMetricFamily("dsareg_workers_alive", "Worker processes alive.", value=ctx.executor.alive_workers())
        hist = HistogramMetricFamily("dsareg_job_duration_seconds", "Run time of finished jobs (started → finished).",
                                     labels=["state"])
        durations = ctx.store.finished_durations()
        for state in ("succeeded", "failed", "canceled"):
            values = [d for s, d in durations if s == state]
            buckets = [(str(b), sum(1 for v in values if v <= b)) for b in DURATION_BUCKETS]
            buckets.append(("+Inf", len(values)))
            hist.add_metric([state], buckets, sum_value=float(sum(values)))
        yield hist


# ---- auth ------------------------------------------------------------------------------------

bearer = HTTPBearer(auto_error=False, description="API key: `Authorization: Bearer <key>`.")


def get_ctx(request: Request) -> ServiceContext:
    return request.app.state.ctx


def principal(request: Request, credentials: HTTPAuthorizationCredentials | None = Depends(bearer)) -> str:  # noqa: B008
    """The caller: ``'anonymous'`` without configured keys, else ``'key:<hash prefix>'``."""
    ctx = get_ctx(request)
    if not ctx.settings.auth_enabled:
        return ANONYMOUS
    if credentials is None or not credentials.credentials:
        raise Problem(401, "send 'Authorization: Bearer <API key>'", headers={"WWW-Authenticate": "Bearer"})
    digest = hashlib.sha256(credentials.credentials.strip().encode("utf-8")).hexdigest()
    match = None
    for known in ctx.settings.api_key_hashes:  # compare against all, in constant time each
        if hmac.compare_digest(digest, known):
            match = known
    if match is None:
        raise Problem(401, "the API key is not valid", headers={"WWW-Authenticate": 'Bearer error="invalid_token"'})
    return "key:" + match[:16]


def owned_job(ctx: ServiceContext, job_id: str, who: str) -> JobRecord:
    job = ctx.store.get(job_id) if len(job_id) <= 64 else None
    if job is None:
        raise Problem(404, f"no registration job with id '{job_id[:64]}'", kind="job-not-found")
    if job.owner != who:
        raise Problem(403, "this job belongs to another API key")
    return job


# ---- app -------------------------------------------------------------------------------------

MULTIPART_SCHEMA = {
    "type": "object",
    "required": ["ap", "lat"],
    "properties": {
        "mesh": {"type": "string", "format": "binary", "description": "Vessel surface mesh (OBJ, STL, PLY, VTK…). Give mesh or volume."},
        "volume": {"type": "array", "items": {"type": "string", "format": "binary"},
                   "description": "Segmented 3D volume (NIfTI, NRRD, or a DICOM series as several files)."},
        "ap": {"type": "string", "format": "binary",
               "description": "AP view: DSA image or vessel mask (PNG, TIFF, DICOM XA…); a .rad + .raw pair as two parts."},
        "lat": {"type": "string", "format": "binary", "description": "LAT view: DSA image or vessel mask (as ap)."},
        "geometry": {"type": "string", "description": "Preset name (e.g. 'paper') or geometry JSON (text or file); "
                                                      "optional when DICOM XA headers carry the geometry."},
        "options": {"type": "string", "description": "RegistrationOptions as JSON, e.g. {\"starts\": 2}.",
                    "example": "{\"starts\": 1, \"max_iterations\": 100}"},
    },
}


def create_app(settings: ServiceSettings, *, executor: Executor | None = None, start_background: bool = True) -> FastAPI:
    holder: dict[str, ServiceContext | None] = {"ctx": None}
    registry = CollectorRegistry(auto_describe=True)
    http_latency = Histogram("dsareg_http_request_duration_seconds", "HTTP request latency by route template.",
                             ["method", "route", "status"], registry=registry,
                             buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60))
    uploads = Counter("dsareg_upload_bytes", "Bytes of accepted input files.", registry=registry)
    registry.register(StoreCollector(lambda: holder["ctx"]))

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        store = SqlJobStore(settings.effective_database_url)
        blobs = make_blob_store(settings, store.engine)
        validator = None
        if start_background:
            validator = ValidatorPool(settings.validation_processes, settings.validation_timeout_seconds,
                                      settings.validation_memory_mb, threads=settings.threads_per_worker)
            validator.start()
        ex = executor or make_executor(settings, store)
        ctx = ServiceContext(settings=settings, store=store, blobs=blobs, validator=validator, executor=ex,
                             registry=registry, uploads=uploads)
        holder["ctx"] = ctx
        app.state.ctx = ctx
        if not settings.auth_enabled:
            log.warning("no API keys configured: authentication is off and the service listens on 127.0.0.1 only")
        if start_background:
            ex.start()
            ctx.sweeper = Sweeper(ctx)
            ctx.sweeper.sweep_once()
            ctx.sweeper.start()
        log.info("dsareg service ready (%d worker processes, store %s)", settings.workers,
                 "sqlite" if store.is_sqlite else store.engine.dialect.name)
        try:
            yield
        finally:
            if ctx.sweeper:
                ctx.sweeper.stop()
            await asyncio.to_thread(ex.stop)
            if validator:
                await asyncio.to_thread(validator.stop)
            store.dispose()
            holder["ctx"] = None

    app = FastAPI(
        title="dsareg registration service",
        version="1.0.0",
        description=(
            "Registers a 3D vessel model to biplane DSA images. Submit a job with `POST /v1/registrations`, "
            "poll the `Location` it returns, then fetch the result and overlays. Errors are "
            "`application/problem+json` (RFC 9457)."
        ),
        lifespan=lifespan,
        responses=problem_responses(500),
        docs_url=None,  # served offline by docs_offline.install_docs
        redoc_url=None,
        generate_unique_id_function=_operation_id,
    )
    app.add_middleware(BodyLimitMiddleware, limit=settings.max_upload_bytes)
    app.add_middleware(MetricsMiddleware, histogram=http_latency, routes_getter=lambda: app.router.routes)
    _install_handlers(app)
    _install_routes(app)
    from .dicom_routes import install_dicom_routes

    install_dicom_routes(app, get_ctx, principal, owned_job)
    install_docs(app)
    original_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        schema = original_openapi()
        document_payloads(schema)  # options, geometry and result schemas; the multipart parts
        schemas = schema.setdefault("components", {}).setdefault("schemas", {})
        schemas["ProblemDetails"] = ProblemDetails.model_json_schema(ref_template="#/components/schemas/{model}")
        # FastAPI documents its own 422 body; ours is problem+json like every other error
        problem_422 = problem_responses(422)[422]
        for operations in schema.get("paths", {}).values():
            for operation in operations.values():
                responses = operation.get("responses", {})
                if "422" in responses:
                    responses["422"] = problem_422
        for name in ("HTTPValidationError", "ValidationError"):
            schemas.pop(name, None)
        if not settings.auth_enabled:  # the scheme stays declared, but anonymous access is allowed
            for operations in schema.get("paths", {}).values():
                for operation in operations.values():
                    if operation.get("security"):
                        operation["security"] = [{}, *operation["security"]]
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]
    return app


# ---- error handlers ----------------------------------------------------------------------------


def _problem_response(status: int, body: dict[str, Any], headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse(body, status_code=status, media_type=PROBLEM_MEDIA_TYPE, headers=headers)


def _install_handlers(app: FastAPI) -> None:
    @app.exception_handler(Problem)
    async def _problem(request: Request, exc: Problem) -> JSONResponse:
        return _problem_response(exc.status, exc.body(request.url.path), exc.headers)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail if isinstance(exc.detail, str) else None
        if exc.status_code == 404 and detail in (None, "Not Found"):
            detail = f"no such endpoint: {request.method} {request.url.path[:200]}; see /docs"
        headers = dict(exc.headers or {})
        if exc.status_code == 405:
            detail = f"{request.method} is not allowed on {request.url.path[:200]}; see /docs"
            headers["Allow"] = allowed_methods(request.app.router.routes, request.scope) or headers.get("Allow", "")
        return _problem_response(exc.status_code, problem_body(exc.status_code, detail, instance=request.url.path),
                                 headers)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        first = errors[0] if errors else {"loc": (), "msg": "invalid request"}
        loc = [str(p) for p in first.get("loc", ())]
        field_name = ".".join(loc[1:]) if len(loc) > 1 else ".".join(loc) or None
        where = loc[0] if loc else "request"
        detail = f"{where} parameter '{field_name}': {first.get('msg')}" if field_name else str(first.get("msg"))
        return _problem_response(422, problem_body(422, detail, kind="invalid-parameter", instance=request.url.path,
                                                   field=field_name))

    @app.exception_handler(ClientDisconnect)
    async def _gone(request: Request, exc: ClientDisconnect) -> JSONResponse:
        # the client went away mid-request (often mid-upload): nothing to answer, nothing broken here
        log.info("client disconnected during %s %s", request.method, _route_template(request))
        return _problem_response(400, problem_body(400, "the client disconnected before the request was complete",
                                                   kind="client-disconnected", instance=request.url.path))

    for outage in store_outage_errors():
        app.add_exception_handler(outage, _store_unavailable)

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception) -> JSONResponse:
        log.error("internal error on %s %s: %s", request.method, _route_template(request), type(exc).__name__,
                  exc_info=exc)
        return _problem_response(500, problem_body(500, "an internal error occurred; it has been logged",
                                                   instance=request.url.path))


def _operation_id(route: Any) -> str:
    """operationId = the handler's name (``submit``, ``get_job``, ``list_jobs``...): what generated clients call."""
    return route.name


async def _store_unavailable(request: Request, exc: Exception) -> JSONResponse:
    """The job database is down or busy: a temporary condition (503 + Retry-After), not a bug (500)."""
    log.warning("job store unavailable on %s %s: %s", request.method, _route_template(request), type(exc).__name__)
    return _problem_response(503, problem_body(503, "the job database is temporarily unavailable; retry later",
                                               kind="store-unavailable", instance=request.url.path),
                             {"Retry-After": STORE_RETRY_AFTER})


def _route_template(request: Request) -> str:
    route = request.scope.get("route")
    return getattr(route, "path", "unmatched")


# ---- routes ------------------------------------------------------------------------------------

ARTIFACTS = {
    ("overlays", "ap"): ("overlay_ap.png", "image/png"),
    ("overlays", "lat"): ("overlay_lat.png", "image/png"),
    ("masks", "ap"): ("mask_ap.png", "image/png"),
    ("masks", "lat"): ("mask_lat.png", "image/png"),
}

PNG_RESPONSE = {200: {"content": {"image/png": {"schema": {"type": "string", "format": "binary"}}},
                      "description": "The image."}}


def _read_text_field(value: Any, name: str, limit: int) -> str:
    if isinstance(value, UploadFile):
        data = value.file.read(limit + 1)
    elif isinstance(value, str):
        data = value.encode("utf-8")
    else:
        raise Problem(400, f"'{name}' must be text or a file", field=name)
    if len(data) > limit:
        raise Problem(413, f"'{name}' is larger than {limit} bytes", field=name)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise Problem(422, "is not UTF-8 text", field=name, accepted="UTF-8 JSON text") from None


def _normalize_geometry(text: str | None) -> str | None:
    """A preset name or compact JSON object text; anything else is refused (422)."""
    if text is None or not text.strip():
        return None
    from dsareg_engine.geometry_file import PRESETS

    text = text.strip()
    if text in PRESETS:
        return text
    if not text.startswith("{"):
        raise Problem(422, f"'{text[:40]}' is not a known preset and not a JSON object", field="geometry",
                      accepted=f"a preset name {sorted(PRESETS)} or geometry JSON (text or file)")
    data = parse_json_part(text, "geometry")
    return json.dumps(data, sort_keys=True, separators=(",", ":"))


def _install_routes(app: FastAPI) -> None:
    @app.post(
        "/v1/registrations",
        status_code=202,
        response_model=JobStatus,
        summary="Submit a registration job",
        description=(
            "multipart/form-data with `mesh` (or `volume`), `ap`, `lat`, optional `geometry` and `options`. "
            "Inputs are fully parsed before the job is accepted. Answers 202 with `Location` of the job. "
            "With an `Idempotency-Key` header, repeating the same request returns the original job (200), "
            "while reusing the key with a different request is a 409."
        ),
        openapi_extra={
            "requestBody": {"required": True, "content": {"multipart/form-data": {"schema": MULTIPART_SCHEMA}}},
            "parameters": [{"name": "Idempotency-Key", "in": "header", "required": False,
                            "schema": {"type": "string", "minLength": 1, "maxLength": 255, "pattern": r"\S"},
                            "description": "Makes retries of the same submission safe. 1 to 255 characters, at "
                                           "least one of them not white space; otherwise 400 (field "
                                           "`Idempotency-Key`)."}],
        },
        responses={
            200: {"description": "Idempotent replay: the job created earlier with this key.", "model": JobStatus},
            202: {"description": "Accepted; poll the Location.", "headers": {
                "Location": {"description": "The job's URL.", "schema": {"type": "string"}},
                "Retry-After": {"description": "Seconds before the first poll.", "schema": {"type": "integer"}}}},
            **problem_responses(400, 401, 409, 413, 415, 422, 429, 503),
        },
        tags=["registrations"],
    )
    async def submit(request: Request, who: str = Depends(principal)) -> Response:
        ctx = get_ctx(request)
        key = request.headers.get("idempotency-key")
        if key is not None and (not key.strip() or len(key) > 255):
            raise Problem(400, "Idempotency-Key must be 1 to 255 characters", field="Idempotency-Key")
        content_type = request.headers.get("content-type", "")
        if content_type.lower().startswith("application/json"):  # inputs by DICOMweb reference
            from .dicom_routes import submit_by_reference

            return await submit_by_reference(ctx, request, who, key)
        if not content_type.lower().startswith("multipart/form-data"):
            raise Problem(415, "send multipart/form-data with the files mesh (or volume), ap and lat",
                          accepted="multipart/form-data")
        form = await request.form(max_files=MAX_VOLUME_FILES + 8, max_fields=20, max_part_size=MAX_OPTIONS_BYTES)
        try:
            return await _submit(ctx, request, form, who, key)
        finally:
            await form.close()

    async def _submit(ctx: ServiceContext, request: Request, form: Any, who: str, key: str | None) -> Response:
        known = {"mesh", "volume", "ap", "lat", "geometry", "options"}
        unknown = sorted(set(form.keys()) - known)
        if unknown:
            raise Problem(422, f"unknown form field(s) {unknown[:5]}", field=str(unknown[0])[:64],
                          accepted="mesh, volume, ap, lat, geometry, options")
        files: dict[str, list[UploadFile]] = {}
        for name in ("mesh", "volume", "ap", "lat"):
            values = form.getlist(name)
            for value in values:
                if not isinstance(value, UploadFile):
                    raise Problem(422, "must be a file part (with a filename)", field=name)
            if values:
                files[name] = values  # type: ignore[assignment]
        if len(files.get("mesh", [])) > 1:
            raise Problem(422, "give exactly one mesh file", field="mesh")
        for name in ("ap", "lat"):
            if len(files.get(name, [])) > 2:
                raise Problem(422, "give one image file (or a .rad + .raw pair)", field=name)
        if "mesh" in files and "volume" in files:
            raise Problem(422, "give either a mesh or a volume, not both", field="mesh", accepted="mesh or volume")
        if "mesh" not in files and "volume" not in files:
            raise Problem(422, "a 3D model is required", field="mesh", accepted="a mesh file or volume file(s)")
        for name in ("ap", "lat"):
            if name not in files:
                raise Problem(422, "this image is required", field=name, accepted="a DSA image or mask file")
        geometry_values = form.getlist("geometry")
        options_values = form.getlist("options")
        if len(geometry_values) > 1 or len(options_values) > 1:
            raise Problem(422, "give geometry and options at most once", field="geometry" if len(geometry_values) > 1 else "options")
        geometry = _normalize_geometry(
            _read_text_field(geometry_values[0], "geometry", MAX_GEOMETRY_BYTES) if geometry_values else None)
        options_text = _read_text_field(options_values[0], "options", MAX_OPTIONS_BYTES) if options_values else None
        from dsareg_engine.errors import DsaregInputError
        from dsareg_engine.registration.options import parse_options

        options_data = parse_json_part(options_text, "options") if options_text and options_text.strip() else None
        try:
            options = parse_options(options_data)
        except DsaregInputError as exc:
            raise Problem(422, exc.message, field=exc.field, accepted=exc.accepted) from None
        check_options(options)
        options_json = options.model_dump(mode="json")

        # store the uploads (content-addressed) and fingerprint the request
        inputs: list[InputFile] = []
        sources: list[UploadFile] = []
        for role in ("mesh", "volume", "ap", "lat"):
            for upload in files.get(role, []):
                await upload.seek(0)
                digest, size = await asyncio.to_thread(ctx.blobs.put_stream, upload.file)
                if size == 0:
                    raise Problem(422, "the file is empty", field=role)
                inputs.append(InputFile(role=role, sha256=digest, size=size, suffix=safe_suffix(upload.filename)))
                sources.append(upload)
        fingerprint = hashlib.sha256(json.dumps(
            {"inputs": [vars(f) for f in inputs], "geometry": geometry, "options": options_json},
            sort_keys=True).encode()).hexdigest()
        total = sum(f.size for f in inputs)

        if key is not None:
            existing = await asyncio.to_thread(ctx.store.find_idempotent, who, key)
            if existing is not None:
                return _replay(existing, fingerprint)

        # back-pressure before the expensive parse
        if await asyncio.to_thread(ctx.store.queued_count) >= ctx.settings.queue_limit:
            raise Problem(503, f"the job queue is full ({ctx.settings.queue_limit} queued); retry later",
                          kind="queue-full", headers={"Retry-After": "30"})
        if who != ANONYMOUS and await asyncio.to_thread(ctx.store.queued_count, who) >= ctx.settings.queue_limit_per_key:
            raise Problem(429, f"this API key already has {ctx.settings.queue_limit_per_key} queued jobs; retry later",
                          headers={"Retry-After": "30"})

        warnings: list[str] = []
        if ctx.validator is not None:
            outcome = await ctx.validator.validate({
                "inputs": [vars(f) for f in inputs], "geometry": geometry, "segmentation": options.segmentation,
                "blob_root": str(ctx.blobs.root), "limits": ctx.settings.input_limits,
                "require_cuda": options.device == "cuda" and ctx.settings.executor == "embedded",
            })
            if outcome.unavailable:
                raise Problem(503, "the registration engine is not available on this server", kind="engine-unavailable",
                              headers={"Retry-After": "60"})
            if not outcome.ok:
                raise Problem(422, outcome.message or "invalid input", field=outcome.field, accepted=outcome.accepted)
            warnings = list((outcome.summary or {}).get("warnings", []))
            views = (outcome.summary or {}).get("views") or {}
            check_job_cost(options, [tuple(size) for size in views.values()], ctx.settings.max_job_cost)

        now = time.time()
        job = JobRecord(
            id=new_job_id(), owner=who, status="queued", created_at=now, updated_at=now,
            max_attempts=ctx.settings.max_attempts, options=options_json, geometry=geometry, inputs=inputs,
            warnings=warnings, idempotency_key=key, request_hash=fingerprint, input_bytes=total,
        )
        try:
            stored, created = await asyncio.to_thread(ctx.store.create, job)
        except ConflictError as exc:
            return _replay(exc.existing, fingerprint)
        if not created:
            return _replay(stored, fingerprint)
        # a concurrent DELETE of another job with the same content may have removed a shared blob
        # between our upload and our insert; now that we reference it, put it back if so
        for item, upload in zip(inputs, sources):
            if not ctx.blobs.exists(item.sha256):
                await upload.seek(0)
                await asyncio.to_thread(ctx.blobs.put_stream, upload.file)
        ctx.uploads.inc(total)
        await asyncio.to_thread(ctx.executor.submit, stored.id)
        log.info("job %s: queued (%d files, %d bytes)", stored.id, len(inputs), total)
        return JSONResponse(
            status_body(stored), status_code=202,
            headers={"Location": f"/v1/registrations/{stored.id}", "Retry-After": RETRY_AFTER_QUEUED},
        )

    def _replay(existing: JobRecord, fingerprint: str) -> Response:
        if existing.request_hash != fingerprint:
            raise Problem(409, "this Idempotency-Key was already used with a different request; use a new key",
                          kind="idempotency-conflict", field="Idempotency-Key",
                          extra={"job_id": existing.id})
        return JSONResponse(status_body(existing), status_code=200,
                            headers={"Location": f"/v1/registrations/{existing.id}"})

    install_track_route(app, _submit, get_ctx, principal, owned_job, MAX_OPTIONS_BYTES)

    @app.get("/v1/registrations", response_model=JobList, tags=["registrations"], summary="List jobs (newest first)",
             responses=problem_responses(400, 401, 422))
    def list_jobs(
        request: Request,
        status: str | None = Query(None, description="Only jobs in this state.",
                                   json_schema_extra={"enum": list(STATUSES)}),
        limit: int = Query(20, ge=1, le=100, description="Page size."),
        cursor: str | None = Query(
            None, max_length=200,
            description="Opaque paging token: exactly the `next_cursor` of the previous page (URL-safe base64 "
                        "without padding, at most 200 characters). Any other value → 400 with field `cursor`."),
        who: str = Depends(principal),
    ) -> Response:
        ctx = get_ctx(request)
        if status is not None and status not in STATUSES:
            raise Problem(422, f"unknown status '{status[:20]}'", field="status", accepted=", ".join(STATUSES))
        if cursor:
            try:
                decode_cursor(cursor)
            except Exception:  # noqa: BLE001
                raise Problem(400, "the cursor is not valid; use next_cursor from a previous page", field="cursor") from None
        records, next_cursor = ctx.store.list(owner=who, status=status, limit=limit, cursor=cursor)
        next_link = None
        if next_cursor:
            next_link = f"/v1/registrations?limit={limit}&cursor={next_cursor}" + (f"&status={status}" if status else "")
        return JSONResponse({"items": [summary_body(r) for r in records], "next_cursor": next_cursor,
                             "links": {"next": next_link}})

    @app.get("/v1/registrations/{job_id}", response_model=JobStatus, tags=["registrations"], summary="Job status",
             responses=problem_responses(401, 403, 404))
    def get_job(request: Request, job_id: str, who: str = Depends(principal)) -> Response:
        job = owned_job(get_ctx(request), job_id, who)
        headers = {"Retry-After": RETRY_AFTER_QUEUED} if job.status in ("queued", "running") else {}
        return JSONResponse(status_body(job), headers=headers)

    @app.get("/v1/registrations/{job_id}/result", tags=["results"], summary="Registration result (JSON)",
             responses={200: {"description": "mesh_to_world, per-view results and metrics",
                              "content": {"application/json": {"example": {
                                  "mesh_to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                                  "views": {"ap": {}, "lat": {}}, "metrics": {"dice": {"ap": 0.91, "lat": 0.9}}}}}},
                        **problem_responses(401, 403, 404)})
    def get_result(request: Request, job_id: str, who: str = Depends(principal)) -> Response:
        job = owned_job(get_ctx(request), job_id, who)
        if job.status != "succeeded" or job.result is None:
            raise Problem(404, f"no result: the job is {job.status}", kind="result-not-available",
                          extra={"job_status": job.status})
        return JSONResponse(job.result)

    def _artifact(request: Request, job_id: str, who: str, name: str, media: str) -> Response:
        ctx = get_ctx(request)
        job = owned_job(ctx, job_id, who)
        digest = job.artifacts.get(name)
        if job.status != "succeeded" or not digest:
            why = f"the job is {job.status}" if job.status != "succeeded" else "the job did not produce it"
            raise Problem(404, f"{name} is not available: {why}", kind="artifact-not-available",
                          extra={"job_status": job.status})
        path = ctx.blobs.local_path(digest)
        if path is None:
            raise Problem(404, f"{name} is no longer stored", kind="artifact-not-available")
        return FileResponse(path, media_type=media, headers={"Cache-Control": "private, max-age=86400"})

    @app.get("/v1/registrations/{job_id}/overlays/{view}.png", tags=["results"], summary="Overlay of the registered mesh",
             response_class=Response, responses={**PNG_RESPONSE, **problem_responses(401, 403, 404, 422)})
    def get_overlay(request: Request, job_id: str, view: Literal["ap", "lat"], who: str = Depends(principal)) -> Response:
        name, media = ARTIFACTS[("overlays", view)]
        return _artifact(request, job_id, who, name, media)

    @app.get("/v1/registrations/{job_id}/masks/{view}.png", tags=["results"], summary="Vessel mask used for a view",
             response_class=Response, responses={**PNG_RESPONSE, **problem_responses(401, 403, 404, 422)})
    def get_mask(request: Request, job_id: str, view: Literal["ap", "lat"], who: str = Depends(principal)) -> Response:
        name, media = ARTIFACTS[("masks", view)]
        return _artifact(request, job_id, who, name, media)

    @app.get("/v1/registrations/{job_id}/animation.gif", tags=["results"], summary="Animation of the optimization",
             response_class=Response,
             responses={200: {"content": {"image/gif": {"schema": {"type": "string", "format": "binary"}}},
                              "description": "Animated GIF (only with options.animation)."},
                        **problem_responses(401, 403, 404)})
    def get_animation(request: Request, job_id: str, who: str = Depends(principal)) -> Response:
        return _artifact(request, job_id, who, "animation.gif", "image/gif")

    @app.get("/v1/registrations/{job_id}/loss.png", tags=["results"], summary="Plot of the loss per iteration",
             response_class=Response, responses={**PNG_RESPONSE, **problem_responses(401, 403, 404)})
    def get_loss_plot(request: Request, job_id: str, who: str = Depends(principal)) -> Response:
        return _artifact(request, job_id, who, "loss.png", "image/png")

    @app.post("/v1/registrations/{job_id}/cancel", response_model=JobStatus, tags=["registrations"],
              summary="Cancel a job",
              description="A queued job is canceled at once (200); a running job stops at its next progress check "
                          "(202, poll until status is canceled). A finished job gives 409.",
              responses={202: {"description": "Cancellation requested; the worker stops shortly.", "model": JobStatus},
                         **problem_responses(401, 403, 404, 409)})
    def cancel_job(request: Request, job_id: str, who: str = Depends(principal)) -> Response:
        ctx = get_ctx(request)
        job = owned_job(ctx, job_id, who)
        if job.status in ("succeeded", "failed"):
            raise Problem(409, f"the job already finished ({job.status}); nothing to cancel", kind="job-finished",
                          extra={"job_status": job.status})
        updated = ctx.store.request_cancel(job_id) or job
        ctx.executor.cancel(job_id)
        code = 202 if updated.status == "running" else 200
        return JSONResponse(status_body(updated), status_code=code)

    @app.delete("/v1/registrations/{job_id}", status_code=204, tags=["registrations"], summary="Delete a job and its files",
                response_class=Response, responses={204: {"description": "Deleted."}, **problem_responses(401, 403, 404)})
    def delete_job(request: Request, job_id: str, who: str = Depends(principal)) -> Response:
        ctx = get_ctx(request)
        job = owned_job(ctx, job_id, who)
        if job.status == "running":
            ctx.store.request_cancel(job_id)
            ctx.executor.cancel(job_id)
        orphans = ctx.store.delete(job_id)
        ctx.blobs.delete(orphans, min_age_seconds=0.0)
        ctx.blobs.remove_job_work(job_id)
        log.info("job %s: deleted", job_id)
        return Response(status_code=204)

    @app.get("/healthz", response_model=Health, tags=["operations"], summary="Liveness")
    def healthz() -> Health:
        return Health(status="ok")

    @app.get("/readyz", response_model=Health, tags=["operations"], summary="Readiness: store writable, a worker alive",
             responses={503: {"description": "Not ready", "model": Health}})
    def readyz(request: Request) -> Response:
        ctx = get_ctx(request)
        checks = {
            "store_writable": ctx.store.ping(),
            "workers_alive": ctx.executor.alive_workers(),
            "validator_alive": ctx.validator.alive() if ctx.validator else False,
            "validator_ready": ctx.validator.ready() if ctx.validator else False,
        }
        data_ok = Path(ctx.settings.data_dir).is_dir()
        checks["data_dir"] = data_ok
        ready = (checks["store_writable"] and checks["workers_alive"] > 0 and data_ok
                 and (ctx.validator is None or checks["validator_ready"]))
        body = Health(status="ok" if ready else "unavailable", checks=checks)
        return JSONResponse(body.model_dump(), status_code=200 if ready else 503,
                            headers=None if ready else {"Retry-After": "5"})

    @app.get("/metrics", tags=["operations"], summary="Prometheus metrics", response_class=Response,
             responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}, "description": "Prometheus text"}})
    def metrics(request: Request) -> Response:
        return Response(generate_latest(get_ctx(request).registry), media_type=CONTENT_TYPE_LATEST)

    _ = EXAMPLE_ID
