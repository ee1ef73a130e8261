"""The volume rows of ``python -m benchmarks.engine clinical``: vessel models read from CTA and TOF-MRA heads.

Each kind builds one synthetic case (:func:`dsareg_engine.simulation.synthetic_volumes.make_volume_case`):
the head's DICOM series as the model (``--volume``), the XA pair of the true tree with the geometry in their
tags; no geometry file, no initial pose. Generators A and B differ in levels, noise, blur and tag layout.
A reference row registers the true tree as a mesh (what a perfect reader would give).
"""

from __future__ import annotations

import resource
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dsareg_engine.io.case import CaseFiles


@dataclass(frozen=True)
class VolumeCaseFiles:
    """One case: the files a client sends and the true ``mesh_to_world`` (the shape of a clinical-table case)."""

    files: CaseFiles
    mesh_to_world: np.ndarray

VOXEL_MM = 0.6
TREE_DEPTH = 3
PIXEL_SPACING_MM = 0.6


def _volume_case(kind: str, variant: str, as_mesh: bool = False) -> Callable[[int, int], VolumeCaseFiles]:
    def build(seed: int, size_px: int) -> VolumeCaseFiles:
        from dsareg_engine.simulation.synthetic_volumes import make_volume_case

        case = make_volume_case(kind, variant, voxel_mm=VOXEL_MM, depth=TREE_DEPTH, seed=3 + seed, image_px=size_px,
                                pixel_spacing_mm=PIXEL_SPACING_MM * 256 / size_px)
        model = {"mesh": _mesh_bytes(case.volume.tree), "mesh_name": "tree.obj"} if as_mesh else {
            "volume": case.volume.parts, "volume_name": "series.dcm"}
        files = CaseFiles(ap=case.ap, ap_name="ap.dcm", lat=case.lat, lat_name="lat.dcm", **model)
        return VolumeCaseFiles(files, case.mesh_to_world)
    return build


def _mesh_bytes(mesh) -> bytes:
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "tree.obj"
        mesh.save(path)
        return path.read_bytes()


VOLUME_CASE_KINDS: list[tuple[str, str, Callable[[int, int], VolumeCaseFiles]]] = [
    ("CTA, generator A", (f"{VOXEL_MM} mm CT series: vessels 350 HU, brain 35, skull 1200 (4 mm), skull-base slab 900 "
     "crossed by the trunk, air; white noise 8 HU, blur 0.5 vox; unsigned + intercept, Contrast/Bolus Agent"),
     _volume_case("cta", "a")),
    ("CTA, generator B", ("vessels 430 HU, brain 42, scalp fat -80, skull 1550, slab 1050; correlated noise 14 HU, blur "
     "0.8 vox; signed, slices reversed, no contrast tag"), _volume_case("cta", "b")),
    ("TOF-MRA, generator A", ("MR series: vessels 560 → 480 distally, brain 210 textured, scalp fat 430, bone 40, CSF 90; "
     "Rician noise 8, blur 0.5 vox; axial, Angio Flag"), _volume_case("mra", "a")),
    ("TOF-MRA, generator B", ("vessels 720 → 520, brain 300 textured ±40, fat 640, bone 60; Rician 15, blur 0.8 vox; "
     "sagittal slices, rescale slope 0.5, no angio tags"), _volume_case("mra", "b")),
    ("  true tree as a mesh", "the reference: the same XA pair (generator A's) with the true surface as the model",
     _volume_case("cta", "a", as_mesh=True)),
]


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_row(build: Callable[[int, int], VolumeCaseFiles], seed: int = 0, size_px: int = 256) -> dict:
    """Load and register one case as ``dsareg register --volume`` does: ADD, verdict (a close call about an input
    lowers ``ok`` to ``check``, as the result's), its reasons, faces, voxels kept, plate share, CPU and wall s."""
    from dsareg_engine.io.case import load_case_files
    from dsareg_engine.io.input_decisions import with_close_calls
    from dsareg_engine.registration.solver import register
    from dsareg_engine.registration.options import parse_options

    case = build(seed, size_px)
    options = parse_options({"device": "cpu", "ground_truth_mesh_to_world": case.mesh_to_world.tolist()})
    wall, cpu = time.perf_counter(), _cpu_seconds()
    loaded = load_case_files(case.files, options.segmentation)
    read_cpu = _cpu_seconds() - cpu
    result = register(loaded.mesh, loaded.fitted, loaded.rig, options)
    errors = result.metrics["ground_truth"]
    confidence = with_close_calls({"metrics": {"confidence": dict(result.metrics.get("confidence") or {})}},
                                  list(loaded.decisions))["metrics"]["confidence"]
    readout = loaded.volume
    return {"add_mm": errors["add_mm"], "rotation_deg": errors["rotation_error_deg"],
            "verdict": confidence.get("verdict", "?"), "reasons": list(confidence.get("reasons") or []),
            "faces": loaded.mesh.n_faces, "voxels_kept": readout.voxels_kept if readout is not None else None,
            "plate_share": readout.plate_share if readout is not None else None,
            "read_cpu_s": read_cpu, "cpu_s": _cpu_seconds() - cpu, "wall_s": time.perf_counter() - wall,
            "volume": readout.text() if readout is not None else ""}


def main(words: list[str]) -> int:
    """``python -m benchmarks.engine.clinical_volumes [WORD ...]``: the rows whose name has a word."""
    print("| input kind | faces | ADD mm | rotation deg | verdict | read CPU s | job CPU s | wall s |")
    print("|---|---|---|---|---|---|---|---|")
    for name, _, build in VOLUME_CASE_KINDS:
        if words and not any(word.lower() in name.lower() for word in words):
            continue
        row = run_row(build)
        print(f"| {name} | {row['faces']} | {row['add_mm']:.3f} | {row['rotation_deg']:.2f} | {row['verdict']} | "
              f"{row['read_cpu_s']:.1f} | {row['cpu_s']:.1f} | {row['wall_s']:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
