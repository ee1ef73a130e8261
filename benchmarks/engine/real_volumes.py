"""``python -m benchmarks.engine real-volumes [FOLDER]``: the real vessel files of ``../shared/data/real-vessels``.

Each file read as a job reads it (a surface: :func:`dsareg_engine.io.mesh_io.read_mesh_detailed`, units measured; a
volume: :func:`dsareg_engine.io.volume_io.read_volume` and :func:`dsareg_engine.io.volume_vessels.extract_vessels`,
kind detected, and for the PC-MRA also read as ``mra``), in a fresh process each (its peak RSS its own). A row:
what was read (kind, unit, faces, voxels kept) or the refusal, CPU s and peak RSS. The files are not in the
repository (their sources and licences: ``../shared/data/README.md``).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

DEFAULT_FOLDER = Path(__file__).resolve().parents[3] / "shared" / "data" / "real-vessels"
SURFACES = (".vtp", ".obj", ".stl", ".ply")
EXTRA_KINDS = {"carotid.vtk": ("mra",)}  # a phase-contrast MRA without tags: also read as what it is


def add_parser(which) -> None:
    sub = which.add_parser("real-volumes", help="the real vessel files (label maps, a PC-MRA, an aorta MHA and its "
                                                "surface, a centimetre model): what is read, CPU s, peak RSS")
    sub.add_argument("folder", nargs="?", default=str(DEFAULT_FOLDER), help="the folder of files")
    sub.set_defaults(func=bench_real_volumes)


def read_one(path: str, kind: str) -> dict:
    """One file read in this process: what was read, or the refusal; CPU s and peak RSS (VmHWM)."""
    import resource

    from dsareg_engine.errors import DsaregInputError

    from .whole_head import peak_rss_kb

    start = resource.getrusage(resource.RUSAGE_SELF)
    try:
        row = _read(Path(path), kind)
    except DsaregInputError as error:
        row = {"read": f"refused: {str(error)[:160]}"}
    end = resource.getrusage(resource.RUSAGE_SELF)
    row["cpu_s"] = end.ru_utime + end.ru_stime - start.ru_utime - start.ru_stime
    row["peak_rss_gb"] = peak_rss_kb() / 1e6
    return row


def _read(path: Path, kind: str) -> dict:
    data = path.read_bytes()
    if path.suffix.lower() in SURFACES:
        from dsareg_engine.io.mesh_io import read_mesh_detailed

        result = read_mesh_detailed(data, path.name)
        extent = result.mesh.vertices.max(0) - result.mesh.vertices.min(0)
        return {"read": f"surface in {result.unit.unit} ({result.unit.source}), extent "
                        f"{' × '.join(f'{v:.0f}' for v in extent)} mm", "faces": result.mesh.n_faces}
    from dsareg_engine.io.volume_io import read_volume
    from dsareg_engine.io.volume_kind import VolumeReading
    from dsareg_engine.io.volume_vessels import extract_vessels

    volume = read_volume(data, path.name)
    extraction = extract_vessels(volume, VolumeReading(kind), release=True)
    readout = extraction.readout
    return {"read": f"{readout.kind} ({readout.kind_source[:60]}); {readout.window()}; {readout.components} piece(s)",
            "faces": readout.faces, "voxels_kept": readout.voxels_kept}


def bench_real_volumes(args) -> int:
    folder = Path(args.folder)
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.endswith(".md"))
    if not files:
        print(f"no files in {folder}")
        return 1
    print("| file | kind asked | read | faces | voxels kept | CPU s | peak RSS GB |")
    print("|---|---|---|---|---|---|---|")
    for path in files:
        for kind in ("auto", *EXTRA_KINDS.get(path.name, ())):
            code = ("import json, sys; from benchmarks.engine.real_volumes import read_one; "
                    "print(json.dumps(read_one(sys.argv[1], sys.argv[2])))")
            out = subprocess.run([sys.executable, "-c", code, str(path), kind], capture_output=True, text=True,
                                 check=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            print(f"| {path.name} | {kind} | {row['read']} | {row.get('faces', '')} | {row.get('voxels_kept', '')} | "
                  f"{row['cpu_s']:.1f} | {row['peak_rss_gb']:.2f} |", flush=True)
    return 0


__all__ = ["add_parser", "bench_real_volumes", "read_one"]
