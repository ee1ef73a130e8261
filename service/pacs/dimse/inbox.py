"""Durable receipt of a DICOM instance: its file is flushed to disk before the index
(:class:`service.storage.inbox.Inbox`, the ``dimse_instances`` table) records it and the C-STORE is answered."""

from __future__ import annotations

import os
from pathlib import Path


def fsync_file(path: Path) -> None:
    """Flush a file and the folder entry that names it to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)
