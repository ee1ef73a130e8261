"""What kind of volume a vessel model comes from — CTA, TOF-MRA or 3D-DSA — and how to read it.

The kind decides how vessels are told from everything else (:mod:`dsareg_engine.io.volume_vessels`):

* ``"cta"``: CT in HU: contrast-filled vessels in a HU window above soft tissue and below bone;
* ``"mra"``: TOF-MRA: bright in-flow vessels over tissue, bright fat in the scalp;
* ``"3d-dsa"``: 3D-DSA / 3D-RA, already subtracted: vessels alone over a dark background.

:func:`detect_volume_kind` decides from the DICOM tags (Modality, SOP Class, Image Type, Series
Description, Contrast/Bolus Agent, Angio Flag) and, where tags are absent or ambiguous (NIfTI, NRRD,
a CT series), from whether the values look like HU with air around a head. :class:`VolumeReading`
(``options.volume_kind``, ``options.volume_vessel_min``, ``options.volume_vessel_max``) overrides it. A label
map or a 0/1 mask is read as its labels (:mod:`.volume_labels`; ``options.volume_labels`` chooses them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DsaregInputError

VOLUME_KINDS = ("auto", "cta", "mra", "3d-dsa")
XA_3D_SOP_CLASSES = ("1.2.840.10008.5.1.4.1.1.13.1.1",)  # X-Ray 3D Angiographic Image Storage
AIR_HU = -500.0
MIN_AIR_FRACTION = 0.02
SUBTRACTED_WORDS = ("SUBTRACT", "DSA", "3D-RA", "3DRA", "3D RA")


@dataclass(frozen=True)
class VolumeReading:
    """How to read vessels from a volume (every field optional; defaults detect and estimate).

    Attributes:
        kind: one of :data:`VOLUME_KINDS`; ``"auto"`` = :func:`detect_volume_kind`.
        vessel_min: the vessel surface level (HU for CTA; the volume's intensity for MRA / 3D-DSA);
            ``None``: halfway between the tissue and the vessels, estimated from the volume.
        vessel_max: CTA only: HU from which a voxel is bone (default :data:`DEFAULT_BONE_HU`).
        labels: a label map's labels that are vessels (:mod:`.volume_labels`); ``None``: every label above 0.
    """

    kind: str = "auto"
    vessel_min: float | None = None
    vessel_max: float | None = None
    labels: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        if self.kind not in VOLUME_KINDS:
            raise DsaregInputError(f"unknown volume kind '{self.kind}'", field="options.volume_kind",
                                   accepted=", ".join(VOLUME_KINDS))
        if self.vessel_min is not None and self.vessel_max is not None and self.vessel_min >= self.vessel_max:
            raise DsaregInputError(f"vessel_min {self.vessel_min} is not below vessel_max {self.vessel_max}",
                                   field="options.volume_vessel_min", accepted="vessel_min < vessel_max")
        if self.labels is not None:
            labels = tuple(self.labels)
            if not labels or any(isinstance(x, bool) or int(x) != x or x < 1 for x in labels):
                raise DsaregInputError(f"labels {list(labels)} are not whole numbers above 0",
                                       field="options.volume_labels", accepted="a list of labels, each 1 or more")
            object.__setattr__(self, "labels", tuple(sorted({int(x) for x in labels})))

    @classmethod
    def from_options(cls, options) -> VolumeReading:
        """From registration options (``volume_kind``, ``volume_vessel_min``, ``volume_vessel_max``,
        ``volume_labels``)."""
        labels = getattr(options, "volume_labels", None)
        return cls(getattr(options, "volume_kind", "auto"), getattr(options, "volume_vessel_min", None),
                   getattr(options, "volume_vessel_max", None), tuple(labels) if labels is not None else None)


def _upper(tags: dict[str, str], key: str) -> str:
    return str(tags.get(key, "")).upper()


def detect_volume_kind(tags: dict[str, str], data: np.ndarray) -> tuple[str, str]:
    """``(kind, why)`` of a volume from its identifying ``tags`` (may be empty) and voxels."""
    modality, image_type = _upper(tags, "Modality"), _upper(tags, "ImageType")
    description = _upper(tags, "SeriesDescription")
    if "SUBTRACT" in image_type or any(word in description for word in SUBTRACTED_WORDS):
        return "3d-dsa", "Image Type / Series Description say subtracted"
    if modality == "XA" or tags.get("SOPClassUID") in XA_3D_SOP_CLASSES:
        return "3d-dsa", f"Modality {modality or 'XA'} (a C-arm 3D reconstruction, taken as subtracted)"
    if modality == "MR":
        angio = tags.get("AngioFlag", "").upper() == "Y" or any(
            word in _upper(tags, key) for key in ("SeriesDescription", "SequenceName") for word in ("TOF", "FL3D", "ANGIO", "INFLOW"))
        return "mra", "Modality MR" + (" with angio tags" if angio else " (no angio tags: read as TOF-MRA)")
    sample = np.asarray(data[::2, ::2, ::2])
    air = float(np.mean(sample < AIR_HU))
    if modality == "CT":
        if air >= MIN_AIR_FRACTION:
            contrast = ", Contrast/Bolus Agent set" if tags.get("ContrastBolusAgent") else ""
            return "cta", f"Modality CT with air around the head ({100 * air:.0f}% of voxels below {AIR_HU:.0f} HU){contrast}"
        return "3d-dsa", "Modality CT without air (below -500 HU): read as already subtracted"
    if modality:
        return "3d-dsa", f"Modality {modality}: read as already subtracted"
    if air >= MIN_AIR_FRACTION and float(np.max(data)) > 300.0:
        return "cta", f"no DICOM tags; values look like HU with air ({100 * air:.0f}% below {AIR_HU:.0f})"
    return "3d-dsa", "no DICOM tags: read as already subtracted (set options.volume_kind for a CTA or MRA)"


CLI_FLAGS = {"options.volume_kind": "--volume-kind", "options.volume_vessel_min": "--vessel-min",
             "options.volume_vessel_max": "--vessel-max", "options.volume_labels": "--labels"}
"""The command line's flags (``dsareg inspect``, ``dsareg mesh``) for the options a volume's reading takes."""


def on_command_line(text: str | None) -> str | None:
    """``text`` (an error's message or accepted) naming the command line's flags instead of the server's options."""
    if text is None:
        return None
    for option, flag in CLI_FLAGS.items():
        text = text.replace(option, flag)
    return text.replace("volume_vessel_min / volume_vessel_max", "--vessel-min / --vessel-max")


__all__ = ["CLI_FLAGS", "VOLUME_KINDS", "VolumeReading", "detect_volume_kind", "on_command_line"]
