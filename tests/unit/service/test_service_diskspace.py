"""ENOSPC mid-write on a real (tiny) tmpfs: the blob store cleans up and says DiskFull (→ 507)."""

from __future__ import annotations

import errno
import io

import pytest
from tests.support.faults_kit import tmpfs

from service.storage.blobs import BlobStore
from service.storage.diskspace import DiskFull, ensure_room, has_room, is_disk_full

MiB = 1 << 20


def test_enospc_mid_upload_leaves_nothing_behind(tmp_path):
    with tmpfs(tmp_path / "disk", 2 * MiB) as disk:
        blobs = BlobStore(disk)
        digest, _ = blobs.put_stream(io.BytesIO(b"small"))
        with pytest.raises(DiskFull) as caught:
            blobs.put_stream(io.BytesIO(b"x" * (3 * MiB)))  # passes no floor: the filesystem says ENOSPC
        assert is_disk_full(caught.value) and isinstance(caught.value.__cause__, OSError)
        with pytest.raises(DiskFull):
            blobs.put_bytes(b"y" * (3 * MiB))
        assert list(blobs.tmp_dir.iterdir()) == []  # no partial file
        assert blobs.all_digests() == [digest]
        blobs.put_stream(io.BytesIO(b"fits again"))  # the space the failed writes took is free again


def test_floor_refuses_before_writing(tmp_path):
    with tmpfs(tmp_path / "disk", 4 * MiB) as disk:
        ensure_room(disk, 1 * MiB, 1 * MiB)
        with pytest.raises(DiskFull, match="MiB are kept free"):
            ensure_room(disk, 1 * MiB, 3 * MiB + MiB // 2)
        assert has_room(disk, 1 * MiB) and not has_room(disk, 8 * MiB)
        ensure_room(disk, 0)  # 0: no floor


def test_disk_full_is_recognised_through_wrapping():
    try:
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError as inner:
            raise RuntimeError("writing the overlay failed") from inner
    except RuntimeError as outer:
        assert is_disk_full(outer)
    assert not is_disk_full(OSError(errno.EACCES, "denied")) and not is_disk_full(None)
