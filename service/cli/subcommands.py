"""``dsareg serve``, ``dsareg worker`` and ``dsareg submit``, contributed to :mod:`dsareg_engine.cli`
through the ``dsareg.commands`` entry-point group (``pyproject.toml``)."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from .db import add_db_parser, migrate_at_start
from .jobs import add_jobs_parser


def add_parser(subparsers: Any) -> None:
    """The service's sub-commands (contributed to ``dsareg`` through the ``dsareg.commands`` entry point)."""
    _add_serve(subparsers)
    _add_worker(subparsers)
    _add_dicom_listener(subparsers)
    _add_submit(subparsers)
    add_db_parser(subparsers)
    add_jobs_parser(subparsers)


def _add_serve(subparsers: Any) -> None:
    serve = subparsers.add_parser(
        "serve", help="run the HTTP registration service with embedded workers",
        description="Run the registration service. Settings come from DSAREG_* environment variables, "
                    "a config file (--config or DSAREG_CONFIG, JSON or TOML), and these flags (highest priority).",
    )
    serve.add_argument("--host", help="bind address (forced to 127.0.0.1 when no API keys are configured)")
    serve.add_argument("--port", type=int, help="TCP port (default 8000)")
    serve.add_argument("--data-dir", type=Path, help="inputs, artifacts and the default SQLite database")
    serve.add_argument("--database-url", help="SQLAlchemy URL (default: SQLite in the data dir)")
    serve.add_argument("--workers", type=int, help="embedded worker processes (default 1)")
    serve.add_argument("--threads-per-worker", type=int, help="torch threads per worker")
    serve.add_argument("--config", metavar="FILE",
                       help="service settings file (JSON or TOML, keys as the DSAREG_* variables without the prefix); "
                            "not the registration configuration, which is an option of each job")
    serve.add_argument("--log-level", help="debug, info, warning, error")
    serve.add_argument("--ssl-certfile", metavar="PEM", help="serve HTTPS with this certificate (chain), with "
                       "--ssl-keyfile: uvicorn's own TLS (docs/deployment/security.md; or TLS at a reverse proxy)")
    serve.add_argument("--ssl-keyfile", metavar="PEM", help="the certificate's private key (PEM, not encrypted)")
    serve.set_defaults(func=run_serve)


def _add_worker(subparsers: Any) -> None:
    worker = subparsers.add_parser(
        "worker", help="run a standalone worker (Celery, or a polling worker on the job store)",
        description="Run one worker process that claims jobs from the shared job store. --engine celery consumes "
                    "the Celery queue (DSAREG_BROKER_URL); --engine embedded polls the job table. Settings as for serve.",
    )
    worker.add_argument("--engine", choices=("celery", "embedded"), default="celery",
                        help="celery: consume the Celery queue; embedded: poll the job table (default celery)")
    worker.add_argument("--pool", choices=("threads", "solo"), default="threads",
                        help="Celery pool; one job at a time either way (threads: revocations arrive while a job runs)")
    worker.add_argument("--hostname", help="Celery node name (default celery@<host>)")
    worker.add_argument("--data-dir", type=Path, help="local scratch space and blob cache")
    worker.add_argument("--database-url", help="SQLAlchemy URL of the shared job store")
    worker.add_argument("--broker-url", help="Celery broker, e.g. redis://redis:6379/0")
    worker.add_argument("--threads-per-worker", type=int, help="torch threads of this process")
    worker.add_argument("--config", metavar="FILE", help="service settings file (JSON or TOML), as for serve")
    worker.add_argument("--log-level", help="debug, info, warning, error")
    worker.set_defaults(func=run_worker)


