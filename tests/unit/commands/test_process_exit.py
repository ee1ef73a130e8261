"""A process's exit leaves its objects to the operating system instead of walking them (process_exit)."""

import argparse
import subprocess
import sys
from pathlib import Path

from dsareg_engine import cli
from dsareg_engine.commands import process_exit

REPO = Path(__file__).resolve().parents[3]
CHILD = """
import gc, os, sys
from dsareg_engine.commands.process_exit import skip_exit_collections
if sys.argv[1] == "skip":
    skip_exit_collections()
    skip_exit_collections()
held = [[n] for n in range(50_000)]
def report(phase, info):
    if phase == "start":
        os.write(1, f"{info['generation']} {gc.get_freeze_count()}\\n".encode())
gc.callbacks.append(report)
"""


def _final_collections(mode: str) -> list[tuple[int, int]]:
    """(generation, objects frozen) of each collection the child runs while it exits."""
    done = subprocess.run([sys.executable, "-c", CHILD, mode], capture_output=True, text=True, cwd=REPO, timeout=60,
                          check=True)
    return [tuple(map(int, line.split())) for line in done.stdout.splitlines()]


def test_the_exit_collections_find_the_heap_frozen():
    plain, skipped = _final_collections("plain"), _final_collections("skip")
    assert plain and all(frozen == 0 for _, frozen in plain), plain  # the interpreter walks every object
    assert skipped and all(frozen > 50_000 for _, frozen in skipped), skipped  # nothing left to walk


def test_every_command_of_the_command_line_exits_that_way(monkeypatch):
    registered = []
    monkeypatch.setattr(process_exit, "_registered", False)
    monkeypatch.setattr(process_exit.atexit, "register", registered.append)
    assert cli.run_parsed(argparse.Namespace(func=lambda args: 0)) == 0
    assert registered == [process_exit.gc.freeze]
    process_exit.skip_exit_collections()
    assert len(registered) == 1  # once per process


def test_an_input_validator_exits_that_way():
    """A server's stop waits for its validators' (and workers') exit."""
    probe = ("import signal; from service.intake.validator_process import _become_validator; _become_validator(None); "
             "from dsareg_engine.commands import process_exit; print(process_exit._registered)")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=REPO, timeout=60, check=True)
    assert done.stdout.split() == ["True"], done.stdout + done.stderr
