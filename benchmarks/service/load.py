"""Bounded load benchmark of the service on loopback (a command, not a test).

    python -m benchmarks.service.load [--submissions 200] [--concurrency 20] [--workers 1,2]

For each worker count it starts ``python -m service serve`` on a free loopback port
with a fresh data dir, submits ``--submissions`` tiny registrations (the phantom seen
by the paper rig shrunk to ``--size`` px, ``--iterations`` iterations, one start) from
``--concurrency`` concurrent clients, reads job status while the workers are busy (4
readers, each one read every ``--poll-seconds``, and one listing per second), waits (at most ``--max-wait`` s) for the jobs to finish, and prints:
accepted submissions/s, p50/p99 status-read latency under load, jobs/minute, and the
peak RSS (VmHWM) of the API process and of the worker processes.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx

from dsareg_engine.warmup import phantom_case_files
from tests.support.servers import free_port


def wait_ready(url: str, timeout: float = 600.0, interval: float = 0.3) -> None:
    """Until the server at ``url`` answers ``/readyz`` 200; RuntimeError after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if httpx.get(url + "/readyz", timeout=5).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(interval)
    raise RuntimeError(f"the server was not ready after {timeout:g} s")


def _peak_rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def _children(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            if int(fields[1]) == pid:
                out.append(int(entry.name))
        except (OSError, IndexError, ValueError):
            continue
    return out


READERS = 4


def _percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q * (len(ordered) - 1))))]


async def _run_load(url: str, case: dict, args: argparse.Namespace) -> dict[str, Any]:
    limits = httpx.Limits(max_connections=args.concurrency + 4)
    async with httpx.AsyncClient(base_url=url, timeout=120, limits=limits) as client:
        started = time.perf_counter()
        ids, rejected = await _submit_all(client, case, args)
        submit_seconds = time.perf_counter() - started
        latencies, finished = await _poll_until_done(client, ids, args.max_wait, args.poll_seconds)
    return _load_summary(ids, rejected, submit_seconds, latencies, finished)


async def _submit_all(client: httpx.AsyncClient, case: dict, args: argparse.Namespace
                      ) -> tuple[list[str], dict[int, int]]:
    """``args.submissions`` submissions from ``args.concurrency`` concurrent submitters: accepted ids, rejections."""
    options = {"starts": 1, "max_iterations": args.iterations}
    ids: list[str] = []
    rejected: dict[int, int] = {}
    counter = iter(range(args.submissions))

    async def submitter() -> None:
        for n in counter:
            files = [("mesh", ("m.obj", case["mesh"])), ("ap", ("a.png", case["ap"])), ("lat", ("l.png", case["lat"]))]
            data = {"geometry": case["geometry"], "options": json.dumps({**options, "seed": n})}
            r = await client.post("/v1/registrations", files=files, data=data)
            if r.status_code == 202:
                ids.append(r.json()["id"])
            else:
                rejected[r.status_code] = rejected.get(r.status_code, 0) + 1

    await asyncio.gather(*(submitter() for _ in range(args.concurrency)))
    return ids, rejected


async def _poll_until_done(client: httpx.AsyncClient, ids: list[str], max_wait: float, poll_seconds: float
                           ) -> tuple[list[float], dict[str, dict]]:
    """Status reads while the workers are busy, until all finished or ``max_wait``: latencies, finished jobs.

    ``READERS`` clients each read a random job's status every ``poll_seconds``."""
    latencies: list[float] = []
    finished: dict[str, dict] = {}
    deadline = time.monotonic() + max_wait

    async def reader() -> None:
        while time.monotonic() < deadline and len(finished) < len(ids):
            job_id = random.choice(ids)
            t0 = time.perf_counter()
            r = await client.get(f"/v1/registrations/{job_id}")
            latencies.append(time.perf_counter() - t0)
            body = r.json()
            if body.get("status") in ("succeeded", "failed", "canceled"):
                finished[job_id] = body
            await asyncio.sleep(poll_seconds)

    async def sweeper() -> None:  # make sure every job gets looked at
        while time.monotonic() < deadline and len(finished) < len(ids):
            cursor = None
            while True:
                params = {"limit": 100, **({"cursor": cursor} if cursor else {})}
                page = (await client.get("/v1/registrations", params=params)).json()
                for item in page["items"]:
                    if item["status"] in ("succeeded", "failed", "canceled"):
                        finished[item["id"]] = item
                cursor = page.get("next_cursor")
                if not cursor:
                    break
            await asyncio.sleep(1.0)

    if ids:
        await asyncio.gather(*(reader() for _ in range(READERS)), sweeper())
    return latencies, finished


