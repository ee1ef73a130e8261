"""Invariants every injected fault must keep, and process-tree helpers (Linux /proc)."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import httpx
from tests.support.service_testkit import ExampleCase, submit

NEXT_POST_SECONDS = 1.0
FINAL = ("succeeded", "failed", "canceled")


def _stat(pid: int) -> tuple[str, int] | None:
    """(state, ppid) of a process, None when it does not exist."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text.rsplit(")", 1)[1].split()
    return fields[0], int(fields[1])


def descendants(pid: int) -> set[int]:
    """Every live process below ``pid`` (children, grandchildren…)."""
    parents: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            info = _stat(int(entry))
            if info is not None:
                parents.setdefault(info[1], []).append(int(entry))
    found: set[int] = set()
    todo = [pid]
    while todo:
        for child in parents.get(todo.pop(), []):
            if child not in found:
                found.add(child)
                todo.append(child)
    return found


def running(pids: Iterable[int]) -> set[int]:
    """The pids that still exist and are not zombies."""
    alive = set()
    for pid in pids:
        info = _stat(pid)
        if info is not None and info[0] != "Z":
            alive.add(pid)
    return alive


def wait_gone(pids: Iterable[int], timeout: float) -> set[int]:
    """Wait until none of ``pids`` runs; returns those still running at the deadline."""
    deadline = time.monotonic() + timeout
    left = running(pids)
    while left and time.monotonic() < deadline:
        time.sleep(0.2)
        left = running(left)
    return left


def timed_post(client: httpx.Client, case: ExampleCase, options: dict) -> tuple[httpx.Response, float]:
    started = time.monotonic()
    response = submit(client, case, options)
    return response, time.monotonic() - started


def settle(events_of: Callable[[str], list[str]], status_of: Callable[[str], str], ids: list[str],
           timeout: float) -> dict[str, str]:
    """Wait for every job to finish; returns ``{id: status}`` (non-final ones are stuck)."""
    deadline = time.monotonic() + timeout
    statuses: dict[str, str] = {}
    while time.monotonic() < deadline:
        statuses = {job_id: status_of(job_id) for job_id in ids}
        if all(s in FINAL for s in statuses.values()):
            break
        time.sleep(0.3)
    return statuses


def tally(ids: list[str], statuses: dict[str, str], events_of: Callable[[str], list[str]]) -> dict[str, int]:
    """Jobs lost (gone from the store), stuck (not finished), run twice to completion."""
    return {
        "lost": sum(1 for job_id in ids if statuses.get(job_id) in (None, "missing")),
        "stuck": sum(1 for job_id in ids if statuses.get(job_id) not in (*FINAL, None, "missing")),
        "duplicated": sum(1 for job_id in ids if sum(e in FINAL for e in events_of(job_id)) > 1),
        "not_succeeded": sum(1 for job_id in ids if statuses.get(job_id) != "succeeded"),
    }


def raw_connection(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def partial_multipart(port: int, declared: int, sent: bytes) -> socket.socket:
    """A POST that declares ``declared`` body bytes and sends only ``sent`` (left open)."""
    sock = raw_connection(port)
    head = (f"POST /v1/registrations HTTP/1.1\r\nHost: 127.0.0.1\r\n"
            f"Content-Type: multipart/form-data; boundary=XyZ\r\nContent-Length: {declared}\r\n\r\n").encode()
    sock.sendall(head + sent)
    return sock


MULTIPART_START = (b"--XyZ\r\nContent-Disposition: form-data; name=\"mesh\"; filename=\"m.obj\"\r\n"
                   b"Content-Type: application/octet-stream\r\n\r\n")
