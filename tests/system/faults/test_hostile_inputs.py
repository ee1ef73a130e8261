"""Hostile-input corpus over HTTP against a real server: never a 5xx, always problem+json naming
the field at fault, the server's and the validator's memory bounded, /healthz answering throughout.

:func:`test_request_parsing_corpus` is the request-parsing half (issue 20): huge text parts on every
route, cut multipart bodies, malformed HTTP framing, DICOM headers with non-numbers, many-page TIFFs,
bad job ids, with a concurrent /healthz poller measuring the longest event-loop stall."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path

import httpx
import pytest

from tests.support.faults_kit import descendants, raw_connection
from tests.support.hostile_images import (
    NUMBER_OF_FRAMES,
    RESCALE_SLOPE,
    many_frame_gif,
    many_page_tiff,
    plain_xa,
    with_dicom_value,
)
from tests.support.service_testkit import FAST_OPTIONS, Server, needs_engine, wait_for
from tests.support.time_bounds import allowed

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
            process = self.srv.process
            if process is None:  # the server stopped (a failed test's teardown)
                return
            for pid in descendants(process.pid):
                try:
                    if _is_validator(pid):
                        self.peak_kb = max(self.peak_kb, _status_kb(pid, "VmRSS"))
                except OSError:
                    pass


def test_hostile_corpus_never_5xx(hostile_server, case, tmp_path):
    srv = hostile_server
    poller = HealthPoller(srv.port, tmp_path / "stop")
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
    stall = poller.stop()
    print(f"hostile corpus: {tried} inputs, 0 5xx; validator peak {validator_peak / 1024:.0f} MB "
          f"(baseline {validator_base / 1024:.0f} MB); API RSS growth {api_growth / 1024:.0f} MB; "
          f"longest /healthz answer {stall['worst_s']:.3f} s over {stall['polls']} polls")
    # the validator parses (the event loop never waits on it), but here it decodes bombs on the same 2 cores:
    # measured 0.17-0.88 s on the shared, loaded machine (load average 8-14), so the bound is the 2 s each
    # /healthz above already had; the 0.5 s target is asserted by the parsing corpus (no decode competing)
    assert stall["worst_s"] < allowed(4 * STALL_LIMIT_S), stall
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


# ---- request parsing (issue 20): one size policy, cut bodies, HTTP framing, headers, pages ----------

STALL_LIMIT_S = 0.5
BOUNDARY = "hostileXyZ"


POLLER = """
import http.client, json, os, sys, time
port, stop = int(sys.argv[1]), sys.argv[2]
worst, polls, slow = 0.0, 0, []
while not os.path.exists(stop):
    started = time.perf_counter()
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=300)
    connection.request("GET", "/healthz")
    assert connection.getresponse().status == 200
    connection.close()
    took = time.perf_counter() - started
    worst, polls = max(worst, took), polls + 1
    if took > 0.25:
        slow.append([round(time.time() - took, 2), round(took, 3)])
    time.sleep(0.05)
