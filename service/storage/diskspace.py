"""A full disk is a known, temporary condition: refused before writing (507 + Retry-After), never a 500.

The data directory keeps ``min_free_bytes`` free (``DSAREG_MIN_FREE_BYTES``): a submission that
would leave less is refused before any byte is written, and a worker below it does not claim
jobs. Writing can still run out of space (a concurrent upload, another process filling the
disk): ``ENOSPC``/``EDQUOT`` anywhere under a request or a job is recognised by
:func:`is_disk_full` — the request gets 507, the job is handed back without using an attempt.
"""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
RETRY_AFTER_SECONDS = 60


class DiskFull(Exception):
    """No room to write (below the floor, or the filesystem said ENOSPC/EDQUOT)."""

    def __init__(self, detail: str):
        super().__init__(detail)
        self.detail = detail


def free_bytes(path: Path) -> int:
    """Free bytes for an unprivileged writer on the filesystem holding ``path``."""
    return shutil.disk_usage(path).free


def is_disk_full(exc: BaseException | None) -> bool:
    """``exc`` or anything in its cause/context chain is a disk-full error."""
    seen = 0
    while exc is not None and seen < 16:
        if isinstance(exc, DiskFull) or (isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS):
            return True
        if "database or disk is full" in str(exc):  # SQLite's SQLITE_FULL (its own message, no errno)
            return True
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return False


def ensure_room(path: Path, floor_bytes: int, needed_bytes: int = 0) -> None:
    """Raise :class:`DiskFull` when writing ``needed_bytes`` under ``path`` would leave less than the floor."""
    if floor_bytes <= 0 and needed_bytes <= 0:
        return
    free = free_bytes(path)
    if free - needed_bytes < floor_bytes:
        raise DiskFull(f"the server's data disk is nearly full ({free // (1 << 20)} MiB free, "
                       f"{floor_bytes // (1 << 20)} MiB are kept free); retry later")


def has_room(path: Path, floor_bytes: int) -> bool:
    try:
        ensure_room(path, floor_bytes)
    except DiskFull:
        return False
    except OSError:
        return True  # cannot tell: let the write decide
    return True
