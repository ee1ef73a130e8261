"""The engine as applications use it (the service goes through this module only, and for its command line through
:mod:`dsareg_engine.commands.kit`).

Importing it loads numpy and pydantic (options, geometry, limits, the DICOM identity), nothing heavier. Four
groups of names load on first use (:func:`__getattr__`), because start-up time needs it: the API process and
``dsareg --help`` / ``dsareg submit`` import this module but never read a case or run one (the input
validator runs in its own processes). Measured 2026-12-03 on the shared 2-core Xeon (loaded), CPU s (user + sys)
of importing each module after this one: :mod:`~dsareg_engine.pipeline` 1.84 s (+1,867 modules: torch, numba,
scipy, pydicom, PIL); :mod:`~dsareg_engine.io.case` 0.30 s (+458: pydicom, PIL, the readers);
:mod:`~dsareg_engine.io.xa_run` 0.20 s (+380) and :mod:`~dsareg_engine.hemodynamics.intake` 0.21 s (+389), both
pydicom and PIL. Importing this module: 0.27 s (docs/concepts/layout.md, "Lazy names").

* options: :class:`RegistrationOptions`, :func:`parse_options`, :func:`validate_rigid`, :data:`PRESETS`
* geometry: :func:`parse_geometry` (the one place a preset name, JSON or a file is told apart) →
  :class:`GeometrySpec`, stored as its canonical JSON (``to_json`` / ``from_json``, :func:`is_canonical_geometry`)
* a case: :class:`CaseFiles` (inputs as bytes; a volume's files also as :class:`FileParts`, read when used), :func:`load_case_files` / :func:`load_case`, :class:`InputLimits`, :func:`input_limits`;
  how multi-frame XA runs are read: :class:`ImageReading` (per-view frames, subtraction), :func:`image_reading` (from options)
  a volume's kept model: :class:`DirectoryModelStore`, keyed by :func:`model_key` (the files' digests, the reading)
* running it: :func:`run_case` (files in, every output written, in one call), :func:`run_registration_case`
  (from a loaded case), :class:`RegistrationCanceled`
* outputs: :data:`ARTIFACTS` and the other names of :mod:`dsareg_engine.artifacts`;
  DICOM: :class:`DicomSources` / :class:`DicomIdentity` (a loaded case carries them: ``case.sources``),
  :func:`read_sources` (from bytes, without a case), :func:`write_dicom_outputs`;
  whose case it is: :func:`case_identity` (patient, study, series per input), :func:`with_source`, :func:`case_search_text`
* process set-up: :func:`set_cpu_threads`, :func:`default_cpu_threads`, :func:`preload_case_loading`,
  :func:`skip_exit_collections` (a quick exit), :func:`warm_up_parsers`, :func:`parse_without_network`, :func:`warm_up_renderer`, :func:`warm_up_kernels`, :func:`warm_up_job` (a worker's first job's set-up),
  :func:`compile_later_groups` (the kernels no first job needs, in the background)

The command line's helpers (for packages that add ``dsareg`` sub-commands) are :mod:`dsareg_engine.commands.kit`.
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
from .commands.process_exit import skip_exit_collections
from .errors import DsaregInputError
from .geometry.file import PRESETS, LatFromAp, RigSpec, ViewSpec
from .geometry.pose import validate_rigid
from .geometry.spec import GeometrySpec, is_canonical_geometry, parse_geometry
from .io.case_identity import case_identity, case_search_text, with_source
from .io.dicom_identity import DicomIdentity, DicomSources, read_sources
from .io.dicom_out import write_dicom_outputs
from .io.dicom_xa import c_arm_rotation
from .io.file_parts import FileParts
from .io.limits import DEFAULT_LIMITS, InputLimits
from .io.model_key import model_key
from .io.volume_kind import VolumeReading
from .registration.options import RegistrationOptions, image_reading, parse_options
from .threads import default_cpu_threads, set_cpu_threads
from .warmup import compile_later_groups, warm_up_job, warm_up_kernels, warm_up_renderer

if TYPE_CHECKING:  # the lazy names below, for type checkers and linters (never imported here at run time)
    from .hemodynamics.intake import check_timed_runs
    from .io.case import CaseFiles, load_case, load_case_files
    from .io.model_cache import DirectoryModelStore
    from .io.volume_cost import VolumeCost, volume_read_cost
    from .io.xa_run import ImageReading
    from .pipeline import RegistrationCanceled, run_case, run_registration_case

_LAZY = {  # heavy: loaded on first use (the module docstring says why and what each costs)
    "CaseFiles": "dsareg_engine.io.case",
    "DirectoryModelStore": "dsareg_engine.io.model_cache",
    "VolumeCost": "dsareg_engine.io.volume_cost",
    "volume_read_cost": "dsareg_engine.io.volume_cost",
    "load_case": "dsareg_engine.io.case",
    "load_case_files": "dsareg_engine.io.case",
    "ImageReading": "dsareg_engine.io.xa_run",
    "check_timed_runs": "dsareg_engine.hemodynamics.intake",
    "run_case": "dsareg_engine.pipeline",
    "run_registration_case": "dsareg_engine.pipeline",
    "RegistrationCanceled": "dsareg_engine.pipeline",
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
    "REGISTRATION_FILES",
    "REG_DCM",
    "RESULT_JSON",
    "CaseFiles",
    "DicomIdentity",
    "DirectoryModelStore",
    "DicomSources",
    "DsaregInputError",
    "FileParts",
    "GeometrySpec",
    "ImageReading",
    "InputLimits",
    "LatFromAp",
    "RegistrationCanceled",
    "RegistrationOptions",
    "RigSpec",
    "VolumeCost",
    "VolumeReading",
    "c_arm_rotation",
    "case_identity",
    "case_search_text",
    "default_cpu_threads",
    "image_reading",
    "input_limits",
    "is_canonical_geometry",
    "load_case",
    "load_case_files",
    "image_png",
    "layers_png",
    "mask_png",
    "model_key",
    "overlay_dcm",
    "overlay_png",
    "parse_geometry",
    "parse_options",
    "preload_case_loading",
    "read_sources",
    "run_case",
    "run_registration_case",
    "set_cpu_threads",
    "skip_exit_collections",
    "ViewSpec",
    "validate_rigid",
    "volume_read_cost",
    "warm_up_job",
    "with_source",
    "warm_up_parsers",
    "parse_without_network",
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
    """The heavy names (:data:`_LAZY`), imported on first use."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def input_limits(limits: dict[str, int] | None) -> Any:
    """``InputLimits`` with the given ceilings (engine defaults for the others and for 0/None)."""
    chosen = {k: v for k, v in (limits or {}).items() if v and k in InputLimits.__dataclass_fields__}
    return InputLimits(**chosen) if chosen else DEFAULT_LIMITS


def preload_case_loading() -> None:
    """Import everything :func:`load_case` needs (raises if the engine cannot load here)."""
    import dsareg_engine.io.case  # noqa: F401


def parse_without_network() -> None:
    """This process checks inputs only: segmentation runs without the vessel network (no torch import; ``auto``
    keeps the DSA border model, ``network`` runs its classical fallback), :func:`~dsareg_engine.vision.angiogram.allow_network`."""
    from .vision.angiogram import allow_network

    allow_network(False)


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

