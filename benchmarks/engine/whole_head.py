"""``python -m benchmarks.engine whole-head``: a whole-head CTA as scanners write it, read and registered twice.

The head (:func:`dsareg_engine.simulation.synthetic_heads_layered.make_layered_cta_head`: tables and diploë, a
cancellous skull base, streak noise; the phantom's tree) on a scanner's grid (default 512 × 512 × 440 at 0.45 mm,
air around a 174 × 204 mm head), written as a DICOM series beside its XA pair (256 px, geometry in the tags). Each
job runs in a fresh process (its peak RSS is its own): the case read as a job reads it, then registered with no
initial pose, with a volume-model store (:mod:`dsareg_engine.io.model_cache`) in a temporary folder shared by
both. Job 1 reads the volume and keeps its model; job 2 takes it. A row: CPU s and peak RSS of the whole job (read +
registration), the read's CPU s, ADD, verdict, voxels kept.
"""

from __future__ import annotations

import json
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

GRID_VOX = (512, 512, 440)
VOXEL_MM = 0.45
HEAD_MM = (70.0, 85.0, 70.0)  # the skull's inner half-extents (a head, not the tree's box)
SWEEP = (  # (kind, voxel mm per axis, scanner grid[, dural sinuses]): the 512² × 300–600 slices at 0.3–0.6
    # mm, anisotropic; a CTA taken late (its dural sinuses filled, triangular or round in section)
    ("cta", (0.45, 0.45, 0.45), (512, 512, 440), "triangle"),
    ("cta", (0.45, 0.45, 0.45), (512, 512, 440), "round"),
    ("cta", (0.4, 0.4, 0.3), (512, 512, 600)),
    ("cta", (0.4, 0.4, 0.45), (512, 512, 400)),
    ("cta", (0.4, 0.4, 0.6), (512, 512, 300)),
    ("cta", (0.5, 0.5, 0.3), (512, 512, 600)),
    ("cta", (0.5, 0.5, 0.45), (512, 512, 400)),
    ("cta", (0.5, 0.5, 0.6), (512, 512, 300)),
    ("mra", (0.4, 0.4, 0.5), (512, 512, 160)),  # a TOF slab: 80 mm from the skull base up, the head cut above
    ("mra", (0.35, 0.35, 0.3), (512, 512, 300)),  # 90 mm
)
"""The ``--sweep`` cells: whole-head CTAs 180 mm tall (a 205 or 256 mm field), two of them taken late (venous
sinuses filled, :mod:`dsareg_engine.simulation.dural_sinuses`), TOF-MRA slabs through the head."""


def add_parser(which) -> None:
    sub = which.add_parser("whole-head", help="a whole-head CTA (512 x 512 x 440 at 0.45 mm): CPU s and peak RSS of "
                                              "two jobs on it (the second takes the kept model)")
    sub.add_argument("--voxel", default=str(VOXEL_MM),
                     help="voxel size, mm: isotropic (0.45) or per axis (0.4x0.4x0.5)")
    sub.add_argument("--kind", choices=("cta", "mra"), default="cta",
                     help="a CTA head (default) or a TOF-MRA slab through it (generator B's layered heads)")
    sub.add_argument("--sweep", action="store_true",
                     help="the first job of each cell of SWEEP (whole-head CTAs 512² × 300–600 slices at 0.3–0.6 "
                          "mm, TOF-MRA slabs): CPU s and peak RSS per cell")
    sub.add_argument("--grid", default="x".join(map(str, GRID_VOX)), help="the scanner's grid, e.g. 512x512x440")
    sub.add_argument("--diploe", type=float, default=None,
                     help="the CTA skull's diploë, mm (2-8 in adults; default 3): cancellous bone in the vessels' "
                          "window, what a whole head's plate search measures")
    sub.add_argument("--sinuses", choices=("triangle", "round"), default=None,
                     help="a CTA taken late: its dural venous sinuses filled, triangular (superior sagittal) or round "
                          "in section (what the reading must set aside: an arterial run shows none of it)")
    sub.add_argument("--intake", action="store_true",
                     help="each job's read only, as the service's validator makes it (warmed up first): its address-"
                          "space and RSS growth, CPU s and wall s (the costs dsareg_engine/io/volume_cost.py sizes "
                          "a submission's allowance from)")
    sub.set_defaults(func=bench_whole_head)


def voxel_argument(text) -> float | tuple[float, float, float]:
    """``--voxel``: one size (isotropic, ``0.45``) or one per axis (``0.4x0.4x0.5``)."""
    sizes = tuple(float(v) for v in str(text).lower().split("x"))
    return sizes[0] if len(sizes) == 1 else sizes


