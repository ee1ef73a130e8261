"""The key a volume's model is kept under (:mod:`.model_cache`): light, so that a service process that computes it
imports no reader (``engine.model_key``).

The key is the SHA-256 of ``MODEL_VERSION``, the volume's files (each one's SHA-256, in order: a
:class:`.file_parts.FileParts` carrying its store's digests reads none), its file name, the
:class:`~.volume_kind.VolumeReading` and the working face budget. Bump ``MODEL_VERSION`` whenever the extraction's
output for the same input changes.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import asdict

from .file_parts import PART_LISTS, file_digests
from .volume_kind import VolumeReading

# 2: separate pieces in bone set aside (session 23); 3: venous sinuses set aside, the volume read again without
# the pieces set aside (session 24)
MODEL_VERSION = "volume-model-3"


def model_key(volume: bytes | Sequence[bytes], name: str | None, reading: VolumeReading | None, working_faces: int) -> str:
    """The cache key of a volume read with ``reading`` into at most ``working_faces`` faces (hex SHA-256)."""
    parts = volume if isinstance(volume, PART_LISTS) else [volume]  # read one at a time, or a store's digests
    described = {"version": MODEL_VERSION, "files": file_digests(parts),
                 "name": name or "", "reading": asdict(reading or VolumeReading()), "faces": int(working_faces)}
    return hashlib.sha256(json.dumps(described, sort_keys=True, default=list).encode()).hexdigest()


__all__ = ["MODEL_VERSION", "model_key"]
