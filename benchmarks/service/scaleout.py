"""Celery scale-out benchmark on this machine (a command, not a test).

    python -m benchmarks.service.scaleout [--workers 1,2,4] [--jobs 12] [--size 64] [--iterations 10] [--sequential 8]

Starts a throw-away Redis and PostgreSQL on loopback (or uses ``--broker-url`` /
``--database-url``), the API with ``DSAREG_EXECUTOR=celery`` and, for each worker count,
that many ``dsareg worker --engine celery`` processes (1 torch thread each). It submits
``--jobs`` identical small registrations at once and reports jobs/minute (first submission
→ last completion, from the job table). Then it measures the per-job overhead of the
Celery path against the embedded executor: ``--sequential`` jobs one after another on one
idle worker, end-to-end time ``finished_at - created_at`` from each job store, and the
dispatch latency (``queued`` → ``claimed`` event). Both paths run the same registration, so
the difference of the medians is the Celery path's overhead (broker round trip, inputs
and artifacts through the database instead of local files, PostgreSQL instead of SQLite).
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx

from dsareg_engine.warmup import phantom_case_files

from tests.support.servers import free_port

REPO = Path(__file__).resolve().parents[2]


def _spawn(args: list[str], env: dict[str, str], log: Path) -> subprocess.Popen:
    """``python -m service ARGS`` in its own process group (for ``killpg``) but in the benchmark's session:
    with the kernel's autogroup scheduling every session shares the cores as one, so a new session per
    process gave 2 workers two shares of a busy machine and 1 worker one (a flattering ratio)."""
    return subprocess.Popen([sys.executable, "-m", "service", *args], cwd=REPO, env={**os.environ, **env},
                            stdout=open(log, "ab"), stderr=subprocess.STDOUT, process_group=0)


def _stop(process: subprocess.Popen, timeout: float = 30.0) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(10)


def _serve(root: Path, env: dict[str, str], workers: int) -> tuple[subprocess.Popen, str]:
    port = free_port()
    data = root / "api"
    process = _spawn(["serve", "--port", str(port), "--data-dir", str(data), "--workers", str(workers)], env,
                     root / f"api-{port}.log")
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"API exited; see {root}")
        try:
            if httpx.get(url + ("/readyz" if workers else "/healthz"), timeout=2).status_code == 200:
                return process, url
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise RuntimeError("API not ready")


def _submit(client: httpx.Client, case: dict[str, Any], options: str) -> str:
    files = [("mesh", ("phantom.obj", case["mesh"], "application/octet-stream")),
             ("ap", ("ap.png", case["ap"], "image/png")), ("lat", ("lat.png", case["lat"], "image/png"))]
    response = client.post("/v1/registrations", files=files, data={"geometry": case["geometry"], "options": options})
    response.raise_for_status()
    return response.json()["id"]


POLL_SECONDS = 0.5
"""Status poll interval, that of ``dsareg submit --wait`` (:meth:`service.cli.client.Client.wait`). The rates
are computed from the job table's timestamps, so polling faster only takes CPU from the workers (at
0.02 s the client and the API answering it used ≈ 0.2 CPU-s per job of the 2 cores)."""


def _wait(client: httpx.Client, job_id: str, timeout: float = 300.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if client.get(f"/v1/registrations/{job_id}").json()["status"] in ("succeeded", "failed", "canceled"):
            return
        time.sleep(POLL_SECONDS)
    raise TimeoutError(job_id)


def _timings(store: Any, ids: list[str]) -> tuple[list[float], list[float]]:
    e2e, dispatch = [], []
    for job_id in ids:
        job = store.get(job_id)
        if job.status != "succeeded":
            raise RuntimeError(f"job {job_id} ended {job.status}: {job.error}")
        e2e.append(job.finished_at - job.created_at)
        events = {e["event"]: e["at"] for e in reversed(store.events(job_id))}
        dispatch.append(events["claimed"] - events["queued"])
    return e2e, dispatch


def _sequential(url: str, case: dict[str, Any], options: str, n: int) -> list[str]:
    ids = []
    with httpx.Client(base_url=url, timeout=60) as client:
        _wait(client, _submit(client, case, options))  # warm-up (first job loads kernels)
        for _ in range(n):
            job_id = _submit(client, case, options)
            _wait(client, job_id)
            ids.append(job_id)
    return ids


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.service.scaleout", description=__doc__.split("\n\n")[0])
    parser.add_argument("--workers", default="1,2,4", help="Celery worker process counts")
    parser.add_argument("--jobs", type=int, default=12, help="jobs per worker count")
    parser.add_argument("--size", type=int, default=64, help="image size of the phantom case (px)")
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--sequential", type=int, default=8, help="jobs of the overhead measurement")
    parser.add_argument("--broker-url", help="use this Redis instead of starting one")
    parser.add_argument("--database-url", help="use this PostgreSQL instead of starting one")
    args = parser.parse_args(argv)

    from tests.support.servers import PostgresServer, RedisServer

    root = Path(tempfile.mkdtemp(prefix="dsareg-bench-celery-"))
    redis = postgres = None
    processes: list[subprocess.Popen] = []
    try:
        broker = args.broker_url or (redis := RedisServer().start()).url
        database = args.database_url or (postgres := PostgresServer().start()).url
        case = phantom_case_files(root, args.size)
        options = f'{{"starts": 1, "max_iterations": {args.iterations}}}'
        overhead: dict[str, tuple[float, float]] = {}
        rows = _celery_rounds(args, root, broker, database, case, options, processes, overhead)
        overhead["embedded"] = _embedded_overhead(args, root, case, options, processes)
        _report(args, rows, overhead)
        return 0
    finally:
        for process in processes:
            _stop(process, timeout=10)
        if redis is not None:
            redis.stop()
        if postgres is not None:
            postgres.stop()
        print(f"(logs in {root})", file=sys.stderr)


def _celery_rounds(args: argparse.Namespace, root: Path, broker: str, database: str, case: dict, options: str,
                   processes: list[subprocess.Popen], overhead: dict[str, tuple[float, float]]) -> list[tuple]:
    """One round per worker count: start the workers, submit concurrently, wait; (count, jobs, span, rate)."""
    from service.storage.store import SqlJobStore

    env = {"DSAREG_EXECUTOR": "celery", "DSAREG_BROKER_URL": broker, "DSAREG_DATABASE_URL": database,
           "DSAREG_BLOB_BACKEND": "database", "DSAREG_THREADS_PER_WORKER": "1", "DSAREG_LOG_LEVEL": "warning",
           "DSAREG_PROGRESS_INTERVAL_SECONDS": "0.5"}
    api, url = _serve(root, env, workers=0)
    processes.append(api)
    store = SqlJobStore(database, create_schema=False)
    rows = []
    for count in [int(x) for x in args.workers.split(",") if x.strip()]:
        began = time.time()
        workers = [_spawn(["worker", "--engine", "celery", "--hostname", f"b{count}-{i}@%h",
                           "--data-dir", str(root / f"w{count}-{i}")], env, root / f"w{count}-{i}.log")
                   for i in range(count)]
        processes.extend(workers)
        while store.live_workers(began) < count:
            time.sleep(0.2)
        time.sleep(1.0)  # consumers connect after the worker registered itself
        rows.append(_round(args, store, url, case, options, count))
        if count == 1:
            e2e, dispatch = _timings(store, _sequential(url, case, options, args.sequential))
            overhead["celery"] = (statistics.median(e2e), statistics.median(dispatch))
        for w in workers:
            _stop(w)
    store.dispose()
    _stop(api)
    return rows


def _round(args: argparse.Namespace, store: Any, url: str, case: dict, options: str, count: int) -> tuple:
    with httpx.Client(base_url=url, timeout=60) as client:
        # concurrent submissions: the API must queue jobs faster than the workers run them,
        # else jobs/min measures the submission rate (with ~1 s jobs it did)
        with ThreadPoolExecutor(max_workers=min(8, args.jobs)) as pool:
            ids = list(pool.map(lambda _: _submit(client, case, options), range(args.jobs)))
        for job_id in ids:
            _wait(client, job_id)
    jobs = [store.get(j) for j in ids]
    span = max(j.finished_at for j in jobs) - min(j.created_at for j in jobs)
    run = statistics.median(j.finished_at - j.started_at for j in jobs)
    busy = max(j.finished_at for j in jobs) - min(j.started_at for j in jobs)
    load = os.getloadavg()[0]
    print(f"{count} worker(s): {args.jobs} jobs in {span:.1f} s = {args.jobs / span * 60.0:.1f} jobs/min "
          f"(first start → last finish {args.jobs / busy * 60.0:.1f} jobs/min; median run time per job "
          f"{run:.2f} s; load average {load:.1f} on {os.cpu_count()} CPUs)", flush=True)
    return (count, args.jobs, span, args.jobs / span * 60.0)


def _embedded_overhead(args: argparse.Namespace, root: Path, case: dict, options: str,
                       processes: list[subprocess.Popen]) -> tuple[float, float]:
    """Median end-to-end and queued→claimed times of sequential jobs on one embedded worker."""
    from service.storage.store import SqlJobStore

    emb_root = root / "embedded"
    emb_root.mkdir()
    emb, emb_url = _serve(emb_root, {"DSAREG_THREADS_PER_WORKER": "1", "DSAREG_LOG_LEVEL": "warning",
                                     "DSAREG_PROGRESS_INTERVAL_SECONDS": "0.5"}, workers=1)
    processes.append(emb)
    emb_ids = _sequential(emb_url, case, options, args.sequential)
    emb_store = SqlJobStore(f"sqlite:///{emb_root / 'api' / 'jobs.sqlite3'}", create_schema=False)
    e2e, dispatch = _timings(emb_store, emb_ids)
    emb_store.dispose()
    _stop(emb)
    return statistics.median(e2e), statistics.median(dispatch)


def _report(args: argparse.Namespace, rows: list[tuple], overhead: dict[str, tuple[float, float]]) -> None:
    cpus = os.cpu_count()
    print(f"\nCelery scale-out on this machine ({cpus} CPUs, 1 torch thread per worker, "
          f"{args.size} px phantom, 1 start, {args.iterations} iterations)\n")
    print("| Celery workers | jobs | wall (s) | jobs/min |\n|---:|---:|---:|---:|")
    for count, n, span, rate in rows:
        print(f"| {count} | {n} | {span:.1f} | {rate:.1f} |")
    print(f"\nPer job, {args.sequential} sequential jobs on one idle worker (medians):\n")
    print("| path | end-to-end (s) | queued→claimed (ms) |\n|---|---:|---:|")
    for name in ("embedded", "celery"):
        if name in overhead:
            print(f"| {name} | {overhead[name][0]:.3f} | {overhead[name][1] * 1000:.1f} |")
    if len(overhead) == 2:
        print(f"\nCelery path overhead vs embedded: "
              f"{(overhead['celery'][0] - overhead['embedded'][0]) * 1000:+.0f} ms per job (end-to-end medians)")

if __name__ == "__main__":
    sys.exit(main())
