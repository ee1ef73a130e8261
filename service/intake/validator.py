"""Full input validation before a job is accepted, isolated from the server's process.

Why not validate in the server's process: readers of meshes, DICOM and volumes are large
C-backed libraries; a hostile or broken file can take seconds of CPU, gigabytes of
memory, or crash the interpreter. So the intake hands *stored blob paths* (never the
bytes) to a small pool of long-lived ``spawn`` processes that run exactly the loader
the worker will run (:func:`service.engine_adapter.load_job_case`: the same
``stored_case_files`` and the engine's ``load_case_files``), each with

* a wall-clock limit (``validation_timeout_seconds``): past it the process is killed
  and replaced, and the submission is refused naming the time limit (an HTTP 422);
* an address-space limit (``validation_memory_mb`` on top of what the warmed-up
  process already uses): a decompression bomb fails with MemoryError, refused alike;
* a larger allowance for a submission whose volume needs it, sized from the volume's header before any voxel is
  decoded and capped by ``validation_volume_memory_mb`` / ``validation_volume_timeout_seconds``
  (:mod:`.allowance`): the process announces it (``{"allowance"}``), the request waits that long (its time counted
  in the process's CPU seconds, its wall-clock bounded by the ceiling), the process is replaced after it; the model
  it made is kept in the model cache for the worker;
* crash containment: a dead or frozen process is replaced by a warm spare within
  ``WATCH_SECONDS`` and the request is sent once more to it (see :class:`ValidatorPool`).

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

from .allowance import Allowance, AllowancePolicy
from .spawner import Spawner
from .validator_process import largest_input, validator_main

log = logging.getLogger("dsareg.service.validation")


@dataclass
class ValidationOutcome:
    ok: bool
    summary: dict[str, Any] | None = None
    message: str | None = None
    field: str | None = None
    accepted: str | None = None
    unavailable: bool = False
    internal: bool = False
    busy: bool = False  # no validator could take the request now (the intake answers Overloaded)


CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
WATCH_SECONDS = 0.2  # how often a waiting request (and the watchdog) looks at its validator's process
WATCHDOG_SECONDS = 0.5


def process_state(pid: int) -> str | None:
    """The kernel's state letter of ``pid`` (``R``, ``S``, ``T`` stopped…), None when it is gone (Linux)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return None


