"""PACS → dsareg → PACS, end to end on this machine, with a throw-away Orthanc.

1. starts Orthanc + DICOMweb plugin (loopback, temp storage) with ``orthanc_trigger.lua``,
2. starts ``dsareg serve`` allowed to use that Orthanc (DSAREG_DICOMWEB_SERVERS),
3. uploads the project's synthetic biplane study (phantom, no patient data) to Orthanc,
4. waits until Orthanc's Lua trigger has posted the job and dsareg has stored the
   Spatial Registration object + overlays back into the study, and compares the REG with the
   known pose.

``--compare N`` then measures what DICOMweb costs: N jobs submitted by reference (pull + push)
against N jobs of the same files uploaded as multipart, alternating.

Needs the Debian packages orthanc and orthanc-dicomweb. Run from the repository root:
``python examples/pacs/run_demo.py [--compare 3]``
"""

from __future__ import annotations

import argparse
import io
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from dsareg_engine.io.dicom_out import read_registration_matrix
from dsareg_engine.simulation.phantom_study import make_biplane_study
from tests.support.servers import OrthancServer, free_port

OPTIONS = {"starts": 1}


def lua_for(dsareg_url: str, dicomweb_url: str) -> str:
    text = (Path(__file__).parent / "orthanc_trigger.lua").read_text()
    values = {"DSAREG": f'"{dsareg_url}"', "PACS_DICOMWEB": f'"{dicomweb_url}"', "OPTIONS": "{ starts = 1 }"}
    lines = []
    for line in text.splitlines():
        for name, value in values.items():
            if line.startswith(f"local {name} = "):
                line = f"local {name} = {value}"
        lines.append(line)
    return "\n".join(lines) + "\n"


def start_dsareg(port: int, data_dir: Path, servers: list[dict]) -> subprocess.Popen:
    env = {**os.environ, "DSAREG_DICOMWEB_SERVERS": json.dumps(servers), "PYTHONUNBUFFERED": "1",
           "DSAREG_POLL_SECONDS": "0.1", "DSAREG_PROGRESS_INTERVAL_SECONDS": "0.5"}
    log = open(data_dir.parent / "dsareg.log", "ab")  # noqa: SIM115
    process = subprocess.Popen([sys.executable, "-m", "service", "serve", "--port", str(port), "--data-dir",
                                str(data_dir), "--workers", "1"], cwd=REPO, env=env, stdout=log,
                               stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=2).status_code == 200:
                return process
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    process.kill()
    raise RuntimeError("dsareg did not become ready")


def wait_job(client: httpx.Client, job_id: str, timeout: float = 600) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        body = client.get(f"/v1/registrations/{job_id}").json()
        if body["status"] in ("succeeded", "failed", "canceled"):
            return body
        time.sleep(0.1)
    raise TimeoutError(job_id)


def compare(dsareg: httpx.Client, orthanc: OrthancServer, study, rounds: int) -> None:
    ref = {"source": {"dicomweb": {
        "url": orthanc.dicomweb_url, "study_uid": study.study_uid, "ap": {"series_uid": study.uids["ap_series"]},
        "lat": {"series_uid": study.uids["lat_series"]}, "volume": {"series_uid": study.uids["volume_series"]}}},
        "options": OPTIONS, "store_results": True}
    files = [("ap", ("ap.dcm", study.ap, "application/dicom")), ("lat", ("lat.dcm", study.lat, "application/dicom"))]
    files += [("volume", (f"v{i:03d}.dcm", part, "application/dicom")) for i, part in enumerate(study.volume)]
    rows: dict[str, list[tuple[float, float]]] = {"dicomweb": [], "upload": []}
    transfer = []
    for _ in range(rounds):
        for kind in ("upload", "dicomweb"):
            started = time.perf_counter()
            if kind == "dicomweb":
                response = dsareg.post("/v1/registrations", json=ref)
            else:
                response = dsareg.post("/v1/registrations", files=files, data={"options": json.dumps(OPTIONS)})
            response.raise_for_status()
            job = wait_job(dsareg, response.json()["id"])
            wall = time.perf_counter() - started
            assert job["status"] == "succeeded", job
            registration = job["result"]["metrics"]["seconds"]["total"]
            rows[kind].append((wall, wall - registration))
            if kind == "dicomweb":  # the STOW-RS runs after the job, in the service's exporter: its export says when
                while job["export"]["state"] not in ("done", "failed"):
                    time.sleep(0.1)
                    job = dsareg.get(f"/v1/registrations/{job['id']}").json()
                export = job["export"]
                store_s = (_when(export["done_at"] or export["last_attempt_at"]) - _when(export["last_attempt_at"]))
                transfer.append((job["result"]["dicom"]["source"]["fetch_seconds"], store_s))
    print(f"\n{rounds} jobs each way, {len(study.volume)} volume slices + 2 XA "
          f"({sum(len(x) for x in study.instances()) / 2**20:.1f} MiB):")
    print("| path | wall s (submit → succeeded), median | wall − registration s, median |")
    print("|---|---|---|")
    for kind, values in rows.items():
        print(f"| {kind} | {statistics.median(v[0] for v in values):.2f} | {statistics.median(v[1] for v in values):.2f} |")
    fetch = statistics.median(t[0] for t in transfer)
    store = statistics.median(t[1] for t in transfer)
    added = statistics.median(v[1] for v in rows["dicomweb"]) - statistics.median(v[1] for v in rows["upload"])
    print(f"DICOMweb: fetch (QIDO+WADO-RS, inside the job) {fetch:.3f} s, store (STOW-RS, by the exporter after the "
          f"job) {store:.3f} s; overhead vs upload {added:+.2f} s")


