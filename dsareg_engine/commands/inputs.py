"""``dsareg inspect``, ``dsareg segment`` and ``dsareg mesh``: look at and convert clinical inputs."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..errors import DsaregInputError
from ..vision.segmentation import SEGMENTATION_METHODS


def add_parser(subparsers) -> None:
    inspect = subparsers.add_parser("inspect", help="say what input files are: kind, size, spacing, geometry")
    inspect.add_argument(
        "files",
        nargs="+",
        metavar="FILE",
        help="mesh, volume (a DICOM series folder, a .rad with its .raw, a .mhd / .nhdr with its data file), image, "
             "or geometry JSON",
    )
    _add_volume_reading(inspect)
    inspect.set_defaults(func=_inspect)

    segment = subparsers.add_parser("segment", help="segment the vessels of a DSA image into a PNG mask")
    segment.add_argument("image", metavar="IMAGE", help="DSA image (PNG, TIFF, JPEG, DICOM XA, .rad with its .raw)")
    segment.add_argument("--out", required=True, metavar="MASK.png", help="where to write the 0/255 mask")
    segment.add_argument("--method", choices=SEGMENTATION_METHODS, default="auto",
                         help="auto: masks as they are; grey images by the dsa border model where it agrees with "
                              "the network, else by the network; network: the U-Net trained on real X-ray "
                              "angiograms; frangi: its classical fallback; dsa, otsu, vesselness: the older "
                              "methods (default auto)")
    segment.add_argument("--frame", default=None, help="multi-frame DICOM: a frame number or 'minip'")
    segment.set_defaults(func=_segment)

    mesh = subparsers.add_parser("mesh", help="extract the vessel surface of a 3D volume")
    mesh.add_argument("volume", metavar="VOLUME", help="NIfTI, NRRD (.nrrd, .nhdr), MetaImage (.mha, .mhd), legacy VTK "
                      "structured points, DICOM (file or series folder), or .rad (+ .raw); a label map or mask too")
    mesh.add_argument("--out", required=True, metavar="MESH.obj", help="output mesh (OBJ, STL, PLY by suffix)")
    mesh.add_argument("--faces", type=int, default=None, help="face budget (default: the working budget)")
    _add_volume_reading(mesh)
    mesh.add_argument("--mip", metavar="PICTURE.png", default=None,
                      help="where to write the MIP picture of the kept vessel voxels over the volume "
                           "(default: beside --out, named <out>_mip.png)")
    mesh.set_defaults(func=_mesh)


def _add_volume_reading(parser) -> None:
    from ..io.volume_kind import VOLUME_KINDS

    parser.add_argument("--volume-kind", choices=VOLUME_KINDS, default="auto",
                        help="cta, mra (TOF), 3d-dsa (already subtracted), or auto: from the DICOM tags and values")
    parser.add_argument("--vessel-min", type=float, default=None, metavar="VALUE",
                        help="lowest vessel value (HU for CTA, intensity otherwise; default: estimated)")
    parser.add_argument("--vessel-max", type=float, default=None, metavar="HU",
                        help="CTA: HU from which a voxel is bone (default 700)")
    parser.add_argument("--labels", type=int, nargs="+", default=None, metavar="LABEL",
                        help="a label map's vessel labels (default: every label above 0)")


def _volume_reading(args: argparse.Namespace):
    from ..io.volume_kind import VolumeReading

    labels = getattr(args, "labels", None)
    return VolumeReading(getattr(args, "volume_kind", "auto"), getattr(args, "vessel_min", None),
                         getattr(args, "vessel_max", None), tuple(labels) if labels else None)


def _cli_error(exc: DsaregInputError) -> DsaregInputError:
    """``exc`` naming the command line's flags (``--vessel-min``) instead of the server's options."""
    from ..io.volume_kind import on_command_line

    return DsaregInputError(on_command_line(exc.message), field=exc.field, accepted=on_command_line(exc.accepted))


# ---- reading files from disk (the readers themselves only see bytes) -------------------


def _read(path: Path, field_name: str) -> bytes:
    if not path.exists():
        raise DsaregInputError(f"'{path}' does not exist", field=field_name)
    return path.read_bytes()


def _file_parts(path: Path, field_name: str) -> bytes | list[bytes]:
    """A folder becomes its files (a DICOM series); a .rad brings its .raw."""
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))
        if not files:
            raise DsaregInputError(f"folder '{path}' is empty", field=field_name)
        return [p.read_bytes() for p in files]
    detached = _detached_data(path, field_name)
    if detached is not None:
        return detached
    if path.suffix.lower() == ".rad":
        raw = path.with_suffix(".raw")
        if not raw.exists():
            raise DsaregInputError(f"'{raw.name}' (the .raw beside the .rad) is missing", field=field_name)
        return [_read(path, field_name), raw.read_bytes()]
    if path.suffix.lower() == ".raw" and path.with_suffix(".rad").exists():
        return [path.with_suffix(".rad").read_bytes(), _read(path, field_name)]
    return _read(path, field_name)


def _detached_data(path: Path, field_name: str) -> list[bytes] | None:
    """A ``.mhd`` / ``.nhdr`` header and the data file it names (beside it), or None for other files."""
    from ..io.volume_formats import detached_data_file

    fmt = {".mhd": "metaimage", ".nhdr": "nrrd"}.get(path.suffix.lower())
    if fmt is None:
        return None
    header = _read(path, field_name)
    name = detached_data_file(header, fmt)
    if name is None:
        return None
    data = path.parent / name
    if not data.is_file():
        raise DsaregInputError(f"'{name}' (the data file its header names) is missing beside it", field=field_name)
    return [header, data.read_bytes()]


def _frame(value: str | None):
    if value is None or value == "minip":
        return value
    try:
        return int(value)
    except ValueError:
        raise DsaregInputError(
            f"'{value}' is not a frame number", field="frame", accepted="an integer or 'minip'"
        ) from None


# ---- inspect --------------------------------------------------------------------------------


def describe(path: Path, reading=None) -> list[str]:
    """Lines describing one input file (what ``dsareg inspect`` prints); ``reading``: how to read a volume's vessels.
    The warnings the readers' libraries raise (pydicom, Pillow) become ``warning:`` lines, not stderr."""
    from ..io.xa_pixels import caught_warnings

    caught: list[str] = []
    with caught_warnings(caught, path.name):
        lines = _describe(path, reading)
    return lines + [line for line in (f"  warning: {w}" for w in caught) if line not in lines]


