"""DIMSE benchmark: ``python -m benchmarks.service.dimse [--stable-seconds 10] [--transfer-only]``.

1. **transfer**: a 20 MB study (40 CT slices of 512 × 512 × 16 bit) by C-STORE from a pynetdicom
   SCU to the node's C-STORE SCP in this process (fsync + index per instance included), over
   loopback: wall seconds and CPU seconds of both ends;
2. **round trip** (unless ``--transfer-only``): ``dsareg serve`` with its DICOM node, the phantom
   biplane study sent by dcmtk ``storescu``, results to a dcmtk ``storescp``: seconds from the
   last instance to the queued job, the job's run time, and from the job's end to the REG
   written by ``storescp``.

Prints one JSON object. Needs dcmtk for part 2.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import io
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from tests.support.servers import free_port


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def big_study(slices: int = 40, side: int = 512):
    """``slices`` CT instances of ``side``² uint16 (noise), about 0.5 MB each at 512²."""
    import pydicom

    from dsareg_engine.io.dicom_out import new_instance, new_uid

    study, series, frame = new_uid(), new_uid(), new_uid()
    rng = np.random.default_rng(0)
    out = []
    for k in range(slices):
        ds = new_instance("1.2.840.10008.5.1.4.1.1.2", new_uid(), charset="ISO_IR 100")
        ds.PatientName, ds.PatientID, ds.StudyInstanceUID, ds.SeriesInstanceUID = "BENCH^DIMSE", "BENCH", study, series
        ds.Modality, ds.FrameOfReferenceUID, ds.InstanceNumber = "CT", frame, k + 1
        ds.ImagePositionPatient, ds.ImageOrientationPatient = [0, 0, float(k)], [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing, ds.SliceThickness = [0.5, 0.5], 1.0
        ds.Rows = ds.Columns = side
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.RescaleIntercept, ds.RescaleSlope = -1024, 1
        ds.PixelData = rng.integers(0, 4000, (side, side), dtype=np.uint16).tobytes()
        buffer = io.BytesIO()
        ds.save_as(buffer, enforce_file_format=True)
        out.append(pydicom.dcmread(io.BytesIO(buffer.getvalue())))
    return out


def transfer(folder: Path) -> dict:
    from pynetdicom import AE

    from service.storage.inbox import Inbox
    from service.pacs.dimse.scp import StoreScp, start_server
    from service.settings import ServiceSettings
    from service.storage.blobs import BlobStore
    from service.storage.store import SqlJobStore

    port = free_port()
    folder.mkdir(parents=True, exist_ok=True)
    settings = ServiceSettings(data_dir=folder, dicom_port=port, min_free_bytes=0,
                               dicom_peers=[{"ae_title": "BENCH", "host": "127.0.0.1", "port": 1}])
    store = SqlJobStore(settings.effective_database_url)
    server = start_server(settings, StoreScp(settings, Inbox(store.engine, store.writer), BlobStore(folder)))
    datasets = big_study()
    size = sum(len(ds.PixelData) for ds in datasets)
    ae = AE(ae_title="BENCH")
    ae.add_requested_context("1.2.840.10008.5.1.4.1.1.2", "1.2.840.10008.1.2.1")
    wall, cpu = time.perf_counter(), _cpu()
    assoc = ae.associate("127.0.0.1", port, ae_title="DSAREG")
    statuses = [int(assoc.send_c_store(ds).Status) for ds in datasets]
    assoc.release()
    wall, cpu = time.perf_counter() - wall, _cpu() - cpu
    server.shutdown()
    store.dispose()
    return {"instances": len(datasets), "megabytes": round(size / 1e6, 1), "all_success": set(statuses) == {0},
            "wall_seconds": round(wall, 3), "cpu_seconds_both_ends": round(cpu, 3)}


def _wait(predicate, timeout: float, step: float = 0.05):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(step)
    raise TimeoutError("timed out")


def _iso(text: str) -> float:
    return _dt.datetime.fromisoformat(text).timestamp()


def round_trip(folder: Path, stable_seconds: float) -> dict:
    import httpx

    from dsareg_engine.simulation.phantom_study import make_biplane_study

    study = make_biplane_study(image_px=160, pixel_spacing_mm=0.9, depth=2)
    files = folder / "study"
    files.mkdir(parents=True)
    for index, data in enumerate(study.instances()):
        (files / f"{index:03d}.dcm").write_bytes(data)
    http, dicom, export = free_port(), free_port(), free_port()
    (folder / "exported").mkdir()
    scp = subprocess.Popen(["storescp", "-aet", "STORESCU", "-od", str(folder / "exported"), str(export)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    env = {**os.environ, "DSAREG_DICOM_PORT": str(dicom), "DSAREG_DICOM_STABLE_SECONDS": str(stable_seconds),
           "DSAREG_DICOM_PEERS": json.dumps([{"ae_title": "STORESCU", "host": "127.0.0.1", "port": export}]),
           "DSAREG_DICOM_JOB_OPTIONS": json.dumps({"starts": 1}), "DSAREG_POLL_SECONDS": "0.1"}
    serve = subprocess.Popen([sys.executable, "-m", "service", "serve", "--port", str(http), "--data-dir",
                              str(folder / "data")], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        client = httpx.Client(base_url=f"http://127.0.0.1:{http}", timeout=30)
        _wait(lambda: _get(client, "/readyz") == 200, 300, 0.5)
        subprocess.run(["storescu", "-aet", "STORESCU", "-aec", "DSAREG", "127.0.0.1", str(dicom),
                        *map(str, sorted(files.iterdir()))], check=True, capture_output=True, timeout=300)
        last = time.time()
        items = _wait(lambda: client.get("/v1/registrations").json()["items"], 120)
        job = _wait(lambda: (j := client.get(items[0]["links"]["self"]).json())["status"] in ("succeeded", "failed")
                    and j, 600, 0.1)
        reg = job["result"]["dicom"]["instances"]["reg.dcm"]["sop_instance_uid"]
        stored = _wait(lambda: [p for p in (folder / "exported").iterdir() if reg in p.name], 30, 0.02)
        return {"stable_seconds": stable_seconds, "status": job["status"],
                "queued_after_last_instance_seconds": round(_iso(job["created_at"]) - last, 2),
                "job_seconds": round(_iso(job["finished_at"]) - _iso(job["started_at"]), 2),
                "reg_at_destination_after_job_seconds": round(stored[0].stat().st_mtime - _iso(job["finished_at"]), 2),
                "export": job.get("export") or job["result"]["dicom"].get("exported")}
    finally:
        serve.terminate()
        scp.terminate()
        serve.wait(30)
        scp.wait(10)


def queue_lag(folder: Path, stable_seconds: float, studies: int) -> dict:
    """``studies`` phantom studies (fresh UIDs) sent one after another by ``storescu`` to ``dsareg serve
    --workers 0``: seconds from the end of each ``storescu`` to the job's ``created_at``."""
    import httpx

    from dsareg_engine.simulation.phantom_study import make_biplane_study
    from tests.support.dimse_kit import renamed_study

    study = make_biplane_study(image_px=160, pixel_spacing_mm=0.9, depth=2)
    http, dicom = free_port(), free_port()
    env = {**os.environ, "DSAREG_DICOM_PORT": str(dicom), "DSAREG_DICOM_STABLE_SECONDS": str(stable_seconds),
           "DSAREG_DICOM_PEERS": json.dumps([{"ae_title": "STORESCU", "host": "127.0.0.1", "port": free_port()}]),
           "DSAREG_DICOM_JOB_OPTIONS": json.dumps({"starts": 1})}
    folder.mkdir(parents=True, exist_ok=True)
    log = open(folder / "serve.log", "wb")  # noqa: SIM115 - closed below
    serve = subprocess.Popen([sys.executable, "-m", "service", "serve", "--port", str(http), "--workers", "0",
                              "--data-dir", str(folder / "data")], env=env, stdout=log,
                             stderr=subprocess.STDOUT)
    lags = []
    try:
        client = httpx.Client(base_url=f"http://127.0.0.1:{http}", timeout=30)
        _wait(lambda: _validators_ready(client), 300, 0.5)  # /readyz is 503 without workers
        for index in range(studies):
            _uid, paths = renamed_study(study, folder / f"s{index}")
            subprocess.run(["storescu", "-aet", "STORESCU", "-aec", "DSAREG", "127.0.0.1", str(dicom),
                            *map(str, paths)], check=True, capture_output=True, timeout=300)
            last = time.time()
            items = _wait(lambda n=index: len(page := client.get("/v1/registrations").json()["items"]) > n and page,
                          120, 0.05)
            lags.append(max(_iso(item["created_at"]) for item in items) - last)
    finally:
        serve.terminate()
        serve.wait(30)
        log.close()
    steps = [line.split("(planning ")[1].rstrip(")\n") for line in (folder / "serve.log").read_text().splitlines()
             if "(planning " in line]
    return {"stable_seconds": stable_seconds, "studies": studies, "dispatcher_steps": steps, "median_seconds": round(float(np.median(lags)), 2),
            "max_seconds": round(max(lags), 2), "lags_seconds": [round(x, 2) for x in lags]}


