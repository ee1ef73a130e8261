"""A registration result as DICOM: a Spatial Registration object and Secondary Capture overlays.

No network here (DICOMweb lives in the service). Written with pydicom directly.

**REG** (Spatial Registration Storage, SOP Class 1.2.840.10008.5.1.4.1.1.66.1; modules Patient,
General Study, General Series, Spatial Registration Series, Frame of Reference, General
Equipment, Spatial Registration, Common Instance Reference, SOP Common):

* The instance's Frame of Reference (the *Registered RCS*, "A") is the C-arm / XA world frame of
  the registration (isocentre origin, patient LPS axes; see ``io/dicom_xa.py``): the XA images'
  own ``FrameOfReferenceUID`` when they carry one (enhanced XA), else a name-based UID derived
  from the two XA instances, so every registration of the same biplane pair shares one frame.
* One Registration Sequence item describes the vessel model's source frame ("B"): the volume's
  ``FrameOfReferenceUID`` when the model came from a DICOM volume (its slices in the item's
  Referenced Image Sequence), a new UID otherwise. Its Matrix Registration holds one RIGID matrix.
  A second item names the XA images (Referenced Image Sequence) in the Registered RCS itself with
  an identity matrix, so that every instance of Common Instance Reference is referenced (C.12.2).
* **Direction.** PS3.3 C.20.2.1.1: the Frame of Reference Transformation Matrix ``AMB``
  "describes how to transform a point (Bx, By, Bz) with respect to RCS B into (Ax, Ay, Az) with
  respect to RCS A", A being the Registered RCS established by this instance. We therefore write
  ``AMB = mesh_to_world`` unchanged: registered (volume / model) frame mm → XA world mm,
  row-major, each value the closest decimal string of 16 characters (round trip ≲ 1e-10 mm).

**Overlays**: Secondary Capture Image Storage (1.2.840.10008.5.1.4.1.1.7), RGB, one instance
per view (and the loss plot) in one new series of the same study.

**Identity**: the patient and study attributes are copied from the DICOM inputs (XA first, then
the volume); when no input is DICOM they are left empty (Type 2) and a new Study Instance UID is
made. Nothing about the patient is invented or logged. The inputs are not parsed here: the case
reader keeps what is needed (:class:`.dicom_identity.DicomSources`, ``case.sources``).
"""

from __future__ import annotations

import datetime as _dt
import io
import uuid
from pathlib import Path

import numpy as np

from .. import artifacts
from .dicom_identity import PATIENT_KEYWORDS, STUDY_KEYWORDS, DicomIdentity, DicomSources, read_sources

__all__ = [
    "PATIENT_KEYWORDS",
    "STUDY_KEYWORDS",
    "DicomIdentity",
    "DicomSources",
    "build_registration",
    "build_secondary_capture",
    "read_registration_matrix",
    "read_sources",
    "write_dicom_outputs",
]

REG_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.66.1"
SC_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.7"
MANUFACTURER = "dsareg"
MODEL_NAME = "dsareg 3D/2D vessel registration"

TYPE2_PATIENT = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex")
TYPE2_STUDY = ("StudyDate", "StudyTime", "ReferringPhysicianName", "StudyID", "AccessionNumber")


def name_uid(*parts: str) -> str:
    """A deterministic ``2.25.<name-based UUID>`` (PS3.5 B.2) from ``parts``."""
    return f"2.25.{uuid.uuid5(uuid.NAMESPACE_OID, '|'.join(parts)).int}"


def new_uid() -> str:
    return f"2.25.{uuid.uuid4().int}"


# ---- common modules -----------------------------------------------------------------------------


def _now() -> tuple[str, str]:
    now = _dt.datetime.now(_dt.UTC).astimezone()
    return now.strftime("%Y%m%d"), now.strftime("%H%M%S.%f")


def _copy(found: tuple, dst) -> None:
    """``(keyword, value)`` pairs of a :class:`DicomIdentity` into ``dst``, where ``dst`` has none yet."""
    import copy

    for keyword, value in found:
        if keyword not in dst:
            setattr(dst, keyword, copy.deepcopy(value))


