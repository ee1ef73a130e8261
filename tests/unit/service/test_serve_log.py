"""The log of a real ``dsareg serve`` (service/cli/subcommands.py, service/api/lifespan.py) from start to a clean
stop by SIGTERM to its process group: every warning once (issue 43 item 7: two warnings were logged twice), no
Alembic set-up lines on a fresh data dir (issue 44 item 13), nothing that reads as a fault on a normal stop
(issue 44 item 6)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import httpx

from tests.support.servers import free_port

ROOT = Path(__file__).resolve().parents[3]


def _serve_then_stop(tmp_path, *args: str) -> str:
    """The whole stderr + stdout of ``dsareg serve ARGS`` (no workers) started, answered once, and stopped."""
    port = free_port()
    env = {**os.environ, "DSAREG_API_KEYS": "", "DSAREG_API_KEY_HASHES": "", "PYTHONUNBUFFERED": "1"}
    log_path = tmp_path / "serve.log"
    with open(log_path, "wb") as log:
        server = subprocess.Popen([sys.executable, "-m", "dsareg_engine.cli", "serve", "--port", str(port), "--workers", "0",
                                   "--data-dir", str(tmp_path / "data"), *args], cwd=ROOT, env=env, stdout=log,
                                  stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline, ready = time.monotonic() + 120, False
            while time.monotonic() < deadline and server.poll() is None and not ready:
                try:
                    ready = httpx.get(f"http://127.0.0.1:{port}/ui/", timeout=2).status_code == 200
                except httpx.HTTPError:
                    time.sleep(0.2)
            assert ready, log_path.read_text(errors="replace")[-3000:]
            time.sleep(1.5)  # the validator's start and the watchdog's first looks
            os.killpg(server.pid, signal.SIGTERM)  # as systemd or `kill -- -PGID` (uvicorn re-raises it: -15)
            assert server.wait(60) in (0, -signal.SIGTERM), log_path.read_text(errors="replace")[-3000:]
        finally:
            if server.poll() is None:
                os.killpg(server.pid, signal.SIGKILL)
                server.wait(10)
    return log_path.read_text(errors="replace")


def _messages(text: str, level: str) -> list[str]:
    """The messages of ``level`` lines, without their time stamps."""
    return [re.sub(r"^\S+ \S+ ", "", line) for line in text.splitlines() if f" {level} " in line]


def test_a_start_and_clean_stop_log_each_warning_once(tmp_path):
    text = _serve_then_stop(tmp_path, "--host", "0.0.0.0")
    assert "Finished server process" in text, text[-3000:]
    warnings = _messages(text, "WARNING")
    assert [line for line, seen in Counter(warnings).items() if seen > 1] == [], warnings
    expected = ("WARNING dsareg.service: no API keys configured: authentication is off and the service listens on "
                "127.0.0.1 only (not 0.0.0.0: serving other machines needs API keys)")
    assert warnings == [expected], warnings
    assert not _messages(text, "ERROR") and "validator replaced" not in text, text[-3000:]
    assert "alembic" not in text.lower(), text[-3000:]  # a fresh data dir: the tables made, no set-up lines
