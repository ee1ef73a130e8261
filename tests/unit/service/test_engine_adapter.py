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


def test_a_volumes_parts_carry_the_stores_digests_and_heads():
    heads: list[tuple[str, int]] = []

    def read_head(digest: str, size: int) -> bytes:
        heads.append((digest, size))
        return b"head of " + digest.encode()

    inputs = [InputFile("volume", f"v{i}", 7, ".dcm") for i in range(3)]
    files = stored_case_files(inputs, None, {}.__getitem__, read_head=read_head)
    assert files.volume.digests == ("v0", "v1", "v2")
    assert files.volume.head(1, 100) == b"head of v1" and heads == [("v1", 100)]
    assert stored_case_files(inputs, None, {"v2": b"slice 2"}.__getitem__).volume.head(2, 3) == b"sli"  # no heads


def test_a_jobs_series_is_read_whole_once_and_a_kept_model_reads_headers_only(tmp_path, monkeypatch):
    """A worker reads a series from its store (the PostgreSQL blob table: 2.2 s for 440 whole files): the model key
    takes the store's digests, the headers come from the files' first bytes, and only the pixels read each file
    whole: once. A second job on the same volume takes the kept model and reads no file whole."""
    import hashlib

    from dsareg_engine.io import dicom_identity
    from service.engine_adapter import load_job_case
    from tests.support.service_testkit import small_cta_case

    monkeypatch.setattr(dicom_identity, "HEADER_BYTES", 4096)  # the slices are 12 KB, their headers 1 KB
    case = small_cta_case()
    blobs = {hashlib.sha256(part).hexdigest(): part for part in case.volume.parts}
    blobs.update({"a": case.ap, "l": case.lat})
    whole: list[str] = []
    heads: list[str] = []

    def read(digest: str) -> bytes:
        whole.append(digest)
        return blobs[digest]

    def read_head(digest: str, size: int) -> bytes:
        heads.append(digest)
        return blobs[digest][:size]

    inputs = [InputFile("volume", hashlib.sha256(p).hexdigest(), len(p), ".dcm") for p in case.volume.parts]
    inputs += [InputFile("ap", "a", len(case.ap), ".dcm"), InputFile("lat", "l", len(case.lat), ".dcm")]
    series = [item.sha256 for item in inputs[:-2]]
    models = {"dir": str(tmp_path / "models"), "entries": 4}
    first = load_job_case(inputs, None, "auto", read, models=models, read_head=read_head)
    assert sorted(d for d in whole if d in series) == sorted(series)  # each slice's pixels: one whole read
    assert sorted(heads) == sorted(series)  # each slice's header: its first bytes
    whole.clear(), heads.clear()
    second = load_job_case(inputs, None, "auto", read, models=models, read_head=read_head)
    assert [d for d in whole if d in series] == [] and sorted(heads) == sorted(series)
    assert second.mesh.n_faces == first.mesh.n_faces and len(second.sources.volume) == len(series)
    assert second.sources.volume == first.sources.volume  # the same DICOM identities, from the headers alone
