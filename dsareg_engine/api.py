"""The engine as applications use it (the service goes through this module only).

Importing it is cheap: the heavy parts (torch, the renderer, the readers) load on first use of a
name, so an API process that only validates options never loads the renderer.

* options: :class:`RegistrationOptions`, :func:`parse_options`, :func:`validate_rigid`, :data:`PRESETS`
* geometry: :func:`parse_geometry` (the one place a preset name, JSON or a file is told apart) →
  :class:`GeometrySpec`, stored as its canonical JSON (``to_json`` / ``from_json``, :func:`is_canonical_geometry`)
* a case: :class:`CaseFiles` (inputs as bytes), :func:`load_case_files` / :func:`load_case`, :class:`InputLimits`, :func:`input_limits`;
  how multi-frame XA runs are read: :class:`ImageReading` (per-view frames, subtraction), :func:`image_reading` (from options)
* running it: :func:`run_case` (files in, every output written, in one call), :func:`run_registration_case`
  (from a loaded case), :class:`RegistrationCanceled`
* outputs: :data:`ARTIFACTS` and the other names of :mod:`dsareg_engine.artifacts`;
  DICOM: :class:`DicomSources` / :class:`DicomIdentity` (a loaded case carries them: ``case.sources``),
  :func:`read_sources` (from bytes, without a case), :func:`write_dicom_outputs`;
  whose case it is: :func:`case_identity` (patient, study, series per input), :func:`with_source`, :func:`case_search_text`
* process set-up: :func:`set_cpu_threads`, :func:`default_cpu_threads`, :func:`preload_case_loading`,
  :func:`skip_exit_collections` (a quick exit), :func:`warm_up_parsers`, :func:`warm_up_renderer`, :func:`warm_up_kernels`, :func:`warm_up_job` (a worker's first job's set-up),
  :func:`compile_later_groups` (the kernels no first job needs, in the background)
* the command line: :func:`run_parsed`, and the helpers sub-commands use (:class:`CommandFailed`,
  :func:`input_file`, :func:`options_help`, :func:`geometry_argument`, :func:`json_argument`, :func:`load_pose`)

Errors in the inputs are :class:`DsaregInputError` (``message``, ``field``, ``accepted``).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .artifacts import (
    ANIMATION_GIF,
    ARTIFACTS,
    DICOM_FILES,
    HEMODYNAMICS_FILES,
    HEMODYNAMICS_JSON,
    HEMODYNAMICS_PLY,
    HEMODYNAMICS_VTK,
    LOSS_DCM,
    LOSS_PNG,
    MODEL_JSON,
    REG_DCM,
    REGISTRATION_FILES,
    RESULT_JSON,
    image_png,
    layers_png,
    mask_png,
    overlay_dcm,
    overlay_png,
    parametric_dcm,
    parametric_png,
)
from .errors import DsaregInputError

if TYPE_CHECKING:  # the lazy names below, for type checkers and linters (never imported here at run time)
    from .cli import run_parsed
    from .commands.arguments import geometry_argument, input_file, json_argument, options_help
    from .commands.failures import CommandFailed
    from .geometry.file import PRESETS, LatFromAp, RigSpec, ViewSpec
    from .commands.progress_lines import REQUIRE_CHOICES, VERDICT_NOT_MET_EXIT, ProgressPrinter, verdict_meets
    from .geometry.spec import GeometrySpec, is_canonical_geometry, parse_geometry
    from .io.case import CaseFiles, load_case, load_case_files
    from .io.xa_run import ImageReading
    from .io.case_identity import case_identity, case_search_text, with_source
    from .io.dicom_identity import DicomIdentity, DicomSources, read_sources
    from .io.dicom_out import write_dicom_outputs
    from .io.dicom_xa import c_arm_rotation
    from .io.limits import DEFAULT_LIMITS, InputLimits
    from .io.volume_kind import VolumeReading
    from .pipeline import RegistrationCanceled, run_case, run_registration_case
    from .geometry.pose import validate_rigid
    from .geometry.pose_file import load_pose
    from .registration.options import RegistrationOptions, image_reading, parse_options
    from .threads import default_cpu_threads, set_cpu_threads
    from .commands.process_exit import skip_exit_collections
    from .warmup import compile_later_groups, warm_up_job, warm_up_kernels, warm_up_renderer
    from .hemodynamics.intake import check_timed_runs

_LAZY = {
    "RegistrationOptions": "dsareg_engine.registration.options",
    "parse_options": "dsareg_engine.registration.options",
    "image_reading": "dsareg_engine.registration.options",
    "ImageReading": "dsareg_engine.io.xa_run",
    "validate_rigid": "dsareg_engine.geometry.pose",
    "PRESETS": "dsareg_engine.geometry.file",
    "RigSpec": "dsareg_engine.geometry.file",
    "ViewSpec": "dsareg_engine.geometry.file",
    "LatFromAp": "dsareg_engine.geometry.file",
    "GeometrySpec": "dsareg_engine.geometry.spec",
    "parse_geometry": "dsareg_engine.geometry.spec",
    "is_canonical_geometry": "dsareg_engine.geometry.spec",
    "CaseFiles": "dsareg_engine.io.case",
    "load_case_files": "dsareg_engine.io.case",
    "InputLimits": "dsareg_engine.io.limits",
    "DEFAULT_LIMITS": "dsareg_engine.io.limits",
    "load_case": "dsareg_engine.io.case",
    "VolumeReading": "dsareg_engine.io.volume_kind",
    "run_registration_case": "dsareg_engine.pipeline",
    "run_case": "dsareg_engine.pipeline",
    "RegistrationCanceled": "dsareg_engine.pipeline",
    "DicomSources": "dsareg_engine.io.dicom_identity",
    "DicomIdentity": "dsareg_engine.io.dicom_identity",
    "c_arm_rotation": "dsareg_engine.io.dicom_xa",
    "read_sources": "dsareg_engine.io.dicom_identity",
    "case_identity": "dsareg_engine.io.case_identity",
    "case_search_text": "dsareg_engine.io.case_identity",
    "with_source": "dsareg_engine.io.case_identity",
    "write_dicom_outputs": "dsareg_engine.io.dicom_out",
    "set_cpu_threads": "dsareg_engine.threads",
    "default_cpu_threads": "dsareg_engine.threads",
    "skip_exit_collections": "dsareg_engine.commands.process_exit",
    "run_parsed": "dsareg_engine.cli",
    "CommandFailed": "dsareg_engine.commands.failures",
    "input_file": "dsareg_engine.commands.arguments",
    "options_help": "dsareg_engine.commands.arguments",
    "geometry_argument": "dsareg_engine.commands.arguments",
    "json_argument": "dsareg_engine.commands.arguments",
    "ProgressPrinter": "dsareg_engine.commands.progress_lines",
    "verdict_meets": "dsareg_engine.commands.progress_lines",
    "REQUIRE_CHOICES": "dsareg_engine.commands.progress_lines",
    "VERDICT_NOT_MET_EXIT": "dsareg_engine.commands.progress_lines",
    "load_pose": "dsareg_engine.geometry.pose_file",
    "warm_up_job": "dsareg_engine.warmup",
    "warm_up_renderer": "dsareg_engine.warmup",
    "warm_up_kernels": "dsareg_engine.warmup",
    "compile_later_groups": "dsareg_engine.warmup",
    "check_timed_runs": "dsareg_engine.hemodynamics.intake",
}

__all__ = [
    "ANIMATION_GIF",
    "ARTIFACTS",
    "DEFAULT_LIMITS",
    "DICOM_FILES",
    "LOSS_DCM",
    "LOSS_PNG",
    "MODEL_JSON",
    "PRESETS",
    "REQUIRE_CHOICES",
    "VERDICT_NOT_MET_EXIT",
    "REGISTRATION_FILES",
    "REG_DCM",
    "RESULT_JSON",
    "CaseFiles",
    "CommandFailed",
    "DicomIdentity",
    "DicomSources",
    "DsaregInputError",
    "GeometrySpec",
    "ImageReading",
    "InputLimits",
    "LatFromAp",
    "ProgressPrinter",
    "RegistrationCanceled",
    "RegistrationOptions",
    "RigSpec",
    "VolumeReading",
    "c_arm_rotation",
    "case_identity",
    "case_search_text",
    "default_cpu_threads",
    "geometry_argument",
    "input_file",
    "image_reading",
    "input_limits",
    "is_canonical_geometry",
    "json_argument",
    "load_case",
    "load_case_files",
    "load_pose",
    "image_png",
    "layers_png",
    "mask_png",
    "options_help",
    "overlay_dcm",
    "overlay_png",
    "parse_geometry",
    "parse_options",
    "preload_case_loading",
    "read_sources",
    "run_case",
    "run_parsed",
    "run_registration_case",
    "set_cpu_threads",
    "skip_exit_collections",
    "ViewSpec",
    "validate_rigid",
    "verdict_meets",
    "warm_up_job",
    "with_source",
    "warm_up_parsers",
    "warm_up_renderer",
    "warm_up_kernels",
    "compile_later_groups",
    "write_dicom_outputs",
    "HEMODYNAMICS_FILES",
    "HEMODYNAMICS_JSON",
    "HEMODYNAMICS_PLY",
    "HEMODYNAMICS_VTK",
    "check_timed_runs",
    "parametric_dcm",
    "parametric_png",
]


def __getattr__(name: str) -> Any:
    """The heavy names, imported on first use."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def input_limits(limits: dict[str, int] | None) -> Any:
    """``InputLimits`` with the given ceilings (engine defaults for the others and for 0/None)."""
    from .io.limits import DEFAULT_LIMITS, InputLimits

    chosen = {k: v for k, v in (limits or {}).items() if v and k in InputLimits.__dataclass_fields__}
    return InputLimits(**chosen) if chosen else DEFAULT_LIMITS


def preload_case_loading() -> None:
    """Import everything :func:`load_case` needs (raises if the engine cannot load here)."""
    import dsareg_engine.io.case  # noqa: F401


def warm_up_parsers() -> None:
    """Run the parsers once on tiny inputs: their lazily imported parts (scikit-image's filters pull
    in scipy.stats, trimesh) cost ~2 s on the first real input otherwise."""
    import numpy as np

    from .io.mesh_io import read_mesh
    from .vision.segmentation import segment_vessels

    image = np.zeros((48, 48), np.float32)
    image[20:28, 4:44] = 1.0
    try:
        segment_vessels(image, "auto")
        read_mesh(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n", "warm.obj")
    except DsaregInputError:
        pass