def new_instance(sop_class: str, sop_instance: str, charset: str = "ISO_IR 192"):
    """An empty explicit-VR little-endian instance: file meta, character set and SOP UIDs."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, ExplicitVRLittleEndian

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = sop_instance
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = Dataset()
    ds.file_meta = meta
    ds.SpecificCharacterSet = charset
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = sop_instance
    return ds


def _base(sop_class: str, sop_instance: str, sources: DicomSources, study_uid: str):
    ds = new_instance(sop_class, sop_instance)
    date, time = _now()
    ds.InstanceCreationDate, ds.InstanceCreationTime = date, time
    # Patient + General Study: copied from the inputs (XA first), never invented
    for src in (*sources.xa, *sources.volume[:1]):
        _copy(src.patient, ds)
    anchor = sources.first
    if anchor is not None:
        _copy(anchor.study, ds)
    ds.StudyInstanceUID = study_uid
    for keyword in (*TYPE2_PATIENT, *TYPE2_STUDY):
        if keyword not in ds:
            setattr(ds, keyword, "")
    # General Equipment
    ds.Manufacturer = MANUFACTURER
    ds.ManufacturerModelName = MODEL_NAME
    ds.SoftwareVersions = _version()
    return ds


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("dsareg")
    except Exception:  # noqa: BLE001
        return "0"


def study_uid_for(sources: DicomSources) -> str:
    anchor = sources.first
    if anchor is not None and anchor.study_instance_uid:
        return anchor.study_instance_uid
    return new_uid()


def xa_frame_uid_for(sources: DicomSources) -> str:
    """The C-arm world frame: the XA images' own Frame of Reference UID, else one derived from them."""
    if sources.xa_frame_uid:
        return sources.xa_frame_uid
    if sources.xa:
        return name_uid("dsareg-xa-isocentre-frame", *(x.sop_instance_uid for x in sources.xa))
    return new_uid()


def _series(ds, modality: str, series_uid: str, number: int, description: str) -> None:
    date, time = _now()
    ds.Modality = modality
    ds.SeriesInstanceUID = series_uid
    ds.SeriesNumber = number
    ds.SeriesDescription = description
    ds.SeriesDate, ds.SeriesTime = date, time
    # no Laterality (Type 2C: required for a paired body part); Body Part Examined says the part is the head, an
    # unpaired one, so a validator can tell that its absence is right (dciodvfy: without it, an error; empty, a warning)
    ds.BodyPartExamined = "HEAD"
    ds.ContentDate, ds.ContentTime = date, time


def _instance_ref(source: DicomIdentity):
    from pydicom.dataset import Dataset

    item = Dataset()
    item.ReferencedSOPClassUID = source.sop_class_uid
    item.ReferencedSOPInstanceUID = source.sop_instance_uid
    return item


def _common_instance_reference(ds, referenced: list[DicomIdentity], study_uid: str) -> None:
    """Common Instance Reference module: every referenced instance, by study and series."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    studies: dict[str, dict[str, list]] = {}
    for ref in referenced:
        study = ref.study_instance_uid or study_uid
        series = ref.series_instance_uid or ""
        if not series:
            continue
        bucket = studies.setdefault(study, {}).setdefault(series, [])
        if all(x.ReferencedSOPInstanceUID != ref.sop_instance_uid for x in bucket):
            bucket.append(_instance_ref(ref))

    def series_items(by_series: dict[str, list]) -> Sequence:
        items = []
        for series, instances in by_series.items():
            item = Dataset()
            item.SeriesInstanceUID = series
            item.ReferencedInstanceSequence = Sequence(instances)
            items.append(item)
        return Sequence(items)

    if study_uid in studies:
        ds.ReferencedSeriesSequence = series_items(studies.pop(study_uid))
    if studies:
        others = []
        for study, by_series in studies.items():
            item = Dataset()
            item.StudyInstanceUID = study
            item.ReferencedSeriesSequence = series_items(by_series)
            others.append(item)
        ds.StudiesContainingOtherReferencedInstancesSequence = Sequence(others)


# ---- REG ------------------------------------------------------------------------------------------


def matrix_to_ds(matrix: np.ndarray) -> list:
    """16 Decimal Strings, row-major, each the closest 16-character decimal."""
    from pydicom.valuerep import DSfloat

    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise ValueError("mesh_to_world must be a finite 4x4 matrix")
    return [DSfloat(float(x), auto_format=True) for x in matrix.ravel()]


def build_registration(
    mesh_to_world: np.ndarray,
    sources: DicomSources,
    *,
    model_frame_uid: str | None = None,
    study_uid: str | None = None,
    series_uid: str | None = None,
    instance_uid: str | None = None,
    xa_frame_uid: str | None = None,
    label: str = "DSAREG_3D2D",
    description: str = "vessel model registered to the biplane DSA (dsareg 3D/2D)",
    comment: str | None = None,
):
    """The Spatial Registration dataset for ``mesh_to_world`` (model frame mm → XA world mm)."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    study_uid = study_uid or study_uid_for(sources)
    instance_uid = instance_uid or new_uid()
    ds = _base(REG_SOP_CLASS, instance_uid, sources, study_uid)
    _series(ds, "REG", series_uid or new_uid(), 9101, "dsareg registration")
    ds.FrameOfReferenceUID = xa_frame_uid or xa_frame_uid_for(sources)
    ds.PositionReferenceIndicator = ""
    # Spatial Registration module + Content Identification macro
    ds.InstanceNumber = 1
    ds.ContentLabel = label
    ds.ContentDescription = description
    ds.ContentCreatorName = ""

    matrix_item = Dataset()
    matrix_item.FrameOfReferenceTransformationMatrixType = "RIGID"
    matrix_item.FrameOfReferenceTransformationMatrix = matrix_to_ds(mesh_to_world)
    registration = Dataset()
    registration.RegistrationTypeCodeSequence = Sequence()
    registration.MatrixSequence = Sequence([matrix_item])
    registration.FrameOfReferenceTransformationComment = (comment or "model mm -> C-arm isocentre LPS mm")[:64]
    item = Dataset()
    item.FrameOfReferenceUID = model_frame_uid or sources.volume_frame_uid or new_uid()
    if sources.volume:
        item.ReferencedImageSequence = Sequence([_instance_ref(v) for v in sources.volume])
    item.MatrixRegistrationSequence = Sequence([registration])
    items = [item]
    if sources.xa:
        items.append(_registered_frame_item(ds.FrameOfReferenceUID, sources.xa))
    ds.RegistrationSequence = Sequence(items)
    _common_instance_reference(ds, [*sources.xa, *sources.volume], study_uid)
    return ds


