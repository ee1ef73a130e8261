"""HTTP read deadlines and the connection bound (service/api/httpdeadlines.py) on a real ``dsareg serve``.

The API alone (no workers: nothing here runs a job), with short deadlines so that the test is quick: a head that
never completes is answered 408 and closed, a body that stalls is a 408 problem, past the connection bound a
request is a 503 at once, and once the late connections are closed the API answers again.
"""

from __future__ import annotations

import time

from tests.support.faults_kit import MULTIPART_START, partial_multipart, raw_connection
from tests.support.service_testkit import Server
from tests.support.time_bounds import allowed

HEAD_S, BODY_S, MAX_CONNECTIONS = 1.5, 1.5, 8


def _answer(sock, timeout_s: float) -> tuple[bytes, float]:
    """Everything the server sends until it closes the connection, and when it closed (seconds from now)."""
    started = time.monotonic()
    sock.settimeout(timeout_s)
    data = b""
    while True:
        chunk = sock.recv(65536)
        if not chunk:
            return data, time.monotonic() - started
        data += chunk


def test_late_heads_and_stalled_bodies_are_408_and_connections_are_bounded(tmp_path):
    srv = Server(tmp_path / "data", workers=0, env={
        "DSAREG_HTTP_HEADER_TIMEOUT_SECONDS": str(HEAD_S), "DSAREG_HTTP_BODY_IDLE_TIMEOUT_SECONDS": str(BODY_S),
        "DSAREG_HTTP_MAX_CONNECTIONS": str(MAX_CONNECTIONS)}).start(wait_ready=False)
    try:
        trickler = raw_connection(srv.port)
        trickler.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # and the end of the head never comes
        stalled = partial_multipart(srv.port, 400_000_000, MULTIPART_START + b"v 0 0 0\n" * 100)  # 1 kB of 400 MB
        head, head_s = _answer(trickler, HEAD_S + 10)
        body, body_s = _answer(stalled, BODY_S + 10)
        assert head.startswith(b"HTTP/1.1 408") and head_s <= HEAD_S + allowed(1.0), (head, head_s)
        assert body.startswith(b"HTTP/1.1 408") and b"application/problem+json" in body, body
        assert b"DSAREG_HTTP_BODY_IDLE_TIMEOUT_SECONDS" in body and body_s <= BODY_S + allowed(1.0), body_s
        idle = [raw_connection(srv.port) for _ in range(MAX_CONNECTIONS)]  # connected, nothing sent
        time.sleep(0.2)
        with srv.client() as client:
            started = time.monotonic()
            refused = client.get("/healthz", timeout=5)
            assert refused.status_code == 503 and time.monotonic() - started < 1.0, refused.status_code
        closed = [_answer(sock, HEAD_S + 10)[1] for sock in idle]  # the head deadline closes each of them
        assert max(closed) <= HEAD_S + 1.0, closed
        with srv.client() as client:
            assert client.get("/healthz", timeout=5).status_code == 200
        assert " ERROR " not in srv.logs(), srv.logs()[-3000:]
    finally:
        srv.stop()
