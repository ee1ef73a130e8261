"""Hostile DIMSE peers against ``dsareg serve``: ``python -m benchmarks.service.dimse_hostile [--bomb-gb 1.5]``.

Starts ``dsareg serve --workers 0`` with its DICOM node (default limits), then sends, each in one
association from a pynetdicom SCU: a deflate bomb (Deflated Explicit VR Little Endian, an XA whose
Pixel Data is ``--bomb-gb`` GB of zeros: about 1.5 MB on the wire), and, with ``--native-mb``, a plain
instance that large (past ``MAX_DICOM_INSTANCE_BYTES`` as it arrives), with ``--valid-mb`` one within the
bounds (stored). Prints one JSON object: per
instance the C-STORE status and answer seconds, the API's peak RSS (VmHWM) before and after, the
largest file in the data folder, and the slowest ``/healthz`` while the bomb was processed.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

from tests.support.dicom_bombs import DEFLATED, EXPLICIT, XA, deflate_bomb, encoded, part10, xa_header
from tests.support.servers import free_port
from tests.support.service_testkit import Server


def _peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return round(int(line.split()[1]) / 1024.0, 1)
    return 0.0


def _send(port: int, path: Path) -> tuple[int, float]:
    from pynetdicom import AE, _config

    _config.STORE_SEND_CHUNKED_DATASET = True  # the file as it is, never decoded here
    ae = AE(ae_title="SCU")
    for syntax in (EXPLICIT, DEFLATED):
        ae.add_requested_context(XA, syntax)
    ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = 600
    assoc = ae.associate("127.0.0.1", port, ae_title="DSAREG")
    assert assoc.is_established, "association refused"
    started = time.monotonic()
    status = int(assoc.send_c_store(path).Status)
    took = time.monotonic() - started
    assoc.release()
    return status, round(took, 2)


def _watch_healthz(url: str, stop: threading.Event, worst: list[float]) -> None:
    with httpx.Client(base_url=url, timeout=30) as client:
        while not stop.wait(0.25):
            started = time.monotonic()
            client.get("/healthz")
            worst[0] = max(worst[0], time.monotonic() - started)


def run(bomb_gb: float, native_mb: int, folder: Path, valid_mb: int = 0) -> dict:
    files = folder / "send"
    files.mkdir(parents=True)
    made = time.process_time()
    bomb = xa_header(rows=1024, columns=1024, frames=1)
    bomb_path = part10(deflate_bomb(bomb, int(bomb_gb * 1e9)), XA, bomb.SOPInstanceUID, DEFLATED, files / "bomb.dcm")
    sends = {"deflate bomb": bomb_path}
    if native_mb:
        big = xa_header(rows=1024, columns=1024, frames=1)
        sends["native, too large"] = part10(encoded(big, pixel_bytes=native_mb << 20), XA, big.SOPInstanceUID,
                                            EXPLICIT, files / "big.dcm")
    if valid_mb:  # within the bounds: stored (1024² 16-bit frames, as many as make valid_mb)
        valid = xa_header(rows=1024, columns=1024, frames=max(1, valid_mb // 2))
        sends["native, within the bounds"] = part10(encoded(valid), XA, valid.SOPInstanceUID, EXPLICIT,
                                                    files / "valid.dcm")
    report: dict = {"bomb_gb": bomb_gb, "bomb_bytes_on_wire": bomb_path.stat().st_size,
                    "build_cpu_s": round(time.process_time() - made, 2)}
    dicom_port = free_port()
    peers = [{"ae_title": "SCU", "host": "127.0.0.1", "port": free_port()}]
    srv = Server(folder / "data", workers=0, env={"DSAREG_DICOM_PORT": str(dicom_port),
                                                   "DSAREG_DICOM_PEERS": json.dumps(peers)}).start(wait_ready=False)
    try:
        report["api_rss_mb_before"] = _peak_rss_mb(srv.process.pid)
        stop, worst = threading.Event(), [0.0]
        watcher = threading.Thread(target=_watch_healthz, args=(srv.url, stop, worst), daemon=True)
        watcher.start()
        report["instances"] = {name: dict(zip(("status", "answer_s"), _send(dicom_port, path), strict=True))
                               for name, path in sends.items()}
        stop.set()
        watcher.join()
        report["healthz_slowest_s"] = round(worst[0], 3)
        report["api_rss_mb_after"] = _peak_rss_mb(srv.process.pid)
        sizes = [p.stat().st_size for p in (folder / "data").rglob("*") if p.is_file()]
        report["largest_file_bytes"] = max(sizes, default=0)
    finally:
        srv.stop()
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    report["server_cpu_s"] = round(usage.ru_utime + usage.ru_stime, 2)
    for status in report["instances"].values():
        status["status"] = f"0x{status['status']:04X}"
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bomb-gb", type=float, default=1.5)
    parser.add_argument("--native-mb", type=int, default=0, help="also a plain instance this large (0: none)")
    parser.add_argument("--valid-mb", type=int, default=0,
                        help="also a plain instance this large within the bounds, stored (0: none)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="dsareg-hostile-") as tmp:
        print(json.dumps(run(args.bomb_gb, args.native_mb, Path(tmp), args.valid_mb), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
