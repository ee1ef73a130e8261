"""Export peers under a stream of jobs (issue 43): ``python -m benchmarks.service.export_peers [--jobs 6]``.

One ``dsareg serve`` (1 worker) with its DICOM node and four C-STORE destinations (``dicom_peers``):
``HEALTHY`` (a dcmtk ``storescp``), ``SLOW`` (a ``storescp`` stopped ``--slow-stop`` s of every
``--slow-stop`` + ``--slow-run`` s: SIGSTOP / SIGCONT toggled by this process), ``DEAD`` (a port where
nothing listens) and ``FROZEN`` (a ``storescp`` SIGSTOPped for its whole stream). For each in turn, a
stream of ``--jobs`` phantom studies (fresh UIDs, one every ``--interval`` s, 10: a worker not saturated) is sent by ``storescu`` with
that peer's AE title as the calling AE, so each job's results go back to it; the baseline ``none`` is the
same stream as multipart uploads of the same DICOM files (no export). The server runs with the
production export settings (DIMSE timeout 20 s, 2 retries, 5 export attempts, back-off 5 s) unless told.

Per stream: the jobs' latency (created → finished), the worker's time beyond the registration (finished −
started − ``metrics.seconds.total``: an export inside the job is in it; median, and its difference to the
baseline's), the worker's time on exports (the export seconds recorded inside the jobs by older versions,
``result.dicom.exported[].seconds`` / ``stored.store_seconds``; this version records none there, and every
export event of a job's audit log is checked to come from the service after the job's ``succeeded``), and the
exports (``export`` of the job, or the inline result of older versions): stored / failed / still retrying
once they settled (at most ``--settle`` s after the stream's last job), and the median time from a job's end
to its results stored.

Prints one JSON object, then the Markdown table of docs/benchmarks/reliability.md. Needs dcmtk.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import shutil
import signal
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

from tests.support.dimse_kit import StoreScp, jobs_of_study, renamed_study, storescu
from tests.support.servers import free_port
from tests.support.service_testkit import Server

STREAMS = ("none", "healthy", "slow", "dead", "frozen")
OPTIONS = {"starts": 1}
OVER = ("done", "failed")


def _at(text: str | None) -> float | None:
    return None if not text else _dt.datetime.fromisoformat(text).timestamp()


class Toggler(threading.Thread):
    """SIGSTOP / SIGCONT a process in turn: a slow peer."""

    def __init__(self, pid: int, stop_s: float, run_s: float):
        super().__init__(daemon=True)
        self.pid, self.stop_s, self.run_s, self.halt = pid, stop_s, run_s, threading.Event()

    def run(self) -> None:
        while not self.halt.is_set():
            os.kill(self.pid, signal.SIGSTOP)
            self.halt.wait(self.stop_s)
            os.kill(self.pid, signal.SIGCONT)
            self.halt.wait(self.run_s)

    def stop(self) -> None:
        self.halt.set()
        self.join(10)
        os.kill(self.pid, signal.SIGCONT)


def start_server(folder: Path, peers: dict[str, int], args) -> Server:
    env = {"DSAREG_DICOM_PORT": str(free_port()), "DSAREG_DICOM_STABLE_SECONDS": "1",
           "DSAREG_DICOM_PEERS": json.dumps([{"ae_title": title, "host": "127.0.0.1", "port": port}
                                             for title, port in peers.items()]),
           "DSAREG_DICOM_JOB_OPTIONS": json.dumps(OPTIONS), "DSAREG_WARM_UP_JOB": "1",
           "DSAREG_DICOM_TIMEOUT_SECONDS": str(args.dicom_timeout),
           "DSAREG_EXPORT_RETRY_BACKOFF_SECONDS": str(args.export_backoff)}
    server = Server(folder / "data", workers=1, env=env).start(timeout=900)
    server.dicom_port = int(env["DSAREG_DICOM_PORT"])
    return server


def submit_stream(server: Server, client, stream: str, study, args, folder: Path) -> list[str]:
    """Send the stream's studies one every ``args.interval`` s; the job ids, in order."""
    files = [("ap", ("ap.dcm", study.ap, "application/dicom")), ("lat", ("lat.dcm", study.lat, "application/dicom"))]
    files += [("volume", (f"v{i:03d}.dcm", part, "application/dicom")) for i, part in enumerate(study.volume)]
    started, ids, uids = time.monotonic(), [], []
    for index in range(args.jobs):
        time.sleep(max(0.0, started + index * args.interval - time.monotonic()))
        if stream == "none":
            answer = client.post("/v1/registrations", files=files, data={"options": json.dumps(OPTIONS)})
            answer.raise_for_status()
            ids.append(answer.json()["id"])
            continue
        uid, paths = renamed_study(study, folder / f"{stream}-{index}")
        sent = storescu(server.dicom_port, paths, calling=stream.upper())
        if sent.returncode != 0:
            raise RuntimeError(sent.stderr[-500:])
        uids.append(uid)
    deadline = time.monotonic() + 120
    while len(ids) < args.jobs:
        ids = [found[0]["id"] for uid in uids if (found := jobs_of_study(client, uid))]
        if time.monotonic() > deadline:
            raise TimeoutError(f"{stream}: {len(ids)} of {args.jobs} studies became jobs")
        time.sleep(0.2)
    return ids


