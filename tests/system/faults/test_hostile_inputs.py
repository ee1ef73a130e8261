"""Hostile-input corpus over HTTP against a real server: never a 5xx, always problem+json naming
the field at fault, the server's and the validator's memory bounded, /healthz answering throughout."""

from __future__ import annotations

import json
import struct
import threading
import zlib
from pathlib import Path

import pytest
from tests.support.faults_kit import descendants, raw_connection
from tests.support.service_testkit import Server, needs_engine

pytestmark = [needs_engine, pytest.mark.slow]

PROBLEM = "application/problem+json"
MiB = 1 << 20


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def png_bomb(width: int = 7900, height: int = 7900, bits: int = 16, color: int = 6) -> bytes:
    """A small PNG that decodes to width × height × channels × bytes (default RGBA16: ≈ 476 MiB)."""
    channels = {0: 1, 2: 3, 4: 2, 6: 4}[color]
    row = b"\x00" * (1 + width * channels * bits // 8)
    packer = zlib.compressobj(9)
    idat = b"".join(packer.compress(row) for _ in range(height)) + packer.flush()
    header = struct.pack(">IIBBBBB", width, height, bits, color, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


def _status_kb(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0


def _validator_pid(srv: Server) -> int:
    for pid in descendants(srv.process.pid):
        if _is_validator(pid):
            return pid
    raise AssertionError("no validator process")


def _is_validator(pid: int) -> bool:
    """A spawned child of the server that is not a worker (workers run a 'parent-link' thread)."""
    try:
        if b"spawn_main" not in Path(f"/proc/{pid}/cmdline").read_bytes():
            return False
        names = {(task / "comm").read_text().strip() for task in Path(f"/proc/{pid}/task").iterdir()}
    except OSError:
        return False
    return "parent-link" not in names


@pytest.fixture(scope="module")
def hostile_server(tmp_path_factory):
    srv = Server(tmp_path_factory.mktemp("hostile") / "data", workers=1,
                 env={"DSAREG_MAX_UPLOAD_BYTES": str(8 * MiB), "DSAREG_VALIDATION_MEMORY_MB": "512",
                      # above the default 64 MiB so that one image reaches the decoder and its memory cap
                      "DSAREG_MAX_IMAGE_BYTES": str(256 * MiB)}).start()
    yield srv
    srv.stop()


def _has_cuda() -> bool:
    import torch

    return bool(torch.cuda.is_available())


def _corpus(case) -> list[tuple[str, dict, dict, str | None]]:
    """(name, files override, form data override, field expected in the problem)."""
    deep = "[" * 10_000 + "]" * 10_000
    big_int = "9" * 5_000
    rigid = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    scaled = [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    obj_zero = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 0 1 2\nf 1 2 3\n"
    return [
        ("geometry nested 10,000 deep", {}, {"geometry": '{"views": ' + deep + "}"}, "geometry"),
        ("geometry 5,000-digit integer", {}, {"geometry": '{"views": ' + big_int + "}"}, "geometry"),
        ("geometry NaN", {}, {"geometry": '{"views": NaN}'}, "geometry"),
        ("geometry 1e999", {}, {"geometry": '{"views": 1e999}'}, "geometry"),
        ("geometry not UTF-8", {}, {"geometry": b"{\xff\xfe}".decode("latin-1")}, "geometry"),
        ("geometry array", {}, {"geometry": "[1, 2]"}, "geometry"),
        ("geometry path", {}, {"geometry": "/etc/passwd"}, "geometry"),
        ("options nested 10,000 deep", {}, {"options": '{"starts": ' + deep + "}"}, "options"),
        ("options 5,000-digit seed", {}, {"options": '{"seed": ' + big_int + "}"}, "options"),
        ("options seed -1", {}, {"options": '{"seed": -1}'}, "options.seed"),
        ("options NaN pose", {}, {"options": '{"initial_mesh_to_world": [[NaN]]}'}, "options"),
        ("options non-rigid pose", {}, {"options": json.dumps({"initial_mesh_to_world": scaled})},
         "options.initial_mesh_to_world"),
        ("options bad ground truth", {}, {"options": json.dumps({"ground_truth_mesh_to_world": rigid[:3]})},
         "options.ground_truth_mesh_to_world"),
        ("options hour-long job", {}, {"options": json.dumps({"starts": 64, "working_size_px": 2000,
                                                               "coarse_to_fine": False})}, "options"),
        *([] if _has_cuda() else [("options device cuda (no CUDA)", {}, {"options": '{"device": "cuda"}'},
                                   "options.device")]),
        ("options unknown key", {}, {"options": '{"sneaky": 1}'}, "options.sneaky"),
        ("options not an object", {}, {"options": "[]"}, "options"),
        ("OBJ face index 0", {"mesh": ("m.obj", obj_zero)}, {}, "mesh"),
        ("PNG memory bomb 7900² RGBA16", {"ap": ("a.png", png_bomb())}, {}, "ap"),
        ("PNG 6000² RGB8: under the byte cap, over the memory cap", {"ap": ("a.png", png_bomb(6000, 6000, 8, 2))}, {},
         "ap"),
        ("PNG truncated", {"lat": ("l.png", b"\x89PNG\r\n\x1a\nnot really")}, {}, "lat"),
        ("empty image", {"ap": ("a.png", b"")}, {}, "ap"),
        ("STL nonsense", {"mesh": ("m.stl", b"solid x\nnonsense")}, {}, "mesh"),
        ("unknown form field", {}, {"surprise": "1"}, "surprise"),
    ]


def _post(client, case, files: dict, data: dict, headers: dict | None = None):
    base = {"mesh": ("m.obj", case.mesh_obj), "ap": ("a.png", case.ap_png), "lat": ("l.png", case.lat_png)}
    form = {"geometry": json.dumps(case.geometry), "options": json.dumps({"starts": 1, "max_iterations": 5})}
    return client.post("/v1/registrations", files={**base, **files}, data={**form, **data}, headers=headers or {})


def _problem(response, field: str | None) -> dict:
    assert response.status_code < 500, (response.status_code, response.text[:500])
    assert response.headers["content-type"].startswith(PROBLEM), response.headers
    body = response.json()
    assert body["status"] == response.status_code and "Traceback" not in response.text
    if field is not None:
        assert body.get("field") == field, body
    return body


class PeakSampler(threading.Thread):
    """Largest RSS of any validator process of the server, sampled every 20 ms (validators are
    replaced after a MemoryError, so their own VmHWM is lost with them)."""

    def __init__(self, srv: Server):
        super().__init__(daemon=True)
        self.srv, self.peak_kb, self.halt = srv, 0, threading.Event()

    def run(self) -> None:
        while not self.halt.wait(0.02):
            for pid in descendants(self.srv.process.pid):
                try:
                    if _is_validator(pid):
                        self.peak_kb = max(self.peak_kb, _status_kb(pid, "VmRSS"))
                except OSError:
                    pass


def test_hostile_corpus_never_5xx(hostile_server, case):
    srv = hostile_server
    with srv.client() as client:
        assert _post(client, case, {}, {}).status_code == 202  # warm: the validator has parsed once
        validator = _validator_pid(srv)
        api_rss = _status_kb(srv.process.pid, "VmRSS")
        validator_base = _status_kb(validator, "VmHWM")
        sampler = PeakSampler(srv)
        sampler.start()
        tried = 0
        for name, files, data, field in _corpus(case):
            response = _post(client, case, files, data)
            assert response.status_code == 422, (name, response.status_code, response.text[:300])
            _problem(response, field)
            assert client.get("/healthz", timeout=2).status_code == 200, name
            tried += 1
        tried += _protocol_cases(client, case)
        sampler.halt.set()
        sampler.join()
        validator_peak = sampler.peak_kb
        api_growth = _status_kb(srv.process.pid, "VmRSS") - api_rss
        metrics = client.get("/metrics").text
    print(f"hostile corpus: {tried} inputs, 0 5xx; validator peak {validator_peak / 1024:.0f} MB "
          f"(baseline {validator_base / 1024:.0f} MB); API RSS growth {api_growth / 1024:.0f} MB")
    assert (validator_peak - validator_base) < 512 * 1024, (validator_peak, validator_base)
    assert api_growth < 256 * 1024, api_growth
    server_errors = [line for line in metrics.splitlines()  # (/readyz is 503 while the validator warms up)
                     if 'status="5' in line and 'route="/v1/registrations"' in line and not line.endswith(" 0.0")]
    assert not server_errors, server_errors


def _raw_post(client, extra_headers: bytes) -> tuple[int, bytes, bytes]:
    port = int(str(client.base_url).rsplit(":", 1)[1].strip("/"))
    with raw_connection(port) as sock:
        sock.sendall(b"POST /v1/registrations HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\n"
                     b"Content-Length: 0\r\nConnection: close\r\n" + extra_headers + b"\r\n")
        data = b""
        while chunk := sock.recv(65536):
            data += chunk
    head, _, payload = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), head.lower(), payload


def _protocol_cases(client, case) -> int:
    """Header/method/paging abuse: documented 4xx answers."""
    status, head, payload = _raw_post(client, b"Idempotency-Key: \t  \r\n")  # httpx refuses to send it
    assert status == 400 and PROBLEM.encode() in head and json.loads(payload)["field"] == "Idempotency-Key"
    response = client.put("/v1/registrations")
    _problem(response, None)
    assert response.status_code == 405 and set(response.headers["allow"].replace(" ", "").split(",")) >= {"GET", "POST"}
    _problem(client.get("/v1/registrations", params={"cursor": "%%%"}), "cursor")
    big = client.post("/v1/registrations", files={"mesh": ("m.obj", b"v 0 0 0\n" * (2 * MiB))},
                      data={"geometry": "paper"})
    assert big.status_code == 413 and big.headers["content-type"].startswith(PROBLEM)
    _problem(client.post("/v1/registrations", content=b"{}", headers={"content-type": "application/json"}), None)
    return 5
