"""One registration case from its clinical inputs: the entry point of the CLI and the service."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import DsaregInputError
from ..geometry.rig import VIEW_NAMES, Rig, ViewGeometry
from ..geometry.spec import GeometrySpec
from ..mesh import TriangleMesh
from ..vision.vessel_target import binary_mask
from .dicom_identity import DicomSources
from .image_io import LoadedImage, read_image
from .input_decisions import InputDecision
from .limits import DEFAULT_LIMITS, InputLimits
from .mesh_io import decimate, read_mesh_detailed
from .mesh_units import MeshUnit, unit_decision
from ..vision.segmentation import SEGMENTATION_METHODS
from ..vision.segmentation_choice import segmentation_decision
from ..vision.segmentation_scale import SegmentationScale, coverage_at_scale
from .view_roles import Acquisition, named_views
from .xa_run import ImageReading
from .model_cache import CachedModel, ModelStore, model_key
from .volume_io import read_volume, read_volume_identities
from .volume_kind import VolumeReading
from .volume_vessels import VolumeReadout, extract_vessels

ASPECT_TOLERANCE = 0.01


@dataclass
class Case:
    """Everything a registration needs, validated.

    Attributes:
        mesh: the vessel surface (mm; for a volume input, in world LPS mm).
        masks: ``{"ap": bool (H, W), "lat": bool (H, W)}``, each matching its view's
            ``image_size`` ``(W, H)`` exactly.
        targets: what registration fits, per view: the mask itself, or for grey-level DSA
            segmented by ``dsa`` its vessel coverage (float in [0, 1], sub-pixel borders;
            the mask is where it is ≥ 0.5). Empty: fit the masks.
        rig: the two views (resized to the images when needed) and the initial pose.
        warnings: things a person should know (decimation, frame chosen, resizing...).
        kinds: what each input was read as (``{"mesh": "stl", "ap": "dicom-xa", ...}``).
        images: the images as read (``(H, W)`` float, before segmentation), shown under
            the overlays' contours.
        readings: per view, what was read from a multi-frame XA run (frames and mask frames used,
            recipe, shift found; :mod:`.xa_run`); empty for other images.
        volume: for a volume input, what was read from it (kind, thresholds, voxels kept).
        decisions: what was decided about each input, on which measure and with what margin
            (:mod:`.input_decisions`); close calls lower the verdict to ``check``.
        sources: the identity of the DICOM inputs (SOP, study, series, frame of reference, patient and
            study attributes), taken when they were read: what the DICOM outputs refer to, so that
            nothing parses the inputs again (:mod:`.dicom_identity`).
        acquisition: whether the two runs were acquired together, from their DICOM headers (:mod:`.view_roles`);
            None without that evidence. The views are named by their headers' beam angles (a swapped pair is
            swapped back, ``decisions`` says so).
    """

    mesh: TriangleMesh
    masks: dict[str, np.ndarray]
    rig: Rig
    warnings: list[str] = field(default_factory=list)
    kinds: dict[str, str] = field(default_factory=dict)
    images: dict[str, np.ndarray] = field(default_factory=dict)
    targets: dict[str, np.ndarray] = field(default_factory=dict)
    readings: dict[str, dict] = field(default_factory=dict)
    volume: VolumeReadout | None = None
    sources: DicomSources = field(default_factory=DicomSources)
    decisions: list[InputDecision] = field(default_factory=list)
    acquisition: Acquisition | None = None

    @property
    def fitted(self) -> dict[str, np.ndarray]:
        """The per-view registration targets (``targets`` when set, else ``masks``)."""
        return self.targets or self.masks


@dataclass(frozen=True)
class CaseFiles:
    """The inputs of one case as given, before reading: what :func:`load_case` takes, as one value.

    Attributes:
        ap, lat: each image file's bytes, or ``[.rad bytes, .raw bytes]``.
        mesh / volume: exactly one: a mesh file, or a volume (one file, a DICOM series as a list of
            files, or a ``.rad`` + ``.raw`` pair as a list).
        ap_name, lat_name, mesh_name, volume_name: file names (their suffix helps tell formats), or None.
        geometry: the parsed geometry, or ``None`` to take it from the image headers.
        frame: multi-frame DICOM: a frame number, ``"minip"``, or ``None`` (maximum opacification), both views.
        reading: per-view frames and subtraction settings (:class:`.xa_run.ImageReading`); overrides ``frame``.
        warnings: notes from getting the files (e.g. a DICOMweb fetch), reported before the case's own.
    """

    ap: bytes | list[bytes] | None
    lat: bytes | list[bytes] | None
    mesh: bytes | None = None
    volume: bytes | list[bytes] | None = None
    ap_name: str | None = None
    lat_name: str | None = None
    mesh_name: str | None = None
    volume_name: str | None = None
    geometry: GeometrySpec | None = None
    frame: int | str | None = None
    warnings: tuple[str, ...] = ()
    reading: ImageReading | None = None


def load_case_files(files: CaseFiles, segmentation: str = "auto", limits: InputLimits = DEFAULT_LIMITS,
                    reading: ImageReading | None = None, volume_reading: VolumeReading | None = None,
                    mesh_units: str | None = None, model_store: ModelStore | None = None) -> Case:
    """:func:`load_case` for a :class:`CaseFiles`; its ``warnings`` come first in the case's.

    ``reading`` (e.g. from the job's options) adds to the files' own: frames given by both must agree.
    """
    own = files.reading if files.reading is not None else ImageReading.both(files.frame)
    case = load_case(mesh=files.mesh, mesh_name=files.mesh_name, volume=files.volume, volume_name=files.volume_name,
                     ap=files.ap, ap_name=files.ap_name, lat=files.lat, lat_name=files.lat_name,
                     geometry=files.geometry, segmentation=segmentation, limits=limits,
                     reading=own.merged(reading), volume_reading=volume_reading, mesh_units=mesh_units,
                     model_store=model_store)
    case.warnings[:0] = list(files.warnings)
    return case


def load_case(
    *,
    mesh: bytes | None = None,
    mesh_name: str | None = None,
    volume: bytes | list[bytes] | None = None,
    volume_name: str | None = None,
    ap: bytes | list[bytes] | None = None,
    ap_name: str | None = None,
    lat: bytes | list[bytes] | None = None,
    lat_name: str | None = None,
    geometry: GeometrySpec | None = None,
    segmentation: str = "auto",
    limits: InputLimits = DEFAULT_LIMITS,
    frame: int | str | None = None,
    reading: ImageReading | None = None,
    volume_reading: VolumeReading | None = None,
    mesh_units: str | None = None,
    model_store: ModelStore | None = None,
) -> Case:
    """Read, validate and segment the inputs of one case.

    Args:
        mesh / volume: exactly one: a surface mesh file's bytes, or a volume (one file,
            a DICOM series as a list of files, or a ``.rad`` + ``.raw`` pair as a list).
        ap, lat: each image file's bytes, or ``[.rad bytes, .raw bytes]``.
        geometry: the parsed geometry (:func:`dsareg_engine.geometry.spec.parse_geometry`, or
            :meth:`GeometrySpec.from_json` for a stored one), or ``None`` to take it from the
            images (DICOM XA tags or ``.rad`` headers).
        segmentation: one of :data:`~dsareg_engine.vision.segmentation.SEGMENTATION_METHODS` (``"auto"``:
            masks as they are, grey images by the DSA border model or the angiogram network).
        frame: for multi-frame DICOM: a frame number, ``"minip"``, or ``None``
            (maximum opacification), both views.
        reading: per-view frames and the subtraction of native runs (:class:`.xa_run.ImageReading`);
            when given, ``frame`` is not used.
        volume_reading: how to read vessels from a volume (kind, thresholds); ``None`` = detect.
        mesh_units: the mesh file's unit (``mm``, ``cm``, ``m``); ``None``: the format's own (GLB: metres), else
            mm. A model whose size is implausible for head arteries in that unit is refused (:mod:`.mesh_units`).
        model_store: where a volume's model is kept for the next case on the same volume (:mod:`.model_cache`);
            ``None``: the volume is read every time.

    Raises:
        DsaregInputError: with ``field`` naming the input at fault.
    """
    warnings: list[str] = []
    kinds: dict[str, str] = {}
    if segmentation not in SEGMENTATION_METHODS:
        raise DsaregInputError(
            f"unknown method '{segmentation}'", field="segmentation", accepted=", ".join(SEGMENTATION_METHODS)
        )
    decisions: list[InputDecision] = []
    surface, volume_readout, volume_sources = _read_surface(mesh, mesh_name, volume, volume_name, limits, warnings,
                                                            kinds, volume_reading, mesh_units, decisions, model_store)

    images: dict[str, LoadedImage] = {}
    reading = reading if reading is not None else ImageReading.both(frame)
    for name, data, filename in (("ap", ap, ap_name), ("lat", lat, lat_name)):
        if data is None or len(data) == 0:
            raise DsaregInputError("the image is missing or empty", field=name, accepted="a DSA image or a mask")
        images[name] = read_image(data, filename, limits, field_name=name, reading=reading.for_view(name))
    images, acquisition = named_views(images, geometry is not None, decisions, kinds, warnings)

    rig = _resolve_rig(geometry, images, warnings, kinds)

    masks: dict[str, np.ndarray] = {}
    targets: dict[str, np.ndarray] = {}
    views: dict[str, ViewGeometry] = {}
    pitches: list[InputDecision] = []
    for name in VIEW_NAMES:
        views[name] = _view_for_image(rig, name, images[name], warnings)
        targets[name] = _segmented(name, images[name], views[name], segmentation, pitches)
        masks[name] = binary_mask(targets[name])
    rig = Rig(views=views, initial_mesh_to_world=rig.initial_mesh_to_world if rig.initial_pose_given else None)
    return Case(mesh=surface, masks=masks, rig=rig, warnings=warnings, kinds=kinds,
                images={name: images[name].pixels for name in VIEW_NAMES}, targets=targets,
                readings={name: images[name].reading for name in VIEW_NAMES if images[name].reading},
                volume=volume_readout, sources=_sources(images, volume_sources), acquisition=acquisition,
                decisions=decisions + [decision for name in VIEW_NAMES for decision in images[name].decisions] + pitches)


def _segmented(name: str, image: LoadedImage, view: ViewGeometry, segmentation: str,
               decisions: list[InputDecision]) -> np.ndarray:
    """The registration target of one view (:func:`~dsareg_engine.vision.segmentation_scale.coverage_at_scale`),
    its pitch and ``auto``'s choice appended to ``decisions``."""
    method = "mask" if image.is_mask and segmentation == "auto" else segmentation
    spacing_mm = min(view.pixel_spacing_mm)
    target, factor, choice = coverage_at_scale(image.pixels, method, spacing_mm, field_name=name,
                                               field_of_view=image.field_of_view)
    if factor > 1:
        decisions.append(_pitch_decision(name, spacing_mm, factor))
    if choice is not None and choice.agreement is not None:
        decisions.append(segmentation_decision(name, choice))
    return target


