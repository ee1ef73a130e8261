"""The service's boundary with the registration engine: the only module in ``service/`` that
imports :mod:`dsareg_engine`, and only its application API :mod:`dsareg_engine.api`
(re-exported here as ``engine``; its heavy parts load on first use).

Both the API's input validator (in its own processes) and the workers go through
:func:`load_job_case`, so what the API accepted is exactly what the worker loads.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from dsareg_engine import api as engine

from .blobs import BlobStore
from .limits import image_decoded_bytes
from .problems import Problem
from .store import InputFile

ROLE_NAMES = {"mesh": "mesh", "volume": "volume", "ap": "ap", "lat": "lat"}


def geometry_argument(geometry: str | None) -> str | dict | None:
    """Stored geometry text → what ``load_case`` takes (a preset name or a parsed dict).

    The API only stores preset names or JSON object text, so a file path can never reach
    ``load_rig`` (which would otherwise read a server-side file).
    """
    if geometry is None:
        return None
    text = geometry.strip()
    if text.startswith("{"):
        return json.loads(text)
    return text


def input_limits(limits: dict[str, int] | None) -> Any:
    """``InputLimits`` with the configured ceilings (engine defaults for the others)."""
    return engine.input_limits(limits)


def check_options(options: Any) -> None:
    """Refuse what the worker would refuse, naming the option (422)."""
    for name in ("initial_mesh_to_world", "ground_truth_mesh_to_world"):
        matrix = getattr(options, name, None)
        if matrix is None:
            continue
        try:
            engine.validate_rigid(matrix, field=f"options.{name}", allow_mirror=False)
        except engine.DsaregInputError as exc:
            raise Problem(422, exc.message, field=exc.field, accepted=exc.accepted) from None


def check_image_budget(data: bytes, field: str, limit: int) -> None:
    """Refuse an image whose decoded pixels would need more than ``limit`` bytes (before decoding)."""
    size = image_decoded_bytes(data)
    if size is not None and size > limit:
        raise engine.DsaregInputError(
            f"decodes to {size / 2**20:.0f} MiB of pixels (width × height × channels × bytes per sample), "
            f"above this server's limit of {limit / 2**20:.0f} MiB",
            field=field, accepted="a smaller image, fewer channels or fewer bits per sample")


def load_job_case(inputs: list[InputFile], geometry: str | None, segmentation: str, read: Any,
                  limits: dict[str, int] | None = None) -> Any:
    """Call ``dsareg_engine.io.case.load_case`` for stored inputs; ``read(sha256) -> bytes``.

    Several files of one role (a DICOM series, a ``.rad`` + ``.raw`` pair) are passed as a
    list in the order they were uploaded; names are ``<role><sanitized suffix>``.
    """
    image_budget = (limits or {}).get("max_image_bytes")
    kwargs: dict[str, Any] = {"geometry": geometry_argument(geometry), "segmentation": segmentation,
                              "limits": input_limits(limits)}
    for role in ("mesh", "volume", "ap", "lat"):
        items = [f for f in inputs if f.role == role]
        if not items:
            continue
        if role == "mesh" or len(items) == 1:
            kwargs[role] = read(items[0].sha256)
        else:
            kwargs[role] = [read(item.sha256) for item in items]
        if image_budget and role in ("ap", "lat"):
            for data in kwargs[role] if isinstance(kwargs[role], list) else [kwargs[role]]:
                check_image_budget(data, role, image_budget)
        kwargs[f"{role}_name"] = role + items[0].suffix
    return engine.load_case(**kwargs)


def case_summary(case: Any) -> dict[str, Any]:
    summary: dict[str, Any] = {"warnings": [str(w) for w in getattr(case, "warnings", []) or []]}
    try:
        summary["faces"] = int(case.mesh.n_faces)
        summary["views"] = {name: list(mask.shape[::-1]) for name, mask in case.masks.items()}
    except Exception:  # noqa: BLE001, S110 - the summary is informative only
        pass
    return summary


def blob_reader(blobs: BlobStore):
    return blobs.read


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
