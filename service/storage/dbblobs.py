"""Blobs (inputs and artifacts) in a table of the job database.

With several API replicas and Celery workers on different machines there is no shared
filesystem: an upload accepted by one API replica must be readable by whichever worker
claims the job, and an overlay written by that worker must be servable by every replica.
We keep the bytes in the job database (``blob_data``), next to the job rows that
reference them, so the deployment needs no extra service (no S3/MinIO) and a blob and
its job row are backed up together.

The local ``<data_dir>/blobs`` directory stays as a *cache*: writes go to the table and
to the cache, reads hit the cache first and fill it from the table. The API's input
validator processes and ``FileResponse`` keep working on local paths.

Trade-off (see the README): bytes in PostgreSQL cost database storage and memory per
transfer (a blob is read/written whole; PostgreSQL ``bytea`` holds at most 1 GiB), which is
fine for this service's inputs (meshes, two images, volumes up to a few hundred MB).
An S3-compatible store would be the choice for much larger volumes.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import time
from pathlib import Path
from typing import BinaryIO

import sqlalchemy as sa

from .blobs import BlobStore
from .dbtimeouts import bulk_statements
from .migrate import upgrade_database
from .schema import blob_data


class DatabaseBlobStore(BlobStore):
    """:class:`BlobStore` whose source of truth is the ``blob_data`` table; files are a local cache."""

    def __init__(self, root: Path, engine: sa.Engine, *, create_schema: bool = True, cache: bool = True):
        super().__init__(root)
        self.engine = engine
        # API: keep local copies (validator and FileResponse read files; retention/GC prune them).
        # Workers: no cache (nothing would prune it); inputs are read from the table per job.
        self.cache = cache
        if create_schema:
            upgrade_database(engine)

    # ---- database side -------------------------------------------------------------------
    def _db_has(self, digest: str) -> bool:
        with self.engine.connect() as conn:
            return conn.execute(sa.select(blob_data.c.sha256).where(blob_data.c.sha256 == digest)).first() is not None

    def _db_put(self, digest: str, data: bytes) -> None:
        now = time.time()
        with self.engine.begin() as conn:
            # refresh created_at of an existing row: protects it from a concurrent garbage collection
            n = conn.execute(blob_data.update().where(blob_data.c.sha256 == digest).values(created_at=now)).rowcount
            if n:
                return
        try:
            with self.engine.begin() as conn:
                bulk_statements(conn)
                conn.execute(blob_data.insert().values(sha256=digest, size=len(data), created_at=now, data=data))
        except sa.exc.IntegrityError:  # a concurrent writer stored the same content
            pass

    def _db_read(self, digest: str) -> bytes | None:
        with self.engine.connect() as conn:
            data = bulk_statements(conn).execute(sa.select(blob_data.c.data).where(blob_data.c.sha256 == digest)).scalar()
        if data is None:
            return None
        data = bytes(data)
        if hashlib.sha256(data).hexdigest() != digest:
            raise OSError(f"blob {digest[:12]}… is corrupt in the database")
        return data

    def _fetch(self, digest: str) -> Path | None:
        """Fill the local cache from the table; the cached path or None when the blob is unknown."""
        target = self.path(digest)
        if target.is_file():
            return target
        data = self._db_read(digest)
        if data is None:
            return None
        fd, name = tempfile.mkstemp(dir=self.tmp_dir, prefix="db-")
        with os.fdopen(fd, "wb") as out:
            out.write(data)
        return self._adopt(Path(name), digest)

    # ---- BlobStore interface -----------------------------------------------------------------
    def put_stream(self, stream: BinaryIO) -> tuple[str, int]:
        if self.cache:
            digest, size = super().put_stream(stream)
            self._db_put(digest, self.path(digest).read_bytes())
            return digest, size
        data = stream.read()
        return self.put_bytes(data)

    def put_bytes(self, data: bytes) -> tuple[str, int]:
        if self.cache:
            digest, size = super().put_bytes(data)
        else:
            digest, size = hashlib.sha256(data).hexdigest(), len(data)
        self._db_put(digest, data)
        return digest, size

    def put_file(self, path: Path) -> tuple[str, int]:
        with open(path, "rb") as f:
            return self.put_stream(f)

    def exists(self, digest: str) -> bool:
        return self._db_has(digest)

    def read(self, digest: str) -> bytes:
        if self.cache:
            path = self._fetch(digest)
            data = None if path is None else path.read_bytes()
        else:
            data = self._db_read(digest)
        return data if data is not None else self._missing(digest)

    def read_head(self, digest: str, size: int) -> bytes:
        """The blob's first ``size`` bytes: from the cache, else only those bytes from the table (no digest check:
        the whole blob's read checks it)."""
        if self.cache:
            return super().read_head(digest, size) if self._fetch(digest) is not None else self._missing(digest)
        with self.engine.connect() as conn:
            head = bulk_statements(conn).execute(
                sa.select(sa.func.substr(blob_data.c.data, 1, int(size))).where(blob_data.c.sha256 == digest)).scalar()
        return bytes(head) if head is not None else self._missing(digest)

    @staticmethod
    def _missing(digest: str) -> bytes:
        raise FileNotFoundError(f"blob {digest[:12]}… is not stored")

    def local_path(self, digest: str) -> Path | None:
        return self._fetch(digest)

    def delete(self, digests: list[str], *, min_age_seconds: float = 10.0) -> int:
        removed = 0
        if digests:
            cutoff = time.time() - min_age_seconds
            with self.engine.begin() as conn:
                for start in range(0, len(digests), 500):
                    chunk = list(digests[start:start + 500])
                    removed += conn.execute(blob_data.delete().where(
                        blob_data.c.sha256.in_(chunk), blob_data.c.created_at <= cutoff)).rowcount
        super().delete(digests, min_age_seconds=min_age_seconds)  # the local cache
        return removed

    def all_digests(self) -> list[str]:
        with self.engine.connect() as conn:
            stored = set(conn.execute(sa.select(blob_data.c.sha256)).scalars())
        return sorted(stored | set(super().all_digests()))


def make_blob_store(settings, engine: sa.Engine | None = None, *, cache: bool = True) -> BlobStore:
    """The blob store the settings ask for (``engine``: the job store's, to share its pool;
    ``cache``: keep local copies of database blobs, for the API)."""
    root = Path(settings.storage.data_dir)
    if settings.effective_blob_backend == "database":
        if engine is None:
            engine = sa.create_engine(settings.effective_database_url, future=True)
        return DatabaseBlobStore(root, engine, cache=cache)
    return BlobStore(root)