print(json.dumps({"worst_s": worst, "polls": polls, "slow": slow[:20]}))
"""


class HealthPoller:
    """``/healthz`` every 50 ms from its own process (the test's own work cannot delay it): the slowest
    answer is the longest event-loop stall of the server."""

    def __init__(self, port: int, stop_file: Path):
        self.stop_file = stop_file
        self.process = subprocess.Popen([sys.executable, "-c", POLLER, str(port), str(stop_file)],
                                        stdout=subprocess.PIPE, text=True)

    def stop(self) -> dict:
        self.stop_file.touch()
        out, _ = self.process.communicate(timeout=320)
        assert self.process.returncode == 0, out
        return json.loads(out)


def multipart(parts: list[tuple[str, str | None, bytes]], *, close: bool = True) -> bytes:
    """A multipart/form-data body of (name, filename or None, content); ``close=False`` leaves out the closing boundary."""
    out = b""
    for name, filename, content in parts:
        disposition = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
        out += f"--{BOUNDARY}\r\nContent-Disposition: {disposition}\r\n\r\n".encode() + content + b"\r\n"
    return out + (f"--{BOUNDARY}--\r\n".encode() if close else b"")


def _raw(port: int, head: bytes, body: bytes = b"") -> tuple[int, bytes, bytes]:
    """Send ``head`` (request line + headers, without the blank line) and ``body``; status, head, payload."""
    with raw_connection(port) as sock:
        sock.sendall(head + b"\r\nConnection: close\r\n\r\n" + body)
        data = b""
        while chunk := sock.recv(65536):
            data += chunk
    answer, _, payload = data.partition(b"\r\n\r\n")
    return int(answer.split()[1]), answer.lower(), payload


@pytest.fixture(scope="module")
def parsing_server(tmp_path_factory, case):
    """Default upload limit (512 MiB: the part caps, not the body cap, must answer) and a succeeded job to track."""
    srv = Server(tmp_path_factory.mktemp("parsing") / "data", workers=1).start()
    with srv.client() as client:
        job = _post(client, case, {}, {"options": json.dumps(FAST_OPTIONS)})
        assert job.status_code == 202, job.text
        assert wait_for(client, job.json()["id"], timeout=300)["status"] == "succeeded"
    srv.job_id = job.json()["id"]
    yield srv
    srv.stop()


def _case_parts(case, *, options: bytes | None = None, options_file: bool = False) -> list:
    parts = [("mesh", "m.obj", case.mesh_obj), ("ap", "a.png", case.ap_png), ("lat", "l.png", case.lat_png),
             ("geometry", None, json.dumps(case.geometry).encode())]
    if options is not None:
        parts.append(("options", "options.json" if options_file else None, options))
    return parts


def _parsing_cases(case, job_id: str) -> list[tuple[str, str, str, dict, int, str | None]]:
    """(name, method, path, request kwargs, expected status, expected field)."""
    big = b'{"starts": 1, "pad": "' + b"x" * (100 * MiB) + b'"}'
    thirty = b" " * (30 * MiB) + b"{}"
    mp = {"content-type": f"multipart/form-data; boundary={BOUNDARY}"}
    track = f"/v1/registrations/{job_id}/track"
    views = [("ap", "a.png", case.ap_png), ("lat", "l.png", case.lat_png)]
    xa = plain_xa()
    image_cases = [
        ("DICOM NumberOfFrames 'abc'", "ap", "a.dcm", with_dicom_value(xa, NUMBER_OF_FRAMES, b"IS", b"abc")),
        ("DICOM RescaleSlope 'abc'", "lat", "l.dcm", with_dicom_value(xa, RESCALE_SLOPE, b"DS", b"abc")),
        ("TIFF of 80,000 pages", "lat", "l.tif", many_page_tiff(80_000)),
        ("GIF of 20,000 frames", "ap", "a.gif", many_frame_gif(20_000)),
    ]
    cases = [
        ("options text part 100 MB", "POST", "/v1/registrations", {"content": multipart(_case_parts(case, options=big))},
         413, "options"),
        ("options file part 100 MB", "POST", "/v1/registrations",
         {"content": multipart(_case_parts(case, options=big, options_file=True))}, 413, "options"),
        ("geometry text part 30 MB", "POST", "/v1/registrations",
         {"content": multipart([("geometry", None, thirty), *_case_parts(case)[:3]])}, 413, "geometry"),
        ("/track options file part 100 MB", "POST", track, {"content": multipart([*views, ("options", "o.json", big)])},
         413, "options"),
        ("/track options text part 30 MB", "POST", track, {"content": multipart([*views, ("options", None, thirty)])},
         413, "options"),
        ("/track options not UTF-8", "POST", track, {"content": multipart([*views, ("options", "o.json", b"\xff{}")])},
         422, "options"),
        ("multipart cut before the closing boundary", "POST", "/v1/registrations",
         {"content": multipart(_case_parts(case, options=b'{"starts": 2}'), close=False)}, 400, "options"),
        ("multipart cut inside the geometry part", "POST", "/v1/registrations",
         {"content": multipart(_case_parts(case), close=False)[:-200]}, 400, "geometry"),
        ("/track multipart cut", "POST", track, {"content": multipart(views, close=False)}, 400, "lat"),
        ("multipart part without a name", "POST", "/v1/registrations",
         {"content": f"--{BOUNDARY}\r\nContent-Disposition: form-data\r\n\r\nx\r\n--{BOUNDARY}--\r\n".encode()},
         400, None),
        ("multipart too many fields", "POST", "/v1/registrations",
         {"content": multipart([(f"f{i}", None, b"1") for i in range(25)])}, 400, "f20"),
        ("multipart without a boundary", "POST", "/v1/registrations",
         {"content": b"x", "headers": {"content-type": "multipart/form-data"}}, 400, None),
        ("JSON reference body 100 MB", "POST", "/v1/registrations",
         {"content": big, "headers": {"content-type": "application/json"}}, 413, "body"),
        ("job id with NUL", "GET", "/v1/registrations/abc%00def", {}, 404, "job_id"),
        ("job id of 5,000 characters", "GET", "/v1/registrations/" + "a" * 5000 + "/result", {}, 404, "job_id"),
        ("/track on a job id with NUL", "POST", "/v1/registrations/abc%00def/track",
         {"content": multipart(views)}, 404, "job_id"),
    ]
    for name, role, filename, data in image_cases:
        parts = [(r, filename, data) if r == role else (r, f, content)
                 for r, f, content in _case_parts(case, options=json.dumps(FAST_OPTIONS).encode())]
        cases.append((name, "POST", "/v1/registrations", {"content": multipart(parts)}, 422, role))
    for _, method, _, kwargs, _, _ in cases:
        if method == "POST" and "headers" not in kwargs:
            kwargs["headers"] = mp
    return cases


def _framing_cases(port: int) -> list[tuple[str, str]]:
    """Content-Length abuse: h11 refuses these before the app; the answer is still problem+json naming the
    header. (name, what went wrong or "") per case."""
    body = multipart([("options", None, b"{}")])
    out = []
    for value in ("-5", "12abc", "5\r\nContent-Length: 7", "99999999999999999999999", "5\x00"):
        head = (f"POST /v1/registrations HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; "
                f"boundary={BOUNDARY}\r\nContent-Length: {value}").encode()
        status, answer, payload = _raw(port, head, body)
        ok = status == 400 and PROBLEM.encode() in answer and json.loads(payload).get("field") == "Content-Length"
        out.append((f"Content-Length {value!r}", "" if ok else f"{status} {payload[:80]!r}"))
    status, answer, payload = _raw(port, b"GET /healthz HTTP/1.1\r\nHost: x\r\nIdempotency-Key: a\x00b")
    out.append(("NUL in a header value", "" if status == 400 and PROBLEM.encode() in answer else f"{status} {payload[:80]!r}"))
    return out


def _try(client: httpx.Client, method: str, path: str, kwargs: dict, status: int, field: str | None) -> tuple[str, float]:
    """One case: what went wrong ("" if nothing) and how long the answer took."""
    started = time.perf_counter()
    try:
        response = client.request(method, path, **kwargs)
    except httpx.HTTPError as exc:
        return f"no answer ({type(exc).__name__})", time.perf_counter() - started
    seconds = time.perf_counter() - started
    body = response.json() if response.headers.get("content-type", "").startswith(PROBLEM) else None
    if response.status_code != status or body is None or (field is not None and body.get("field") != field):
        return (f"{response.status_code} {response.headers.get('content-type', '')[:24]} field "
                f"{None if body is None else body.get('field')!r}: {response.text[:120]!r}"), seconds
    return ("" if seconds < 30 else f"answered after {seconds:.0f} s"), seconds


def test_request_parsing_corpus(parsing_server, case, tmp_path):
    srv = parsing_server
    cases = _parsing_cases(case, srv.job_id)  # built before the poller starts
    poller = HealthPoller(srv.port, tmp_path / "stop")
    failures, rows = [], []
    try:
        with httpx.Client(base_url=srv.url, timeout=120) as client:
            jobs_before = len(client.get("/v1/registrations", params={"limit": 100}).json()["items"])
            for name, method, path, kwargs, status, field in cases:
                wrong, seconds = _try(client, method, path, kwargs, status, field)
                rows.append(f"  {name}: {wrong or 'ok'} ({seconds:.2f} s)")
                if wrong:
                    failures.append((name, wrong))
            for name, wrong in _framing_cases(srv.port):
                rows.append(f"  {name}: {wrong or 'ok'}")
                if wrong:
                    failures.append((name, wrong))
            tried = len(rows)
            jobs_after = len(client.get("/v1/registrations", params={"limit": 100}).json()["items"])
    finally:
        stall = poller.stop()
    print("\n".join(rows))
    print(f"request-parsing corpus: {tried} inputs, {len(failures)} wrong; longest /healthz answer "
          f"{stall['worst_s']:.3f} s over {stall['polls']} polls")
    assert not failures, failures
    assert jobs_after == jobs_before  # nothing refused was accepted (the cut body used to make a job)
    assert stall["polls"] > 10 and stall["worst_s"] < allowed(STALL_LIMIT_S), stall
    assert "Traceback" not in srv.logs()