def _write_case(folder: Path, voxel_mm, grid: tuple[int, int, int], kind: str = "cta",
                diploe_mm: float | None = None, sinuses: str | None = None) -> Path:
    from dsareg_engine.io.case import CaseFiles
    from dsareg_engine.simulation.synthetic_heads_layered import DIPLOE_MM, make_layered_cta_head, make_layered_mra_head
    from dsareg_engine.simulation.synthetic_volumes import fitting_pixel_spacing_mm, vessel_tree, volume_case_of

    from .clinical_volumes import TREE_DEPTH, VolumeCaseFiles

    tree = vessel_tree(TREE_DEPTH, 3)
    if kind == "cta":
        volume = make_layered_cta_head(voxel_mm=voxel_mm, tree=tree, seed=3, min_head_mm=HEAD_MM, grid_vox=grid,
                                       diploe_mm=DIPLOE_MM if diploe_mm is None else diploe_mm, sinuses=sinuses)
    else:
        volume = make_layered_mra_head(voxel_mm=voxel_mm, tree=tree, seed=3, min_head_mm=HEAD_MM, grid_vox=grid)
    case = volume_case_of(volume, image_px=256, pixel_spacing_mm=fitting_pixel_spacing_mm(tree, 256))
    files = CaseFiles(ap=case.ap, ap_name="ap.dcm", lat=case.lat, lat_name="lat.dcm", volume=volume.parts,
                      volume_name="series.dcm")
    path = folder / "case.pickle"
    path.write_bytes(pickle.dumps(VolumeCaseFiles(files, case.mesh_to_world)))
    return path


def run_job(case_path: str, models: str) -> dict:
    """One job in this process: read (with the model store ``models``) and register; CPU s and peak RSS."""
    import resource
    import time

    from dsareg_engine.io.case import load_case_files
    from dsareg_engine.io.input_decisions import with_close_calls
    from dsareg_engine.io.model_cache import DirectoryModelStore
    from dsareg_engine.registration.options import parse_options
    from dsareg_engine.registration.solver import register

    with open(case_path, "rb") as stream:  # streamed: the pickle's bytes and the files are never held together
        case = pickle.load(stream)
    files, truth = series_on_disk(case.files, Path(case_path).parent / "series"), case.mesh_to_world
    del case  # the files as `dsareg register` and a worker give them: read when used (`FileParts`), not held
    _reset_peak_rss()  # the unpickled files' peak is not the job's

    def cpu() -> float:
        usage = resource.getrusage(resource.RUSAGE_SELF)
        return usage.ru_utime + usage.ru_stime

    options = parse_options({"device": "cpu", "ground_truth_mesh_to_world": truth.tolist()})
    start, wall = cpu(), time.perf_counter()
    loaded = load_case_files(files, options.segmentation, model_store=DirectoryModelStore(models))
    read_cpu = cpu() - start
    result = register(loaded.mesh, loaded.fitted, loaded.rig, options)
    confidence = with_close_calls({"metrics": {"confidence": dict(result.metrics.get("confidence") or {})}},
                                  list(loaded.decisions))["metrics"]["confidence"]
    return {"read_cpu_s": read_cpu, "cpu_s": cpu() - start, "wall_s": time.perf_counter() - wall,
            "peak_rss_gb": peak_rss_kb() / 1e6,
            "add_mm": result.metrics["ground_truth"]["add_mm"], "verdict": confidence.get("verdict", "?"),
            "voxels_kept": loaded.volume.voxels_kept, "faces": loaded.mesh.n_faces}


def series_on_disk(files, folder: Path):
    """``files`` with its volume's series written to ``folder`` (once) and given as ``FileParts`` of those files."""
    import dataclasses

    from dsareg_engine.io.file_parts import FileParts

    if not isinstance(files.volume, list):
        return files
    folder.mkdir(exist_ok=True)
    paths = [folder / f"{index:05d}.dcm" for index in range(len(files.volume))]
    for path, part in zip(paths, files.volume):
        if not path.is_file():
            path.write_bytes(part)
    return dataclasses.replace(files, volume=FileParts.from_paths(paths))


def read_as_validator(case_path: str, models: str) -> dict:
    """The case read in this process as the service's validator reads it: warmed up as it is (the engine's case
    loading imported, parsers run once), then ``load_case_files``; the growth of the address space (``VmPeak``
    after − ``VmSize`` before, what its ``RLIMIT_AS`` meets) and of the RSS, CPU s and wall s of the read."""
    import resource
    import time

    from dsareg_engine import api as engine
    from dsareg_engine.io.case import load_case_files
    from dsareg_engine.io.model_cache import DirectoryModelStore

    engine.preload_case_loading()
    engine.parse_without_network()
    engine.warm_up_parsers()
    with open(case_path, "rb") as stream:  # the files in memory, as the validator holds the blobs (streamed: the
        case = pickle.load(stream)  # pickle's bytes and the files are never held together, a peak not the read's)
    _reset_peak_rss()
    before, usage, wall = _vm(), resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    loaded = load_case_files(case.files, "auto", model_store=DirectoryModelStore(models))
    after, done = _vm(), resource.getrusage(resource.RUSAGE_SELF)
    return {"as_growth_mb": after["VmPeak"] - before["VmSize"], "rss_growth_mb": after["VmHWM"] - before["VmRSS"],
            "cpu_s": done.ru_utime + done.ru_stime - usage.ru_utime - usage.ru_stime,
            "wall_s": time.perf_counter() - wall, "voxels_kept": loaded.volume.voxels_kept}