def _registered_frame_item(frame_uid: str, xa: list[DicomIdentity]):
    """The second Registration Sequence item: the XA images in the Registered RCS itself (identity).

    PS3.3 C.12.2 lists in Common Instance Reference only instances referenced elsewhere in the
    object; the XA images are referenced here, as the images whose frame *is* the Registered RCS
    (an identity RIGID matrix), so a viewer knows which images the model was registered to.
    """
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    matrix_item = Dataset()
    matrix_item.FrameOfReferenceTransformationMatrixType = "RIGID"
    matrix_item.FrameOfReferenceTransformationMatrix = matrix_to_ds(np.eye(4))
    registration = Dataset()
    registration.RegistrationTypeCodeSequence = Sequence()
    registration.MatrixSequence = Sequence([matrix_item])
    registration.FrameOfReferenceTransformationComment = "XA images: C-arm isocentre LPS frame (identity)"
    item = Dataset()
    item.FrameOfReferenceUID = frame_uid
    item.ReferencedImageSequence = Sequence([_instance_ref(x) for x in xa])
    item.MatrixRegistrationSequence = Sequence([registration])
    return item


def read_registration_matrix(ds, model_frame_uid: str | None = None) -> np.ndarray:
    """The 4x4 of a REG's item for ``model_frame_uid`` (default the first item), product of its matrices."""
    items = list(ds.RegistrationSequence)
    if model_frame_uid is not None:
        items = [i for i in items if str(getattr(i, "FrameOfReferenceUID", "")) == model_frame_uid]
        if not items:
            raise KeyError(f"no Registration Sequence item for frame {model_frame_uid}")
    total = np.eye(4)
    for matrix in items[0].MatrixRegistrationSequence[0].MatrixSequence:
        total = total @ np.array([float(x) for x in matrix.FrameOfReferenceTransformationMatrix]).reshape(4, 4)
    return total


# ---- Secondary Capture ----------------------------------------------------------------------------


def build_secondary_capture(
    rgb: np.ndarray,
    sources: DicomSources,
    *,
    study_uid: str,
    series_uid: str,
    instance_number: int,
    derivation: str,
    instance_uid: str | None = None,
):
    """An RGB Secondary Capture image (``rgb``: (H, W, 3) uint8) in ``study_uid``."""
    from pydicom.sequence import Sequence

    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError("an RGB image (H, W, 3) is needed")
    ds = _base(SC_SOP_CLASS, instance_uid or new_uid(), sources, study_uid)
    _series(ds, "OT", series_uid, 9102, "dsareg registration overlays")
    ds.ConversionType = "WSD"  # workstation
    ds.InstanceNumber = instance_number
    ds.PatientOrientation = ""
    ds.ImageType = ["DERIVED", "SECONDARY"]
    ds.DerivationDescription = derivation[:1024]
    ds.BurnedInAnnotation = "NO"
    ds.SamplesPerPixel = 3
    ds.PhotometricInterpretation = "RGB"
    ds.PlanarConfiguration = 0
    ds.Rows, ds.Columns = int(rgb.shape[0]), int(rgb.shape[1])
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 8, 8, 7, 0
    ds.PixelData = rgb.tobytes()
    sources_seq = []
    for src in sources.xa:
        item = _instance_ref(src)
        sources_seq.append(item)
    if sources_seq:
        ds.SourceImageSequence = Sequence(sources_seq)
        _common_instance_reference(ds, list(sources.xa), study_uid)
    ds.LossyImageCompression = "00"
    return ds


