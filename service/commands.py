"""``dsareg serve`` and ``dsareg submit`` (plugged into :mod:`dsareg_engine.cli`)."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any


def add_parser(subparsers: Any) -> None:
    serve = subparsers.add_parser(
        "serve", help="run the HTTP registration service with embedded workers",
        description="Run the registration service. Settings come from DSAREG_* environment variables, "
                    "a config file (--config or DSAREG_CONFIG, JSON or TOML), and these flags (highest priority).",
    )
    serve.add_argument("--host", help="bind address (forced to 127.0.0.1 when no API keys are configured)")
    serve.add_argument("--port", type=int)
    serve.add_argument("--data-dir", type=Path, help="inputs, artifacts and the default SQLite database")
    serve.add_argument("--database-url", help="SQLAlchemy URL (default: SQLite in the data dir)")
    serve.add_argument("--workers", type=int, help="embedded worker processes (default 1)")
    serve.add_argument("--threads-per-worker", type=int, help="torch threads per worker")
    serve.add_argument("--config", help="config file (JSON or TOML)")
    serve.add_argument("--log-level", help="debug, info, warning, error")
    serve.set_defaults(func=run_serve)

    worker = subparsers.add_parser(
        "worker", help="run a standalone worker (Celery, or a polling worker on the job store)",
        description="Run one worker process that claims jobs from the shared job store. --engine celery consumes "
                    "the Celery queue (DSAREG_BROKER_URL); --engine embedded polls the job table. Settings as for serve.",
    )
    worker.add_argument("--engine", choices=("celery", "embedded"), default="celery")
    worker.add_argument("--pool", choices=("threads", "solo"), default="threads",
                        help="Celery pool; one job at a time either way (threads: revocations arrive while a job runs)")
    worker.add_argument("--hostname", help="Celery node name (default celery@<host>)")
    worker.add_argument("--data-dir", type=Path, help="local scratch space and blob cache")
    worker.add_argument("--database-url", help="SQLAlchemy URL of the shared job store")
    worker.add_argument("--broker-url", help="Celery broker, e.g. redis://redis:6379/0")
    worker.add_argument("--threads-per-worker", type=int, help="torch threads of this process")
    worker.add_argument("--config", help="config file (JSON or TOML)")
    worker.add_argument("--log-level", help="debug, info, warning, error")
    worker.set_defaults(func=run_worker)

    submit = subparsers.add_parser("submit", help="submit a registration to a dsareg server",
                                   description="Submit a job; with --wait, show progress and download the outputs.")
    submit.add_argument("--server", required=True, help="base URL, e.g. http://127.0.0.1:8000")
    model = submit.add_mutually_exclusive_group(required=True)
    model.add_argument("--mesh", type=Path, help="vessel mesh file")
    model.add_argument("--volume", type=Path, nargs="+", help="volume file(s) (a DICOM series: several files)")
    submit.add_argument("--ap", type=Path, required=True)
    submit.add_argument("--lat", type=Path, required=True)
    submit.add_argument("--geometry", help="preset name, geometry JSON file, or JSON text")
    submit.add_argument("--options", help="options as JSON text or a JSON file")
    submit.add_argument("--api-key", help="API key (default: DSAREG_API_KEY)")
    submit.add_argument("--idempotency-key", help="makes retrying this submission safe")
    submit.add_argument("--wait", action="store_true", help="wait for the job, showing progress")
    submit.add_argument("--out", type=Path, help="with --wait: directory for result.json, overlays and masks")
    submit.add_argument("--timeout", type=float, default=3600.0, help="with --wait: give up after this many seconds")
    submit.set_defaults(func=run_submit)


def run_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from .app import create_app
    from .settings import load_settings

    settings = load_settings(
        args.config, host=args.host, port=args.port, data_dir=args.data_dir, database_url=args.database_url,
        workers=args.workers, threads_per_worker=args.threads_per_worker, log_level=args.log_level,
    )
    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    log = logging.getLogger("dsareg.service")
    host = settings.effective_host
    if host != settings.host:
        log.warning("no API keys configured: binding to 127.0.0.1 instead of %s", settings.host)
    app = create_app(settings)
    uvicorn.run(app, host=host, port=settings.port, log_level=settings.log_level.lower(), access_log=False,
                timeout_graceful_shutdown=10)
    return 0


def run_worker(args: argparse.Namespace) -> int:
    from .settings import load_settings

    settings = load_settings(
        args.config, data_dir=args.data_dir, database_url=args.database_url, broker_url=args.broker_url,
        threads_per_worker=args.threads_per_worker, log_level=args.log_level,
    )
    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    if args.engine == "celery":
        from .celery_executor import run_worker as run_celery_worker

        run_celery_worker(settings, pool=args.pool, hostname=args.hostname)
        return 0
    from .store import SqlJobStore
    from .worker import worker_main

    SqlJobStore(settings.effective_database_url).dispose()  # create the schema if this is the first process
    worker_main(settings, 0)
    return 0


def _read_json_arg(value: str | None, field: str) -> Any:
    if value is None:
        return None
    text = value
    if not value.lstrip().startswith(("{", "[")) and Path(value).is_file():
        text = Path(value).read_text(encoding="utf-8")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        from dsareg_engine.errors import DsaregInputError

        raise DsaregInputError(f"is not valid JSON ({exc.msg})", field=field) from None


def run_submit(args: argparse.Namespace) -> int:
    import os

    from .client import RegistrationClient, ServiceError

    geometry: Any = args.geometry
    if geometry is not None and not geometry.lstrip().startswith("{") and Path(geometry).is_file():
        geometry = Path(geometry)
    options = _read_json_arg(args.options, "options")
    client = RegistrationClient(args.server, api_key=args.api_key or os.environ.get("DSAREG_API_KEY"))
    try:
        job = client.submit(ap=args.ap, lat=args.lat, mesh=args.mesh, volume=args.volume, geometry=geometry,
                            options=options, idempotency_key=args.idempotency_key)
        print(f"job {job['id']}: {job['status']}", file=sys.stderr)
        if not args.wait:
            print(json.dumps(job, indent=2))
            return 0
        bar = _ProgressBar()
        final = client.wait(job["id"], progress=bar.update, timeout=args.timeout)
        bar.close()
        print(f"job {final['id']}: {final['status']}", file=sys.stderr)
        if final["status"] != "succeeded":
            err = final.get("error") or {}
            if err:
                print(f"  {err.get('title')}: {err.get('detail')}", file=sys.stderr)
            return 1
        if args.out:
            written = client.download_all(final["id"], args.out)
            for path in written:
                print(f"  wrote {path}", file=sys.stderr)
        print(json.dumps(final.get("result"), indent=2))
        return 0
    except ServiceError as exc:
        print(f"dsareg: error: {exc}", file=sys.stderr)
        return 2
    finally:
        client.close()


class _ProgressBar:
    def __init__(self, width: int = 30):
        self.width = width
        self.stream = sys.stderr
        self.drawn = False

    def update(self, status: dict) -> None:
        progress = status.get("progress") or {}
        fraction = float(progress.get("fraction") or 0.0)
        filled = round(fraction * self.width)
        loss = progress.get("loss")
        loss_text = f" loss {loss:.4f}" if isinstance(loss, (int, float)) else ""
        line = (f"\r[{'#' * filled}{'.' * (self.width - filled)}] {fraction * 100:5.1f}% "
                f"{status.get('status', ''):9s} {progress.get('stage', '')} it {progress.get('iteration', 0)}{loss_text}")
        self.stream.write(line[:120].ljust(100))
        self.stream.flush()
        self.drawn = True

    def close(self) -> None:
        if self.drawn:
            self.stream.write("\n")
            self.stream.flush()