def wait_jobs(client, ids: list[str], timeout: float) -> list[dict]:
    deadline = time.monotonic() + timeout
    while True:
        jobs = [client.get(f"/v1/registrations/{job_id}").json() for job_id in ids]
        if all(job["status"] in ("succeeded", "failed", "canceled") for job in jobs):
            return jobs
        if time.monotonic() > deadline:
            raise TimeoutError("jobs not finished")
        time.sleep(0.5)


def export_of(job: dict) -> dict:
    """``state``, ``stored_after_job_s`` of a job's export (``export``, or an older version's inline one)."""
    if job.get("export"):
        done = _at(job["export"].get("done_at"))
        return {"state": job["export"]["state"], "attempts": job["export"]["attempts"],
                "stored_after_job_s": None if done is None else round(done - _at(job["finished_at"]), 2),
                "error": (job["export"].get("error") or {}).get("detail")}
    exported = ((job.get("result") or {}).get("dicom") or {}).get("exported")
    if not exported:
        return {"state": "none"}
    ok = all(item["status"] == "stored" for item in exported)
    return {"state": "done" if ok else "failed", "attempts": max(item["attempts"] for item in exported),
            "stored_after_job_s": 0.0 if ok else None, "inline": True,
            "error": None if ok else exported[0]["error"]["detail"]}


def settle(client, jobs: list[dict], seconds: float) -> list[dict]:
    """The jobs again once every export is over, or after ``seconds``."""
    deadline = time.monotonic() + seconds
    while True:
        jobs = [client.get(f"/v1/registrations/{job['id']}").json() for job in jobs]
        if all(export_of(job)["state"] in (*OVER, "none") for job in jobs) or time.monotonic() > deadline:
            return jobs
        time.sleep(0.5)


def inside_the_job(client, job: dict) -> tuple[float, bool]:
    """The seconds of export the worker spent inside ``job`` (an older version's inline ``result.dicom.exported``
    / ``stored``), and whether every export event of its audit log came after the job's end (and not from it)."""
    dicom = (job.get("result") or {}).get("dicom") or {}
    inline = sum(item.get("seconds") or 0.0 for item in dicom.get("exported") or [])
    inline += (dicom.get("stored") or {}).get("store_seconds") or 0.0
    events = client.get(f"/v1/registrations/{job['id']}/audit").json()["items"]
    ended = max(_at(e["at"]) for e in events if e["event"] == "succeeded")
    exports = [e for e in events if e["event"] in ("export_retry", "exported", "export_failed")]
    return inline, all(_at(e["at"]) >= ended and e["actor"] == "service" for e in exports)


def summary(stream: str, client, jobs: list[dict], settled: list[dict], base: float | None) -> dict:
    beyond = [_at(j["finished_at"]) - _at(j["started_at"]) - j["result"]["metrics"]["seconds"]["total"] for j in jobs]
    latency = [_at(j["finished_at"]) - _at(j["created_at"]) for j in jobs]
    exports = [export_of(job) for job in settled]
    states = [e["state"] for e in exports]
    stored = [e["stored_after_job_s"] for e in exports if e.get("stored_after_job_s") is not None]
    inside = [inside_the_job(client, job) for job in settled]
    return {"stream": stream, "jobs": len(jobs), "succeeded": sum(j["status"] == "succeeded" for j in jobs),
            "latency_median_s": round(statistics.median(latency), 2), "latency_max_s": round(max(latency), 2),
            "registration_median_s": round(statistics.median(j["result"]["metrics"]["seconds"]["total"] for j in jobs), 2),
            "worker_beyond_registration_s": [round(x, 2) for x in beyond],
            "beyond_vs_none_s": None if base is None else round(statistics.median(beyond) - base, 2),
            "worker_on_exports_s": round(sum(seconds for seconds, _ in inside), 1),
            "exports_after_the_job": sum(after for _, after in inside),
            "exports": {"done": states.count("done"), "failed": states.count("failed"),
                        "retrying": sum(s in ("pending", "exporting") for s in states), "none": states.count("none")},
            "stored_after_job_median_s": round(statistics.median(stored), 2) if stored else None,
            "errors": sorted({e["error"][:160] for e in exports if e.get("error")})}


