"""The service's inputs as the engine reads them (``service/engine_adapter.py``)."""

from __future__ import annotations

from dsareg_engine.api import FileParts
from service.engine_adapter import stored_case_files
from service.storage.records import InputFile


def test_a_volumes_files_are_read_from_the_store_when_the_engine_reads_them():
    """A job's volume (here a three-file series) comes as ``FileParts``: nothing read until used, each file read
    again on each use, none kept (a whole head's series is 0.23 GB); the runs are read once, as bytes."""
    blobs = {"v0": b"slice 0", "v1": b"slice 1", "v2": b"slice 2", "a": b"ap run", "l": b"lat run"}
    reads: list[str] = []

    def read(digest: str) -> bytes:
        reads.append(digest)
        return blobs[digest]

    inputs = [InputFile("volume", f"v{i}", 7, ".dcm") for i in range(3)]
    inputs += [InputFile("ap", "a", 6, ".dcm"), InputFile("lat", "l", 7, ".dcm")]
    files = stored_case_files(inputs, None, read)
    assert files.ap == b"ap run" and files.lat == b"lat run" and sorted(reads) == ["a", "l"]
    assert isinstance(files.volume, FileParts) and len(files.volume) == 3 and files.volume_name == "volume.dcm"
    assert list(files.volume) == [b"slice 0", b"slice 1", b"slice 2"] and list(files.volume) == list(files.volume)
    assert reads.count("v1") == 3


def test_a_single_volume_file_is_read_when_used_too():
    files = stored_case_files([InputFile("volume", "n", 3, ".nii")], None, {"n": b"nii"}.__getitem__)
    assert isinstance(files.volume, FileParts) and list(files.volume) == [b"nii"] and files.volume_name == "volume.nii"
