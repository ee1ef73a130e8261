"""Vessel models shared by the nodes of a scale-out deployment, through the job database.

Each process keeps a volume's model in its node's ``<data_dir>/models`` (``engine.DirectoryModelStore``, keyed by
``engine.model_key``: the files' digests and the volume options). With the database blob backend the API replicas
and the workers share no filesystem, so a model kept on one node served no other: the API's validator read the
volume, then the worker read it again, and every worker node once more. :class:`SharedModels` copies a model's file
between a node's folder and the ``volume_models`` table: **pull** before the engine runs (a model another node kept
becomes this node's file), **push** after (a model this node made goes to the table).

The table holds the model files' bytes (a surface and its readout; no DICOM identity, no patient data), at most
``max_entries`` rows: the least recently used go first. A damaged row is a miss for the engine (its reader
rejects the file and removes it); nothing here is needed for a job to succeed, so every database error is a miss,
logged by type only.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import sqlalchemy as sa

from .dbtimeouts import bulk_statements
from .schema import volume_models

log = logging.getLogger("dsareg.service.models")


class SharedModels:
    """A node's model folder mirrored through the ``volume_models`` table of ``engine``; ``local``: the node's
    ``engine.DirectoryModelStore`` (``path(key)``, ``put_bytes(key, data)``, ``root``, ``max_entries``; made by
    ``service.engine_adapter.model_store``: only the adapter imports the engine)."""

    def __init__(self, engine: sa.Engine, local: Any):
        self.engine, self.local, self.max_entries = engine, local, int(local.max_entries)

    @property
    def folder(self) -> Path:
        return self.local.root

    def pull(self, key: str) -> bool:
        """The table's model ``key`` written to this node's folder when the folder lacks it: whether it was."""
        if self.local.path(key).is_file():
            return False
        try:
            with self.engine.begin() as conn:
                data = bulk_statements(conn).execute(
                    sa.select(volume_models.c.data).where(volume_models.c.model_key == key)).scalar()
                if data is not None:
                    conn.execute(volume_models.update().where(volume_models.c.model_key == key)
                                 .values(used_at=time.time()))
        except sa.exc.SQLAlchemyError as exc:
            log.warning("the shared model store could not be read (%s): the volume is read here", type(exc).__name__)
            return False
        return data is not None and self.local.put_bytes(key, bytes(data))

    def push(self, key: str) -> bool:
        """This node's model ``key`` put in the table when the table lacks it (the oldest rows beyond
        ``max_entries`` then removed): whether it was."""
        try:
            data = self.local.path(key).read_bytes()
        except OSError:
            return False
        now = time.time()
        try:
            with self.engine.begin() as conn:
                if conn.execute(volume_models.update().where(volume_models.c.model_key == key)
                                .values(used_at=now)).rowcount:
                    return False
            with self.engine.begin() as conn:
                bulk_statements(conn).execute(volume_models.insert().values(model_key=key, size=len(data),
                                                                            used_at=now, data=data))
            self._evict()
        except sa.exc.IntegrityError:  # another node put the same model meanwhile
            return False
        except sa.exc.SQLAlchemyError as exc:
            log.warning("the shared model store could not be written (%s)", type(exc).__name__)
            return False
        return True

    def _evict(self) -> None:
        with self.engine.begin() as conn:
            kept = sa.select(volume_models.c.model_key).order_by(volume_models.c.used_at.desc()).limit(self.max_entries)
            conn.execute(volume_models.delete().where(volume_models.c.model_key.not_in(kept.scalar_subquery())))

    def keys(self) -> list[str]:
        """The keys in the table, most recently used first."""
        with self.engine.connect() as conn:
            return list(conn.execute(sa.select(volume_models.c.model_key)
                                     .order_by(volume_models.c.used_at.desc())).scalars())


def shared_models_for(settings, blobs, local: Any) -> SharedModels | None:
    """The shared model store of a deployment with the database blob backend and the model cache on (``local``: the
    node's model store, or None when the cache is off), else None (one node: its ``<data_dir>/models`` is shared by
    its processes already)."""
    engine = getattr(blobs, "engine", None)
    if local is None or engine is None or settings.effective_blob_backend != "database":
        return None
    return SharedModels(engine, local)
