"""Content-addressed files under the data directory.

A blob lives at ``<data_dir>/blobs/<sha[:2]>/<sha>``; its path is built only from the
hex digest we computed, never from anything a client sent. Scratch space of running
jobs is ``<data_dir>/work/<job id>/<attempt>-<token>`` (server-made names as well).
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import tempfile
import time
from pathlib import Path
from typing import BinaryIO

from .diskspace import DiskFull, is_disk_full

_HEX64 = re.compile(r"^[0-9a-f]{64}$")
_SUFFIX_PART = re.compile(r"^[A-Za-z0-9]{1,8}$")
CHUNK = 1 << 20


def safe_suffix(filename: str | None, max_parts: int = 2) -> str:
    """The extension of a client file name, sanitized (``'.nii.gz'``, ``'.obj'``, or ``''``).

    Only this is kept of a client's file name (names may carry patient identifiers).
    """
    if not filename:
        return ""
    base = filename.replace("\\", "/").rsplit("/", 1)[-1]
    parts = base.split(".")[1:]
    kept: list[str] = []
    for part in reversed(parts[-max_parts:]):
        if not _SUFFIX_PART.match(part):
            break
        kept.insert(0, part.lower())
    # only keep the second part for well-known compound suffixes
    if len(kept) == 2 and kept[1] not in ("gz", "bz2", "xz", "zip"):
        kept = kept[1:]
    return "".join("." + p for p in kept)


UNNAMED_FILE_AGE_S = 3600.0
"""A stored file that no row names is removed once this old (by the API's sweeper and the standalone DICOM
listener): a store in flight, its row not yet written, is never that old; the file of an index write that failed is."""


class BlobStore:
    def __init__(self, root: Path):
        self.root = Path(root)
        self.blob_dir = self.root / "blobs"
        self.tmp_dir = self.root / "tmp"
        self.work_dir = self.root / "work"
        for d in (self.blob_dir, self.tmp_dir, self.work_dir):
            d.mkdir(parents=True, exist_ok=True)

    def path(self, digest: str) -> Path:
        if not _HEX64.match(digest):
            raise ValueError("not a sha256 hex digest")
        return self.blob_dir / digest[:2] / digest

    def exists(self, digest: str) -> bool:
        return self.path(digest).is_file()

    def _adopt(self, tmp: Path, digest: str) -> Path:
        target = self.path(digest)
        target.parent.mkdir(parents=True, exist_ok=True)
        if target.exists():
            tmp.unlink(missing_ok=True)
            os.utime(target)  # fresh mtime protects it from a concurrent garbage collection
        else:
            os.replace(tmp, target)
        return target

    def put_stream(self, stream: BinaryIO) -> tuple[str, int]:
        """Copy a (seekable or not) file object into the store; returns ``(sha256, size)``."""
        digest = hashlib.sha256()
        size = 0
        fd, name = tempfile.mkstemp(dir=self.tmp_dir, prefix="up-")
        tmp = Path(name)
        try:
            with os.fdopen(fd, "wb") as out:
                while True:
                    chunk = stream.read(CHUNK)
                    if not chunk:
                        break
                    digest.update(chunk)
                    size += len(chunk)
                    out.write(chunk)
            hexdigest = digest.hexdigest()
            self._adopt(tmp, hexdigest)
            return hexdigest, size
        except OSError as exc:
            if is_disk_full(exc):
                raise DiskFull("the server's data disk is full; retry later") from exc
            raise
        finally:
            tmp.unlink(missing_ok=True)  # a partial file never stays behind

    def put_bytes(self, data: bytes) -> tuple[str, int]:
        hexdigest = hashlib.sha256(data).hexdigest()
        if self.exists(hexdigest):
            os.utime(self.path(hexdigest))
            return hexdigest, len(data)
        fd, name = tempfile.mkstemp(dir=self.tmp_dir, prefix="put-")
        try:
            with os.fdopen(fd, "wb") as out:
                out.write(data)
            self._adopt(Path(name), hexdigest)
        except OSError as exc:
            if is_disk_full(exc):
                raise DiskFull("the server's data disk is full; retry later") from exc
            raise
        finally:
            Path(name).unlink(missing_ok=True)
        return hexdigest, len(data)

    def put_file(self, path: Path) -> tuple[str, int]:
        with open(path, "rb") as f:
            return self.put_stream(f)

    def read(self, digest: str) -> bytes:
        return self.path(digest).read_bytes()

    def read_head(self, digest: str, size: int) -> bytes:
        """The blob's first ``size`` bytes (all of it when shorter): a DICOM slice's header without its pixels."""
        with open(self.path(digest), "rb") as stream:
            return stream.read(size)

    def local_path(self, digest: str) -> Path | None:
        """A local file with the blob's content (None when not stored)."""
        path = self.path(digest)
        return path if path.is_file() else None

    def delete(self, digests: list[str], *, min_age_seconds: float = 10.0) -> int:
        """Remove blobs (those touched in the last ``min_age_seconds`` are left for the next sweep)."""
        removed = 0
        now = time.time()
        for digest in digests:
            try:
                p = self.path(digest)
                if now - p.stat().st_mtime >= min_age_seconds:
                    p.unlink()
                    removed += 1
            except (FileNotFoundError, ValueError):
                continue
        return removed

    def all_digests(self) -> list[str]:
        return [p.name for p in self.blob_dir.glob("??/*") if _HEX64.match(p.name)]

    def collect_garbage(self, referenced: set[str], *, min_age_seconds: float = UNNAMED_FILE_AGE_S) -> int:
        return self.delete([d for d in self.all_digests() if d not in referenced], min_age_seconds=min_age_seconds)

    def job_work_dir(self, job_id: str) -> Path:
        if not re.fullmatch(r"[0-9a-f]{32}", job_id):
            raise ValueError("bad job id")
        return self.work_dir / job_id

    def remove_job_work(self, job_id: str) -> None:
        try:
            shutil.rmtree(self.job_work_dir(job_id), ignore_errors=True)
        except ValueError:
            pass

    def clean_tmp(self, older_than_seconds: float = 3600.0) -> None:
        now = time.time()
        for p in self.tmp_dir.iterdir():
            try:
                if now - p.stat().st_mtime > older_than_seconds:
                    p.unlink()
            except OSError:
                continue
