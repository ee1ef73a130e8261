"""Pose files: JSON objects ``{"mesh_to_world": [[4x4]]}``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import DsaregInputError
from .pose import validate_rigid


def load_pose(path: str | Path) -> np.ndarray:
    """Read ``mesh_to_world`` from a pose file; errors name the file and the key."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise DsaregInputError(f"cannot read pose file {path}: {exc}", field="pose") from None
    if not isinstance(data, dict) or "mesh_to_world" not in data:
        raise DsaregInputError("needs a 'mesh_to_world' key", field=str(path), accepted='{"mesh_to_world": [[4x4]]}')
    return validate_rigid(data["mesh_to_world"], field=f"{path}: mesh_to_world", allow_mirror=False)


def save_pose(path: str | Path, mesh_to_world: np.ndarray) -> None:
    Path(path).write_text(json.dumps({"mesh_to_world": np.asarray(mesh_to_world).tolist()}, indent=2))
