"""Where a fresh install's first start goes: numba compile seconds per kernel specialization (a command).

    python -m benchmarks.service.kernel_compile [--threads 2] [--steps renderer,job,search]

Runs, in this process, with ``NUMBA_CACHE_DIR`` pointed at a new empty folder (the worktree's own
``__pycache__`` is neither read nor written), the steps a worker's warm-up takes: ``renderer``
(:func:`dsareg_engine.warmup.warm_up_renderer`), ``job`` (one tiny registration, as the worker
runs after it) and ``search`` (the same without an initial pose). It records numba's
``numba:compile`` events (:mod:`numba.core.event`) and prints one row per compiled specialization
(kernel, argument types, seconds, outermost compiles only) and the wall/CPU seconds of each step.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


class CompileRecorder:
    """Outermost ``numba:compile`` events: ``[(kernel, signature, seconds)]`` (nested compiles of the
    callees are inside their caller's seconds)."""

    def __init__(self) -> None:
        self.rows: list[tuple[str, str, float]] = []
        self._depth = 0
        self._started = 0.0

    def on_start(self, event) -> None:
        if self._depth == 0:
            self._started = time.perf_counter()
        self._depth += 1

    def on_end(self, event) -> None:
        self._depth -= 1
        if self._depth == 0:
            data = event.data or {}
            dispatcher = data.get("dispatcher")
            name = getattr(dispatcher, "__qualname__", None) or getattr(getattr(dispatcher, "py_func", None),
                                                                         "__qualname__", str(dispatcher))
            signature = ", ".join(str(arg) for arg in data.get("args", ()))
            self.rows.append((name, signature, time.perf_counter() - self._started))


def _listen(recorder: CompileRecorder) -> None:
    from numba.core import event

    class _Listener(event.Listener):
        def on_start(self, ev):
            recorder.on_start(ev)

        def on_end(self, ev):
            recorder.on_end(ev)

    event.register("numba:compile", _Listener())


def _run_step(step: str) -> None:
    from pathlib import Path

    from dsareg_engine.warmup import warm_up_job, warm_up_renderer

    if step == "renderer":
        warm_up_renderer()
        return
    with tempfile.TemporaryDirectory(prefix="dsareg-compile-") as work_dir:
        warm_up_job(Path(work_dir), pose_search=step == "search")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2, help="CPU threads of the process (a worker's budget)")
    parser.add_argument("--steps", default="renderer,job,search", help="comma-separated: renderer, job, search")
    parser.add_argument("--keep-cache", action="store_true",
                        help="use the installed cache (numba's default place) instead of an empty folder")
    args = parser.parse_args(argv)
    if not args.keep_cache:
        os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="dsareg-numba-cache-")
    started, cpu_started = time.perf_counter(), _cpu_seconds()
    from dsareg_engine.threads import set_cpu_threads

    set_cpu_threads(args.threads)
    recorder = CompileRecorder()
    _listen(recorder)
    print(f"imports {time.perf_counter() - started:.1f} s wall, {_cpu_seconds() - cpu_started:.1f} CPU-s; "
          f"cache {os.environ.get('NUMBA_CACHE_DIR', '(installed)')}")
    for step in args.steps.split(","):
        first = len(recorder.rows)
        wall, cpu = time.perf_counter(), _cpu_seconds()
        _run_step(step)
        print(f"\n## step {step}: {time.perf_counter() - wall:.1f} s wall, {_cpu_seconds() - cpu:.1f} CPU-s")
        print("| kernel | argument types | compile s |\n|---|---|---|")
        for name, signature, seconds in recorder.rows[first:]:
            print(f"| {name} | {signature[:110]} | {seconds:.1f} |")
    total = sum(seconds for _, _, seconds in recorder.rows)
    print(f"\n{len(recorder.rows)} specializations, {total:.1f} s compiling; "
          f"total {time.perf_counter() - started:.1f} s wall, {_cpu_seconds() - cpu_started:.1f} CPU-s; "
          f"load average {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