def _pitch_decision(name: str, spacing_mm: float, factor: int) -> InputDecision:
    """The record of a grey-level image segmented on ``factor`` × ``factor`` averaged pixels (:mod:`~dsareg_engine.vision.segmentation_scale`)."""
    return InputDecision(name, "segmentation pitch", f"{factor}x{factor} pixels averaged ({factor * spacing_mm:.3f} mm)",
                         f"detector pixel spacing (mm) finer than {SegmentationScale().pitch_mm:g} mm / 1.5",
                         round(float(spacing_mm), 5), source="tag")


def _sources(images: dict[str, LoadedImage], volume: DicomSources) -> DicomSources:
    """The DICOM identities the readers took: the AP and LAT images', then the volume's instances."""
    unreadable = tuple(name for name in VIEW_NAMES if images[name].dicom_unreadable) + volume.unreadable
    return DicomSources(ap=images["ap"].dicom, lat=images["lat"].dicom, volume=volume.volume, unreadable=unreadable)



def _read_surface(mesh: bytes | None, mesh_name: str | None, volume: bytes | list[bytes] | None,
                  volume_name: str | None, limits: InputLimits, warnings: list[str],
                  kinds: dict[str, str], volume_reading: VolumeReading | None = None, mesh_units: str | None = None,
                  decisions: list[InputDecision] | None = None, model_store: ModelStore | None = None,
                  ) -> tuple[TriangleMesh, VolumeReadout | None, DicomSources]:
    """The vessel surface from exactly one of a mesh or a volume (read by its kind, meshed, decimated), and for a
    volume what was read from it and its DICOM identities (``DicomSources.volume``); the mesh's unit (its size
    checked) is appended to ``decisions``."""
    decisions = [] if decisions is None else decisions
    has_mesh = mesh is not None and (len(mesh) > 0 or mesh_name is not None)
    has_volume = volume is not None
    if has_mesh == has_volume:
        raise DsaregInputError(
            "give exactly one of a mesh or a volume" + (" (both were given)" if has_mesh else ""),
            field="mesh",
            accepted="a surface mesh (OBJ/STL/PLY/OFF/GLB) or a 3D volume (NIfTI/NRRD/DICOM/.rad)",
        )
    if has_mesh:
        result = read_mesh_detailed(mesh, mesh_name, limits, field_name="mesh", units=mesh_units)
        decisions.append(unit_decision(result.mesh, result.unit, "mesh"))
        kinds["mesh"] = result.format
        warnings.extend(result.warnings)
        return result.mesh, None, DicomSources()
    key = model_key(volume, volume_name, volume_reading, limits.working_faces) if model_store is not None else None
    model = model_store.get(key) if model_store is not None and key is not None else None
    if model is not None:  # the same volume read the same way before: its headers only, for the DICOM outputs
        identities, unreadable = read_volume_identities(volume, volume_name, field_name="volume")
    else:
        model, identities, unreadable = _read_volume_model(volume, volume_name, limits, volume_reading)
        if model_store is not None and key is not None:
            model_store.put(key, model)
    warnings.extend(model.warnings)
    decisions.extend(model.readout.decisions)  # kind, vessel window, bone threshold, vessel shape
    kinds["volume"] = model.kind
    sources = DicomSources(volume=identities, unreadable=("volume",) if unreadable else ())
    return model.surface, model.readout, sources


