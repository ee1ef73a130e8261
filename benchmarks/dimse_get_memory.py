"""Peak memory of a C-GET pull: ``python -m benchmarks.dimse_get_memory [--size-mb 200] [--instances 1]``.

Orthanc (its DICOM server on loopback) holds ``--instances`` multi-frame XA instances of about ``--size-mb`` MB
each (uint16 noise, Explicit VR Little Endian: nothing compresses them); a fresh Python process retrieves them
with :func:`service.pacs.dimse.pull.c_get`, as a job by DIMSE reference with ``"retrieve": "get"`` does, and
reports its peak resident memory (``VmHWM``, reset after its imports) above what it held then, with the CPU seconds of
the retrieval. Prints one JSON object. Needs Orthanc.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from tests.support.dimse_kit import large_xa
from tests.support.servers import OrthancServer, free_port

CHILD = """
import json, resource, sys, time
from pathlib import Path
from service.pacs.dimse.pull import c_get
from service.settings import ServiceSettings

args = json.loads(sys.argv[1])
settings = ServiceSettings(data_dir=Path(args["data_dir"]), dicom_timeout_seconds=60,
                           max_upload_bytes=8 << 30, max_dicom_instance_bytes=4 << 30, max_dicom_pixel_bytes=4 << 30,
                           dicom_peers=[{"ae_title": "ORTHANC", "host": "127.0.0.1", "port": args["port"]}])
import pydicom, pynetdicom  # noqa: E401,F401 - in the baseline


def status_mb(key):
    line = next(l for l in Path("/proc/self/status").read_text().splitlines() if l.startswith(key + ":"))
    return int(line.split()[1]) / 1024


Path("/proc/self/clear_refs").write_text("5")  # the peak (VmHWM) restarts from the resident size now
rss_before = status_mb("VmRSS")
before = resource.getrusage(resource.RUSAGE_SELF)
started = time.perf_counter()
got = c_get(settings, "ORTHANC", "SERIES", {"StudyInstanceUID": args["study"], "SeriesInstanceUID": args["series"]},
            "retrieve (C-GET)")
wall = time.perf_counter() - started
after = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"received": len(got), "received_mb": round(sum(map(len, got)) / 2**20, 1),
                  "rss_before_mb": round(rss_before, 1), "peak_rss_mb": round(status_mb("VmHWM"), 1),
                  "peak_above_before_mb": round(status_mb("VmHWM") - rss_before, 1),
                  "cpu_s": round(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, 2),
                  "wall_s": round(wall, 2)}))
"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size-mb", type=float, default=200.0, help="size of each instance (default 200)")
    parser.add_argument("--instances", type=int, default=1, help="instances in the series (default 1)")
    args = parser.parse_args(argv)
    from dsareg_engine.io.dicom_out import new_uid

    orthanc = OrthancServer(dicom_modalities={"dsareg": ["DSAREG", "127.0.0.1", free_port()]}).start()
    try:
        import httpx

        study, series = new_uid(), new_uid()
        with httpx.Client(base_url=orthanc.url, auth=(orthanc.user, orthanc.password), timeout=600) as pacs:
            for number in range(1, args.instances + 1):
                answer = pacs.post("/instances", content=large_xa(args.size_mb, study, series, number))
                answer.raise_for_status()
        with tempfile.TemporaryDirectory(prefix="dsareg-bench-cget-") as data_dir:
            child = json.dumps({"data_dir": data_dir, "port": orthanc.dicom_port, "study": study, "series": series})
            done = subprocess.run([sys.executable, "-c", CHILD, child], capture_output=True, text=True, timeout=900,
                                  cwd=Path(__file__).resolve().parents[1],
                                  env={**os.environ, "OMP_NUM_THREADS": "1"})
            if done.returncode != 0:
                print(done.stderr[-3000:], file=sys.stderr)
                return 1
            measured = json.loads(done.stdout.strip().splitlines()[-1])
    finally:
        orthanc.stop()
    load = os.getloadavg()[0]
    print(json.dumps({"date": _dt.date.today().isoformat(), "instances": args.instances, "size_mb": args.size_mb,
                      "load_average": round(load, 1), **measured}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