def _reset_peak_rss() -> None:
    """``VmHWM`` set back to the current RSS (Linux ≥ 4.0: ``5`` written to ``/proc/self/clear_refs``), so the growth
    measured is the read's, not an earlier peak's (the case's unpickling)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _vm() -> dict[str, float]:
    """This process's ``Vm*`` lines of ``/proc/self/status``, MB."""
    lines = (line.split(":") for line in Path("/proc/self/status").read_text().splitlines() if line.startswith("Vm"))
    return {key: int(value.split()[0]) / 1024 for key, value in lines}


def peak_rss_kb() -> int:
    """This process's peak RSS (``VmHWM``): ``ru_maxrss`` carries the parent's peak across exec (the generator's GBs)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def bench_whole_head(args) -> int:
    if getattr(args, "sweep", False):
        return _bench_sweep()
    grid = tuple(int(v) for v in args.grid.lower().split("x"))
    voxel = voxel_argument(args.voxel)
    kind = getattr(args, "kind", "cta")
    with tempfile.TemporaryDirectory() as folder:
        print(f"writing a {grid[0]} x {grid[1]} x {grid[2]} {kind.upper()} at {args.voxel} mm ...", flush=True)
        case_path = _write_case(Path(folder), voxel, grid, kind, getattr(args, "diploe", None),
                                getattr(args, "sinuses", None))
        if getattr(args, "intake", False):
            return _bench_intake(case_path, Path(folder) / "models")
        print("| job | read CPU s | job CPU s | wall s | peak RSS GB | ADD mm | verdict | voxels kept | faces |")
        print("|---|---|---|---|---|---|---|---|---|")
        for job in ("1: reads the volume", "2: the kept model"):
            row = _job_row(case_path, Path(folder) / "models")
            if "error" in row:
                raise SystemExit(row["error"])
            print(f"| {job} | {row['read_cpu_s']:.1f} | {row['cpu_s']:.1f} | {row['wall_s']:.1f} | "
                  f"{row['peak_rss_gb']:.2f} | {row['add_mm']:.3f} | {row['verdict']} | {row['voxels_kept']} | "
                  f"{row['faces']} |", flush=True)
    return 0


def _job_row(case_path: Path, models: Path) -> dict:
    """:func:`run_job` in a fresh process (its peak RSS is its own)."""
    code = ("import json, sys; from benchmarks.engine.whole_head import run_job; "
            "print(json.dumps(run_job(sys.argv[1], sys.argv[2])))")
    out = subprocess.run([sys.executable, "-c", code, str(case_path), str(models)], capture_output=True, text=True,
                         check=False)
    if out.returncode != 0:  # a refusal (DsaregInputError) or a crash: its last line, in the table
        return {"error": (out.stderr.strip().splitlines() or [f"exit {out.returncode}"])[-1]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _bench_sweep() -> int:
    """The first job of each :data:`SWEEP` cell (a fresh model store each): read + registration with no pose."""
    print("| kind | grid | voxel mm | voxels M | read CPU s | job CPU s | wall s | peak RSS GB | ADD mm | verdict | "
          "voxels kept |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for kind, voxel, grid, *sinuses in SWEEP:
        with tempfile.TemporaryDirectory() as folder:
            case_path = _write_case(Path(folder), voxel, grid, kind, sinuses=(sinuses or [None])[0])
            row = _job_row(case_path, Path(folder) / "models")
        size = " × ".join(map(str, grid))
        late = f", sinuses {sinuses[0]}" if sinuses else ""
        cell = f"| {kind}{late} | {size} | {' × '.join(f'{v:g}' for v in voxel)} | {np.prod(grid) / 1e6:.0f} | "
        if "error" in row:
            print(cell + f"{row['error'][:160]} | | | | | | |", flush=True)
            continue
        print(cell + f"{row['read_cpu_s']:.1f} | {row['cpu_s']:.1f} | {row['wall_s']:.1f} | {row['peak_rss_gb']:.2f} | "
              f"{row['add_mm']:.3f} | {row['verdict']} | {row['voxels_kept']} |", flush=True)
    return 0


def _bench_intake(case_path: Path, models: Path) -> int:
    """Two reads (the first, then the kept model's), each in a fresh process: :func:`read_as_validator`."""
    print("| read | address-space growth MB | RSS growth MB | CPU s | wall s | voxels kept |")
    print("|---|---|---|---|---|---|")
    for which in ("1: reads the volume", "2: the kept model"):
        code = ("import json, sys; from benchmarks.engine.whole_head import read_as_validator; "
                "print(json.dumps(read_as_validator(sys.argv[1], sys.argv[2])))")
        out = subprocess.run([sys.executable, "-c", code, str(case_path), str(models)], capture_output=True, text=True,
                             check=True)
        row = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"| {which} | {row['as_growth_mb']:.0f} | {row['rss_growth_mb']:.0f} | {row['cpu_s']:.1f} | "
              f"{row['wall_s']:.1f} | {row['voxels_kept']} |", flush=True)
    return 0


__all__ = ["add_parser", "bench_whole_head", "peak_rss_kb", "read_as_validator", "run_job", "voxel_argument"]
