"""``python -m benchmarks.engine jobcost``: what one registration job costs, stage by stage, on fixed cases.

The cases are the native XA runs of ``bench clinical`` (generator A: skull, LIN, recipe; generator B: texture,
LOG, MONOCHROME1, no recipe) at the seeds and sizes of docs/benchmarks/clinical.md, round 10 (issue 30, "time
per job within 1.2×"). Iteration counts (Adam steps, L-BFGS evaluations) are deterministic for a given code and
input, so they compare across machine load where CPU seconds do not.
"""

from __future__ import annotations

import argparse
import json

CASES = (("B", 0, 512), ("B", 1, 512), ("B", 2, 512), ("B", 3, 512), ("A", 0, 512), ("A", 1, 512), ("A", 2, 512),
         ("B", 2, 1024), ("A", 2, 1024))
"""``(generator, seed, image side px)`` per case: the round-10 table's nine."""


def bench_job_cost(args: argparse.Namespace) -> int:
    import torch

    from .clinical import _native, run_one

    torch.set_num_threads(1)
    cases = [case for case in CASES if not args.only or f"{case[0]}{case[1]}-{case[2]}" in args.only]
    print("one thread; CPU s of the whole job (reading, pose search, stages); iterations per stage")
    print("| case | ADD mm | verdict | job CPU s | iterations | per stage |")
    print("|---|---|---|---|---|---|")
    total_cpu, total_iterations = 0.0, 0
    for generator, seed, size in cases:
        result = run_one(_native("skull" if generator == "A" else "texture", False)(seed, size),
                         {"device": "cpu", **json.loads(args.options)})
        stages = result["iterations"]
        total_cpu += result["cpu_s"]
        total_iterations += sum(stages.values())
        per_stage = " / ".join(f"{name.split(':', 1)[1]} {count}" for name, count in stages.items())
        print(f"| {generator} seed {seed}, {size} | {result['add_mm']:.3f} | {result['verdict']} | {result['cpu_s']:.2f} | "
              f"{sum(stages.values())} | {per_stage} |", flush=True)
    print(f"| **all** | | | **{total_cpu:.1f}** | **{total_iterations}** | |")
    return 0
