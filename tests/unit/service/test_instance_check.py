"""Header validation of received DICOM instances (service/pacs/instance_check.py) on small generated data."""

from __future__ import annotations

import pytest

from service.pacs.dimse.scp import STORAGE_CLASSES
from service.pacs.inflating_reader import InflateBoundExceeded, InflateError, inflate_bounded
from service.pacs.instance_check import InstanceLimits, InstanceRefused, check_instance
from tests.support.dicom_bombs import DEFLATED, EXPLICIT, XA, deflate_bomb, deflated, encoded, xa_header

LIMITS = InstanceLimits(max_instance_bytes=1 << 20, max_pixel_bytes=1 << 19)


def _check(data: bytes, ds, syntax: str = EXPLICIT, limits: InstanceLimits = LIMITS):
    return check_instance(data, syntax, XA, str(ds.SOPInstanceUID), STORAGE_CLASSES, limits)


def _status(data: bytes, ds, syntax: str = EXPLICIT, limits: InstanceLimits = LIMITS) -> int:
    with pytest.raises(InstanceRefused) as refused:
        _check(data, ds, syntax, limits)
    return refused.value.status


def test_a_wellformed_instance_passes_in_both_syntaxes():
    ds = xa_header(rows=16, columns=12, frames=3)
    for data, syntax in ((encoded(ds), EXPLICIT), (deflated(encoded(ds)), DEFLATED)):
        checked = _check(data, ds, syntax)
        assert (checked.study_uid, checked.sop_instance_uid) == (ds.StudyInstanceUID, ds.SOPInstanceUID)
        assert checked.header.Rows == 16 and "PixelData" not in checked.header


def test_a_deflate_bomb_is_out_of_resources_without_inflating_it_whole():
    ds = xa_header(rows=512, columns=512, frames=2)  # header within the pixel bound, the data is not
    bomb = deflate_bomb(ds, pixel_bytes=64 << 20)
    assert len(bomb) < 200_000  # 64 MiB of zeros deflate to ~65 kB
    assert _status(bomb, ds, DEFLATED, InstanceLimits(1 << 20, 1 << 30)) == 0xA700
    with pytest.raises(InflateBoundExceeded):
        inflate_bounded(bomb, limit_bytes=1 << 20, keep_bytes=1024)


def test_inflate_keeps_a_prefix_and_counts_the_rest():
    data = bytes(range(256)) * 4096
    inflated = inflate_bounded(deflated(data), limit_bytes=len(data), keep_bytes=1000)
    assert inflated.prefix == data[:1000] and inflated.size_bytes == len(data)
    with pytest.raises(InflateError):
        inflate_bounded(deflated(data)[:-40], limit_bytes=len(data), keep_bytes=10)  # cut short
    with pytest.raises(InflateError):
        inflate_bounded(b"not deflate at all" * 10, limit_bytes=len(data), keep_bytes=10)


def test_sizes_past_the_limits_are_out_of_resources():
    ds = xa_header(rows=65535, columns=65535, frames=2000)  # the header lies; 128 bytes of pixels follow
    assert _status(encoded(ds, pixel_bytes=128), ds) == 0xA700
    small = xa_header(rows=8, columns=8)
    assert _status(encoded(small), small, limits=InstanceLimits(100, 1 << 19)) == 0xA700


def test_truncated_instances_cannot_be_understood():
    ds = xa_header(rows=64, columns=64)
    whole = encoded(ds)
    assert _status(whole[:-100], ds) == 0xC000  # inside Pixel Data
    assert _status(whole[:len(whole) - 64 * 64 * 2 - 4], ds) == 0xC000  # inside Pixel Data's element header
    head = whole[:len(whole) - 64 * 64 * 2 - 8]
    assert _status(head, ds) == 0xC000  # no Pixel Data at all
    assert _status(whole[:40], ds) in (0xC000, 0xA900)  # cut in the first elements


def test_pixel_data_shorter_than_the_header_says_does_not_match():
    ds = xa_header(rows=64, columns=64)
    assert _status(encoded(ds, pixel_bytes=64 * 64), ds) == 0xA900


@pytest.mark.parametrize("keyword, value", [("SOPInstanceUID", "../../etc/passwd"), ("StudyInstanceUID", "../x"),
                                            ("SeriesInstanceUID", ""), ("StudyInstanceUID", "1." + "2" * 70)])
def test_malformed_uids_do_not_match(keyword, value):
    ds = xa_header()
    setattr(ds, keyword, value)
    assert _status(encoded(ds), ds) == 0xA900


def test_the_request_and_the_data_set_must_agree():
    ds = xa_header()
    with pytest.raises(InstanceRefused) as refused:
        check_instance(encoded(ds), EXPLICIT, XA, "1.2.3", STORAGE_CLASSES, LIMITS)
    assert refused.value.status == 0xA900
    ds.SOPClassUID = "1.2.840.10008.5.1.4.1.1.481.1"  # RT Image: not one we store
    with pytest.raises(InstanceRefused) as refused:
        check_instance(encoded(ds), EXPLICIT, ds.SOPClassUID, ds.SOPInstanceUID, STORAGE_CLASSES, LIMITS)
    assert refused.value.status == 0xA900


def test_an_image_without_dimensions_does_not_match():
    ds = xa_header()
    del ds.Rows
    assert _status(encoded(ds, pixel_bytes=128), ds) == 0xA900


def test_a_dicom_file_is_checked_for_size_without_its_identity(tmp_path):
    from service.pacs.instance_check import check_file
    from tests.support.dicom_bombs import part10

    ds = xa_header(rows=16, columns=16)
    ds.StudyInstanceUID = "not-ours-to-judge"  # an upload's UIDs are left alone
    plain = part10(encoded(ds), XA, ds.SOPInstanceUID, EXPLICIT, tmp_path / "plain.dcm").read_bytes()
    assert check_file(plain, LIMITS).Rows == 16
    assert check_file(b"\x89PNG\r\n\x1a\n" + bytes(200), LIMITS) is None  # not DICOM: not this check's business
    bomb = xa_header(rows=512, columns=512, frames=2)
    data = part10(deflate_bomb(bomb, 64 << 20), XA, bomb.SOPInstanceUID, DEFLATED, tmp_path / "bomb.dcm").read_bytes()
    with pytest.raises(InstanceRefused) as refused:
        check_file(data, InstanceLimits(1 << 20, 1 << 30))
    assert refused.value.status == 0xA700
    with pytest.raises(InstanceRefused) as refused:
        check_file(plain[:-50], LIMITS)
    assert refused.value.status == 0xC000