def _describe(path: Path, reading=None) -> list[str]:
    from ..geometry.spec import parse_geometry
    from ..io import rad
    from ..io.image_io import detect_image_format
    from ..io.mesh_io import detect_mesh_format, read_mesh_detailed
    from ..io.volume_io import detect_volume_format, read_volume

    field_name = path.name
    data = _file_parts(path, field_name)
    lines = [f"{path}:"]
    first = data[0] if isinstance(data, list) else data
    if isinstance(data, list) and len(data) == 2 and rad.looks_like_rad(first[:4096]):
        header = rad.parse_rad_header(first, field_name=field_name)
        kind = "rad-volume" if header.ndim == 3 else "rad-image"
    elif isinstance(data, list):
        kind = "volume"
    elif first.lstrip()[:1] == b"{":
        kind = "geometry"
    elif detect_volume_format(first) in ("nifti", "nrrd", "metaimage", "vtk-image"):
        kind = "volume"
    elif detect_image_format(first) in ("png", "jpeg", "tiff"):
        kind = "image"
    elif detect_image_format(first) == "dicom":
        kind = "dicom"
    elif detect_mesh_format(first) is not None or path.suffix.lower().lstrip(".") in (
        "obj",
        "stl",
        "ply",
        "off",
        "glb",
        "vtp",
    ):
        kind = "mesh"
    else:
        raise DsaregInputError("is not a recognised mesh, volume, image or geometry file", field=field_name)

    if kind == "dicom":  # a multi-frame volume or an XA image
        try:
            read_volume([first], path.name, field_name=field_name)
            kind = "volume"
        except DsaregInputError:
            kind = "image"
    if kind == "geometry":
        rig = parse_geometry(first, field=field_name).rig
        lines.append("  kind: geometry")
        for name, view in rig.views.items():
            lines.append(f"  {name}: {_view_text(view)}")
        if len(rig.views) == 2:
            lines.append(f"  angle between views: {rig.angle_between_views_deg():.1f} deg")
    elif kind == "mesh":
        result = read_mesh_detailed(first, path.name, field_name=field_name)
        extent = np.ptp(result.mesh.vertices, axis=0)
        lines += [
            f"  kind: mesh ({result.format})",
            f"  faces: {result.original_faces} (working: {result.mesh.n_faces})",
            f"  unit: {_unit_text(result.unit)}",
            f"  extent mm: {np.round(extent, 2).tolist()}",
        ]
        lines += _unit_check_lines(result)
        lines += [f"  warning: {w}" for w in result.warnings]
    elif kind in ("volume", "rad-volume"):
        volume = read_volume(data, path.name, field_name=field_name)
        lines += [
            f"  kind: volume ({volume.kind})",
            f"  size: {list(volume.data.shape)}",
            f"  spacing mm: {[round(s, 4) for s in volume.spacing_mm]}",
            f"  intensity: [{float(volume.data.min()):.4g}, {float(volume.data.max()):.4g}]",
        ]
        lines += _vessel_lines(volume, reading, field_name)
        lines += [f"  warning: {w}" for w in volume.warnings]
    else:
        lines += _image_or_refusal(data, path.name, field_name)
    return lines


