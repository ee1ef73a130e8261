"""Submission limits (service/budgets.py) and the process links (service/jobs/procwatch.py), in-process."""

from __future__ import annotations

import io
import multiprocessing as mp
import os
import signal
import struct
import subprocess
import sys
import time
import zlib

import pytest

from service.engine_adapter import check_image_budget
from service.budgets import (
    MAX_JSON_DEPTH,
    image_decoded_bytes,
    job_cost,
    json_depth,
    parse_json_part,
)
from service.intake.refusals import InvalidInput


def test_json_depth_ignores_brackets_in_strings():
    assert json_depth('{"a": [1, {"b": "[[[[{{{{"}]}') == 3
    assert json_depth("[" * 10_000 + "]" * 10_000) == 10_000


@pytest.mark.parametrize("text, needle", [
    ('{"a": ' + "[" * 10_000 + "]" * 10_000 + "}", "nested"),
    ('{"a": ' + "9" * 5_000 + "}", "characters"),
    ('{"a": 1e999}', "out of range"),
    ('{"a": NaN}', "NaN"),
    ('{"a": -Infinity}', "Infinity"),
    ("[1, 2]", "object"),
    ("{broken", "not valid JSON"),
])
def test_hostile_json_is_a_422_naming_the_part(text, needle):
    with pytest.raises(InvalidInput) as caught:
        parse_json_part(text, "geometry")
    assert caught.value.field == "geometry"
    assert needle in caught.value.detail


def test_ordinary_json_parses():
    data = parse_json_part('{"views": {"ap": {"sid_mm": 1200.5, "size": [1024, 1024]}}, "n": -3}', "geometry")
    assert data["views"]["ap"]["sid_mm"] == 1200.5 and data["n"] == -3
    assert MAX_JSON_DEPTH >= 8


def test_job_cost_scales_with_working_size():
    class Options:
        starts, max_iterations, working_size_px = 64, 300, 2000

    assert job_cost(Options, [(1000, 500), (1000, 1000)]) == pytest.approx(64 * 300 * (2000 * 1000 + 2000 * 2000))
    Options.working_size_px = 0
    assert job_cost(Options, [(100, 100)]) == 64 * 300 * 10_000


def _png_header_only(width: int, height: int, bits: int, color: int) -> bytes:
    header = struct.pack(">IIBBBBB", width, height, bits, color, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + header
            + struct.pack(">I", zlib.crc32(b"IHDR" + header)))


def test_decoded_bytes_from_the_header():
    from PIL import Image

    from dsareg_engine.errors import DsaregInputError

    assert image_decoded_bytes(_png_header_only(7900, 7900, 16, 6)) == 7900 * 7900 * 4 * 2
    assert image_decoded_bytes(_png_header_only(100, 50, 8, 0)) == 5000
    buffer = io.BytesIO()
    Image.new("RGB", (300, 200)).save(buffer, format="TIFF")
    assert image_decoded_bytes(buffer.getvalue()) == 300 * 200 * 3
    with pytest.raises(DsaregInputError) as caught:
        check_image_budget(_png_header_only(7900, 7900, 16, 6), "ap", 64 << 20)
    assert caught.value.field == "ap" and "MiB" in caught.value.message
    check_image_budget(_png_header_only(1024, 1024, 16, 0), "ap", 64 << 20)


def _sleeper(link, parent_pid):  # spawn target: a worker-like child following the server's pipe
    from service.jobs.procwatch import WorkerControl, die_with_parent

    control = WorkerControl()
    signal.signal(signal.SIGTERM, control.request_stop)
    die_with_parent(parent_pid)
    control.watch(link)
    while not control.stop.is_set():
        control.wait_for_work(0.1)


def test_closing_the_wake_link_stops_the_child():
    from service.jobs.procwatch import WakeLink

    ctx = mp.get_context("spawn")
    link = WakeLink(ctx)
    child = ctx.Process(target=_sleeper, args=(link.child_end(), os.getpid()))
    child.start()
    link.started()
    for _ in range(100_000):  # far more than a pipe buffer: notify never blocks
        link.notify()
    link.close()
    child.join(30)
    assert child.exitcode == 0


def _state(pid: int) -> str | None:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return None


MIDDLE = """
import multiprocessing as mp, os, sys, time
sys.path.insert(0, {here!r})
from test_service_limits import _sleeper
from service.jobs.procwatch import WakeLink
if __name__ == "__main__":
    ctx = mp.get_context("spawn")
    link = WakeLink(ctx)
    p = ctx.Process(target=_sleeper, args=(link.child_end(), os.getpid()))
    p.start()
    link.started()
    print(p.pid, flush=True)
    time.sleep(600)
"""


def test_child_dies_with_a_sigkilled_parent(tmp_path):
    """A middle process starts a linked child and is SIGKILLed: the child must go too."""
    script = tmp_path / "middle.py"
    script.write_text(MIDDLE.format(here=os.path.dirname(__file__)))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")])}
    middle = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, env=env, text=True)
    child_pid = int(middle.stdout.readline())
    assert _state(child_pid) not in (None, "Z")
    middle.kill()
    middle.wait(10)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and _state(child_pid) not in (None, "Z"):
        time.sleep(0.1)
    assert _state(child_pid) in (None, "Z")