def _read_rgb(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as image:
        return np.asarray(image.convert("RGB"))


def to_bytes(ds) -> bytes:
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def overlay_derivation(view: str, fitted: bool = True) -> str:
    """Derivation Description of an overlay: the contour colours are those ``overlay.py`` draws; ``fitted`` False: a
    single-plane track fitted the other plane only, and this view's image is not from the run tracked."""
    from ..overlay import FINAL_BGR, INITIAL_BGR

    initial, final = colour_name(INITIAL_BGR[::-1]), colour_name(FINAL_BGR[::-1])
    unfitted = ("; this view was not fitted (a single-plane track of the other plane): its image is an earlier "
                "run's, not this run's, shown under the new pose" if not fitted else "")
    return (f"dsareg overlay, {view.upper()} view: target vessel mask (grey), initial ({initial}) and "
            f"registered ({final}) model silhouette contours{unfitted}")


NAMED_COLOURS_RGB = {"red": (230, 30, 30), "orange": (255, 140, 0), "yellow": (240, 220, 0), "green": (30, 180, 30),
                     "cyan": (0, 200, 220), "blue": (0, 90, 220), "magenta": (220, 0, 220), "grey": (128, 128, 128)}


def colour_name(rgb) -> str:
    """The nearest of a few plain colour names to ``rgb`` (by hue; grey when unsaturated)."""
    import colorsys

    r, g, b = (c / 255.0 for c in rgb)
    hue, _, saturation = colorsys.rgb_to_hls(r, g, b)
    if saturation < 0.2:
        return "grey"
    best, distance = "grey", 2.0
    for name, ref in NAMED_COLOURS_RGB.items():
        if name == "grey":
            continue
        ref_hue = colorsys.rgb_to_hls(*(c / 255.0 for c in ref))[0]
        d = min(abs(hue - ref_hue), 1 - abs(hue - ref_hue))
        if d < distance:
            best, distance = name, d
    return best


OUTPUT_FILES = {artifacts.REG_DCM: "registration", artifacts.overlay_dcm("ap"): "overlay ap",
                artifacts.overlay_dcm("lat"): "overlay lat", artifacts.LOSS_DCM: "loss plot"}


def write_dicom_outputs(
    out_dir: Path,
    mesh_to_world: np.ndarray,
    sources: DicomSources,
    dicom_dir: Path | None = None,
    *,
    model_frame_uid: str | None = None,
    unfitted: tuple[str, ...] = (),
) -> dict[str, dict[str, str]]:
    """Write ``reg.dcm``, ``overlay_{ap,lat}.dcm`` (and ``loss.dcm``) from a finished ``out_dir``.

    ``out_dir`` holds the PNGs that :func:`dsareg_engine.pipeline.write_outputs` wrote;
    the DICOM files go to ``dicom_dir`` (default ``out_dir``). ``unfitted``: views a single-plane track did not fit
    (their image an earlier run's), said so in their overlay's Derivation Description.

    Returns:
        ``{file name: {"sop_class_uid", "sop_instance_uid", "series_instance_uid", "study_instance_uid"}}``
    """
    out_dir = Path(out_dir)
    dicom_dir = Path(dicom_dir) if dicom_dir is not None else out_dir
    dicom_dir.mkdir(parents=True, exist_ok=True)
    study_uid = study_uid_for(sources)
    written: dict[str, dict[str, str]] = {}

    def save(name: str, ds) -> None:
        (dicom_dir / name).write_bytes(to_bytes(ds))
        written[name] = {"sop_class_uid": str(ds.SOPClassUID), "sop_instance_uid": str(ds.SOPInstanceUID),
                         "series_instance_uid": str(ds.SeriesInstanceUID), "study_instance_uid": study_uid}

    save(artifacts.REG_DCM, build_registration(mesh_to_world, sources, study_uid=study_uid, model_frame_uid=model_frame_uid))
    series_uid = new_uid()
    number = 0
    for view in ("ap", "lat"):
        png = out_dir / artifacts.overlay_png(view)
        if png.is_file():
            number += 1
            ds = build_secondary_capture(
                _read_rgb(png), sources, study_uid=study_uid, series_uid=series_uid, instance_number=number,
                derivation=overlay_derivation(view, fitted=view not in unfitted))
            save(artifacts.overlay_dcm(view), ds)
    loss = out_dir / artifacts.LOSS_PNG
    if loss.is_file():
        number += 1
        save(artifacts.LOSS_DCM, build_secondary_capture(
            _read_rgb(loss), sources, study_uid=study_uid, series_uid=series_uid, instance_number=number,
            derivation="dsareg registration loss per iteration (log scale)"))
    return written
