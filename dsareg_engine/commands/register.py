"""``dsareg register``: two-view registration from files to result.json and overlays."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..errors import DsaregInputError
from ..registration.options import CONFIGURATIONS
from .arguments import geometry_argument, input_file, json_argument, options_help
from .progress_lines import REQUIRE_CHOICES, VERDICT_NOT_MET_EXIT, ProgressPrinter, ground_truth_text, verdict_meets


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "register", help="register a mesh to AP/LAT images on this machine; writes result.json and overlays",
        description="Register a vessel mesh to a biplane pair (AP and LAT) without a server. Writes result.json, "
                    "overlay_{ap,lat}.png, mask_{ap,lat}.png, loss.png (and animation.gif) into --out and prints a "
                    "summary on stdout (progress and warnings go to stderr: a line per stage when it is not a terminal).",
        epilog="Exit status: 0 done (also when not converged: read the summary), 1 failed, 2 usage or input error, "
               f"{VERDICT_NOT_MET_EXIT} the verdict is below --require.")
    model = parser.add_mutually_exclusive_group(required=True)
    model.add_argument("--mesh", type=input_file, metavar="FILE",
                       help="vessel surface mesh in mm (OBJ, STL, PLY, OFF, GLB)")
    model.add_argument("--volume", nargs="+", metavar="FILE|DIR",
                       help="3D volume instead of a mesh: one file (NIfTI, NRRD, DICOM), every file of a DICOM "
                            "series, or the series' folder; a CTA, TOF-MRA or 3D-DSA (told from its tags; override "
                            "with --options '{\"volume_kind\": \"cta\"}', volume_vessel_min / volume_vessel_max)")
    parser.add_argument("--ap", required=True, type=input_file, metavar="FILE",
                        help="AP DSA image or vessel mask (PNG, TIFF, JPEG, DICOM XA, .rad with its .raw)")
    parser.add_argument("--lat", required=True, type=input_file, metavar="FILE", help="LAT image or mask (as --ap)")
    parser.add_argument("--geometry", metavar="PRESET|FILE|JSON",
                        help="C-arm geometry: a preset name (paper), a geometry JSON file, or JSON text; "
                             "optional when both images are DICOM XA / .rad with geometry in their headers")
    parser.add_argument("--configuration", "--config", dest="config", default="simultaneous", choices=CONFIGURATIONS,
                        metavar="NAME",
                        help=f"which views to use and in which order: {', '.join(CONFIGURATIONS)} (the paper's "
                             "Table 1 rows; default simultaneous). "
                             "Not a settings file: that is `dsareg serve --config`")
    parser.add_argument("--initial", type=input_file, metavar="POSE.json",
                        help='pose file {"mesh_to_world": 4x4} overriding the geometry\'s initial pose '
                             '(a previous result.json works)')
    parser.add_argument("--track", action="store_true",
                        help='re-register after a small motion from --initial (options.mode "track": fast, one start)')
    parser.add_argument("--ground-truth", type=input_file, metavar="POSE.json",
                        help='pose file {"mesh_to_world": 4x4} of the true pose; adds error metrics (ADD, mTRE...)')
    for name in ("ap", "lat"):
        parser.add_argument(f"--{name}-frame", metavar="N|minip",
                            help=f"multi-frame XA: the {name.upper()} frame to use (0-based) or 'minip' (default: "
                                 "maximum opacification; native runs are subtracted first); the views may differ")
    parser.add_argument("--mesh-units", choices=("mm", "cm", "m"),
                        help="the --mesh file's unit (default: the format's own, metres for GLB, else mm)")
    parser.add_argument("--options", metavar="JSON|FILE", help=options_help())
    region = parser.add_mutually_exclusive_group()
    region.add_argument("--region-box", type=float, nargs=6, metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"),
                        help="register only the model's part inside this box (model frame, mm): what the run injected")
    region.add_argument("--region-sphere", type=float, nargs=4, metavar=("X", "Y", "Z", "R"),
                        help="register only the model's part inside this sphere (model frame, mm)")
    region.add_argument("--region-branch", type=float, nargs=3, metavar=("X", "Y", "Z"),
                        help="register only the branch nearest this point (model frame, mm) and what lies downstream of it")
    parser.add_argument("--animation", action="store_true", help="also write animation.gif of the optimization")
    parser.add_argument("--hemodynamics", action="store_true",
                        help="also map contrast arrival and time to peak from both runs onto the model (timed "
                             "multi-frame DICOM XA runs): hemodynamics.json/.ply/.vtk, parametric_{ap,lat}.png")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    parser.add_argument("--dicom-out", metavar="DIR",
                        help="also write reg.dcm (Spatial Registration) and overlay_{ap,lat}.dcm (Secondary Capture) here")
    parser.add_argument("--json", action="store_true", help="print the result JSON on stdout instead of the summary")
    parser.add_argument("--require", choices=REQUIRE_CHOICES,
                        help=f"exit {VERDICT_NOT_MET_EXIT} unless the verdict is at least this (ok, or check = ok or check)")
    parser.set_defaults(func=run)


def _flag_options(args: argparse.Namespace) -> dict:
    """The options the plain flags set (--animation, --hemodynamics, --mesh-units)."""
    flags = {"animation": args.animation or None, "hemodynamics": args.hemodynamics or None,
             "mesh_units": args.mesh_units}
    return {key: value for key, value in flags.items() if value is not None}


def _timed_runs(options, model: dict, ap: bytes, lat: bytes):
    """With ``options.hemodynamics``: the files the step reads, after checking both views are timed runs."""
    if not options.hemodynamics:
        return None
    from ..hemodynamics.intake import check_timed_runs
    from ..io.case import CaseFiles

    files = CaseFiles(ap=ap, lat=lat, mesh=model.get("mesh"), mesh_name=model.get("mesh_name"))
    check_timed_runs(files)
    return files


def _model_inputs(args: argparse.Namespace) -> dict:
    if args.mesh:
        return {"mesh": Path(args.mesh).read_bytes(), "mesh_name": Path(args.mesh).name}
    from ..io.file_parts import FileParts

    paths = [Path(p) for p in args.volume]
    if len(paths) == 1 and paths[0].is_dir():  # a DICOM series folder
        paths = sorted(p for p in paths[0].iterdir() if p.is_file())
        if not paths:
            raise DsaregInputError(f"the folder '{args.volume[0]}' holds no files", field="--volume",
                                   accepted="a volume file, or a folder with the files of a DICOM series")
    for path in paths:  # a missing or unreadable file is named now, not when the series is read
        with path.open("rb"):
            pass
    return {"volume": FileParts.from_paths(paths), "volume_name": paths[0].name}  # read when used, not held


def frame_argument(value: str, flag: str) -> int | str:
    """``--ap-frame`` / ``--lat-frame``: a 0-based frame index or ``minip``."""
    if value == "minip":
        return value
    try:
        return int(value)
    except ValueError:
        raise DsaregInputError(f"'{value}' is not a frame index", field=flag, accepted="an integer ≥ 0 or 'minip'") from None


def run(args: argparse.Namespace) -> int:
    from ..io.case import load_case  # the engine (torch) loads only when a registration runs
    from ..io.volume_kind import VolumeReading
    from ..pipeline import write_outputs
    from ..geometry.pose_file import load_pose
    from ..registration.solver import register
    from ..registration.options import image_reading, parse_options
    from ..hemodynamics.dicom import write_parametric_dicom
    from ..hemodynamics.run import attach

    options = json_argument(args.options, "--options") or {}
    if not isinstance(options, dict):
        raise DsaregInputError("must be a JSON object", field="--options", accepted='e.g. {"starts": 2}')
    options["configuration"] = args.config
    if args.initial:
        options["initial_mesh_to_world"] = load_pose(args.initial).tolist()
    if args.ground_truth:
        options["ground_truth_mesh_to_world"] = load_pose(args.ground_truth).tolist()
    options.update(_flag_options(args))
    if args.region_box:
        options["region"] = {"box_mm": [args.region_box[:3], args.region_box[3:]]}
    elif args.region_sphere:
        options["region"] = {"sphere": {"centre_mm": args.region_sphere[:3], "radius_mm": args.region_sphere[3]}}
    elif args.region_branch:
        options["region"] = {"branch_near_mm": args.region_branch}
    for name in ("ap", "lat"):
        value = getattr(args, f"{name}_frame")
        if value is not None:
            options.setdefault("frames", {})[name] = frame_argument(value, f"--{name}-frame")
    if args.track:
        if not args.initial:
            raise DsaregInputError("--track re-registers from a previous pose: give it with --initial",
                                   field="--initial", accepted="a pose JSON or a previous result.json")
        options["mode"] = "track"
    parsed = parse_options(options)
    geometry = geometry_argument(args.geometry)
    model = _model_inputs(args)
    ap_bytes, lat_bytes = Path(args.ap).read_bytes(), Path(args.lat).read_bytes()
    case = load_case(
        **model,
        ap=ap_bytes, ap_name=Path(args.ap).name,
        lat=lat_bytes, lat_name=Path(args.lat).name,
        geometry=geometry, segmentation=parsed.segmentation, reading=image_reading(parsed),
        volume_reading=VolumeReading.from_options(parsed), mesh_units=parsed.mesh_units,
    )
    timed = _timed_runs(parsed, model, ap_bytes, lat_bytes)  # hemodynamics: refused before registering
    printer = ProgressPrinter()
    for warning in case.warnings:
        printer.message(f"warning: {warning}")
    if case.volume is not None:
        printer.message(f"volume: {case.volume.text()}; {case.volume.faces} faces extracted")
    out = Path(args.out)
    try:
        result = register(case.mesh, case.fitted, case.rig, parsed, progress=printer.update)
        data = write_outputs(result, case.masks, out, case.mesh, case.rig, animation=parsed.animation,
                             images=case.images, progress=printer.update, warnings=case.warnings,
                             readings=case.readings, volume=case.volume.to_dict() if case.volume is not None else None,
                             decisions=case.decisions)  # input_decisions; a close call lowers ok to check
        if timed is not None:
            attach(timed, case, data, out)
    finally:
        printer.close()
    if args.dicom_out:
        from ..io.dicom_out import write_dicom_outputs

        written = write_dicom_outputs(out, result.mesh_to_world, case.sources, Path(args.dicom_out))
        if timed is not None:
            written.update(write_parametric_dicom(out, case.sources, Path(args.dicom_out)))
        print(f"DICOM: {', '.join(sorted(written))} -> {args.dicom_out}", file=sys.stderr)
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        print("\n".join(summary_lines(result, out)))
    verdict = (result.metrics.get("confidence") or {}).get("verdict")
    if not verdict_meets(verdict, args.require):
        print(f"dsareg: verdict {verdict or 'none'} is below --require {args.require}", file=sys.stderr)
        return VERDICT_NOT_MET_EXIT
    return 0


def summary_lines(result, out: Path) -> list[str]:
    """The summary: verdict, convergence, Dice, time (and why, motion, ground-truth errors)."""
    metrics = result.metrics
    dice_text = ", ".join(f"{name} dice {view.dice:.3f}" for name, view in result.views.items())
    confidence = metrics.get("confidence") or {}
    verdict = f"verdict {confidence['verdict']}; " if confidence.get("verdict") else ""
    lines = [f"{verdict}{'converged' if metrics['converged'] else 'NOT converged'} ({metrics['reason']}); {dice_text}; "
             f"{metrics['seconds']['total']:.1f} s -> {out / 'result.json'}"]
    if confidence.get("verdict") in ("check", "failed"):
        lines.append("why: " + "; ".join(str(reason) for reason in confidence.get("reasons", [])))
    if "motion" in metrics:
        lines.append(f"motion since --initial: {metrics['motion']['rotation_deg']:.3f} deg, "
                     f"{metrics['motion']['translation_mm']:.3f} mm")
    if "ground_truth" in metrics:
        lines.append(ground_truth_text(metrics["ground_truth"]))
    return lines
