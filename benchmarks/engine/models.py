"""``python -m benchmarks.engine models``: the model's units and handedness, on the phantom and on a given mesh.

Each case: the model at a random visible pose on a clinical biplane rig (107°, a mirrored LAT detector, no
initial pose), its silhouettes as the masks. Rows: the model as an OBJ in mm (the reference); the same model
as a GLB in metres, read through the mesh reader (glTF's unit); the model mirrored along x, y and z (one
axis flipped through its centre, faces turned). A row prints ADD (vs the true pose), the verdicts, how many
results name the mirror, how many ran the mirror fit, and the CPU seconds per job (user + system).
"""

from __future__ import annotations

import argparse
import json
import resource

import numpy as np

ROWS = ("OBJ in mm", "GLB in metres", "mirrored x", "mirrored y", "mirrored z")


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def model_as(mesh, row: str):
    """The model a user would send for ``row``: read back through the mesh reader (mm inside)."""
    import trimesh

    from dsareg_engine.io.mesh_io import read_mesh_detailed
    from dsareg_engine.mesh import TriangleMesh

    if row.startswith("mirrored"):
        axis = "xyz".index(row[-1])
        vertices = mesh.vertices.copy()
        vertices[:, axis] = 2.0 * mesh.centroid[axis] - vertices[:, axis]
        return TriangleMesh(vertices, np.ascontiguousarray(mesh.faces[:, ::-1]))
    scale, file_type = (1000.0, "glb") if row.startswith("GLB") else (1.0, "obj")
    data = trimesh.Trimesh(mesh.vertices / scale, mesh.faces, process=False).export(file_type=file_type)
    return read_mesh_detailed(data.encode() if isinstance(data, str) else data, f"model.{file_type}").mesh


def run_case(mesh, row: str, seed: int, size_px: int, options: dict) -> dict:
    from dsareg_engine.geometry.rig import Rig
    from dsareg_engine.registration import parse_options
    from dsareg_engine.registration.solver import register
    from dsareg_engine.simulation.clinical_rig import clinical_biplane_rig, random_visible_pose, render_masks

    rig = clinical_biplane_rig(size_px=size_px)
    truth = random_visible_pose(mesh, rig, np.random.default_rng(seed))
    masks = render_masks(mesh, rig, truth)
    parsed = parse_options({**options, "ground_truth_mesh_to_world": truth.tolist()})
    started = _cpu_seconds()
    result = register(model_as(mesh, row), masks, Rig(views=rig.views), parsed)
    confidence = result.metrics["confidence"]
    return {"add_mm": float(result.metrics["ground_truth"]["add_mm"]), "verdict": confidence["verdict"],
            "named": any("mirrored" in reason for reason in confidence["reasons"]),
            "mirror_fit": "mirror" in confidence["signals"], "cpu_s": _cpu_seconds() - started}


def bench_models(args: argparse.Namespace) -> int:
    from dsareg_engine.commands.render import load_mesh_argument

    options = {"device": args.device if args.device != "auto" else "cpu", **json.loads(args.options)}
    meshes = [(path, load_mesh_argument(path)) for path in args.mesh] or [("phantom", load_mesh_argument(None))]
    print(f"{args.cases} case(s) per row, {args.size} px clinical rig (107°, mirrored LAT), seed {args.seed}; "
          "no initial pose")
    print("| model | row | ADD mm median / max | verdicts | mirror named | mirror fits run | CPU s median |")
    print("|---|---|---|---|---|---|---|")
    for label, mesh in meshes:
        for row in [r for r in ROWS if not args.rows or any(word in r for word in args.rows)]:
            cases = [run_case(mesh, row, args.seed + i, args.size, options) for i in range(args.cases)]
            adds = [case["add_mm"] for case in cases]
            verdicts = ", ".join(f"{v} {sum(c['verdict'] == v for c in cases)}" for v in sorted({c["verdict"] for c in cases}))
            add = "-" if row.startswith("mirrored") else f"{np.median(adds):.4f} / {max(adds):.4f}"
            print(f"| {label} | {row} | {add} | {verdicts} | {sum(c['named'] for c in cases)}/{len(cases)} | "
                  f"{sum(c['mirror_fit'] for c in cases)}/{len(cases)} | {np.median([c['cpu_s'] for c in cases]):.1f} |",
                  flush=True)
    return 0