def _load_summary(ids: list[str], rejected: dict[int, int], submit_seconds: float, latencies: list[float],
                  finished: dict[str, dict]) -> dict[str, Any]:
    done = [b for b in finished.values() if b["status"] == "succeeded"]
    from datetime import datetime

    def ts(text: str) -> float:
        return datetime.fromisoformat(text).timestamp()

    jobs_per_minute = float("nan")
    if len(done) >= 2:
        first_start = min(ts(b["started_at"]) for b in done)
        last_finish = max(ts(b["finished_at"]) for b in done)
        jobs_per_minute = len(done) / max(1e-6, last_finish - first_start) * 60.0
    return {
        "accepted": len(ids), "rejected": rejected, "accepted_per_s": len(ids) / submit_seconds if submit_seconds else 0,
        "status_reads": len(latencies), "status_p50_ms": _percentile(latencies, 0.5) * 1000,
        "status_p99_ms": _percentile(latencies, 0.99) * 1000, "succeeded": len(done),
        "failed": sum(1 for b in finished.values() if b["status"] == "failed"), "jobs_per_minute": jobs_per_minute,
        "mean_status_ms": statistics.fmean(latencies) * 1000 if latencies else float("nan"),
    }


def run_for_workers(workers: int, case: dict, args: argparse.Namespace, root: Path) -> dict[str, Any]:
    port = free_port()
    data = root / f"data-w{workers}"
    env = {**os.environ, "DSAREG_QUEUE_LIMIT": str(max(1000, args.submissions + 10)), "DSAREG_POLL_SECONDS": "0.2"}
    for key in ("DSAREG_API_KEYS", "DSAREG_API_KEY_HASHES"):
        env.pop(key, None)
    log = open(root / f"server-w{workers}.log", "wb")  # noqa: SIM115 - lives as long as the server
    server = subprocess.Popen(
        [sys.executable, "-m", "service", "serve", "--port", str(port), "--data-dir", str(data),
         "--workers", str(workers), "--threads-per-worker", str(args.threads), "--log-level", "warning"],
        env=env, stdout=log, stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        wait_ready(url, 120.0)
        result = asyncio.run(_run_load(url, case, args))
        children = _children(server.pid)
        result["api_peak_rss_mb"] = _peak_rss_mb(server.pid)
        result["child_peak_rss_mb"] = sorted((round(_peak_rss_mb(p), 1) for p in children), reverse=True)
        result["workers"] = workers
        return result
    finally:
        server.terminate()
        try:
            server.wait(30)
        except subprocess.TimeoutExpired:
            server.kill()
        log.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.service.load", description=__doc__.split("\n\n")[0])
    parser.add_argument("--submissions", type=int, default=200)
    parser.add_argument("--concurrency", type=int, default=20)
    parser.add_argument("--workers", default="1,2", help="comma-separated worker counts to measure")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per worker")
    parser.add_argument("--size", type=int, default=64, help="image side in pixels of the tiny case")
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--max-wait", type=float, default=300.0, help="seconds to wait for the jobs per worker count")
    parser.add_argument("--poll-seconds", type=float, default=0.5,
                        help="each of the 4 status readers' interval (0.5 s: that of `dsareg submit --wait`; it was "
                             "0.02 s, and 200 reads/s took as much CPU as the workers on a 2-core machine)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="dsareg-bench-") as tmp:
        root = Path(tmp)
        case = phantom_case_files(root, args.size)
        rows = []
        for workers in [int(w) for w in args.workers.split(",") if w.strip()]:
            row = run_for_workers(workers, case, args, root)
            rows.append(row)
            print(json.dumps(row), flush=True)
        print()
        print(f"{'workers':>7} {'accepted/s':>10} {'p50 ms':>8} {'p99 ms':>8} {'jobs/min':>9} {'done':>6} "
              f"{'API MB':>7}  child processes peak RSS MB (workers + validator)")
        for r in rows:
            print(f"{r['workers']:>7} {r['accepted_per_s']:>10.1f} {r['status_p50_ms']:>8.1f} {r['status_p99_ms']:>8.1f} "
                  f"{r['jobs_per_minute']:>9.1f} {r['succeeded']:>3}/{r['accepted']:<3} {r['api_peak_rss_mb']:>6.0f}  "
                  f"{r['child_peak_rss_mb']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