def _validators_ready(client) -> bool:
    try:
        checks = client.get("/readyz").json()["checks"]
    except Exception:  # noqa: BLE001 - not up yet
        return False
    return bool(checks.get("validator_ready") and checks.get("validator_spare_ready"))


def _get(client, path: str) -> int:
    try:
        return client.get(path).status_code
    except Exception:  # noqa: BLE001 - not up yet
        return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.service.dimse", description=__doc__.splitlines()[0])
    parser.add_argument("--stable-seconds", type=float, default=10.0)
    parser.add_argument("--transfer-only", action="store_true")
    parser.add_argument("--lag-studies", type=int, default=0,
                        help="only measure the queue lag (last instance -> job) over this many studies")
    args = parser.parse_args(argv)
    folder = Path(tempfile.mkdtemp(prefix="dsareg-bench-dimse-"))
    try:
        if args.lag_studies:
            out = {"loadavg_1min": round(os.getloadavg()[0], 1),
                   "queue_lag": queue_lag(folder / "lag", args.stable_seconds, args.lag_studies)}
            print(json.dumps(out, indent=1))
            return 0
        out = {"loadavg_1min": round(os.getloadavg()[0], 1), "transfer_20mb": transfer(folder / "transfer")}
        if not args.transfer_only:
            out["round_trip"] = round_trip(folder / "trip", args.stable_seconds)
        print(json.dumps(out, indent=1))
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
