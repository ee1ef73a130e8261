"""``dsareg warmup``: compile every numba kernel a job can use into the on-disk cache, ahead of the
first job (the Docker image runs it at build time; on a fresh install it otherwise happens in each
worker's warm-up, minutes on 2 cores)."""

from __future__ import annotations

import argparse
import sys
import time


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "warmup", help="compile the kernels into the cache ahead of the first job",
        description="Compile the renderer's, the pose search's, tracking's and hemodynamics' numba kernels (the parallel ones and "
                    "their 1-thread serial twins) into numba's on-disk cache, independent groups in parallel "
                    "processes, and run one tiny job end to end. "
                    "A worker started afterwards is ready in seconds instead of minutes.")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import tempfile
    from pathlib import Path

    from ..threads import default_cpu_threads, set_cpu_threads
    from ..warmup import JOB_GROUPS, LATER_GROUPS, compile_group, start_helper, warm_up_job, warm_up_renderer

    started = time.monotonic()
    counts = sorted({1, default_cpu_threads()})  # 1 thread: the serial twins; more: the parallel kernels
    _say(f"warmup: compiling the numba kernels for {' and '.join(map(str, counts))} thread(s) into the cache, then "
         "a tiny job (about a minute per thread count on 2 cores on a fresh install; seconds once cached). Without "
         "it, each worker's first start pays this before /readyz answers 200")
    for threads in counts:
        set_cpu_threads(threads)
        step = time.monotonic()
        for number, (first, *others) in enumerate((JOB_GROUPS, LATER_GROUPS), 1):  # a stage's groups in parallel
            _say(f"warmup: {threads} thread(s): kernel groups {', '.join((first, *others))} ({number}/2) …")
            helpers = [helper for group in others if (helper := start_helper([group])) is not None]
            compile_group(first)
            for helper in helpers:
                helper.communicate()
        _say(f"warmup: {threads} thread(s): the renderer, then a tiny job with and without a pose search …")
        warm_up_renderer()
        for pose_search in (False, True):
            with tempfile.TemporaryDirectory(prefix="dsareg-warmup-") as work_dir:
                warm_up_job(Path(work_dir), pose_search=pose_search)
        _say(f"warmup: kernels for {threads} thread(s) ready in {time.monotonic() - step:.1f} s")
    print(f"warmup: done in {time.monotonic() - started:.1f} s")
    return 0


def _say(text: str) -> None:
    """A progress line on stderr, at once (stderr may be a pipe: a CI log shows it as it happens)."""
    print(text, file=sys.stderr, flush=True)
