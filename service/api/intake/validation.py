"""Full input validation before a job is accepted, isolated from the API process.

Why not validate in the API process: readers of meshes, DICOM and volumes are large
C-backed libraries; a hostile or broken file can take seconds of CPU, gigabytes of
memory, or crash the interpreter. So the API hands *stored blob paths* (never the
bytes) to a small pool of long-lived ``spawn`` processes that run exactly the loader
the worker will run (:func:`service.engine_adapter.load_job_case`: the same
``stored_case_files`` and the engine's ``load_case_files``), each with

* a wall-clock limit (``validation_timeout_seconds``): past it the process is killed
  and replaced, and the request gets a 422 naming the time limit;
* an address-space limit (``validation_memory_mb`` on top of what the warmed-up
  process already uses): a decompression bomb fails with MemoryError → 422;
* crash containment: a dead process is replaced, the request gets a 422.

The processes import the engine once at start (warm), so a validation costs only the
parse itself. The worker parses again from the same blobs (the ``Case`` is not
shipped between processes), which costs little next to a registration.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import multiprocessing as mp
import os
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

log = logging.getLogger("dsareg.service.validation")


def _set_memory_limit(extra_mb: int) -> None:
    if extra_mb <= 0:
        return
    try:
        import resource

        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[0])
        current = pages * os.sysconf("SC_PAGE_SIZE")
        limit = current + extra_mb * 1024 * 1024
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    except Exception:  # noqa: BLE001, S110 - best effort on platforms without it
        pass


def _validator_main(conn: Connection, memory_mb: int, threads: int, parent_pid: int | None = None) -> None:
    """Child loop: one request at a time ``{"inputs", "geometry", "segmentation", "blob_root", "reading"}``."""
    import signal

    from ...jobs.procwatch import die_with_parent, set_process_name

    set_process_name("dsareg-validate")

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if parent_pid is not None:  # a parse in progress must not outlive a SIGKILLed server
        die_with_parent(parent_pid, signal.SIGKILL)
    engine_ok = True
    # parsing needs no torch (the engine imports it only to register); should a parser import it,
    # its thread pool reads this at start-up
    os.environ["OMP_NUM_THREADS"] = str(max(1, threads or 1))
    try:
        from ...engine_adapter import engine

        engine.preload_case_loading()
        engine.warm_up_parsers()
    except Exception:  # noqa: BLE001
        engine_ok = False
    _set_memory_limit(memory_mb)
    from ...storage.blobs import BlobStore
    from ...engine_adapter import case_summary, engine, load_job_case
    from ...storage.store import InputFile

    conn.send({"ready": True, "engine": engine_ok})
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        if not engine_ok:
            try:
                engine.preload_case_loading()
                engine_ok = True
            except Exception:  # noqa: BLE001
                conn.send({"ok": False, "unavailable": True})
                continue
        if request.get("require_cuda") and not _cuda_available():
            conn.send({"ok": False, "message": "CUDA is not available on this server", "field": "options.device",
                       "accepted": "auto or cpu"})
            continue
        try:
            blobs = BlobStore(request["blob_root"])
            inputs = [InputFile(**item) for item in request["inputs"]]
            case = load_job_case(inputs, request["geometry"], request["segmentation"], blobs.read, request.get("limits"),
                                 request.get("reading"))
            conn.send({"ok": True, "summary": case_summary(case)})
        except engine.DsaregInputError as exc:
            conn.send({"ok": False, "message": exc.message, "field": exc.field, "accepted": exc.accepted})
        except MemoryError:
            conn.send({"ok": False, "message": f"decoding needs more than the {memory_mb} MB this server allows "
                                               "for parsing one submission", "field": _largest_input(request),
                       "accepted": "smaller inputs", "recycle": True})
        except Exception as exc:  # noqa: BLE001 - reported as a generic input problem, logged by type only
            conn.send({"ok": False, "internal": True, "kind": type(exc).__name__})


def _largest_input(request: dict) -> str | None:
    """The input that most likely exhausted the memory limit: the largest decoded image, else the largest file."""
    from ...storage.blobs import BlobStore
    from ...budgets import image_decoded_bytes

    blobs = BlobStore(request["blob_root"])
    best, best_size = None, -1
    for item in request["inputs"]:
        size = item["size"]
        if item["role"] in ("ap", "lat"):
            try:
                size = image_decoded_bytes(blobs.read(item["sha256"])) or size
            except Exception:  # noqa: BLE001, S110 - informative only
                pass
        if size > best_size:
            best, best_size = item["role"], size
    return best


def _cuda_available() -> bool:
    try:
        import torch

        return bool(torch.cuda.is_available())
    except Exception:  # noqa: BLE001
        return False


@dataclass
class ValidationOutcome:
    ok: bool
    summary: dict[str, Any] | None = None
    message: str | None = None
    field: str | None = None
    accepted: str | None = None
    unavailable: bool = False
    internal: bool = False


class _Slot:
    def __init__(self, ctx: Any, memory_mb: int, threads: int):
        self.ctx = ctx
        self.memory_mb = memory_mb
        self.threads = threads
        self.process: Any = None
        self.conn: Connection | None = None
        self.ready = False
        self.lock = threading.Lock()  # the pipe is used by one request thread and by readiness checks

    def start(self) -> None:
        parent, child = self.ctx.Pipe(duplex=True)
        self.process = self.ctx.Process(
            target=_validator_main, args=(child, self.memory_mb, self.threads, os.getpid()), name="dsareg-validator",
            daemon=True
        )
        self.process.start()
        child.close()
        self.conn = parent
        self.ready = False

    def wait_ready(self, timeout: float) -> bool:
        if self.ready:
            return True
        assert self.conn is not None
        if self.conn.poll(timeout):
            try:
                self.conn.recv()
                self.ready = True
            except (EOFError, OSError):
                return False
        return self.ready

    def kill(self) -> None:
        if self.process is not None and self.process.is_alive():
            self.process.kill()
            self.process.join(5)
        if self.conn is not None:
            self.conn.close()
        self.process = None
        self.conn = None
        self.ready = False

    def check_ready(self) -> bool:
        """Non-blocking: has the process finished its start-up (imports, warm-up)?"""
        if self.ready or not self.lock.acquire(blocking=False):
            return self.ready  # busy with a request: it was ready
        try:
            return self.conn is not None and self.wait_ready(0)
        finally:
            self.lock.release()

    def call(self, request: dict, timeout: float) -> dict | None:
        with self.lock:
            return self._call(request, timeout)

    def _call(self, request: dict, timeout: float) -> dict | None:
        """Blocking; ``None`` on timeout or crash (the process is then replaced)."""
        deadline = time.monotonic() + timeout
        try:
            if self.process is None or not self.process.is_alive():
                self.kill()
                self.start()
            if not self.wait_ready(max(0.1, deadline - time.monotonic()) + 120.0):
                raise TimeoutError
            assert self.conn is not None
            self.conn.send(request)
            if not self.conn.poll(max(0.0, deadline - time.monotonic())):
                raise TimeoutError
            reply = self.conn.recv()
            if reply.get("recycle"):  # memory the allocator keeps after a MemoryError: start afresh
                self.kill()
                self.start()
            return reply
        except (TimeoutError, EOFError, OSError, BrokenPipeError):
            self.kill()
            self.start()
            return None


class ValidatorPool:
    """Successful outcomes are cached by request content (inputs are content-addressed, so
    the same hashes + geometry + segmentation + limits parse the same way)."""

    CACHE_SIZE = 512

    def __init__(self, processes: int, timeout_seconds: float, memory_mb: int, threads: int = 1):
        self.ctx = mp.get_context("spawn")
        self.timeout = timeout_seconds
        self.slots = [_Slot(self.ctx, memory_mb, threads) for _ in range(processes)]
        self._free: asyncio.Queue[_Slot] | None = None
        self._cache: OrderedDict[str, ValidationOutcome] = OrderedDict()

    @staticmethod
    def _cache_key(request: dict) -> str:
        fields = {k: request.get(k) for k in ("inputs", "geometry", "segmentation", "limits", "require_cuda", "reading")}
        return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()

    def start(self) -> None:
        for slot in self.slots:
            slot.start()

    def _queue(self) -> asyncio.Queue:
        if self._free is None:
            self._free = asyncio.Queue()
            for slot in self.slots:
                self._free.put_nowait(slot)
        return self._free

    async def validate(self, request: dict) -> ValidationOutcome:
        key = self._cache_key(request)
        cached = self._cache.get(key)
        if cached is not None:
            self._cache.move_to_end(key)
            return cached
        outcome = await self._validate(request)
        if outcome.ok:
            self._cache[key] = outcome
            while len(self._cache) > self.CACHE_SIZE:
                self._cache.popitem(last=False)
        return outcome

    async def _validate(self, request: dict) -> ValidationOutcome:
        free = self._queue()
        slot = await free.get()
        try:
            started = time.monotonic()
            reply = await asyncio.to_thread(slot.call, request, self.timeout)
            log.info("validation took %.2f s", time.monotonic() - started)
        finally:
            free.put_nowait(slot)
        if reply is None:
            return ValidationOutcome(
                ok=False, message=f"the inputs could not be parsed within {self.timeout:g} s (or crashed the parser)",
                accepted="well-formed mesh/volume and image files",
            )
        if reply.get("ok"):
            return ValidationOutcome(ok=True, summary=reply.get("summary") or {})
        if reply.get("unavailable"):
            return ValidationOutcome(ok=False, unavailable=True)
        if reply.get("internal"):
            log.warning("validation raised %s", reply.get("kind"))
            return ValidationOutcome(ok=False, internal=True, message="the inputs could not be read",
                                     accepted="well-formed mesh/volume and image files")
        return ValidationOutcome(ok=False, message=reply.get("message"), field=reply.get("field"), accepted=reply.get("accepted"))

    def ready(self) -> bool:
        """Every parser process started and warmed up (so a submission is not kept waiting on imports)."""
        return all(slot.check_ready() for slot in self.slots)

    def alive(self) -> bool:
        return any(s.process is not None and s.process.is_alive() for s in self.slots)

    def stop(self) -> None:
        for slot in self.slots:
            try:
                if slot.conn is not None:
                    slot.conn.send(None)
            except (OSError, BrokenPipeError):
                pass
        for slot in self.slots:
            if slot.process is not None:
                slot.process.join(2)
            slot.kill()
