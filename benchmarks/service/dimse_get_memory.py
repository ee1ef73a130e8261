"""Peak memory of a C-GET pull: ``python -m benchmarks.service.dimse_get_memory [--size-mb 200] [--instances 1]``.

Orthanc (its DICOM server on loopback) holds ``--instances`` multi-frame XA instances of about ``--size-mb`` MB
each (uint16 noise, Explicit VR Little Endian: nothing compresses them); a fresh Python process retrieves them
with :func:`service.pacs.dimse.pull.c_get`, as a job by DIMSE reference with ``"retrieve": "get"`` does, and
reports its peak resident memory above what it held after its imports, with the CPU seconds of the retrieval
(:mod:`tests.support.cget_probe`). Prints one JSON object. Needs Orthanc.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import sys
import tempfile
from pathlib import Path

from tests.support.cget_probe import probe
from tests.support.dimse_kit import large_xa
from tests.support.servers import OrthancServer, free_port

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
            measured = probe(orthanc.dicom_port, study, series, Path(data_dir))
            measured.pop("sop_instance_uids")
    finally:
        orthanc.stop()
    load = os.getloadavg()[0]
    print(json.dumps({"date": _dt.date.today().isoformat(), "instances": args.instances, "size_mb": args.size_mb,
                      "load_average": round(load, 1), **measured}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