class RefusedInput(Exception):
    """A file that reads, but not as registration would use it: ``lines`` describe it, ``error`` says why."""

    def __init__(self, lines: list[str], error: DsaregInputError):
        super().__init__(str(error))
        self.lines, self.error = lines, error


def _image_or_refusal(data, name: str, field_name: str) -> list[str]:
    """The image's lines; a run that registration refuses (no contrast, a recipe it cannot apply) is still
    described as stored, and :class:`RefusedInput` carries the lines and the reason."""
    from ..io.image_io import read_image
    from ..io.xa_run import RunReading

    try:
        return image_lines(read_image(data, name, field_name=field_name))
    except DsaregInputError as exc:
        try:
            stored = read_image(data, name, field_name=field_name, reading=RunReading(subtraction="off"))
        except DsaregInputError:
            raise exc from None
        if stored.reading.get("frames", 1) <= 1:
            raise
        raise RefusedInput(image_lines(stored), exc) from None


def image_lines(image) -> list[str]:
    """What ``inspect`` says about a 2D image: kind, size, geometry (or the part of it the file holds), field of
    view, the run's reading, warnings."""
    height, width = image.pixels.shape
    lines = [f"  kind: image ({image.kind}{', mask' if image.is_mask else ''})", f"  size: {width}x{height}"]
    lines += geometry_lines(image.geometry, image.geometry_tags)
    for decision in image.decisions:
        if decision.what == "field of view":
            lines.append(f"  field of view: {decision.chosen} ({decision.basis})")
    if image.annotation_mask is not None:
        lines.append(f"  overlay graphics: {int(image.annotation_mask.sum())} px drawn over the image (masked)")
    lines += reading_lines(image.reading)
    lines += [f"  warning: {w}" for w in image.warnings]
    return lines


