"""A whole-head CTA submitted to a server with its default settings, twice (issue 41; a command, not a test).

    python -m benchmarks.service.whole_head_intake [--grid 512x512x440] [--voxel 0.45] [--kind cta|mra] [--fixed]
                                                   [--case CASE.pickle]

Writes the whole-head CTA (``--kind mra``: the TOF-MRA slab) of ``python -m benchmarks.engine whole-head`` (a DICOM
series of 440 slices beside its XA pair; ``--voxel 0.4x0.4x0.5`` for anisotropic voxels; ``--case``: a case that
command's ``--sweep`` or an earlier run wrote, not written again), starts ``python -m service serve`` with no
``DSAREG_*`` setting but its data folder (``--fixed``: the fixed limits of before,
``DSAREG_VALIDATION_VOLUME_MEMORY_MB=0`` and ``..._TIMEOUT_SECONDS=0``), submits it with no initial pose, waits
for the job, then submits it again. Per submission: the seconds to the answer (the upload and the validator's
read), the answer, the job's seconds queued-to-finished, ADD and verdict; the peak RSS (``VmHWM``) of the validator
and worker processes seen meanwhile (sampled every 0.2 s); the allowance the validator logged; the machine's load
average.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

from benchmarks.service.load import wait_ready
from tests.support.servers import free_port

REPO = Path(__file__).resolve().parents[2]


class PeakWatch(threading.Thread):
    """The largest ``VmHWM`` (MB) of each process named ``dsareg-validate`` / ``dsareg-worker*``, while it runs."""

    def __init__(self):
        super().__init__(daemon=True)
        self.peaks: dict[str, float] = {}
        self.halt = threading.Event()

    def run(self) -> None:
        while not self.halt.wait(0.2):
            for entry in Path("/proc").iterdir():
                if not entry.name.isdigit():
                    continue
                try:
                    name = (entry / "comm").read_text().strip()
                    if not name.startswith(("dsareg-validate", "dsareg-worker")):
                        continue
                    hwm = next(int(line.split()[1]) for line in (entry / "status").read_text().splitlines()
                               if line.startswith("VmHWM:"))
                except (OSError, StopIteration, ValueError):
                    continue
                kind = "validator" if name.startswith("dsareg-validate") else "worker"
                self.peaks[kind] = max(self.peaks.get(kind, 0.0), hwm / 1024)

    def take(self) -> dict[str, float]:
        peaks, self.peaks = self.peaks, {}
        return peaks


def _serve(data_dir: Path, port: int, fixed: bool) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if not k.startswith("DSAREG_")}
    if fixed:
        env.update(DSAREG_VALIDATION_VOLUME_MEMORY_MB="0", DSAREG_VALIDATION_VOLUME_TIMEOUT_SECONDS="0")
    log = open(data_dir.parent / "server.log", "ab")  # noqa: SIM115 - lives as long as the server
    return subprocess.Popen([sys.executable, "-m", "service", "serve", "--host", "127.0.0.1", "--port", str(port),
                             "--data-dir", str(data_dir), "--workers", "1"], cwd=REPO, env=env, stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True)


def _submit(url: str, case, watch: PeakWatch) -> dict:
    files = [("ap", ("ap.dcm", case.files.ap, "application/dicom")),
             ("lat", ("lat.dcm", case.files.lat, "application/dicom"))]
    files += [("volume", (f"s{i:03d}.dcm", part, "application/dicom")) for i, part in enumerate(case.files.volume)]
    options = {"device": "cpu", "ground_truth_mesh_to_world": case.mesh_to_world.tolist()}
    with httpx.Client(base_url=url, timeout=900) as client:
        sent = time.monotonic()
        response = client.post("/v1/registrations", files=files, data={"options": json.dumps(options)})
        row = {"answer_s": time.monotonic() - sent, "status": response.status_code, "validator_peak_mb": None}
        row["validator_peak_mb"] = watch.take().get("validator")
        if response.status_code != 202:
            row["detail"] = response.json().get("detail")
            return row
        job_id = response.json()["id"]
        while True:
            job = client.get(f"/v1/registrations/{job_id}").json()
            if job["status"] in ("succeeded", "failed", "canceled"):
                break
            time.sleep(1.0)
    row.update(job_s=time.monotonic() - sent - row["answer_s"], job=job["status"],
               worker_peak_mb=watch.take().get("worker"))
    metrics = (job.get("result") or {}).get("metrics") or {}
    row["add_mm"] = (metrics.get("ground_truth") or {}).get("add_mm")
    row["verdict"] = (metrics.get("confidence") or {}).get("verdict")
    row["reasons"] = (metrics.get("confidence") or {}).get("reasons")
    row["error"] = (job.get("error") or {}).get("detail")
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", default="512x512x440")
    parser.add_argument("--voxel", default="0.45", help="mm, one value or AxBxC")
    parser.add_argument("--kind", choices=("cta", "mra"), default="cta")
    parser.add_argument("--case", type=Path, help="a case pickle written before (its grid, voxel and kind)")
    parser.add_argument("--fixed", action="store_true", help="the fixed validator limits of before (no allowance)")
    args = parser.parse_args(argv)
    from benchmarks.engine.whole_head import _write_case, voxel_argument

    grid = tuple(int(v) for v in args.grid.lower().split("x"))
    with tempfile.TemporaryDirectory() as folder:
        if args.case is not None:
            case = pickle.loads(args.case.read_bytes())
        else:
            print(f"writing a {args.grid} {args.kind.upper()} at {args.voxel} mm ...", flush=True)
            case = pickle.loads(_write_case(Path(folder), voxel_argument(args.voxel), grid, args.kind).read_bytes())
        port, data_dir = free_port(), Path(folder) / "data"
        server, watch = _serve(data_dir, port, args.fixed), PeakWatch()
        watch.start()
        try:
            url = f"http://127.0.0.1:{port}"
            wait_ready(url, interval=0.5)
            for which in ("first", "second"):
                row = _submit(url, case, watch)
                print(which, json.dumps(row), flush=True)
                if row["status"] != 202:
                    break
            log = (Path(folder) / "server.log").read_text(errors="replace")
            print("\n".join(re.findall(r".*(?:was given|validation took|job \w+: \w+ after).*", log)))
            print("load average", os.getloadavg())
        finally:
            watch.halt.set()
            server.terminate()
            server.wait(60)
    return 0




if __name__ == "__main__":
    raise SystemExit(main())
