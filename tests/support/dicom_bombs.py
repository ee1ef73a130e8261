"""Hostile DICOM instances built from bytes: deflate bombs, lying headers, truncations, bad UIDs.

``xa_header`` is a small XA data set; ``encoded`` its data set bytes in a transfer syntax (no file meta);
``part10`` wraps data set bytes in a file (for a pynetdicom SCU sending files as they are); ``deflate_bomb``
deflates a data set whose Pixel Data is ``pixel_bytes`` zeros without ever holding them.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.filebase import DicomBytesIO
from pydicom.filewriter import write_dataset, write_file_meta_info

from dsareg_engine.io.dicom_out import new_uid

XA = "1.2.840.10008.5.1.4.1.1.12.1"
EXPLICIT, DEFLATED = "1.2.840.10008.1.2.1", "1.2.840.10008.1.2.1.99"


def xa_header(rows: int = 8, columns: int = 8, frames: int = 1, **uids: str) -> Dataset:
    """An XA data set without Pixel Data (fresh UIDs unless given: StudyInstanceUID=…, SOPInstanceUID=…)."""
    ds = Dataset()
    ds.SOPClassUID = XA
    ds.SOPInstanceUID = uids.get("SOPInstanceUID", new_uid())
    ds.StudyInstanceUID = uids.get("StudyInstanceUID", new_uid())
    ds.SeriesInstanceUID = uids.get("SeriesInstanceUID", new_uid())
    ds.Modality = "XA"
    ds.Rows, ds.Columns, ds.NumberOfFrames = rows, columns, frames
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    return ds


def encoded(ds: Dataset, pixel_bytes: int | None = None) -> bytes:
    """``ds`` in Explicit VR Little Endian, with ``pixel_bytes`` zero bytes of Pixel Data (default: what it says)."""
    fp = DicomBytesIO()
    fp.is_little_endian, fp.is_implicit_VR = True, False
    write_dataset(fp, ds)
    if pixel_bytes is None:
        pixel_bytes = int(ds.Rows) * int(ds.Columns) * int(ds.NumberOfFrames) * 2
    return fp.getvalue() + pixel_header(pixel_bytes) + bytes(pixel_bytes)


def pixel_header(length: int) -> bytes:
    """The (7FE0,0010) OW element header of ``length`` bytes, explicit VR little endian."""
    return struct.pack("<HH", 0x7FE0, 0x0010) + b"OW\x00\x00" + struct.pack("<I", length)


def deflate_bomb(ds: Dataset, pixel_bytes: int) -> bytes:
    """``ds`` with ``pixel_bytes`` zeros of Pixel Data, deflated (raw deflate) chunk by chunk."""
    head = DicomBytesIO()
    head.is_little_endian, head.is_implicit_VR = True, False
    write_dataset(head, ds)
    packer = zlib.compressobj(9, zlib.DEFLATED, -zlib.MAX_WBITS)
    parts = [packer.compress(head.getvalue() + pixel_header(pixel_bytes))]
    zeros = bytes(1 << 20)
    left = pixel_bytes
    while left:
        step = min(left, len(zeros))
        parts.append(packer.compress(zeros[:step]))
        left -= step
    return b"".join(parts) + packer.flush()


def deflated(data_set: bytes) -> bytes:
    packer = zlib.compressobj(6, zlib.DEFLATED, -zlib.MAX_WBITS)
    return packer.compress(data_set) + packer.flush()


def part10(data_set: bytes, sop_class: str, sop_instance: str, transfer_syntax: str, path: Path) -> Path:
    """A DICOM file holding ``data_set`` as it is, with file meta naming ``transfer_syntax``."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = sop_class, sop_instance
    meta.TransferSyntaxUID = transfer_syntax
    fp = DicomBytesIO()
    fp.is_little_endian, fp.is_implicit_VR = True, False
    write_file_meta_info(fp, meta, enforce_standard=True)
    path.write_bytes(b"\x00" * 128 + b"DICM" + fp.getvalue() + data_set)
    return path