def geometry_lines(view, found: dict) -> list[str]:
    """The geometry, or what the file holds of it (angles) and which tags are missing."""
    from ..io.dicom_xa import GEOMETRY_TAGS

    angles = [f"{name} {found[key]:.1f} deg" for name, key in (("primary", "PositionerPrimaryAngle"),
                                                               ("secondary", "PositionerSecondaryAngle"))
              if isinstance(found.get(key), float)]
    angle_text = f"C-arm angles {', '.join(angles)} (primary: LAO+, secondary: CRA+)" if angles else ""
    if view is not None:
        return [f"  geometry: {_view_text(view)}"] + ([f"  {angle_text}"] if angle_text else [])
    if not found:
        return ["  geometry: none in the file"]
    alternatives = {"DistanceSourceToPatient": "DistanceSourceToIsocenter", "ImagerPixelSpacing": "PixelSpacing"}
    missing = [k for k in GEOMETRY_TAGS if k not in found and alternatives.get(k) not in found]
    present = [k for k in found if not k.startswith("Positioner")]
    text = "; ".join(part for part in (angle_text, f"found {', '.join(present)}" if present else "",
                                       f"missing {', '.join(missing)}" if missing else "") if part)
    return [f"  geometry: incomplete in the file: {text} (a geometry file is needed to register)"]


def _unit_text(unit) -> str:
    """How ``inspect`` names the unit a mesh was read in."""
    return unit.unit + {"tag": " (the format's unit)", "option": " (as given)"}.get(unit.source, " (no unit in the "
                                                                                              "format: mm assumed)")


def _unit_check_lines(result) -> list[str]:
    """A line when the mesh's size is implausible for head arteries in the unit read (the registration refuses it)."""
    from ..io.mesh_units import unit_decision

    try:
        unit_decision(result.mesh, result.unit, "mesh")
    except DsaregInputError as exc:
        return [f"  units: refused: {exc.message} (accepted: {exc.accepted})"]
    return []


def _vessel_lines(volume, reading, field_name: str) -> list[str]:
    """What the vessel reader keeps of a volume (or why it refuses it)."""
    from ..io.volume_vessels import extract_vessels

    try:
        readout = extract_vessels(volume, reading, field_name=field_name).readout
    except DsaregInputError as exc:
        return [f"  vessels: refused: {_cli_error(exc).message}"]
    levels = ", ".join(f"{name} {value:.0f}" for name, value in (("tissue", readout.tissue_level),
                                                                 ("vessels", readout.vessel_level)) if value is not None)
    return [f"  volume kind: {readout.kind} ({readout.kind_source})",
            f"  vessel window: {readout.window()}" + (f" (estimated {levels})" if levels else "")
            + ("" if readout.surface == "level" else f"; surface at each vessel's {readout.surface}"),
            f"  voxels kept: {readout.voxels_kept} of {readout.voxels_total} in {readout.components} component(s); "
            f"{readout.faces} faces"]


def reading_lines(reading: dict) -> list[str]:
    """What ``inspect`` says about a multi-frame XA run (frame indices 0-based)."""
    if not reading or reading.get("frames", 1) <= 1:
        return []
    lines = [f"  frames: {reading['frames']}, {reading['run']} ({reading['why']})"]
    if reading["run"] == "native":
        lines.append(f"  pixel intensity: {reading['pixel_intensity_relationship']}, sign {reading['sign']:+d} "
                     "(subtracted in the log domain)")
        recipe = reading.get("recipe")
        if isinstance(recipe, list):
            for number, item in enumerate(recipe):
                details = ", ".join(f"{k} {v}" for k, v in item.items() if k != "operation")
                lines.append(f"  recipe item {number}: {item['operation']} ({details}; DICOM frame numbers)")
        else:
            lines.append(f"  recipe: {recipe}")
        lines.append(f"  mask frames used: {reading['mask_frame_indices']} (0-based)")
        shift = reading["mask_shift_px"]
        lines.append(f"  mask moved onto the contrast frame by {shift['total_px']} px (down, right): "
                     f"recipe {shift['recipe_px']}, patient motion found {shift['found_px']}")
    if reading.get("combined") == "minip":
        lines.append(f"  image: MinIP of frames {reading.get('frame_indices')} (0-based)")
    if reading.get("frame_index") is not None:
        lines.append(f"  frame used: {reading['frame_index']} (0-based; DICOM frame number {reading['frame_number']}); "
                     "its geometry is the one shown")
    return lines