def _add_dicom_listener(subparsers: Any) -> None:
    listener = subparsers.add_parser(
        "dicom-listener", help="run the DICOM node (C-ECHO, C-STORE SCP) in its own process",
        description="Receive studies over DIMSE (DSAREG_DICOM_PORT, DSAREG_DICOM_AE_TITLE, DSAREG_DICOM_PEERS) and "
                    "queue their registrations in the shared job store; results go back by C-STORE. Settings as for "
                    "serve (see docs/pacs/dimse.md). One listener per job database.")
    listener.add_argument("--port", type=int, help="DICOM TCP port (DSAREG_DICOM_PORT)")
    listener.add_argument("--ae-title", help="AE title (DSAREG_DICOM_AE_TITLE, default DSAREG)")
    listener.add_argument("--data-dir", type=Path, help="inputs, artifacts and the default SQLite database")
    listener.add_argument("--database-url", help="SQLAlchemy URL of the shared job store")
    listener.add_argument("--config", metavar="FILE", help="service settings file (JSON or TOML), as for serve")
    listener.add_argument("--log-level", help="debug, info, warning, error")
    listener.set_defaults(func=run_dicom_listener)


def run_dicom_listener(args: argparse.Namespace) -> int:
    from ..pacs.dimse.standalone import run_dicom_listener as run_listener
    from ..settings import load_settings

    settings = load_settings(args.config, dicom_port=args.port, dicom_ae_title=args.ae_title, data_dir=args.data_dir,
                             database_url=args.database_url, log_level=args.log_level)
    logging.basicConfig(level=settings.server.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return run_listener(settings)


def _add_submit(subparsers: Any) -> None:
    from ..engine_adapter import commands

    input_file, options_help = commands.input_file, commands.options_help
    require_choices, not_met = commands.REQUIRE_CHOICES, commands.VERDICT_NOT_MET_EXIT

    submit = subparsers.add_parser(
        "submit", help="submit a registration to a dsareg server (and wait for it)",
        description="Submit a job to a running `dsareg serve`. Without --wait, prints the job id and returns; with "
                    "--wait (or --out), shows progress on stderr (a line per stage when stderr is not a terminal), "
                    "prints a one-line summary on stdout and, with --out, downloads result.json, overlays, masks, "
                    "the animation and the DICOM objects. A job that succeeded only ran: its verdict (ok / check / "
                    "failed) says whether to trust the pose; --require makes that the exit status.",
        epilog="Exit status: 0 succeeded (or submitted, without --wait), 1 the job failed or the server is "
               "unreachable, 2 usage or input error (the server's 4xx answers name the field), "
               f"{not_met} the job succeeded but its verdict is below --require.")
    submit.add_argument("--server", required=True, metavar="URL", help="base URL, e.g. http://127.0.0.1:8000")
    model = submit.add_mutually_exclusive_group(required=True)
    model.add_argument("--mesh", type=input_file, metavar="FILE",
                       help="vessel mesh in mm (OBJ, STL, PLY, OFF, GLB, VTP, legacy VTK polydata)")
    model.add_argument("--volume", type=input_file, nargs="+", metavar="FILE",
                       help="vessel volume file(s): NIfTI, NRRD (.nrrd, or .nhdr + its data file), MetaImage (.mha, "
                            "or .mhd + its data file), legacy VTK structured points, .rad + .raw, or a DICOM series "
                            "as several files")
    submit.add_argument("--ap", type=input_file, required=True, metavar="FILE",
                        help="AP DSA image or vessel mask (PNG, TIFF, JPEG, DICOM XA)")
    submit.add_argument("--lat", type=input_file, required=True, metavar="FILE", help="LAT image or mask (as --ap)")
    submit.add_argument("--geometry", metavar="PRESET|FILE|JSON",
                        help="a preset name (paper), a geometry JSON file, or JSON text; optional with DICOM XA")
    submit.add_argument("--options", metavar="JSON|FILE", help=options_help())
    submit.add_argument("--mesh-units", choices=("mm", "cm", "m"),
                        help="the --mesh file's unit, sent as options.mesh_units (default: the format's own, metres "
                             "for GLB, else mm)")
    submit.add_argument("--hemodynamics", action="store_true",
                        help="also map contrast arrival and time to peak onto the model (options.hemodynamics; needs "
                             "timed multi-frame DICOM XA runs); --out downloads hemodynamics.json/.ply/.vtk and the "
                             "parametric maps")
    submit.add_argument("--ground-truth", type=input_file, metavar="POSE.json",
                        help='pose file {"mesh_to_world": 4x4} of the true pose; adds error metrics to the result')
    submit.add_argument("--api-key", help="API key (default: the DSAREG_API_KEY environment variable)")
    submit.add_argument("--idempotency-key", metavar="KEY", help="makes retrying this submission safe")
    submit.add_argument("--wait", action="store_true", help="wait for the job, showing progress")
    submit.add_argument("--out", type=Path, metavar="DIR",
                        help="download result.json, overlays, masks (and the animation) here; implies --wait")
    submit.add_argument("--json", action="store_true",
                        help="print the job (without --wait) or the result (with --wait) as JSON on stdout")
    submit.add_argument("--timeout", type=float, default=3600.0, metavar="SECONDS",
                        help="with --wait: give up after this many seconds (default 3600)")
    submit.add_argument("--require", choices=require_choices,
                        help=f"implies --wait; exit {not_met} unless the verdict is at least this "
                             "(ok; or check: ok or check)")
    submit.add_argument("--callback-url", metavar="URL",
                        help="the server POSTs the job summary here when the job ends (signed; the server must "
                             "allow the URL's prefix)")
    submit.set_defaults(func=run_submit)


def run_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from ..app import create_app, http_protocol, tls_options, uvicorn_options
    from ..settings import load_settings

    settings = load_settings(
        args.config, host=args.host, port=args.port, data_dir=args.data_dir, database_url=args.database_url,
        workers=args.workers, threads_per_worker=args.threads_per_worker, log_level=args.log_level,
    )
    logging.basicConfig(level=settings.server.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    tls = tls_options(args.ssl_certfile, args.ssl_keyfile)  # a wrong file: one line, exit 2, nothing started
    if settings.dimse.dicom_port:  # the DICOM node's settings, before anything starts (a SettingError, exit 2)
        from ..pacs.dimse.job_options import dicom_job_options

        dicom_job_options(settings)
    if settings.effective_database_url.startswith("sqlite"):
        settings.storage.data_dir.mkdir(parents=True, exist_ok=True)
    migrate_at_start(settings.effective_database_url)  # the job database's schema (docs/operations/upgrades.md)
    host = settings.effective_host  # 127.0.0.1 without API keys: the app's start-up says so (api/lifespan.py)
    app = create_app(settings)
    uvicorn.run(app, host=host, port=settings.server.port, log_level=settings.server.log_level.lower(), access_log=False,
                timeout_graceful_shutdown=10, http=http_protocol(settings),  # bad Content-Length → problem+json
                **uvicorn_options(settings), **tls)  # at most http_max_connections; HTTPS when given
    return 0


def run_worker(args: argparse.Namespace) -> int:
    from ..settings import load_settings

    settings = load_settings(
        args.config, data_dir=args.data_dir, database_url=args.database_url, broker_url=args.broker_url,
        threads_per_worker=args.threads_per_worker, log_level=args.log_level,
    )
    logging.basicConfig(level=settings.server.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    settings.storage.data_dir.mkdir(parents=True, exist_ok=True)
    if args.engine == "celery":
        from ..jobs.celery.worker import run_worker as run_celery_worker

        run_celery_worker(settings, pool=args.pool, hostname=args.hostname)
        return 0
    from ..storage.store import SqlJobStore
    from ..jobs.worker import worker_main

    SqlJobStore(settings.effective_database_url).dispose()  # migrate the job database (storage/migrate.py)
    worker_main(settings, 0)
    return 0


def summary_line(final: dict[str, Any]) -> str:
    """One line like `dsareg register` prints: verdict, Dice per view, time, ground-truth errors."""
    result = final.get("result") or {}
    metrics = result.get("metrics") or {}
    confidence = metrics.get("confidence") or {}
    verdict = confidence.get("verdict")
    state = (f"verdict {verdict}; " if verdict else "") + ("converged" if metrics.get("converged") else "NOT converged")
    reason = metrics.get("reason")
    views = result.get("views") or {}
    dice = ", ".join(f"{name} dice {view.get('dice', float('nan')):.3f}" for name, view in views.items()
                     if isinstance(view, dict) and isinstance(view.get("dice"), (int, float)))
    seconds = (metrics.get("seconds") or {}).get("total")
    parts = [f"job {final.get('id')}: {state}" + (f" ({reason})" if reason else "")]
    if dice:
        parts.append(dice)
    if isinstance(seconds, (int, float)):
        parts.append(f"{seconds:.1f} s")
    gt = metrics.get("ground_truth")
    if isinstance(gt, dict) and "add_mm" in gt:
        from ..engine_adapter import commands

        parts.append(commands.ground_truth_text(gt))
    if verdict in ("check", "failed") and confidence.get("reasons"):
        parts.append("why: " + " / ".join(str(reason) for reason in confidence["reasons"]))
    return "; ".join(parts)


def run_submit(args: argparse.Namespace) -> int:
    import os

    from .client import RegistrationClient
    from ..engine_adapter import commands, engine

    CommandFailed, DsaregInputError = commands.CommandFailed, engine.DsaregInputError
    geometry_argument, json_argument, load_pose = commands.geometry_argument, commands.json_argument, commands.load_pose

    spec = geometry_argument(args.geometry)  # parsed here: errors before any upload
    geometry = None if spec is None else spec.as_input()
    options = json_argument(args.options, "--options")
    if options is not None and not isinstance(options, dict):
        raise DsaregInputError("must be a JSON object", field="--options", accepted='e.g. {"starts": 2}')
    if args.ground_truth:
        options = {**(options or {}), "ground_truth_mesh_to_world": load_pose(args.ground_truth).tolist()}
    if args.mesh_units:
        options = {**(options or {}), "mesh_units": args.mesh_units}
    if args.hemodynamics:
        options = {**(options or {}), "hemodynamics": True}
    wait = args.wait or args.out is not None or args.require is not None
    client = RegistrationClient(args.server, api_key=args.api_key or os.environ.get("DSAREG_API_KEY"))
    try:
        job = client.submit(ap=args.ap, lat=args.lat, mesh=args.mesh, volume=args.volume, geometry=geometry,
                            options=options, idempotency_key=args.idempotency_key, callback_url=args.callback_url)
        print(f"job {job['id']}: {job['status']} ({args.server.rstrip('/')}{job['links']['self']})", file=sys.stderr)
        if not wait:
            print(json.dumps(job, indent=2) if args.json else job["id"])
            return 0
        final = _wait(client, job["id"], args.timeout, commands.ProgressPrinter())
        if final["status"] != "succeeded":
            err = final.get("error") or {}
            detail = f": {err.get('title')}: {err.get('detail')}" if err else ""
            raise CommandFailed(f"job {final['id']} {final['status']}{detail}")
        if args.out:
            for path in client.download_all(final["id"], args.out):
                print(f"  wrote {path}", file=sys.stderr)
        print(json.dumps(final.get("result"), indent=2) if args.json else summary_line(final))
        verdict = final.get("verdict") or ((final.get("result") or {}).get("verdict"))
        if not commands.verdict_meets(verdict, args.require):
            print(f"dsareg: job {final['id']}: verdict {verdict or 'none'} is below --require {args.require}",
                  file=sys.stderr)
            return commands.VERDICT_NOT_MET_EXIT
        return 0
    finally:
        client.close()


def _wait(client: Any, job_id: str, timeout: float, printer: Any) -> dict[str, Any]:
    """Poll the job to its end, showing progress on stderr."""
    try:
        return client.wait(job_id, progress=lambda status: printer.update(status.get("progress") or {},
                                                                          status.get("status")), timeout=timeout)
    finally:
        printer.close()
