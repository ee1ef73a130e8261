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
    for threads in sorted({1, default_cpu_threads()}):  # 1 thread: the serial twins; more: the parallel kernels
        set_cpu_threads(threads)
        step = time.monotonic()
        for first, *others in (JOB_GROUPS, LATER_GROUPS):  # the groups of a stage compile in parallel processes
            helpers = [helper for group in others if (helper := start_helper([group])) is not None]
            compile_group(first)
            for helper in helpers:
                helper.communicate()
        warm_up_renderer()
        for pose_search in (False, True):
            with tempfile.TemporaryDirectory(prefix="dsareg-warmup-") as work_dir:
                warm_up_job(Path(work_dir), pose_search=pose_search)
        print(f"warmup: kernels for {threads} thread(s) ready in {time.monotonic() - step:.1f} s", file=sys.stderr)
    print(f"warmup: done in {time.monotonic() - started:.1f} s")
    return 0
