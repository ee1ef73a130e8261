"""Fresh-install first start: ``dsareg serve`` → /readyz 200 → the first job running (a command, not a test).

    python -m benchmarks.service.first_start [--ref HEAD] [--workers 1]

Exports the sources of git revision ``--ref`` (``git archive``: no ``__pycache__``, so no numba cache
and no bytecode, as after a fresh install) into a temporary folder, starts ``python -m service serve``
from there (this interpreter and its packages; ``NUMBA_CACHE_DIR`` unset) on a free loopback port with a
new data dir, submits one small job (the phantom at 64 px, 30 iterations) as soon as the API accepts it,
and prints the seconds from the start to: the API answering, the job accepted, ``/readyz`` 200, the job's
``started_at`` (the server's clock), the job seen running and the job finished, with the CPU seconds of the server's process tree (user + system, children
included) at the time the job was running, and the load average (the machine may be shared).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

from dsareg_engine.warmup import phantom_case_files

from tests.support.servers import free_port

REPO = Path(__file__).resolve().parents[2]
TICKS = os.sysconf("SC_CLK_TCK")


def _tree_cpu_seconds(root: int) -> float:
    """utime + stime + cutime + cstime of ``root`` and its live descendants."""
    children: dict[int, list[int]] = {}
    stats: dict[int, list[str]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            stats[int(entry.name)] = fields
            children.setdefault(int(fields[1]), []).append(int(entry.name))
    total, todo = 0.0, [root]
    while todo:
        pid = todo.pop()
        if pid in stats:
            total += sum(int(x) for x in stats[pid][11:15]) / TICKS
        todo.extend(children.get(pid, []))
    return total


def _export(ref: str, folder: Path) -> None:
    archive = subprocess.run(["git", "-C", str(REPO), "archive", ref], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)


def _submit(client: httpx.Client, files: dict) -> str | None:
    """The job's id; a retry after a timeout returns the same job (Idempotency-Key), never a second one."""
    try:
        response = client.post("/v1/registrations", files={
            "mesh": ("phantom.obj", files["mesh"]), "ap": ("ap.png", files["ap"]), "lat": ("lat.png", files["lat"])},
            data={"geometry": files["geometry"], "options": json.dumps({"starts": 1, "max_iterations": 30})},
            headers={"Idempotency-Key": "first-start-benchmark"}, timeout=300)
    except httpx.HTTPError:
        return None
    return response.json()["id"] if response.status_code in (200, 202) else None


def _iso_seconds(text: str) -> float:
    from datetime import datetime

    return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def _watch(server: subprocess.Popen, url: str, files: dict, timeout: float) -> dict[str, float]:
    """Seconds since the start of each milestone, and the tree's CPU seconds when the job ran."""
    marks: dict[str, float] = {}
    started, wall_started, job_id = time.monotonic(), time.time(), None
    with httpx.Client(base_url=url, timeout=30) as client:
        while "finished" not in marks and time.monotonic() - started < timeout and server.poll() is None:
            now = time.monotonic() - started
            try:
                if "api" not in marks and client.get("/healthz").status_code == 200:
                    marks["api"] = now
                if "api" in marks and job_id is None and (job_id := _submit(client, files)):
                    marks["accepted"] = time.monotonic() - started
                if "ready" not in marks and client.get("/readyz").status_code == 200:
                    marks["ready"] = now
                body = client.get(f"/v1/registrations/{job_id}").json() if job_id else {}
                status = body.get("status")
            except httpx.HTTPError:
                status = None
            if status in ("running", "succeeded") and "running" not in marks:
                marks["running"], marks["cpu_at_running"] = now, _tree_cpu_seconds(server.pid)
                marks["started_at"] = _iso_seconds(body["started_at"]) - wall_started
            if status in ("succeeded", "failed", "canceled"):
                marks["finished"] = now
            time.sleep(0.2)
    return marks


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ref", default="HEAD", help="git revision whose sources are started (default HEAD)")
    parser.add_argument("--workers", type=int, default=1, help="embedded worker processes")
    parser.add_argument("--timeout", type=float, default=900.0, help="give up after this many seconds")
    parser.add_argument("--log", type=Path, default=None, help="write the server's log here")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="dsareg-first-start-") as tmp:
        tree, port = Path(tmp) / "src", free_port()
        tree.mkdir()
        _export(args.ref, tree)
        files = phantom_case_files(Path(tmp), size_px=64)
        env = {k: v for k, v in os.environ.items() if not k.startswith(("DSAREG_", "NUMBA_CACHE_DIR"))}
        env.update(PYTHONPATH=str(tree), PYTHONDONTWRITEBYTECODE="0")
        load_before = os.getloadavg()[0]
        log = open(args.log, "wb") if args.log else subprocess.DEVNULL  # noqa: SIM115 - closed below
        server = subprocess.Popen([sys.executable, "-m", "service", "serve", "--port", str(port), "--data-dir",
                                   str(Path(tmp) / "data"), "--workers", str(args.workers)], cwd=tree, env=env,
                                  stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            marks = _watch(server, f"http://127.0.0.1:{port}", files, args.timeout)
        finally:
            server.terminate()
            server.wait(30)
            if args.log:
                log.close()
    print(f"ref {args.ref}, {args.workers} worker(s), {os.cpu_count()} CPUs, load average {load_before:.1f} → "
          f"{os.getloadavg()[0]:.1f}")
    for name in ("api", "accepted", "ready", "started_at", "running", "finished"):
        print(f"{name:>9}: " + (f"{marks[name]:.1f} s" if name in marks else "not reached"))
    if "cpu_at_running" in marks:
        print(f"first job running after {marks['running']:.1f} s wall, {marks['cpu_at_running']:.1f} CPU-s (server tree)")
    return 0 if "running" in marks else 1


if __name__ == "__main__":
    sys.exit(main())
