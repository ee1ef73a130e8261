"""``python -m benchmarks.engine clinical``: registration from clinical inputs as they are stored, per input kind.

:data:`CASE_KINDS` is the table of rows: each kind builds one synthetic case (the files a client
would send, and the true pose) from a seed and an image size. Every case is registered as a user
would: no geometry file (the geometry comes from the image headers), no initial pose. A row prints
success (verdict ok and ADD < 1 mm), ADD, the verdicts and the whole job's wall and CPU time
(reading, subtraction, segmentation and registration). Add a kind by adding a :class:`CaseKind`.
"""

from __future__ import annotations

import argparse
import resource
import time
from collections.abc import Callable
from dataclasses import dataclass

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from dsareg_engine.io.case import CaseFiles

SUCCESS_ADD_MM = 1.0


@dataclass(frozen=True)
class ClinicalCase:
    """One case: its input files and the true ``mesh_to_world`` of the model the files hold."""

    files: CaseFiles
    mesh_to_world: np.ndarray


@dataclass(frozen=True)
class CaseKind:
    name: str
    description: str
    build: Callable[[int, int], ClinicalCase]  # (seed, size_px) → case


def _mesh_bytes(mesh) -> bytes:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "mesh.obj"
        mesh.save(path)
        return path.read_bytes()


def _native(generator: str, subtracted: bool) -> Callable[[int, int], ClinicalCase]:
    def build(seed: int, size_px: int) -> ClinicalCase:
        if generator == "skull":
            from dsareg_engine.simulation.native_run_skull import SkullRunSettings, make_skull_run

            run = make_skull_run(seed, SkullRunSettings(size_px=size_px))
        else:
            from dsareg_engine.simulation.native_run_texture import TextureRunSettings, make_texture_run

            run = make_texture_run(seed, TextureRunSettings(size_px=size_px))
        return case_of(run, subtracted)
    return build


def case_of(run, subtracted: bool = False) -> ClinicalCase:
    """The case of a :class:`~dsareg_engine.simulation.native_run.NativeRunCase`: its native runs (or their
    pre-subtracted peak frames) and its mesh."""
    from dsareg_engine.io.case import CaseFiles

    images = run.subtracted if subtracted else run.files
    files = CaseFiles(ap=images["ap"], ap_name="ap.dcm", lat=images["lat"], lat_name="lat.dcm",
                      mesh=_mesh_bytes(run.mesh), mesh_name="mesh.obj")
    return ClinicalCase(files, run.mesh_to_world)


CASE_KINDS: list[CaseKind] = [
    CaseKind("native XA, generator A", "skull, Poisson noise, LIN, classic multi-frame XA, AVG_SUB recipe, 0.6 px motion",
             _native("skull", False)),
    CaseKind("  same, pre-subtracted", "generator A's peak frame subtracted with the aligned noise-free mask",
             _native("skull", True)),
    CaseKind("native XA, generator B", "textured background, Gaussian noise, LOG sign -1, MONOCHROME1, enhanced XA, "
             "no recipe, per-frame angles, 0.85 px motion", _native("texture", False)),
    CaseKind("  same, pre-subtracted", "generator B's peak frame subtracted with the aligned noise-free mask",
             _native("texture", True)),
]


def _volume_rows() -> list[CaseKind]:
    """The CTA / TOF-MRA rows (:mod:`.bench_clinical_volumes`): a head series as the model, the XA pair."""
    from .clinical_volumes import VOLUME_CASE_KINDS

    return [CaseKind(name, description, build) for name, description, build in VOLUME_CASE_KINDS]


CASE_KINDS += _volume_rows()


def run_one(case: ClinicalCase, options: dict) -> dict:
    """Load and register one case as ``dsareg register`` does; ADD, verdict, wall and CPU seconds, iterations per stage."""
    from dsareg_engine.io.case import load_case_files
    from dsareg_engine.registration.solver import register
    from dsareg_engine.registration.options import image_reading, parse_options

    parsed = parse_options({**options, "ground_truth_mesh_to_world": case.mesh_to_world.tolist()})
    wall, cpu = time.perf_counter(), _cpu_seconds()
    loaded = load_case_files(case.files, parsed.segmentation, reading=image_reading(parsed))
    result = register(loaded.mesh, loaded.fitted, loaded.rig, parsed)
    metrics = result.metrics
    verdict = (metrics.get("confidence") or {}).get("verdict", "?")
    if verdict == "ok" and any(decision.close for decision in loaded.decisions):
        verdict = "check"  # a close call about an input, as the pipeline's result says (input_decisions)
    return {"add_mm": float(metrics["ground_truth"]["add_mm"]), "verdict": verdict,
            "wall_s": time.perf_counter() - wall, "cpu_s": _cpu_seconds() - cpu, "iterations": dict(metrics["iterations"])}


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def bench_clinical(args: argparse.Namespace) -> int:
    import json

    options = {"device": args.device if args.device != "auto" else "cpu", **json.loads(args.options)}
    if getattr(args, "sweep", None) == "runs":
        from .clinical_runs import bench_runs

        return bench_runs(args, options, run_one, case_of)
    if getattr(args, "sweep", None) == "volumes":
        from .clinical_volume_sweep import bench_volumes

        return bench_volumes(args)
    kinds = [k for k in CASE_KINDS if not args.kinds or any(word.lower() in k.name.lower() for word in args.kinds)]
    print(f"{args.cases} case(s) per kind, {args.size} px, seed {args.seed}; no geometry file, no initial pose")
    print("| input kind | cases | success (ok, ADD < 1 mm) | ADD mm median / max | verdicts | wall s median | CPU s median |")
    print("|---|---|---|---|---|---|---|")
    for kind in kinds:
        rows = [run_one(kind.build(args.seed + i, args.size), options) for i in range(args.cases)]
        adds = [r["add_mm"] for r in rows]
        ok = sum(r["verdict"] == "ok" and r["add_mm"] < SUCCESS_ADD_MM for r in rows)
        verdicts = ", ".join(f"{v} {sum(r['verdict'] == v for r in rows)}" for v in sorted({r["verdict"] for r in rows}))
        print(f"| {kind.name} | {len(rows)} | {ok}/{len(rows)} | {np.median(adds):.4f} / {max(adds):.4f} | {verdicts} | "
              f"{np.median([r['wall_s'] for r in rows]):.1f} | {np.median([r['cpu_s'] for r in rows]):.1f} |", flush=True)
    return 0
