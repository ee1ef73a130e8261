"""``dsareg register``: two-view registration from files to result.json and overlays."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..io.case import load_case
from ..pipeline import write_outputs
from ..pose_file import load_pose
from ..registration import CONFIGURATIONS, register
from ..registration.options import parse_options


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("register", help="register a mesh to AP/LAT images; writes result.json and overlays")
    model = parser.add_mutually_exclusive_group(required=True)
    model.add_argument("--mesh", help="vessel mesh file")
    model.add_argument("--volume", nargs="+", help="3D volume: one file, or every file of a DICOM series")
    parser.add_argument("--ap", required=True, help="AP image or mask (PNG/TIFF/JPEG/DICOM XA)")
    parser.add_argument("--lat", required=True, help="LAT image or mask")
    parser.add_argument("--geometry", help="geometry JSON file or preset name; optional with DICOM XA inputs")
    parser.add_argument("--config", default="simultaneous", choices=CONFIGURATIONS)
    parser.add_argument("--initial", help='pose JSON overriding the geometry\'s initial pose')
    parser.add_argument("--ground-truth", help="pose JSON of the true pose (adds error metrics)")
    parser.add_argument("--options", help="registration options as JSON text (see RegistrationOptions)")
    parser.add_argument("--animation", action="store_true", help="also write animation.gif")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--dicom-out", help="also write reg.dcm (Spatial Registration) and overlay_{ap,lat}.dcm here")
    parser.set_defaults(func=run)


def _model_inputs(args: argparse.Namespace) -> dict:
    if args.mesh:
        return {"mesh": Path(args.mesh).read_bytes(), "mesh_name": Path(args.mesh).name}
    paths = [Path(p) for p in args.volume]
    if len(paths) == 1 and paths[0].is_dir():  # a DICOM series folder
        paths = sorted(p for p in paths[0].iterdir() if p.is_file())
    parts = [p.read_bytes() for p in paths]
    return {"volume": parts if len(parts) > 1 else parts[0], "volume_name": paths[0].name}


def run(args: argparse.Namespace) -> int:
    options = json.loads(args.options) if args.options else {}
    options["configuration"] = args.config
    if args.initial:
        options["initial_mesh_to_world"] = load_pose(args.initial).tolist()
    if args.ground_truth:
        options["ground_truth_mesh_to_world"] = load_pose(args.ground_truth).tolist()
    if args.animation:
        options["animation"] = True
    parsed = parse_options(options)
    geometry = args.geometry
    if geometry is not None and Path(geometry).is_file():
        geometry = Path(geometry).read_text()
    model = _model_inputs(args)
    ap_bytes, lat_bytes = Path(args.ap).read_bytes(), Path(args.lat).read_bytes()
    case = load_case(
        **model,
        ap=ap_bytes, ap_name=Path(args.ap).name,
        lat=lat_bytes, lat_name=Path(args.lat).name,
        geometry=geometry, segmentation=parsed.segmentation,
    )
    for warning in case.warnings:
        print(f"warning: {warning}")

    def show(event: dict) -> None:
        print(f"\r{event['stage']:>14} it {event['iteration']:4d} loss {event['loss']:.5f}", end="", flush=True)

    result = register(case.mesh, case.masks, case.rig, parsed, progress=show)
    print()
    out = Path(args.out)
    write_outputs(result, case.masks, out, case.mesh, case.rig, animation=parsed.animation)
    if args.dicom_out:
        from ..io.dicom_out import read_sources, write_dicom_outputs

        sources = read_sources(ap_bytes, lat_bytes, model.get("volume"))
        written = write_dicom_outputs(out, result.mesh_to_world, sources, Path(args.dicom_out))
        print(f"DICOM: {', '.join(sorted(written))} -> {args.dicom_out}")
    metrics = result.metrics
    dice_text = ", ".join(f"{name} dice {view.dice:.3f}" for name, view in result.views.items())
    print(f"{'converged' if metrics['converged'] else 'NOT converged'} ({metrics['reason']}); {dice_text}; "
          f"{metrics['seconds']['total']:.1f} s -> {out / 'result.json'}")
    if "ground_truth" in metrics:
        gt = metrics["ground_truth"]
        print(f"rotation {gt['rotation_error_deg']:.4f} deg, translation {gt['translation_error_mm']:.4f} mm, ADD {gt['add_mm']:.4f} mm")
    return 0
