"""A volume's files read when used (``io/file_parts.py``): nothing kept, and a series never held whole."""

import weakref

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.file_parts import FileParts, volume_parts
from dsareg_engine.io.model_cache import model_key
from dsareg_engine.io.volume_io import read_volume, read_volume_identities


class _Tracked(bytearray):
    """A file's content whose liveness a test can see (bytes objects take no weak references)."""


class _Loads:
    """Loaders over ``contents`` that count reads and the most files alive at once when one is read."""

    def __init__(self, contents: list[bytes]):
        self.contents, self.reads, self.refs, self.most_alive = contents, 0, [], 0

    def alive(self) -> int:
        return sum(ref() is not None for ref in self.refs)

    def loader(self, index: int):
        def load():
            self.reads += 1
            self.most_alive = max(self.most_alive, self.alive() + 1)  # those not let go, and this one
            data = _Tracked(self.contents[index])
            self.refs.append(weakref.ref(data))
            return data

        return load

    def parts(self) -> FileParts:
        return FileParts(self.loader(i) for i in range(len(self.contents)))


def test_items_are_read_on_each_access_and_not_kept():
    loads = _Loads([b"first", b"second", b"third"])
    parts = loads.parts()
    assert len(parts) == 3 and loads.reads == 0  # made without reading
    assert bytes(parts[1]) == b"second" and bytes(parts[-1]) == b"third" and loads.reads == 2
    assert [bytes(p) for p in parts] == [b"first", b"second", b"third"] and loads.reads == 5
    assert loads.alive() == 0  # the parts object kept none of them
    assert [bytes(p) for p in parts[1:]] == [b"second", b"third"] and isinstance(parts[1:], FileParts)
    with pytest.raises(IndexError):
        parts[3]


def test_from_paths_reads_the_files_when_used(tmp_path):
    (tmp_path / "a").write_bytes(b"one")
    (tmp_path / "b").write_bytes(b"two")
    parts = FileParts.from_paths([tmp_path / "a", tmp_path / "b"])
    (tmp_path / "a").write_bytes(b"changed")  # read when used, not when made
    assert list(parts) == [b"changed", b"two"]
    assert "2 files" in repr(parts)


def test_volume_parts():
    assert volume_parts(None) == [] and volume_parts(b"x") == [b"x"]
    assert volume_parts([b"a", b"b"]) == [b"a", b"b"] and volume_parts(FileParts([lambda: b"c"])) == [b"c"]


def test_a_series_read_from_file_parts_never_holds_all_its_files(build):
    """The series is read header by header, then slice by slice: the read's peak of traced memory is the volume and
    a few files, not the volume and every file (a list of the same files: all held), and the volume is the one the
    list gives. The slices are 400 × 400, so that pixels outweigh the headers' objects."""
    import tracemalloc

    volume = np.random.default_rng(3).integers(0, 1200, (400, 400, 24)).astype(np.float32)
    affine = np.diag([0.5, 0.5, 1.0, 1.0])
    files = build.ct_series(volume, affine)
    total = sum(len(f) for f in files)
    loads = _Loads(files)
    tracemalloc.start()
    try:
        from_parts = read_volume(loads.parts(), "ct")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    grid = from_parts.data.nbytes
    assert peak < grid + 0.5 * total, f"peak {peak} B: the volume {grid} B and {(peak - grid) / total:.2f} of the files"
    assert loads.most_alive <= 2 and loads.reads == 2 * len(files)  # each header, then each slice's pixels
    from_list = read_volume(list(files), "ct")
    np.testing.assert_array_equal(from_parts.data, from_list.data)
    np.testing.assert_array_equal(from_parts.affine, from_list.affine)
    assert from_parts.dicom == from_list.dicom and from_parts.tags == from_list.tags
    assert read_volume_identities(loads.parts(), "ct") == read_volume_identities(list(files), "ct")
    assert model_key(loads.parts(), "ct", None, 20_000) == model_key(list(files), "ct", None, 20_000)


def test_file_parts_of_one_or_two_files_read_as_lists_do(phantom_volume, build):
    volume, affine, _ = phantom_volume
    files = build.ct_series(volume[:, :, :6], affine)
    with pytest.raises(DsaregInputError, match="single-slice"):
        read_volume(FileParts([lambda: files[0]]), "slice.dcm")
    with pytest.raises(DsaregInputError, match="no files"):
        read_volume(FileParts([]), "ct")
    with pytest.raises(DsaregInputError, match="empty"):
        read_volume(FileParts([lambda: files[0], lambda: files[1], lambda: b""]), "ct")


def test_a_stores_digests_make_the_model_key_without_reading_a_file(tmp_path):
    import hashlib

    files = [b"first slice", b"second slice", b"third slice"]

    def unread():
        raise AssertionError("a file was read for the key")

    known = FileParts([unread] * 3, digests=[hashlib.sha256(f).hexdigest() for f in files])
    assert model_key(known, "ct", None, 20_000) == model_key(list(files), "ct", None, 20_000)
    assert known[1:].digests == known.digests[1:] and FileParts([unread]).digests is None
    with pytest.raises(ValueError, match="2 digests or heads for 3 files"):
        FileParts([unread] * 3, digests=["a", "b"])
    with pytest.raises(ValueError, match="1 digests or heads for 3 files"):
        FileParts([unread] * 3, heads=[lambda n: b""])


def test_heads_read_only_a_files_first_bytes(tmp_path):
    (tmp_path / "a").write_bytes(b"0123456789")
    parts = FileParts.from_paths([tmp_path / "a"])
    assert parts.head(0, 4) == b"0123" and parts.head(0, 100) == b"0123456789" and parts[0:1].head(0, 2) == b"01"
    assert FileParts([lambda: b"whole file"]).head(0, 5) == b"whole"  # no head loader: the whole file, cut
    assert volume_parts(FileParts([lambda: b"x"], heads=[lambda n: b"?"])) == [b"x"]


def test_a_series_with_heads_reads_each_file_whole_once(build, monkeypatch):
    """Headers from the files' first bytes, pixels from the whole files: one whole read a file, and the volume
    the list of the same files gives."""
    from dsareg_engine.io import dicom_identity

    monkeypatch.setattr(dicom_identity, "HEADER_BYTES", 2048)  # the slices are 20 KB, their headers under 1 KB
    volume = np.random.default_rng(4).integers(0, 1200, (100, 100, 8)).astype(np.float32)
    files = build.ct_series(volume, np.diag([0.5, 0.5, 1.0, 1.0]))
    loads, heads = _Loads(files), []

    def head(index):
        return lambda size: heads.append(index) or files[index][:size]

    parts = FileParts((loads.loader(i) for i in range(len(files))), heads=[head(i) for i in range(len(files))])
    read = read_volume(parts, "ct")
    assert loads.reads == len(files) and sorted(heads) == list(range(len(files)))
    from_list = read_volume(list(files), "ct")
    np.testing.assert_array_equal(read.data, from_list.data)
    assert read.dicom == from_list.dicom and read.tags == from_list.tags
    heads.clear()
    assert read_volume_identities(parts, "ct") == read_volume_identities(list(files), "ct")
    assert loads.reads == len(files) and len(heads) == len(files)  # the identities: heads alone
