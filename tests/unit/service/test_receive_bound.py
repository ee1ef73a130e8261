"""The per-instance receive buffer of the DICOM node (service/pacs/dimse/receive_bound.py)."""

from __future__ import annotations

import os

from service.pacs.dimse.receive_bound import BoundedBuffer


def _fill(buffer: BoundedBuffer, data: bytes, step: int = 1 << 20) -> None:
    for start in range(0, len(data), step):
        buffer.write(data[start:start + step])


def test_past_its_memory_share_the_data_set_goes_to_an_unnamed_file(tmp_path):
    data = os.urandom(5 << 20)
    buffer = BoundedBuffer(limit_bytes=8 << 20, spill_dir=tmp_path, memory_bytes=1 << 20)
    _fill(buffer, data)
    assert buffer._file is not None and len(buffer.getbuffer()) == 0  # nothing of it left in memory
    assert list(tmp_path.iterdir()) == []  # unnamed: nothing to clean up after a crash
    assert bytes(buffer.view()) == data and buffer.getvalue() == data
    assert buffer.reader(b"PREFIX").read() == b"PREFIX" + data
    buffer.release()
    assert buffer._file is None and not buffer.exceeded


def test_past_the_limit_nothing_is_kept_and_the_rest_is_only_counted(tmp_path):
    buffer = BoundedBuffer(limit_bytes=3 << 20, spill_dir=tmp_path, memory_bytes=1 << 20)
    _fill(buffer, bytes(10 << 20))
    assert buffer.exceeded and buffer.received_bytes == 10 << 20
    assert buffer._file is None and len(buffer.getbuffer()) == 0


def test_small_data_sets_stay_in_memory(tmp_path):
    buffer = BoundedBuffer(limit_bytes=3 << 20, spill_dir=tmp_path / "never")
    buffer.write(b"abc")
    assert buffer._file is None and bytes(buffer.view()) == b"abc" and not (tmp_path / "never").exists()
