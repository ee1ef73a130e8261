"""The command line and the API process stay light: building the parser, an argument error and
``create_app`` import neither torch nor numba, ``dsareg --help`` needs well under a second of CPU, and
an idle ``dsareg serve`` stays under 150 MB resident (dsareg_engine/cli.py, dsareg_engine/commands/)."""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.support.servers import free_port

REPO = Path(__file__).resolve().parents[3]
HEAVY = ("torch", "numba")
HELP_CPU_SECONDS = 1.0
IDLE_RSS_MB = 170
"""150 until round 13; python-gdcm (the XA reader's decoder for JPEG extended streams libjpeg refuses, issue 40) is
loaded by pydicom's decoder registry when pydicom is imported: +17 MB measured (158 MB idle on 2026-12-06)."""


def _python(code: str, *extra_env: tuple[str, str]) -> dict:
    """Run ``code`` in a fresh interpreter; it prints a JSON object on its last line."""
    env = {**os.environ, **dict(extra_env)}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO,
                          env=env, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


LOADED = f"print(__import__('json').dumps({{'loaded': [m for m in {HEAVY!r} if m in __import__('sys').modules]}}))"


def test_building_the_parser_imports_no_engine():
    assert _python("from dsareg_engine.cli import build_parser\nbuild_parser()\n" + LOADED)["loaded"] == []


@pytest.mark.parametrize("argv", [["register", "--bogus"], ["render"],
                                  ["submit", "--server"], ["serve", "--port", "x"]])
def test_an_argument_error_imports_no_engine(argv):
    code = (f"from dsareg_engine.cli import main\ntry:\n    main({argv!r})\nexcept SystemExit as exc:\n"
            "    assert exc.code == 2\n") + LOADED
    assert _python(code)["loaded"] == []


def test_create_app_imports_no_engine(tmp_path):
    code = (f"from service.app import create_app\nfrom service.settings import load_settings\n"
            f"create_app(load_settings(None, data_dir={str(tmp_path)!r}))\n" + LOADED)
    assert _python(code)["loaded"] == []


def test_dsareg_help_takes_under_a_second_of_cpu():
    dsareg = shutil.which("dsareg", path=str(Path(sys.executable).parent)) or "dsareg"
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    proc = subprocess.run([dsareg, "--help"], capture_output=True, text=True, timeout=60, check=False)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    print(f"dsareg --help: {cpu:.2f} s CPU, {wall:.2f} s wall")
    assert proc.returncode == 0 and "serve" in proc.stdout and "register" in proc.stdout
    assert cpu < HELP_CPU_SECONDS, (cpu, wall)  # CPU, not wall: the test machine is shared


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def test_dsareg_serve_idle_rss_is_small(tmp_path):
    dsareg = shutil.which("dsareg", path=str(Path(sys.executable).parent)) or "dsareg"
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("DSAREG_")}
    log = open(tmp_path / "serve.log", "wb")  # noqa: SIM115 - closed below
    proc = subprocess.Popen([dsareg, "serve", "--port", str(port), "--data-dir", str(tmp_path / "data"),
                             "--workers", "0"], env=env, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            assert proc.poll() is None, (tmp_path / "serve.log").read_text()[-2000:]
            try:
                if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.2)
        time.sleep(1.0)
        rss = _rss_mb(proc.pid)
        print(f"dsareg serve idle RSS {rss:.0f} MB")
        assert rss <= IDLE_RSS_MB, rss
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
