"""``dsareg register``: two-view registration from files to result.json and overlays."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..errors import DsaregInputError
from ..io.case import load_case
from ..pipeline import write_outputs
from ..pose_file import load_pose
from ..registration import CONFIGURATIONS, register
from ..registration.options import parse_options


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("register", help="register a mesh to AP/LAT images; writes result.json and overlays")
    parser.add_argument("--mesh", required=True, help="vessel mesh file")
    parser.add_argument("--ap", required=True, help="AP image or mask (PNG/TIFF/JPEG/DICOM XA)")
    parser.add_argument("--lat", required=True, help="LAT image or mask")
    parser.add_argument("--geometry", help="geometry JSON file or preset name; optional with DICOM XA inputs")
    parser.add_argument("--config", default="simultaneous", choices=CONFIGURATIONS)
    parser.add_argument("--initial", help='pose JSON overriding the geometry\'s initial pose (a previous result.json works)')
    parser.add_argument("--track", action="store_true",
                        help='re-register after a small motion from --initial (options.mode "track": fast, one start)')
    parser.add_argument("--ground-truth", help="pose JSON of the true pose (adds error metrics)")
    parser.add_argument("--options", help="registration options as JSON text (see RegistrationOptions)")
    parser.add_argument("--animation", action="store_true", help="also write animation.gif")
    parser.add_argument("--out", required=True, help="output directory")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    options = json.loads(args.options) if args.options else {}
    options["configuration"] = args.config
    if args.initial:
        options["initial_mesh_to_world"] = load_pose(args.initial).tolist()
    if args.ground_truth:
        options["ground_truth_mesh_to_world"] = load_pose(args.ground_truth).tolist()
    if args.animation:
        options["animation"] = True
    if args.track:
        if not args.initial:
            raise DsaregInputError("--track re-registers from a previous pose: give it with --initial",
                                   field="--initial", accepted="a pose JSON or a previous result.json")
        options["mode"] = "track"
    parsed = parse_options(options)
    geometry = args.geometry
    if geometry is not None and Path(geometry).is_file():
        geometry = Path(geometry).read_text()
    case = load_case(
        mesh=Path(args.mesh).read_bytes(), mesh_name=Path(args.mesh).name,
        ap=Path(args.ap).read_bytes(), ap_name=Path(args.ap).name,
        lat=Path(args.lat).read_bytes(), lat_name=Path(args.lat).name,
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
    metrics = result.metrics
    dice_text = ", ".join(f"{name} dice {view.dice:.3f}" for name, view in result.views.items())
    print(f"{'converged' if metrics['converged'] else 'NOT converged'} ({metrics['reason']}); {dice_text}; "
          f"{metrics['seconds']['total']:.1f} s -> {out / 'result.json'}")
    if "motion" in metrics:
        print(f"motion since --initial: {metrics['motion']['rotation_deg']:.3f} deg, {metrics['motion']['translation_mm']:.3f} mm")
    if "ground_truth" in metrics:
        gt = metrics["ground_truth"]
        print(f"rotation {gt['rotation_error_deg']:.4f} deg, translation {gt['translation_error_mm']:.4f} mm, ADD {gt['add_mm']:.4f} mm")
    return 0
