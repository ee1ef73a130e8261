"""Hostile image files built from bytes (shared by the reader tests and the HTTP hostile corpus)."""

from __future__ import annotations

import struct

TIFF_TAGS_1PX = ((256, 3, 1), (257, 3, 1), (258, 3, 8), (259, 3, 1), (262, 3, 1), (273, 4, 8), (278, 3, 1), (279, 4, 1))
"""One 1×1 8-bit grey page: width, length, bits, compression, photometric, strip offset, rows, strip bytes."""


def many_page_tiff(pages: int) -> bytes:
    """A little-endian TIFF of ``pages`` 1×1 pages sharing one strip (about 100 bytes a page)."""
    ifd_bytes = 2 + 12 * len(TIFF_TAGS_1PX) + 4
    out = bytearray(b"II*\x00" + struct.pack("<I", 12) + b"\x80\x00\x00\x00")  # header, then the strip at 8
    for page in range(pages):
        at = 12 + page * ifd_bytes
        out += struct.pack("<H", len(TIFF_TAGS_1PX))
        for tag, kind, value in TIFF_TAGS_1PX:
            out += struct.pack("<HHI", tag, kind, 1) + (struct.pack("<HH", value, 0) if kind == 3 else struct.pack("<I", value))
        out += struct.pack("<I", at + ifd_bytes if page + 1 < pages else 0)
    return bytes(out)


def many_frame_gif(frames: int) -> bytes:
    """A GIF89a of ``frames`` 1×1 frames."""
    head = b"GIF89a" + struct.pack("<HHBBB", 1, 1, 0x80, 0, 0) + b"\x00\x00\x00\xff\xff\xff"
    frame = b"\x21\xf9\x04\x00\x01\x00\x00\x00" + b"\x2c" + struct.pack("<HHHHB", 0, 0, 1, 1, 0) + b"\x02\x02\x44\x01\x00"
    return head + frame * frames + b"\x3b"


def with_dicom_value(data: bytes, tag: tuple[int, int], vr: bytes, value: bytes) -> bytes:
    """``data`` (explicit VR little endian) with the element ``tag`` (present once) holding ``value`` as it is."""
    key = struct.pack("<HH", *tag) + vr
    at = data.index(key)
    length = struct.unpack_from("<H", data, at + 6)[0]
    value = value + b" " * (len(value) % 2)
    return data[:at] + key + struct.pack("<H", len(value)) + value + data[at + 8 + length:]


NUMBER_OF_FRAMES = (0x0028, 0x0008)
RESCALE_SLOPE = (0x0028, 0x1053)


def plain_xa(rows: int = 64, cols: int = 64, frames: int = 2) -> bytes:
    """A small multi-frame DICOM XA (no geometry tags, RescaleSlope 1) to corrupt with :func:`with_dicom_value`."""
    import io

    import numpy as np
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.12.1"
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID, ds.Modality = meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID, "XA"
    ds.Rows, ds.Columns, ds.NumberOfFrames, ds.SamplesPerPixel = rows, cols, frames, 1
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.PhotometricInterpretation, ds.RescaleSlope, ds.RescaleIntercept = "MONOCHROME2", 1, 0
    ds.PixelData = (np.arange(frames * rows * cols, dtype=np.uint16) % 4000).tobytes()
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()
