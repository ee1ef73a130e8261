"""The kernel compile lock: one compiler per group, and a frozen or killed holder never blocks a job for long."""

import logging
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from dsareg_engine.kernels import compile_lock

# The lock module alone, from its file (so the same install key and lock path): the package's __init__ loads torch and
# the renderer, which holding a lock does not need (1.2 -> 0.35 CPU-s a holder, load 7).
HOLDER = textwrap.dedent("""
    import importlib.util, sys, time
    spec = importlib.util.spec_from_file_location("dsareg_engine.kernels.compile_lock", sys.argv[3])
    compile_lock = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(compile_lock)
    with compile_lock.compiling_group(sys.argv[1]):
        print("held", flush=True)
        time.sleep(float(sys.argv[2]))
""")


@pytest.fixture
def group(request):
    """A group name of this test alone (the lock file is per install, group and thread budget)."""
    name = f"test-{os.getpid()}-{request.node.name}"
    yield name
    compile_lock.lock_path(name).unlink(missing_ok=True)


def _holder(group: str, seconds: float) -> subprocess.Popen:
    """A real process holding the group's lock (as the background compile helper does) for ``seconds``."""
    process = subprocess.Popen([sys.executable, "-c", HOLDER, group, str(seconds), compile_lock.__file__],
                               stdout=subprocess.PIPE, text=True,
                               env={**os.environ, "NUMBA_NUM_THREADS": str(compile_lock._threads())})
    assert process.stdout.readline().strip() == "held"
    return process


def _end(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGCONT)
        process.kill()
    process.wait(timeout=10)


def test_a_waiter_goes_on_when_the_holder_finishes(group):
    holder = _holder(group, 1.0)
    try:
        started = time.monotonic()
        compile_lock.wait_for_group(group, wait_limit_s=30.0)
        waited = time.monotonic() - started
        assert 0.5 < waited < 10.0  # it did wait for the compile, and no longer than it took
    finally:
        _end(holder)


def test_a_frozen_holder_blocks_a_waiter_only_up_to_the_limit(group, caplog):
    holder = _holder(group, 600.0)
    holder.send_signal(signal.SIGSTOP)  # frozen mid-compile: it keeps the lock
    try:
        started = time.monotonic()
        with caplog.at_level(logging.WARNING, logger=compile_lock.__name__):
            compile_lock.wait_for_group(group, wait_limit_s=1.5)
        waited = time.monotonic() - started
        assert 1.4 < waited < 5.0
        assert any("frozen?" in record.getMessage() and group in record.getMessage() for record in caplog.records)
        started = time.monotonic()
        compile_lock.wait_for_group(group, wait_limit_s=1.5)  # once per process: the next call does not wait again
        assert time.monotonic() - started < 0.1
        assert holder.poll() is None  # the frozen holder was left alone, still frozen, nothing orphaned by the waiter
    finally:
        _end(holder)


def test_a_killed_holder_releases_the_lock_at_once(group):
    holder = _holder(group, 600.0)
    holder.send_signal(signal.SIGSTOP)
    holder.kill()  # killed while frozen, mid-compile
    holder.wait(timeout=10)
    started = time.monotonic()
    compile_lock.wait_for_group(group, wait_limit_s=30.0)
    assert time.monotonic() - started < 1.0


def test_a_second_compiler_waits_for_the_first_and_is_not_reported_as_frozen(group, caplog):
    holder = _holder(group, 1.0)
    try:
        with caplog.at_level(logging.WARNING, logger=compile_lock.__name__):
            started = time.monotonic()
            with compile_lock.compiling_group(group):
                waited = time.monotonic() - started
        assert 0.5 < waited < 10.0
        assert not caplog.records
    finally:
        _end(holder)