def _view_text(view) -> str:
    return (
        f"{view.width}x{view.height} px, spacing {[round(s, 4) for s in view.pixel_spacing_mm]} mm, "
        f"SID {view.sid_mm:.1f} mm, source at {np.round(view.source_position_world, 1).tolist()} mm"
    )


def _inspect(args: argparse.Namespace) -> int:
    """Every file described on stdout; one that cannot be read says why on stderr, and the others are still read
    (a run registration refuses is described as stored, with the reason). Exit status: the worst file's
    (:func:`.failures.explain`: 2 for an input that cannot be used), 0 when all read."""
    import sys

    from .failures import explain

    status, failed = 0, 0
    for name in args.files:
        try:
            print("\n".join(describe(Path(name), _volume_reading(args))))
        except RefusedInput as refused:
            status, failed = max(status, 2), failed + 1
            print("\n".join([f"{name}: (frames as stored)", *refused.lines, f"  refused: {refused.error}"]))
        except Exception as exc:  # reported per file; the others are still read
            if getattr(args, "debug", False):
                raise
            code, message = explain(exc)
            status, failed = max(status, code), failed + 1
            print(f"dsareg: error: {name}: {message}", file=sys.stderr)
    if failed:
        print(f"inspect: {failed} of {len(args.files)} file(s) could not be read or are refused", file=sys.stderr)
    return status


# ---- segment / mesh ----------------------------------------------------------------------


def _segment(args: argparse.Namespace) -> int:
    from PIL import Image

    from ..io.image_io import read_image
    from ..vision.segmentation import segment_vessels_and_choice

    path = Path(args.image)
    image = read_image(_file_parts(path, "image"), path.name, frame=_frame(args.frame), field_name="image")
    method = "mask" if args.method == "auto" and image.is_mask else args.method
    mask, choice = segment_vessels_and_choice(image.pixels, method, field_name="image",
                                              field_of_view=image.field_of_view)
    Image.fromarray(mask.astype(np.uint8) * 255).save(args.out, format="PNG")
    for warning in image.warnings:
        print(f"warning: {warning}")
    how = method if choice is None else (f"auto: {choice.method}" + (
        "" if choice.agreement is None else f", dsa / network masks agree at Dice {choice.agreement:.2f}"))
    print(f"{args.out}: {mask.shape[1]}x{mask.shape[0]} mask, {int(mask.sum())} vessel pixels "
          f"({100 * mask.mean():.1f} % of the image; {how})")
    return 0


def _mesh(args: argparse.Namespace) -> int:
    from ..io.limits import DEFAULT_LIMITS
    from ..io.mesh_io import decimate
    from ..io.volume_io import read_volume
    from ..io.volume_picture import mip_picture
    from ..io.volume_vessels import extract_vessels
    from ..overlay import write_png

    path = Path(args.volume)
    volume = read_volume(_file_parts(path, "volume"), path.name)
    try:
        extraction = extract_vessels(volume, _volume_reading(args))
    except DsaregInputError as exc:
        raise _cli_error(exc) from None
    mesh = extraction.mesh
    budget = args.faces or DEFAULT_LIMITS.working_faces
    extracted = mesh.n_faces
    mesh = decimate(mesh, budget)
    mesh.save(args.out)
    out = Path(args.out)
    picture = Path(args.mip) if args.mip else out.with_name(out.stem + "_mip.png")
    readout, excluded = extraction.readout, extraction.excluded  # (each made on the whole grid when asked for)
    write_png(picture, mip_picture(volume.data, volume.affine, extraction.kept,
                                   f"{readout.kind}: {readout.voxels_kept} vessel voxels kept (red), {extracted} faces"
                                   + ("; MIP without what was set aside (bone / scalp)"
                                      if excluded is not None else ""), excluded))
    for warning in volume.warnings:
        print(f"warning: {warning}")
    print(f"volume: {readout.text()}")
    print(f"{args.out}: {mesh.n_faces} faces (extracted {extracted}), world = patient LPS mm; picture {picture}")
    return 0
