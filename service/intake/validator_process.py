"""The validator process itself: one request at a time from its pipe, parsed with the worker's own loader.

Started by :class:`service.intake.validator.ValidatorPool` (``spawn``); it names itself ``dsareg-validate``,
dies with the server, and runs under an address-space limit on top of its warmed-up size. A request is
``{"inputs", "geometry", "segmentation", "blob_root", "limits", "reading", "volume_reading", "mesh_units",
"hemodynamics", "require_cuda"}``; the reply ``{"ok": True, "summary"}`` or why not (``message``, ``field``,
``accepted``; ``unavailable``: no engine; ``internal``: a reader raised; ``recycle``: replace this process).
"""

from __future__ import annotations

import os
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from .allowance import Allowance, AllowancePolicy, TooLarge, size_allowance

MB = 1 << 20


def _set_memory_limit(extra_mb: int, ceiling_mb: int = 0) -> int | None:
    """Address space at most ``extra_mb`` over the current size (the soft limit), raisable per request up to
    ``ceiling_mb`` over it (the hard limit); the current size in bytes, or None when there is no limit."""
    if extra_mb <= 0:
        return None
    try:
        import resource

        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[0])
        current = pages * os.sysconf("SC_PAGE_SIZE")
        resource.setrlimit(resource.RLIMIT_AS, (current + extra_mb * MB, current + max(extra_mb, ceiling_mb) * MB))
        return current
    except Exception:  # noqa: BLE001 - best effort on platforms without it
        return None


def _allow_memory(start: int | None, extra_mb: int) -> None:
    """Raise this process's soft address-space limit to ``extra_mb`` over its warmed-up size ``start``."""
    if start is None or extra_mb <= 0:
        return
    try:
        import resource

        _, hard = resource.getrlimit(resource.RLIMIT_AS)
        wanted = start + extra_mb * MB
        resource.setrlimit(resource.RLIMIT_AS, (wanted if hard == resource.RLIM_INFINITY else min(wanted, hard), hard))
    except Exception:  # noqa: BLE001, S110 - best effort
        pass


