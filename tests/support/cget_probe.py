"""The peak resident memory of one C-GET, in a fresh process (used by a test and by
``python -m benchmarks.service.dimse_get_memory``).

:func:`probe` runs this module in a new interpreter: it imports what a worker's C-GET needs, restarts the kernel's
peak counter (``VmHWM``, by ``/proc/self/clear_refs``), retrieves the series with
:func:`service.pacs.dimse.pull.c_get` and prints what it got and the peak above what it held before, as JSON. A
fresh process, because a long-lived one reuses memory it freed earlier and hides what a retrieval takes.
"""

from __future__ import annotations

import io
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def probe(port: int, study: str, series: str, data_dir: Path, timeout: float = 900.0) -> dict:
    """C-GET ``series`` from the peer ORTHANC at ``port`` in a fresh process; what it measured."""
    args = json.dumps({"port": port, "study": study, "series": series, "data_dir": str(data_dir)})
    done = subprocess.run([sys.executable, "-m", "tests.support.cget_probe", args], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1"})
    if done.returncode != 0:
        raise RuntimeError(f"the C-GET probe failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _status_mib(key: str) -> float:
    line = next(line for line in Path("/proc/self/status").read_text().splitlines() if line.startswith(key + ":"))
    return int(line.split()[1]) / 1024


def _main(args: dict) -> dict:
    import pydicom  # noqa: F401 - in what is held before
    import pynetdicom  # noqa: F401

    from service.pacs.dimse.pull import c_get
    from service.settings import ServiceSettings

    settings = ServiceSettings(data_dir=Path(args["data_dir"]), dicom_timeout_seconds=60, max_upload_bytes=8 << 30,
                               max_dicom_instance_bytes=4 << 30, max_dicom_pixel_bytes=4 << 30,
                               dicom_peers=[{"ae_title": "ORTHANC", "host": "127.0.0.1", "port": args["port"]}])
    Path("/proc/self/clear_refs").write_text("5")  # the peak restarts from the resident size now
    rss_before, before, started = _status_mib("VmRSS"), resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    got = c_get(settings, "ORTHANC", "SERIES", {"StudyInstanceUID": args["study"], "SeriesInstanceUID": args["series"]},
                "retrieve (C-GET)")
    wall, after, peak = time.perf_counter() - started, resource.getrusage(resource.RUSAGE_SELF), _status_mib("VmHWM")
    return {"received": len(got), "received_mb": round(sum(map(len, got)) / 2**20, 1),
            "sop_instance_uids": [str(pydicom.dcmread(io.BytesIO(data), stop_before_pixels=True).SOPInstanceUID)
                                  for data in got],
            "rss_before_mb": round(rss_before, 1), "peak_rss_mb": round(peak, 1),
            "peak_above_before_mb": round(peak - rss_before, 1),
            "cpu_s": round(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, 2),
            "wall_s": round(wall, 2)}


if __name__ == "__main__":
    print(json.dumps(_main(json.loads(sys.argv[1]))))