def run_stream(server, client, stream: str, peers: dict, study, args, folder: Path, base) -> dict:
    toggler = None
    if stream == "frozen":
        os.kill(peers["frozen"].process.pid, signal.SIGSTOP)
    if stream == "slow":
        toggler = Toggler(peers["slow"].process.pid, args.slow_stop, args.slow_run)
        toggler.start()
    try:
        ids = submit_stream(server, client, stream, study, args, folder)
        jobs = wait_jobs(client, ids, timeout=args.jobs * 600)
        settled = settle(client, jobs, args.settle)
    finally:
        if toggler is not None:
            toggler.stop()
    out = summary(stream, client, jobs, settled, base)
    print(json.dumps(out), file=sys.stderr, flush=True)
    return out


def _seconds(value: float | None, digits: int = 1) -> str:
    return "—" if value is None else f"{value:.{digits}f} s"


def table(rows: list[dict]) -> str:
    head = ("| export peer | jobs ok | latency median / max | worker beyond registration, median (vs none) | worker "
            "time on exports | exports done / failed / retrying | stored after the job, median |")
    lines = [head, "|---|---|---|---|---|---|---|"]
    for r in rows:
        beyond, exports = r["worker_beyond_registration_s"], r["exports"]
        versus = "" if r["beyond_vs_none_s"] is None else f" ({r['beyond_vs_none_s']:+.2f})"
        lines.append(f"| {r['stream']} | {r['succeeded']}/{r['jobs']} | {r['latency_median_s']:.1f} / "
                     f"{r['latency_max_s']:.1f} s | {statistics.median(beyond):.2f} s{versus} | "
                     f"{r['worker_on_exports_s']:.1f} s | {exports['done']} / {exports['failed']} / "
                     f"{exports['retrying']} | {_seconds(r['stored_after_job_median_s'], 2)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.service.export_peers", description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=6)
    parser.add_argument("--interval", type=float, default=10.0, help="seconds between two studies of a stream")
    parser.add_argument("--streams", default=",".join(STREAMS), help=f"a subset of {','.join(STREAMS)} (none first)")
    parser.add_argument("--settle", type=float, default=90.0, help="at most this long for the exports to end")
    parser.add_argument("--dicom-timeout", type=float, default=20.0, help="DSAREG_DICOM_TIMEOUT_SECONDS")
    parser.add_argument("--export-backoff", type=float, default=5.0, help="DSAREG_EXPORT_RETRY_BACKOFF_SECONDS")
    parser.add_argument("--slow-stop", type=float, default=3.0)
    parser.add_argument("--slow-run", type=float, default=0.5)
    args = parser.parse_args(argv)
    from dsareg_engine.simulation.phantom_study import make_biplane_study

    folder = Path(tempfile.mkdtemp(prefix="dsareg-bench-export-"))
    study = make_biplane_study(image_px=160, pixel_spacing_mm=0.9, depth=2)
    scps = {name: StoreScp(folder / name, title=name.upper()).start() for name in ("healthy", "slow", "frozen")}
    ports = {"HEALTHY": scps["healthy"].port, "SLOW": scps["slow"].port, "FROZEN": scps["frozen"].port,
             "DEAD": free_port()}
    server = start_server(folder, ports, args)
    rows, base = [], None
    try:
        with server.client() as client:
            for stream in args.streams.split(","):
                rows.append(run_stream(server, client, stream, scps, study, args, folder, base))
                if stream == "none":
                    base = statistics.median(rows[-1]["worker_beyond_registration_s"])
    finally:
        server.stop()
        for scp in scps.values():
            os.kill(scp.process.pid, signal.SIGCONT)
            scp.stop()
        shutil.rmtree(folder, ignore_errors=True)
    print(json.dumps({"loadavg_1min": round(os.getloadavg()[0], 1), "cpus": os.cpu_count(), "streams": rows},
                     indent=1))
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
