"""The service's boundary with the registration engine: the only module in ``service/`` that
imports :mod:`dsareg_engine`, and only its application API :mod:`dsareg_engine.api`
(re-exported here as ``engine``; its heavy parts load on first use) and the helpers of the command line,
:mod:`dsareg_engine.commands.kit` (as ``commands``, for :mod:`service.cli`).

* geometry: :func:`submitted_geometry` parses a submission's ``geometry`` part once
  (``engine.parse_geometry``) and returns the canonical JSON the job stores;
  :func:`job_geometry` reads a stored one back (see there for rows written before the canonical form).
* inputs: :func:`stored_case_files` (the job's blobs → ``engine.CaseFiles``), shared by the API's
  input validator (:func:`load_job_case`, in its own processes) and the workers, so what the API
  accepted is exactly what a worker loads; :func:`fetched_case_files` for a DICOMweb fetch.
* running: :func:`run_job`, a worker's one call into the engine (``engine.run_case``).
* outputs: :func:`collect_artifacts` (the engine's artifact table into the blob store).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dsareg_engine import api as engine
from dsareg_engine.commands import kit as commands

from .storage.blobs import BlobStore
from .budgets import image_decoded_bytes, parse_json_part

if TYPE_CHECKING:  # the job store (SQLAlchemy) is not needed to parse the CLI or call the engine
    from .storage.store import InputFile

ROLES = ("mesh", "volume", "ap", "lat")


# ---- geometry ----------------------------------------------------------------------------------


def submitted_geometry(text: str | None) -> str | None:
    """A submission's ``geometry`` part → the canonical JSON to store; blank or absent → ``None``.

    Parsed once here (a preset name or a JSON object; never a file path, so a client cannot make
    the server read its own files), with the service's bounded JSON parser; an unusable geometry raises
    ``engine.DsaregInputError`` naming the field (the API answers 422: :mod:`service.api.handlers`).
    """
    if text is None or not text.strip():
        return None
    spec = engine.parse_geometry(text, loads=lambda part: parse_json_part(part, "geometry"))
    return spec.to_json()


def job_geometry(stored: str | None) -> Any:
    """A job's stored geometry as the engine's ``GeometrySpec`` (``None``: from the image headers).

    Rows hold the canonical JSON (``GeometrySpec.to_json``), read back without deciding anything.
    Rows written before the canonical form (service versions up to the layout change) hold what
    those versions stored: a preset name or the submitted JSON object, compacted. They are parsed
    with ``engine.parse_geometry`` (which accepts exactly those two forms, never a path), so a
    service restarted on an older database runs its queued jobs, and tracks its finished ones, unchanged.
    """
    if stored is None:
        return None
    if engine.is_canonical_geometry(stored):
        return engine.GeometrySpec.from_json(stored)
    return engine.parse_geometry(stored)  # a row from before the canonical form


def canonical_geometry(stored: str | None) -> str | None:
    """A stored geometry (either row format) as canonical JSON (``/track`` copies the job's)."""
    spec = job_geometry(stored)
    return None if spec is None else spec.to_json()


# ---- inputs ------------------------------------------------------------------------------------


def input_limits(limits: dict[str, int] | None) -> Any:
    """``InputLimits`` with the configured ceilings (engine defaults for the others)."""
    return engine.input_limits(limits)


def check_options(options: Any) -> None:
    """Refuse what the worker would refuse: ``engine.DsaregInputError`` naming the option (422 in the API)."""
    for name in ("initial_mesh_to_world", "ground_truth_mesh_to_world"):
        matrix = getattr(options, name, None)
        if matrix is not None:
            engine.validate_rigid(matrix, field=f"options.{name}", allow_mirror=False)


def check_image_budget(data: bytes, field: str, limit: int) -> None:
    """Refuse an image whose decoded pixels would need more than ``limit`` bytes (before decoding)."""
    size = image_decoded_bytes(data)
    if size is not None and size > limit:
        raise engine.DsaregInputError(
            f"decodes to {size / 2**20:.0f} MiB of pixels (width × height × channels × bytes per sample), "
            f"above this server's limit of {limit / 2**20:.0f} MiB",
            field=field, accepted="a smaller image, fewer channels or fewer bits per sample")


def stored_case_files(inputs: list[InputFile], geometry: str | None, read: Any,
                      limits: dict[str, int] | None = None, read_head: Any = None) -> Any:
    """A job's stored inputs as ``engine.CaseFiles``; ``read(sha256) -> bytes``, ``read_head(sha256, n)``: a blob's
    first ``n`` bytes (``BlobStore.read_head``), or None.

    Several files of one role (a DICOM series, a ``.rad`` + ``.raw`` pair) are passed as a
    list in the order they were uploaded; names are ``<role><sanitized suffix>``. Images
    whose decoded size exceeds ``max_image_bytes`` are refused before decoding. A volume's files are an
    ``engine.FileParts`` (:func:`volume_parts`): read from the store when the engine reads them, never held.
    """
    image_budget = (limits or {}).get("max_image_bytes")
    parts: dict[str, Any] = {"ap": None, "lat": None}
    for role in ROLES:
        items = [f for f in inputs if f.role == role]
        if not items:
            continue
        if role == "volume":
            data = volume_parts(items, read, read_head)
        elif role == "mesh" or len(items) == 1:
            data = read(items[0].sha256)
        else:
            data = [read(item.sha256) for item in items]
        if image_budget and role in ("ap", "lat"):
            for part in data if isinstance(data, list) else [data]:
                check_image_budget(part, role, image_budget)
        parts[role], parts[f"{role}_name"] = data, role + items[0].suffix
    return engine.CaseFiles(**parts, geometry=job_geometry(geometry))


def volume_parts(items: list[InputFile], read: Any, read_head: Any = None) -> Any:
    """A volume's stored files as an ``engine.FileParts``: each read from the store when used and never held (a
    whole head's are 0.23 GB), their digests the store's (a model key reads none of them), and with ``read_head`` a
    series' headers read from the files' first bytes (the worker's table reads: 2.2 s for 440 whole files)."""
    return engine.FileParts((partial(read, item.sha256) for item in items), digests=[item.sha256 for item in items],
                            heads=None if read_head is None else [partial(read_head, item.sha256) for item in items])


def volume_model_key(inputs: list[InputFile], options: Any, limits: dict[str, int] | None = None) -> str | None:
    """The key the engine keeps this job's volume model under (``engine.model_key`` of the files as
    :func:`stored_case_files` gives them, read as the parsed ``options`` say), from the inputs' digests alone; None
    without a volume."""
    items = [f for f in inputs if f.role == "volume"]
    if not items:
        return None
    return engine.model_key(volume_parts(items, _not_read), "volume" + items[0].suffix,
                            engine.VolumeReading(**volume_reading(options)), input_limits(limits).working_faces)


def _not_read(digest: str) -> bytes:
    raise AssertionError(f"blob {digest[:12]}… read for a model key")  # the key takes the digests


def fetched_case_files(ap: bytes, lat: bytes, volume: list[bytes], frames: tuple[Any, Any],
                       warnings: list[str]) -> Any:
    """Inputs fetched from a PACS as ``engine.CaseFiles`` (the geometry comes from the XA headers);
    ``frames``: the (ap, lat) frame choices of the references."""
    return engine.CaseFiles(ap=ap, ap_name="ap.dcm", lat=lat, lat_name="lat.dcm", volume=volume,
                            volume_name="volume.dcm", warnings=tuple(warnings),
                            reading=engine.ImageReading(ap_frame=frames[0], lat_frame=frames[1]))


def image_reading_json(options: Any) -> dict[str, Any]:
    """The options' image reading (frames per view, subtraction) as JSON for the validator."""
    return vars(engine.image_reading(options))


def volume_reading(options: Any) -> dict[str, Any]:
    """The options that decide how a volume is read (kind, vessel window), as the validator request carries them."""
    labels = getattr(options, "volume_labels", None)
    return {"kind": options.volume_kind, "vessel_min": options.volume_vessel_min,
            "vessel_max": options.volume_vessel_max, "labels": list(labels) if labels is not None else None}


def xa_view_angle_deg(a: tuple[float, float], b: tuple[float, float]) -> float:
    """Degrees between the view directions of two C-arm positions ``(primary°, secondary°)``
    (the engine's C-arm convention, ``engine.c_arm_rotation``)."""
    import numpy as np

    beam_at_ap = np.array([0.0, -1.0, 0.0])  # the AP view looks along −y (LPS: anterior)
    da, db = (engine.c_arm_rotation(p, s) @ beam_at_ap for p, s in (a, b))
    return float(np.degrees(np.arccos(np.clip(float(da @ db), -1.0, 1.0))))


def load_job_case(inputs: list[InputFile], geometry: str | None, segmentation: str, read: Any,
                  limits: dict[str, int] | None = None, reading: dict[str, Any] | None = None,
                  volume: dict[str, Any] | None = None, mesh_units: str | None = None, *,
                  hemodynamics: bool = False, models: dict[str, Any] | None = None, read_head: Any = None) -> Any:
    """Read a job's stored inputs as the worker will (the API's validator calls this); ``reading``:
    :func:`image_reading_json` of the job's options; ``volume``: :func:`volume_reading` of them; ``mesh_units``:
    the options' ``mesh_units``; ``hemodynamics``: the views must also be timed runs (``engine.check_timed_runs``);
    ``models``: :func:`model_cache` (a volume's model is kept there for the worker and later jobs); ``read_head``: as
    :func:`stored_case_files`."""
    files = stored_case_files(inputs, geometry, read, limits, read_head)
    case = engine.load_case_files(files, segmentation, input_limits(limits),
                                  reading=engine.ImageReading(**reading) if reading else None,
                                  volume_reading=engine.VolumeReading(**(volume or {})), mesh_units=mesh_units,
                                  model_store=model_store(models))
    if hemodynamics:
        engine.check_timed_runs(files)
    return case


def volume_cost(inputs: list[InputFile], read: Any, limits: dict[str, int] | None = None,
                volume: dict[str, Any] | None = None, models: dict[str, Any] | None = None,
                read_head: Any = None) -> Any:
    """What reading a job's volume will cost, from its header (``engine.VolumeCost``; no voxel decoded): None
    without a volume or a declared shape; raises ``engine.DsaregInputError`` for what its header already refuses.
    The files as :func:`stored_case_files` gives them; ``volume``: :func:`volume_reading`; ``models``:
    :func:`model_cache` (a kept model: the read costs headers only); ``read_head``: as :func:`stored_case_files`."""
    items = [f for f in inputs if f.role == "volume"]
    if not items:
        return None
    data = read(items[0].sha256) if len(items) == 1 else volume_parts(items, read, read_head)
    return engine.volume_read_cost(data, "volume" + items[0].suffix, input_limits(limits),
                                   engine.VolumeReading(**(volume or {})), model_store(models))


def model_cache(storage: Any) -> dict[str, Any] | None:
    """The volume-model cache of ``storage`` (:class:`service.settings.StorageSettings`) as plain data for another
    process: ``{"dir", "entries"}``, or None when it is off."""
    folder = storage.model_dir
    return None if folder is None else {"dir": str(folder), "entries": int(storage.model_cache_entries)}


def model_store(models: dict[str, Any] | None) -> Any:
    """The engine's store for :func:`model_cache`'s description (files shared by every process), or None."""
    if not models:
        return None
    return engine.DirectoryModelStore(models["dir"], max_entries=models["entries"])


def case_summary(case: Any) -> dict[str, Any]:
    summary: dict[str, Any] = {"warnings": [str(w) for w in getattr(case, "warnings", []) or []]}
    try:  # whose case it is, from the headers the readers kept (the caller sets the source and file names)
        summary["case"] = json_safe(engine.case_identity(case.sources, source="upload"))
    except Exception:  # noqa: BLE001 - informative only: the job is accepted without it
        summary["case"] = None
    try:
        summary["faces"] = int(case.mesh.n_faces)
        summary["views"] = {name: list(mask.shape[::-1]) for name, mask in case.masks.items()}
    except Exception:  # noqa: BLE001, S110 - the summary is informative only
        pass
    return summary


def job_case(identity: dict[str, Any] | None, source: str, file_names: dict[str, list[str]] | None = None, *,
             carried: Mapping[str, str] | None = None) -> tuple[dict[str, Any], str | None]:
    """A job's case identity (``identity`` from the validator's summary, with its source and upload file
    names set; ``carried``: a tracking job's planes not sent again → the job each image was sent with, as the
    inputs' ``carried_from``) and the text ``?q=`` searches."""
    case = engine.with_source(identity, source=source, file_names=file_names)
    for row in case.get("inputs", []):
        if carried and row.get("role") in carried:
            row["carried_from"] = carried[row["role"]]
    return case, engine.case_search_text(case)


def fetched_case(files: Any, source: str) -> tuple[dict[str, Any], str | None]:
    """The case identity of inputs a worker fetched from a PACS (headers only; never fails the job)."""
    try:
        sources = engine.read_sources(files.ap, files.lat, files.volume)
        identity = json_safe(engine.case_identity(sources, source=source))
    except Exception:  # noqa: BLE001 - informative only
        identity = None
    return job_case(identity, source)


# ---- running and outputs -----------------------------------------------------------------------


def run_job(files: Any, options: dict[str, Any], out_dir: Path, *, limits: dict[str, int] | None, control: Any,
            label: str, dicom: str, models: dict[str, Any] | None = None) -> dict[str, Any]:
    """A worker's one call into the engine: ``engine.run_case`` (read, register, write every output).

    ``control`` gives ``progress(update)`` and ``should_stop()``; ``dicom``: ``"best_effort"`` or
    ``"required"`` (a job by DICOMweb reference stores them in its PACS). Returns the result as
    strict JSON (no NaN, no numpy types), warnings included. ``models``: :func:`model_cache`.
    """
    result = engine.run_case(files, options, out_dir, limits=input_limits(limits), progress=control.progress,
                             should_stop=control.should_stop, label=label, dicom=dicom, model_store=model_store(models))
    return json_safe(result)


def json_safe(value: Any) -> Any:
    """Plain JSON: numpy scalars/arrays to Python, NaN/inf to None (strict JSON has no NaN)."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        return json_safe(value.tolist())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (str, int, bool)) or value is None:
        return value
    return str(value)


ARTIFACT_FILES = engine.ARTIFACTS
"""The engine's output files (registration and DICOM), ``{file name: media type}``."""


def collect_artifacts(out_dir: Path, blobs: BlobStore) -> dict[str, str]:
    """Move the engine's known output files into the blob store: ``{file name: sha256}``."""
    artifacts: dict[str, str] = {}
    for name in ARTIFACT_FILES:
        path = out_dir / name
        if path.is_file():
            digest, _ = blobs.put_file(path)
            artifacts[name] = digest
    return artifacts