def _become_validator(parent_pid: int | None) -> None:
    """Name the process (``dsareg-validate``), exit quickly, ignore Ctrl-C and SIGTERM (the server stops it), die
    with the server.

    A stop signal sent to the whole process group (Ctrl-C, systemd's stop, ``kill -TERM -- -PGID``) reaches the
    validators too; ended by it, they were found dead by the pool's watchdog before the server stopped the pool,
    and a normal stop logged ``validator replaced (dead while idle)``. The server stops them itself. The signals
    are ignored before the imports (about a second): a stop soon after a validator started killed it there."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from ..engine_adapter import engine
    from ..jobs.procwatch import die_with_parent, set_process_name

    set_process_name("dsareg-validate")
    engine.skip_exit_collections()  # a server's stop waits for its validators' exit
    if parent_pid is not None:  # a parse in progress must not outlive a SIGKILLed server
        die_with_parent(parent_pid, signal.SIGKILL)


def validator_main(conn: Connection, memory_mb: int, threads: int, parent_pid: int | None = None,
                   policy: AllowancePolicy | None = None) -> None:
    """Child loop: one request at a time ``{"inputs", "geometry", "segmentation", "blob_root", "reading",
    "volume_reading", "mesh_units"}``. ``policy``: the allowance a large volume may be given (:mod:`.allowance`);
    a request given more than the base limits first sends ``{"allowance": ...}`` (its parent waits that long), and
    its process is replaced after it (the memory its allocator keeps)."""
    _become_validator(parent_pid)
    policy = policy or AllowancePolicy(memory_mb, 0.0)
    engine_ok = True
    # parsing needs no torch (the engine imports it only to register); should a parser import it,
    # its thread pool reads this at start-up
    os.environ["OMP_NUM_THREADS"] = str(max(1, threads or 1))
    try:
        from ..engine_adapter import engine

        engine.preload_case_loading()
        engine.parse_without_network()  # torch's import alone exceeds the memory limit below; the worker decides
        engine.warm_up_parsers()
    except Exception:  # noqa: BLE001
        engine_ok = False
    start = _set_memory_limit(memory_mb, policy.ceiling_mb)
    from ..engine_adapter import engine

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
        conn.send(_answer(conn, request, policy, start))


def _answer(conn: Connection, request: dict, policy: AllowancePolicy, start: int | None) -> dict[str, Any]:
    """The reply to one request: its volume's allowance sized (and announced), its inputs read as the worker will."""
    from ..engine_adapter import case_summary, engine, load_job_case
    from ..storage.blobs import BlobStore
    from ..storage.store import InputFile

    allowance = policy.base()
    try:
        blobs = BlobStore(request["blob_root"])
        inputs = [InputFile(**item) for item in request["inputs"]]
        allowance = _allowance(inputs, request, blobs, policy)
        if allowance.raised:
            conn.send({"allowance": allowance.as_json()})
            _allow_memory(start, allowance.memory_mb)
        case = load_job_case(inputs, request["geometry"], request["segmentation"], blobs.read, request.get("limits"),
                             request.get("reading"), request.get("volume_reading"), request.get("mesh_units"),
                             hemodynamics=bool(request.get("hemodynamics")), models=request.get("models"),
                             read_head=blobs.read_head)
        reply = {"ok": True, "summary": case_summary(case)}
    except TooLarge as exc:
        reply = {"ok": False, "message": exc.message, "field": "volume", "accepted": exc.accepted}
    except engine.DsaregInputError as exc:
        reply = {"ok": False, "message": exc.message, "field": exc.field, "accepted": exc.accepted}
    except MemoryError:
        reply = {"ok": False, "message": f"decoding needs more than the {allowance.memory_mb} MB this server allows "
                                         f"for parsing {_what(allowance)}", "field": largest_input(request),
                 "accepted": "smaller inputs", "recycle": True}
    except Exception as exc:  # noqa: BLE001 - reported as a generic input problem, logged by type only
        reply = {"ok": False, "internal": True, "kind": type(exc).__name__}
    if allowance.raised:  # the memory its allocator keeps after a large read
        reply["recycle"] = reply.get("recycle") or "after a volume's allowance"
    return reply


def _allowance(inputs: list, request: dict, blobs: Any, policy: AllowancePolicy) -> Allowance:
    """The base limits, or more for a volume whose header says its first read needs more (:mod:`.allowance`)."""
    from ..engine_adapter import volume_cost

    volume = [item for item in inputs if item.role == "volume"]
    if not volume or (policy.volume_memory_mb <= 0 and policy.volume_timeout_s <= 0):
        return policy.base()
    cost = volume_cost(inputs, blobs.read, request.get("limits"), request.get("volume_reading"), request.get("models"),
                       blobs.read_head)
    return size_allowance(cost, sum(item.size for item in volume), policy)


def _what(allowance: Allowance) -> str:
    return f"a submission with a {allowance.volume} volume" if allowance.raised else "one submission"


def largest_input(request: dict) -> str | None:
    """The input that most likely exhausted the memory limit: the largest decoded image, else the largest file."""
    from ..budgets import image_decoded_bytes
    from ..storage.blobs import BlobStore

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
    """Whether a CUDA job could run here, answered without importing torch: its import alone exceeds the
    validator's memory limit (and under that limit it may abort or stall). A CUDA build of torch (its
    ``libtorch_cuda`` library) and a loaded NVIDIA driver; the worker still decides for good."""
    import importlib.util

    try:
        spec = importlib.util.find_spec("torch")
    except (ImportError, ValueError):
        return False
    if spec is None or spec.origin is None:
        return False
    torch_lib = Path(spec.origin).parent / "lib"
    has_cuda_build = any(torch_lib.glob("libtorch_cuda*"))
    return has_cuda_build and (Path("/proc/driver/nvidia/version").exists() or Path("/dev/nvidia0").exists())