def _when(text: str) -> float:
    import datetime

    return datetime.datetime.fromisoformat(text).timestamp()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--compare", type=int, default=0, help="also time N jobs by reference vs N uploads")
    parser.add_argument("--slice-px", type=int, default=None, help="pad the volume's slices to this size (e.g. 512)")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="dsareg-pacs-demo-"))
    dsareg_port = free_port()
    orthanc = OrthancServer(stable_age=2)
    orthanc.lua = lua_for(f"http://127.0.0.1:{dsareg_port}", orthanc.dicomweb_url)
    servers = [{"url": orthanc.dicomweb_url, "username": orthanc.user, "password": orthanc.password}]
    print("making the synthetic biplane study (phantom, no patient data)…")
    study = make_biplane_study(slice_px=args.slice_px)
    orthanc.start()
    dsareg = None
    try:
        dsareg = start_dsareg(dsareg_port, work / "data", servers)
        print(f"Orthanc {orthanc.url} (DICOMweb {orthanc.dicomweb_url}), dsareg http://127.0.0.1:{dsareg_port}")
        with httpx.Client(base_url=orthanc.url, auth=(orthanc.user, orthanc.password), timeout=60) as pacs:
            for data in study.instances():
                pacs.post("/instances", content=data).raise_for_status()
            print(f"uploaded study {study.study_uid}; waiting for Orthanc's trigger and dsareg's results…")
            started = time.monotonic()
            reg = None
            while reg is None and time.monotonic() - started < 600:
                time.sleep(1)
                try:
                    series = pacs.get("/series", params={"expand": ""}).json()
                except httpx.TransportError:
                    continue
                for item in series:
                    if item["MainDicomTags"].get("Modality") == "REG":
                        reg = pacs.get(f"/instances/{item['Instances'][0]}/file").content
            if reg is None:
                print("no REG arrived; see", work)
                return 1
            print(f"REG stored back {time.monotonic() - started:.1f} s after the upload (stable age 2 s included)")
        import pydicom

        matrix = read_registration_matrix(pydicom.dcmread(io.BytesIO(reg)), study.uids["volume_frame"])
        cos = (np.trace(matrix[:3, :3].T @ study.mesh_to_world[:3, :3]) - 1) / 2
        print("mesh_to_world from the REG:\n", np.array2string(matrix, precision=4, suppress_small=True))
        print(f"vs the known pose: rotation {np.degrees(np.arccos(np.clip(cos, -1, 1))):.3f} deg, "
              f"translation {np.linalg.norm(matrix[:3, 3] - study.mesh_to_world[:3, 3]):.3f} mm")
        if args.compare:
            with httpx.Client(base_url=f"http://127.0.0.1:{dsareg_port}", timeout=120) as client:
                compare(client, orthanc, study, args.compare)
    finally:
        if dsareg is not None:
            dsareg.terminate()
            dsareg.wait(30)
        orthanc.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
