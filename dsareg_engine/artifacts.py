"""The files a registration writes into its output folder: names and media types (the one place they are spelled).

:func:`dsareg_engine.pipeline.write_outputs` writes the registration's files,
:func:`dsareg_engine.io.dicom_out.write_dicom_outputs` the DICOM ones; applications (the
service) serve them by these names.
"""

from __future__ import annotations

VIEWS = ("ap", "lat")

RESULT_JSON = "result.json"
LOSS_PNG = "loss.png"
ANIMATION_GIF = "animation.gif"
REG_DCM = "reg.dcm"
LOSS_DCM = "loss.dcm"


def overlay_png(view: str) -> str:
    return f"overlay_{view}.png"


def mask_png(view: str) -> str:
    return f"mask_{view}.png"


def overlay_dcm(view: str) -> str:
    return f"overlay_{view}.dcm"


HEMODYNAMICS_JSON = "hemodynamics.json"
HEMODYNAMICS_PLY = "hemodynamics.ply"
HEMODYNAMICS_VTK = "hemodynamics.vtk"


def parametric_png(view: str) -> str:
    return f"parametric_{view}.png"


def parametric_dcm(view: str) -> str:
    return f"parametric_{view}.dcm"


HEMODYNAMICS_FILES: dict[str, str] = {
    HEMODYNAMICS_JSON: "application/json",
    HEMODYNAMICS_PLY: "application/octet-stream",
    HEMODYNAMICS_VTK: "application/octet-stream",
    **{parametric_png(view): "image/png" for view in VIEWS},
}
"""What the hemodynamics step (``options.hemodynamics``, :mod:`dsareg_engine.hemodynamics.run`) may write."""


def image_png(view: str) -> str:
    """The image registered (frame or frames combined, subtracted), 8-bit grey (:mod:`.io.review_files`)."""
    return f"image_{view}.png"


def layers_png(view: str) -> str:
    """Outlines (initial, registered), mask and unfilled pixels as RGB layers (:mod:`.io.review_files`)."""
    return f"layers_{view}.png"


MODEL_JSON = "model.json"


REGISTRATION_FILES: dict[str, str] = {
    RESULT_JSON: "application/json",
    **{overlay_png(view): "image/png" for view in VIEWS},
    **{mask_png(view): "image/png" for view in VIEWS},
    ANIMATION_GIF: "image/gif",
    LOSS_PNG: "image/png",
    **{image_png(view): "image/png" for view in VIEWS},
    **{layers_png(view): "image/png" for view in VIEWS},
    MODEL_JSON: "application/json",
}
"""What :func:`~dsareg_engine.pipeline.write_outputs` may write: ``{file name: media type}``."""

DICOM_FILES: dict[str, str] = {
    REG_DCM: "application/dicom",
    **{overlay_dcm(view): "application/dicom" for view in VIEWS},
    LOSS_DCM: "application/dicom",
    **{parametric_dcm(view): "application/dicom" for view in VIEWS},
}
"""What :func:`~dsareg_engine.io.dicom_out.write_dicom_outputs` may write."""

ARTIFACTS: dict[str, str] = {**REGISTRATION_FILES, **HEMODYNAMICS_FILES, **DICOM_FILES}
"""Every output file of a registration, ``{file name: media type}``."""
