"""``python -m benchmarks.engine clinical --sweep volumes``: CTA and TOF-MRA heads across the voxel sizes real series have.

A cell is one head series read as the model (``--volume``) and the XA pair of its true tree (256 px, the DICOM
phantom study's biplane, geometry in the tags; no geometry file, no initial pose): input kind (CTA, TOF-MRA) ×
generator (A: :mod:`dsareg_engine.simulation.synthetic_volumes`, skull shell and skull-base slab; B:
:mod:`dsareg_engine.simulation.synthetic_heads_layered`, tables and diploë, cancellous skull base, streak noise,
coil inhomogeneity, marrow fat) × vessel tree (the phantom's; a mesh file's with ``--mesh``, e.g. the paper's,
trunk along +y) × voxel size (isotropic 0.3…1.0 mm, and slices thicker than the pixels: 0.4×0.4×0.8,
0.5×0.5×1.0). The detector pixel grows with the tree so that it fits both views. A cell prints ADD, the verdict
(lowered to ``check`` by a close call about an input, as the result is), the plate share of the kept voxels,
the faces, and the CPU seconds of reading and of the whole job (reading, extraction, registration).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

VOXELS_MM: tuple[tuple[float, float, float], ...] = (
    (0.3,) * 3, (0.4,) * 3, (0.5,) * 3, (0.6,) * 3, (0.8,) * 3, (1.0,) * 3, (0.4, 0.4, 0.8), (0.5, 0.5, 1.0))
KINDS = ("cta", "mra")
GENERATORS = ("A", "B")
IMAGE_PX = 256
WRONG_ADD_MM = 0.5  # the target: a cell above it reading ok is a wrong pose read as ok


@dataclass(frozen=True)
class VolumeCell:
    kind: str  # "cta" or "mra"
    generator: str  # "A" or "B"
    tree: str  # "phantom" or "mesh"
    voxel_mm: tuple[float, float, float]

    @property
    def name(self) -> str:
        return f"{'CTA' if self.kind == 'cta' else 'TOF-MRA'} {self.generator} {self.tree} {voxel_text(self.voxel_mm)}"


def voxel_text(voxel_mm) -> str:
    """``0.4`` or ``0.4x0.4x0.8``."""
    sizes = [f"{v:g}" for v in voxel_mm]
    return sizes[0] if len(set(sizes)) == 1 else "x".join(sizes)


def parse_voxel(text: str) -> tuple[float, float, float]:
    """``"0.5"`` → (0.5, 0.5, 0.5); ``"0.4x0.4x0.8"`` → (0.4, 0.4, 0.8)."""
    parts = [float(p) for p in text.lower().split("x")]
    if len(parts) not in (1, 3) or min(parts) <= 0:
        raise ValueError(f"voxel size {text!r}: one size or three joined by x (0.4x0.4x0.8), in mm")
    return tuple(parts * 3 if len(parts) == 1 else parts)


def cells(*, mesh: bool, kinds=KINDS, generators=GENERATORS, trees=("phantom", "mesh"),
          voxels=VOXELS_MM) -> list[VolumeCell]:
    """The sweep's cells, per tree by voxel size in the order given (the mesh tree's only when ``mesh``)."""
    trees = [t for t in trees if t == "phantom" or mesh]
    return [VolumeCell(k, g, t, tuple(v)) for t in trees for v in voxels for k in kinds for g in generators]


def build_cell(cell: VolumeCell, tree_mesh=None, seed: int = 0, cisterns: bool = False):
    """The :class:`~benchmarks.engine.clinical_volumes.VolumeCaseFiles` of ``cell`` (``tree_mesh``:
    the mesh tree, already turned trunk-up, for ``cell.tree == "mesh"``; ``cisterns``: generator B's head with CSF
    cisterns, :class:`~dsareg_engine.simulation.cisterns.Cisterns`)."""
    from dsareg_engine.simulation.cisterns import Cisterns
    from dsareg_engine.io.case import CaseFiles
    from dsareg_engine.simulation.synthetic_heads_layered import make_layered_cta_head, make_layered_mra_head
    from dsareg_engine.simulation.synthetic_volumes import (fitting_pixel_spacing_mm, make_cta_head, make_tof_mra_head,
                                                vessel_tree, volume_case_of)
    from .clinical_volumes import TREE_DEPTH, VolumeCaseFiles

    tree = tree_mesh if cell.tree == "mesh" else vessel_tree(TREE_DEPTH, 3 + seed)
    if cell.generator == "A":
        maker = make_cta_head if cell.kind == "cta" else make_tof_mra_head
        volume = maker("a", voxel_mm=cell.voxel_mm, seed=3 + seed, tree=tree)
    else:
        maker = make_layered_cta_head if cell.kind == "cta" else make_layered_mra_head
        volume = maker(voxel_mm=cell.voxel_mm, tree=tree, seed=3 + seed, cisterns=Cisterns() if cisterns else None)
    case = volume_case_of(volume, image_px=IMAGE_PX, pixel_spacing_mm=fitting_pixel_spacing_mm(tree, IMAGE_PX))
    files = CaseFiles(ap=case.ap, ap_name="ap.dcm", lat=case.lat, lat_name="lat.dcm", volume=volume.parts,
                      volume_name="series.dcm")
    return VolumeCaseFiles(files, case.mesh_to_world)


def _mesh_tree(path: str | None):
    if path is None:
        return None
    from pathlib import Path

    from dsareg_engine.io.mesh_io import read_mesh
    from dsareg_engine.simulation.synthetic_volumes import tree_of_mesh

    return tree_of_mesh(read_mesh(Path(path).read_bytes(), Path(path).name))


def bench_volumes(args) -> int:
    """Print the sweep's table, one row per cell (``--cells-out``: also one JSON line per cell)."""
    from .clinical_volumes import run_row

    voxels = [parse_voxel(v) for v in args.voxels] if getattr(args, "voxels", None) else VOXELS_MM
    kinds = [k for k in KINDS if not args.kinds or any(w.lower() in (k, "tof-mra" if k == "mra" else k)
                                                      for w in args.kinds)]
    chosen = cells(mesh=args.mesh is not None, kinds=kinds, generators=args.generators or GENERATORS,
                   trees=args.trees or ("phantom", "mesh"), voxels=voxels)
    tree_mesh = _mesh_tree(args.mesh)
    print(f"{len(chosen)} cell(s), one case each (seed {args.seed}); {IMAGE_PX} px; no geometry file, no initial pose"
          + ("; generator B with CSF cisterns" if getattr(args, "cisterns", False) else ""))
    print("| kind | gen | tree | voxel mm | voxels kept | plate share | faces | ADD mm | verdict | read CPU s | "
          "job CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for cell in chosen:
        row = _run_cell(cell, tree_mesh, args.seed, run_row, getattr(args, "cisterns", False))
        rows.append(row)
        print(f"| {cell.kind.upper() if cell.kind == 'cta' else 'TOF-MRA'} | {cell.generator} | {cell.tree} | "
              f"{voxel_text(cell.voxel_mm)} | {row.get('voxels_kept', '')} | {_num(row.get('plate_share'), 2)} | "
              f"{row.get('faces', '')} | {_num(row.get('add_mm'), 3)} | {row['verdict']} | "
              f"{_num(row.get('read_cpu_s'), 1)} | {_num(row.get('cpu_s'), 1)} |", flush=True)
        if args.cells_out:
            with open(args.cells_out, "a", encoding="utf-8") as out:
                out.write(json.dumps({"cell": cell.name, **row}) + "\n")
    _summary(rows)
    return 0


def _run_cell(cell: VolumeCell, tree_mesh, seed: int, run_row, cisterns: bool = False) -> dict:
    from dsareg_engine.errors import DsaregInputError

    case = build_cell(cell, tree_mesh, seed, cisterns)
    try:
        return run_row(lambda *_: case)
    except DsaregInputError as error:  # a refusal is a cell's result too
        return {"verdict": "refused", "reasons": [str(error)]}


def _num(value, digits: int) -> str:
    return "" if value is None else f"{value:.{digits}f}"


def _summary(rows: list[dict]) -> None:
    adds = [r["add_mm"] for r in rows if r.get("add_mm") is not None]
    within = sum(a <= WRONG_ADD_MM for a in adds)
    wrong_ok = sum(r["verdict"] == "ok" and r.get("add_mm", 0.0) > WRONG_ADD_MM for r in rows)
    refused = sum(r["verdict"] == "refused" for r in rows)
    verdicts = ", ".join(f"{v} {sum(r['verdict'] == v for r in rows)}" for v in sorted({r["verdict"] for r in rows}))
    worst = f"{max(adds):.3f}" if adds else "-"
    print(f"\n{within}/{len(rows)} cells ADD <= {WRONG_ADD_MM} mm (worst {worst}); {refused} refused; verdicts: "
          f"{verdicts}; wrong poses (ADD > {WRONG_ADD_MM} mm) read ok: {wrong_ok}; job CPU s median "
          f"{np.median([r['cpu_s'] for r in rows if 'cpu_s' in r]) if adds else float('nan'):.1f}")


__all__ = ["VOXELS_MM", "VolumeCell", "bench_volumes", "build_cell", "cells", "parse_voxel", "voxel_text"]