def process_cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of ``pid`` (its own, not its children's), None when it is gone (Linux)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS
    except (OSError, IndexError, ValueError):
        return None


class _Slot:
    """One validator process and its pipe (the process started on ``spawner``'s thread)."""

    def __init__(self, ctx: Any, policy: AllowancePolicy, threads: int, spawner: Spawner):
        self.ctx = ctx
        self.spawner = spawner
        self.policy = policy
        self.memory_mb = policy.memory_mb
        self.threads = threads
        self.process: Any = None
        self.conn: Connection | None = None
        self.ready = False
        self.lock = threading.Lock()  # the pipe is used by one request thread and by readiness checks
        self.waited_s = 0.0  # the last call's wait for the process's start-up (imports, parser warm-up)
        self.allowance = policy.base()  # the last call's (a large volume's is announced by the process)
        self.cpu_budget: tuple[float, float] | None = None  # (the process's CPU s when given, the CPU s allowed)
        self.cpu_used: float | None = None  # the CPU s the last large volume's read took
        self.ended = ""  # how a process found dead ended, for the one line that replaces it (ValidatorPool._refill)

    def start(self) -> None:
        parent, child = self.ctx.Pipe(duplex=True)
        self.process = self.ctx.Process(
            target=validator_main, args=(child, self.memory_mb, self.threads, os.getpid(), self.policy),
            name="dsareg-validator",
            daemon=True
        )
        self.spawner.run(self.process.start)
        child.close()
        self.conn = parent
        self.ready = False

    def adopt(self, other: _Slot) -> None:
        """Take ``other``'s (warm) process; ours must have been killed."""
        self.process, self.conn, self.ready = other.process, other.conn, other.ready
        other.process, other.conn, other.ready = None, None, False

    def note_end(self) -> None:
        """Keep how the (dead) process ended, for the pool's one log line: a negative exit code is the signal's
        number (-9: killed, the memory cap or the OOM killer)."""
        if self.process is not None:
            self.process.join(1)
            self.ended = f"pid {self.process.pid} ended with exit code {self.process.exitcode}"

    def health(self) -> str:
        """``ok``, ``frozen`` (stopped by a signal or a debugger) or ``dead``."""
        if self.process is None or self.conn is None or not self.process.is_alive():
            return "dead"
        state = process_state(self.process.pid)
        if state is None or state in "ZX":
            return "dead"
        return "frozen" if state in "Tt" else "ok"

    def _receive(self, deadline: float) -> Any:
        """The next message from the process, watching it meanwhile: raises ``TimeoutError`` past the
        deadline, ``_Unhealthy`` as soon as the process is found dead or frozen."""
        assert self.conn is not None
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError
            if self.conn.poll(min(WATCH_SECONDS, left)):
                return self.conn.recv()
            health = self.health()
            if health != "ok":
                raise _Unhealthy(health)
            if self.cpu_budget is not None and self._cpu_now() - self.cpu_budget[0] > self.cpu_budget[1]:
                raise TimeoutError  # a large volume's read past its CPU seconds

    def _reply(self, deadline: float, sent: float) -> dict:
        """The request's reply; a large volume's allowance (``{"allowance"}``, sent first) moves the deadline to
        its wall-clock after ``sent`` and counts the process's CPU seconds from now against its ``cpu_s`` (both at
        most the policy's ceiling)."""
        self.allowance, self.cpu_budget, self.cpu_used = self.policy.base(), None, None
        try:
            while True:
                message = self._receive(deadline)
                if "allowance" not in message:
                    if self.cpu_budget is not None:
                        self.cpu_used = self._cpu_now() - self.cpu_budget[0]
                    return message
                given, ceiling = message["allowance"], self.policy.ceiling_s
                self.allowance = Allowance(int(given["memory_mb"]), min(float(given["timeout_s"]), ceiling),
                                           str(given["volume"]), min(float(given.get("cpu_s") or 0.0), ceiling))
                deadline = max(deadline, sent + self.allowance.timeout_s)
                if self.allowance.cpu_s > 0:
                    self.cpu_budget = (self._cpu_now(), self.allowance.cpu_s)
        finally:
            self.cpu_budget = None

    def _cpu_now(self) -> float:
        """The process's CPU seconds so far (0 when it is gone: its health says so)."""
        return (process_cpu_seconds(self.process.pid) if self.process is not None else None) or 0.0

    def wait_ready(self, timeout: float) -> bool:
        if self.ready:
            return True
        assert self.conn is not None
        if timeout <= 0:
            if self.conn.poll(0):
                self.conn.recv()
                self.ready = True
            return self.ready
        self._receive(time.monotonic() + timeout)
        self.ready = True
        return True

    def kill(self) -> None:
        if self.process is not None and self.process.is_alive():
            self.process.kill()  # SIGKILL ends a stopped process too
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
        except (EOFError, OSError):
            return False
        finally:
            self.lock.release()

    def call(self, request: dict, timeout: float) -> tuple[dict | None, str | None]:
        """``(reply, None)``, or ``(None, why)`` with why ``timeout``, ``dead`` or ``frozen`` (the process is
        then killed; the pool gives the slot a fresh one). Blocking; the caller holds ``lock``."""
        deadline = time.monotonic() + timeout
        self.allowance, self.cpu_used = self.policy.base(), None
        try:
            if self.health() != "ok":
                raise _Unhealthy(self.health())
            waiting = time.monotonic()
            self.wait_ready(max(0.1, deadline - time.monotonic()) + 120.0)  # start-up is not the request's time
            self.waited_s = time.monotonic() - waiting
            assert self.conn is not None
            self.conn.send(request)
            return self._reply(deadline, time.monotonic()), None
        except _Unhealthy as exc:
            why = exc.health
        except TimeoutError:
            why = "timeout"
        except (EOFError, OSError, BrokenPipeError):
            why = "dead"
        if why == "dead":
            self.note_end()
        self.kill()
        return None, why


def log_validation_time(seconds: float, waited_s: float, allowance: Allowance | None = None,
                        cpu_s: float | None = None) -> None:
    """The time a submission's parse took; a request that came while its validator was still starting (before
    /readyz answers 200) says how much of it was that start, paid once per validator; a large volume's allowance."""
    if allowance is not None and allowance.raised:
        used = "" if cpu_s is None else f"; its read took {cpu_s:.1f} CPU s"
        log.info("a %s volume was given %d MB and %s to parse (sized from its header)%s", allowance.volume,
                 allowance.memory_mb, allowance.describe(), used)
    if waited_s >= 0.5:
        log.info("validation took %.2f s, %.2f s of it waiting for the validator to finish starting (imports and "
                 "parser warm-up, once per validator process: a request sent before /readyz answers 200 pays it)",
                 seconds, waited_s)
    else:
        log.info("validation took %.2f s", seconds)


class _Unhealthy(Exception):
    def __init__(self, health: str):
        super().__init__(health)
        self.health = health


class ValidatorPool:
    """Validator processes plus one warm spare, and a watchdog.

    A validator found dead or frozen (SIGSTOP) — by the request waiting on it (checked every
    ``WATCH_SECONDS``) or by the watchdog while idle — is killed and its slot takes the warm
    spare at once (a new spare starts once that request is answered), so a request is not kept waiting on
    a process that will not answer, nor on a cold start: the request in flight is sent again to
    the fresh process; if that one dies too the input is what kills parsers (refused naming the
    largest input); if it freezes too, busy (the intake answers Overloaded).

    Successful outcomes are cached by request content (inputs are content-addressed, so
    the same hashes + geometry + segmentation + volume reading + limits parse the same way)."""

    CACHE_SIZE = 512
    RETRY_AFTER_SECONDS = 5

    def __init__(self, processes: int, timeout_seconds: float, memory_mb: int, threads: int = 1, *,
                 volume_memory_mb: int = 0, volume_timeout_seconds: float = 0.0):
        """``volume_memory_mb`` / ``volume_timeout_seconds``: the most one submission's large volume may be given
        (:mod:`.allowance`; 0 and 0: the base limits for every submission)."""
        self.ctx = mp.get_context("spawn")
        self.timeout = timeout_seconds
        policy = AllowancePolicy(memory_mb, timeout_seconds, volume_memory_mb, volume_timeout_seconds)
        self.spawner = Spawner()  # a validator dies with the thread that started it (PR_SET_PDEATHSIG)
        self.slots = [_Slot(self.ctx, policy, threads, self.spawner) for _ in range(processes)]
        self.spare = _Slot(self.ctx, policy, threads, self.spawner)
        self.replaced = 0
        self._spare_lock = threading.Lock()
        self._halt = threading.Event()
        self._watchdog = threading.Thread(target=self._watch, name="validator-watchdog", daemon=True)
        self._free: asyncio.Queue[_Slot] | None = None
        self._cache: OrderedDict[str, ValidationOutcome] = OrderedDict()

    @staticmethod
    def _cache_key(request: dict) -> str:
        fields = {k: request.get(k) for k in ("inputs", "geometry", "segmentation", "limits", "require_cuda", "reading",
                                              "volume_reading", "mesh_units", "hemodynamics")}
        return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()

    def start(self) -> None:
        for slot in self.slots:
            slot.start()
        self.spare.start()
        self._watchdog.start()

    def _queue(self) -> asyncio.Queue:
        if self._free is None:
            self._free = asyncio.Queue()
            for slot in self.slots:
                self._free.put_nowait(slot)
        return self._free

    def _refill(self, slot: _Slot, why: str, *, spare_now: bool = True) -> None:
        """``slot`` (its process killed) takes the warm spare; a new spare starts now, or (``spare_now=False``,
        a request is about to be sent again) after that request, so its warm-up does not compete with it."""
        ended, slot.ended = slot.ended, ""
        with self._spare_lock:
            if self._halt.is_set():
                return
            if self.spare.health() == "ok":
                slot.adopt(self.spare)
            else:
                self.spare.kill()
                slot.start()
            if spare_now:
                self.spare.start()
            self.replaced += 1
        log.warning("validator replaced (%s); pid %s takes over%s", why, slot.process.pid if slot.process else None,
                    f" ({ended})" if ended else "")  # one line per replaced process (was also "found dead")

    def _watch(self) -> None:
        """Idle validators (and the spare) found dead or frozen are replaced before a request meets them."""
        while not self._halt.wait(WATCHDOG_SECONDS):
            for slot in self.slots:
                if not slot.lock.acquire(blocking=False):
                    continue  # busy: the request waiting on it watches it
                try:
                    health = slot.health()
                    if health != "ok" and not self._halt.is_set():
                        if health == "dead":
                            slot.note_end()
                        slot.kill()
                        self._refill(slot, f"{health} while idle")
                finally:
                    slot.lock.release()
            with self._spare_lock:  # a missing spare (process None) is started by the request that used it
                if not self._halt.is_set() and self.spare.process is not None and self.spare.health() != "ok":
                    self.spare.kill()
                    self.spare.start()

    def _ensure_spare(self) -> None:
        with self._spare_lock:
            if not self._halt.is_set() and self.spare.process is None:
                self.spare.start()

    def _run(self, slot: _Slot, request: dict) -> tuple[dict | None, str | None]:
        """One request on ``slot`` (in a thread), sent once more to a fresh process when its validator
        died or froze under it."""
        with slot.lock:
            try:
                reply, why = slot.call(request, self.timeout)
                if why is not None:
                    self._refill(slot, why, spare_now=False)
                    if why in ("dead", "frozen"):
                        reply, second = slot.call(request, self.timeout)
                        if second is not None:
                            self._refill(slot, second, spare_now=False)
                            why = "dead twice" if second == "dead" else second
                        else:
                            why = None
                elif reply is not None and reply.get("recycle"):  # memory the allocator keeps after a MemoryError
                    slot.kill()                                       # or a large volume's read
                    recycle = reply["recycle"]
                    self._refill(slot, "recycled " + (recycle if isinstance(recycle, str) else "after MemoryError"))
            finally:
                self._ensure_spare()
        return reply, why

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
            slot.waited_s = 0.0
            reply, why = await asyncio.to_thread(self._run, slot, request)
            allowance = slot.allowance
            log_validation_time(time.monotonic() - started, slot.waited_s, allowance, slot.cpu_used)
        finally:
            free.put_nowait(slot)
        if why is not None:
            return self._failed(why, request, allowance)
        assert reply is not None
        if reply.get("ok"):
            return ValidationOutcome(ok=True, summary=reply.get("summary") or {})
        if reply.get("unavailable"):
            return ValidationOutcome(ok=False, unavailable=True)
        if reply.get("internal"):
            log.warning("validation raised %s", reply.get("kind"))
            return ValidationOutcome(ok=False, internal=True, message="the inputs could not be read",
                                     accepted="well-formed mesh/volume and image files")
        return ValidationOutcome(ok=False, message=reply.get("message"), field=reply.get("field"), accepted=reply.get("accepted"))

    def _failed(self, why: str, request: dict, allowance: Allowance) -> ValidationOutcome:
        if why == "frozen":  # two validators stopped in a row: a machine problem, not the input's
            return ValidationOutcome(ok=False, busy=True, message="input validation is temporarily unavailable")
        if why == "timeout":
            given = f" (the time allowed for a {allowance.volume} volume)" if allowance.raised else ""
            return ValidationOutcome(ok=False, message=f"the inputs could not be parsed within "
                                                       f"{allowance.describe()}{given}",
                                     field="volume" if allowance.raised else largest_input(request),
                                     accepted="smaller or simpler inputs")
        return ValidationOutcome(ok=False, message="the inputs crashed the parser on two fresh processes",
                                 field=largest_input(request), accepted="well-formed mesh/volume and image files")

    def ready(self) -> bool:
        """Every parser process started and warmed up (so a submission is not kept waiting on imports)."""
        return all(slot.check_ready() for slot in self.slots)

    def alive(self) -> bool:
        return any(s.process is not None and s.process.is_alive() for s in self.slots)

    def spare_ready(self) -> bool:
        """The spare has warmed up (a validator lost now is replaced without a cold start)."""
        return self.spare.check_ready()

    def stop(self) -> None:
        self._halt.set()
        if self._watchdog.is_alive():
            self._watchdog.join(5)
        everyone = [*self.slots, self.spare]
        for slot in everyone:
            try:
                if slot.conn is not None:
                    slot.conn.send(None)
            except (OSError, BrokenPipeError):
                pass
        for slot in everyone:
            if slot.process is not None:
                slot.process.join(2)
            slot.kill()
        self.spawner.stop()