def _read_volume_model(volume: bytes | list[bytes], volume_name: str | None, limits: InputLimits,
                       volume_reading: VolumeReading | None) -> tuple[CachedModel, tuple, bool]:
    """A volume read, its vessels extracted, the surface decimated to the working budget: the model, the volume's
    DICOM identities and whether one was unreadable."""
    loaded = read_volume(volume, volume_name, limits, field_name="volume")
    warnings = list(loaded.warnings)
    extraction = extract_vessels(loaded, volume_reading, field_name="volume", release=True)
    surface = extraction.mesh
    unit_decision(surface, MeshUnit("mm", "tag"), "volume")  # a size no head has: a wrong voxel spacing
    if surface.n_faces > limits.working_faces:
        original = surface.n_faces
        surface = decimate(surface, limits.working_faces)
        warnings.append(f"volume: surface decimated from {original} to {surface.n_faces} faces")
    model = CachedModel(surface, extraction.readout, tuple(warnings), loaded.kind)
    return model, loaded.dicom, loaded.dicom_unreadable


def _view_for_image(rig: Rig, name: str, image: LoadedImage, warnings: list[str]) -> ViewGeometry:
    """The rig's ``name`` view, rescaled to the image when only the size (not the aspect ratio) differs."""
    if name not in rig.views:
        raise DsaregInputError(f"the geometry has no '{name}' view", field="geometry.views")
    view = rig.views[name]
    width, height = image.image_size
    if (width, height) != view.image_size:
        view_aspect = view.width / view.height
        if abs(width / height - view_aspect) > ASPECT_TOLERANCE * view_aspect:
            raise DsaregInputError(
                f"image is {width}x{height} but the geometry's {name} view is "
                f"{view.width}x{view.height} (different aspect ratio)",
                field=name,
                accepted=f"an image of {view.width}x{view.height} or the same aspect ratio",
            )
        warnings.append(f"{name}: geometry {view.width}x{view.height} rescaled to the image's {width}x{height}")
        view = view.resized(width, height)
    return view

def _resolve_rig(geometry: GeometrySpec | None, images: dict[str, LoadedImage], warnings: list[str],
                 kinds: dict[str, str]) -> Rig:
    """The given geometry, else the one the image headers carry (DICOM XA tags, ``.rad``)."""
    if geometry is not None:
        if not isinstance(geometry, GeometrySpec):
            raise TypeError(f"load_case takes geometry as a GeometrySpec (see parse_geometry), not {type(geometry).__name__}")
        kinds["geometry"] = geometry.source
        if any(image.geometry is not None for image in images.values()):
            warnings.append("geometry: the explicit geometry was used; the geometry in the image headers was ignored")
        return geometry.rig
    missing = [name for name in VIEW_NAMES if images[name].geometry is None]
    if missing:
        raise DsaregInputError(
            f"no geometry was given and the {' and '.join(missing)} image(s) carry none",
            field="geometry",
            accepted="a preset name (e.g. 'paper'), a JSON geometry, or DICOM XA / .rad images with geometry",
        )
    kinds["geometry"] = "headers"
    return Rig(views={name: images[name].geometry for name in VIEW_NAMES})
