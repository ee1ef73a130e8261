"""Vessel models extracted from volumes, kept for the next job on the same volume.

A hospital registers one CTA against several runs; each job read it again (a whole-head CTA: a minute of CPU and
GBs). Here a volume's model is kept under a key made of the volume's content and of everything its reading depends
on, and a later job with the same key takes the model instead of reading the volume:

* **key** (:func:`.model_key.model_key`): SHA-256 of ``MODEL_VERSION``, the volume's files (each one's SHA-256, in order), its
  file name, the :class:`~.volume_kind.VolumeReading` (kind, window, labels) and the working face budget;
* **value** (:class:`CachedModel`): the surface (after decimation), the readout with its decisions, the reader's
  warnings and the volume's format. No DICOM identity is kept (patient data stays with the uploads): a hit reads
  the series' headers again (:func:`.volume_io.read_volume_identities`, no pixel decoding);
* **store** (:class:`DirectoryModelStore`): one ``.npz`` file per key in a folder every process of a deployment
  shares (the service's data folder), written to a temporary name then renamed (a reader never sees half a file,
  two writers of one key write the same bytes), bounded in entries and bytes (the least recently used go first),
  read without pickle. An unreadable entry is a miss (and removed); a temporary file a killed writer left is
  removed by the next write once it is an hour old.

Bump ``MODEL_VERSION`` (:mod:`.model_key`) whenever the extraction's output for the same input changes.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from ..mesh import TriangleMesh
from .input_decisions import InputDecision
from .model_key import MODEL_VERSION, model_key

if TYPE_CHECKING:  # the readers are imported where a model is read back (:func:`from_bytes`), not for the files
    from .volume_vessels import VolumeReadout

STALE_TEMPORARY_S = 3600.0  # a temporary file this old is no write in progress (a model is written in seconds)


@dataclass(frozen=True)
class CachedModel:
    """What a volume's reading gave a case: its surface (world mm, decimated), readout, warnings and format."""

    surface: TriangleMesh
    readout: VolumeReadout
    warnings: tuple[str, ...]
    kind: str


def to_bytes(model: CachedModel) -> bytes:
    """An ``.npz`` of the model: ``vertices``, ``faces`` and ``meta`` (JSON: readout, decisions, warnings, kind)."""
    readout = asdict(model.readout)
    meta = {"readout": readout, "warnings": list(model.warnings), "kind": model.kind}
    out = io.BytesIO()
    np.savez(out, vertices=model.surface.vertices, faces=model.surface.faces,
             meta=np.frombuffer(json.dumps(meta).encode(), np.uint8))
    return out.getvalue()


def from_bytes(data: bytes) -> CachedModel:
    """The model :func:`to_bytes` wrote (no pickle); raises ``ValueError`` / ``KeyError`` on anything else."""
    with np.load(io.BytesIO(data), allow_pickle=False) as stored:
        vertices, faces = np.array(stored["vertices"], np.float64), np.array(stored["faces"], np.int64)
        meta = json.loads(bytes(stored["meta"]).decode())
    readout = dict(meta["readout"])
    readout["decisions"] = [InputDecision(**item) for item in readout.get("decisions", [])]
    from .volume_vessels import VolumeReadout

    return CachedModel(TriangleMesh(vertices, faces), VolumeReadout(**readout), tuple(meta["warnings"]),
                       str(meta["kind"]))


class ModelStore(Protocol):
    """Where models are kept: ``get`` a key's model (None: a miss), ``put`` one."""

    def get(self, key: str) -> CachedModel | None: ...

    def put(self, key: str, model: CachedModel) -> None: ...


class DirectoryModelStore:
    """Models as files in ``root`` (created on first use), at most ``max_entries`` of them and ``max_bytes`` in all."""

    def __init__(self, root: str | os.PathLike, max_entries: int = 32, max_bytes: int = 256 << 20):
        self.root, self.max_entries, self.max_bytes = Path(root), int(max_entries), int(max_bytes)

    def path(self, key: str) -> Path:
        """Where the model of ``key`` is kept (whether or not it is there)."""
        if len(key) != 64 or any(c not in "0123456789abcdef" for c in key):
            raise ValueError("a model key is a hex SHA-256")
        return self.root / f"{key}.npz"

    def get(self, key: str) -> CachedModel | None:
        path = self.path(key)
        try:
            model = from_bytes(path.read_bytes())
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError):  # a damaged entry: a miss, and gone
            path.unlink(missing_ok=True)
            return None
        try:
            os.utime(path)  # recently used
        except OSError:
            pass
        return model

    def put(self, key: str, model: CachedModel) -> None:
        self.put_bytes(key, to_bytes(model))

    def put_bytes(self, key: str, data: bytes) -> bool:
        """A model file's bytes (:func:`to_bytes`'s) kept under ``key``: written to a temporary name, then renamed;
        whether it was (not when larger than ``max_bytes`` or the folder cannot be written)."""
        if len(data) > self.max_bytes:
            return False
        self.root.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=self.root, prefix=".model-", suffix=".tmp")
        try:
            with os.fdopen(handle, "wb") as out:
                out.write(data)
            os.replace(temporary, self.path(key))
        except OSError:
            Path(temporary).unlink(missing_ok=True)
            return False
        self._evict()
        return True

    def _evict(self) -> None:
        stale = time.time() - STALE_TEMPORARY_S  # a writer killed between its write and its rename left these
        for path in self.root.glob(".model-*.tmp"):
            try:
                if path.stat().st_mtime < stale:
                    path.unlink()
            except OSError:
                continue
        entries = []
        for path in self.root.glob("*.npz"):
            try:
                status = path.stat()
            except OSError:
                continue
            entries.append((status.st_mtime, status.st_size, path))
        entries.sort(reverse=True)  # newest first
        total = 0
        for rank, (_, size, path) in enumerate(entries):
            total += size
            if rank >= self.max_entries or total > self.max_bytes:
                path.unlink(missing_ok=True)


__all__ = ["MODEL_VERSION", "CachedModel", "DirectoryModelStore", "ModelStore", "from_bytes", "model_key", "to_bytes"]
