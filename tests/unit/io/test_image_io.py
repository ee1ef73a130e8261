import io
import struct
import time
import zlib

import numpy as np
import pytest
from PIL import Image

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.image_io import max_opacification_frame, read_image
from dsareg_engine.io.limits import InputLimits
from dsareg_engine.io.rad import format_rad_header


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload) & 0xFFFFFFFF)


def bomb_png(width=50_000, height=50_000) -> bytes:
    """A valid-looking PNG that declares width × height 8-bit grey pixels in a few dozen bytes."""
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(b"\x00" * 1000))
        + _chunk(b"IEND", b"")
    )


def _encode(array, fmt: str, mode=None) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(array, mode=mode).save(buffer, format=fmt)
    return buffer.getvalue()


def test_png_bomb_rejected_before_decoding():
    data = bomb_png()
    assert len(data) < 200
    start = time.perf_counter()
    with pytest.raises(DsaregInputError, match="50000x50000") as info:
        read_image(data, "ap.png", field_name="ap")
    assert time.perf_counter() - start < 0.5 and info.value.field == "ap"


def test_pixel_limit_from_header_for_other_formats(build):
    image, _ = build.dsa()
    with pytest.raises(DsaregInputError, match="megapixels"):
        read_image(_encode(image, "TIFF"), "a.tif", InputLimits(max_image_pixels=1000))
    with pytest.raises(DsaregInputError, match="megapixels"):
        read_image(_encode(image, "JPEG"), "a.jpg", InputLimits(max_image_pixels=1000))


@pytest.mark.parametrize("fmt", ["PNG", "TIFF", "JPEG"])
def test_raster_formats(build, fmt):
    image, _ = build.dsa()
    loaded = read_image(_encode(image, fmt), f"dsa.{fmt.lower()}")
    assert loaded.pixels.shape == image.shape and loaded.pixels.dtype == np.float32
    assert loaded.geometry is None and not loaded.is_mask
    tolerance = 12 if fmt == "JPEG" else 0
    assert np.abs(loaded.pixels - image).mean() <= tolerance


def test_16bit_and_colour_and_mask():
    ramp = np.arange(40 * 30, dtype=np.uint16).reshape(30, 40) * 50
    loaded = read_image(_encode(ramp, "PNG"), "a.png")
    assert loaded.pixels.max() == ramp.max()
    rgb = np.zeros((30, 40, 3), np.uint8)
    rgb[..., 1] = 200
    assert read_image(_encode(rgb, "PNG"), "a.png").pixels[0, 0] == pytest.approx(0.587 * 200, abs=0.01)
    mask = np.zeros((30, 40), np.uint8)
    mask[10:20, 5:9] = 255
    loaded = read_image(_encode(mask, "PNG"), "mask.png")
    assert loaded.is_mask and loaded.kind == "png"


def test_wrong_extension_and_bad_data(build):
    image, _ = build.dsa()
    png = _encode(image, "PNG")
    loaded = read_image(png, "dsa.jpg")
    assert loaded.kind == "png" and "content is PNG" in loaded.warnings[0]
    with pytest.raises(DsaregInputError, match="empty"):
        read_image(b"", "a.png")
    with pytest.raises(DsaregInputError, match="truncated|unreadable"):
        read_image(png[: len(png) // 2], "a.png")
    with pytest.raises(DsaregInputError, match="truncated"):
        read_image(png[:20], "a.png")
    with pytest.raises(DsaregInputError, match="not a recognised"):
        read_image(b"GIF89a" + b"\x00" * 50, "a.gif")
    with pytest.raises(DsaregInputError, match=r"\.rad"):
        read_image(b"\x00" * 64, "image.raw")


def test_rad_raw_image():
    tposition = np.array([[1.0, 0, 0, -6.0], [0, 1.0, 0, -4.5], [0, 0, 1.0, 200.0], [0, 0, 0, 1.0]])
    header = format_rad_header((40, 30), (0.3, 0.3), "float", tposition, [0.0, 0.0, 1200.0])
    pixels = np.random.default_rng(0).random((30, 40)).astype("<f4")
    loaded = read_image([header, pixels.tobytes()], "ap.rad")
    assert loaded.kind == "rad" and loaded.geometry.image_size == (40, 30)
    np.testing.assert_array_equal(loaded.pixels, pixels)
    assert loaded.geometry.sid_mm == pytest.approx(1000.0)
    with pytest.raises(DsaregInputError, match="needs"):
        read_image([header, pixels.tobytes()[:-4]], "ap.rad", field_name="ap")
    with pytest.raises(DsaregInputError, match=r"\.raw"):
        read_image(header, "ap.rad")


def test_dicom_xa_single_frame_with_geometry(build):
    image, _ = build.dsa()
    loaded = read_image(build.xa(image.astype(np.uint16) * 16, primary=30.0), "ap.dcm")
    assert loaded.kind == "dicom-xa" and loaded.geometry is not None
    assert loaded.geometry.image_size == (image.shape[1], image.shape[0])
    np.testing.assert_allclose(loaded.pixels, image * 16.0)


def test_dicom_monochrome1_inverted(build):
    image, _ = build.dsa()
    loaded = read_image(build.xa(image.astype(np.uint16), monochrome1=True), "ap.dcm")
    assert np.median(loaded.pixels) < 0.5 * loaded.pixels.max()  # background now dark


def test_dicom_without_pixels_or_geometry(build):
    with pytest.raises(DsaregInputError, match="no pixel data") as info:
        read_image(build.xa(None), "ap.dcm", field_name="ap")
    assert info.value.field == "ap"
    image, _ = build.dsa()
    loaded = read_image(build.xa(image.astype(np.uint16), primary=None, sod=None), "ap.dcm")
    assert loaded.geometry is None and "lacks geometry tags" in loaded.warnings[0]
    data = build.xa(image.astype(np.uint16))
    with pytest.raises(DsaregInputError, match="truncated|unreadable|shape"):
        read_image(data[: len(data) - 3000], "ap.dcm")


def test_multiframe_selection(build):
    image, truth = build.dsa()
    frames = []
    for strength in (0.0, 0.3, 0.7, 1.0, 0.5):  # contrast arrives, peaks at frame 3, washes out
        frame = np.full(image.shape, 3000.0)
        frame[truth] -= 1500 * strength
        frames.append(frame)
    stack = np.array(frames, dtype=np.uint16)
    data = build.xa(stack)
    assert max_opacification_frame(stack.astype(np.float32)) == 3
    chosen = read_image(data, "run.dcm")
    assert chosen.kind == "dicom-xa-multiframe" and "frame 3 of 5" in chosen.warnings[0]
    np.testing.assert_array_equal(chosen.pixels, stack[3])
    np.testing.assert_array_equal(read_image(data, "run.dcm", frame=1).pixels, stack[1])
    np.testing.assert_array_equal(read_image(data, "run.dcm", frame="minip").pixels, stack.min(axis=0))
    with pytest.raises(DsaregInputError, match="frame 9"):
        read_image(data, "run.dcm", frame=9)
    with pytest.raises(DsaregInputError, match="not understood"):
        read_image(data, "run.dcm", frame="max")


# ---- hostile headers: numbers that are not numbers, page counts (counted before decoding) ------


@pytest.mark.parametrize(("tag", "vr", "value", "keyword"), [
    ((0x0028, 0x0008), b"IS", b"abc", "NumberOfFrames"),
    ((0x0028, 0x0008), b"IS", b"1e999", "NumberOfFrames"),
    ((0x0028, 0x0008), b"IS", b"-3", "NumberOfFrames"),
    ((0x0028, 0x1053), b"DS", b"abc", "RescaleSlope"),
    ((0x0028, 0x1053), b"DS", b"NaN", "RescaleSlope"),
])
def test_dicom_numbers_that_are_not_numbers_name_the_image(build, tag, vr, value, keyword):
    from tests.support.hostile_images import with_dicom_value
    from pydicom import dcmread

    image, _ = build.dsa()
    ds = dcmread(io.BytesIO(build.xa(image.astype(np.uint16)[None].repeat(2, axis=0))))
    ds.RescaleSlope, ds.RescaleIntercept = 1, 0
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    data = with_dicom_value(buffer.getvalue(), tag, vr, value)
    with pytest.raises(DsaregInputError) as info:
        read_image(data, "ap.dcm", field_name="ap")
    assert info.value.field == "ap"
    assert keyword in info.value.message or "frames" in info.value.message, info.value.message


def test_tiff_page_count_is_read_from_the_header_before_decoding():
    from tests.support.hostile_images import many_page_tiff

    from dsareg_engine.io.image_io import tiff_page_count

    assert tiff_page_count(many_page_tiff(3), 10) == 3
    assert read_image(many_page_tiff(3), "a.tif").warnings == ["image: 3 pages; the first is used"]
    data = many_page_tiff(80_000)  # 8 MB; Pillow's n_frames walks it in about a minute
    started = time.process_time()
    with pytest.raises(DsaregInputError, match="more than 1000 pages") as info:
        read_image(data, "a.tif", limits=InputLimits(), field_name="lat")
    assert info.value.field == "lat"
    assert time.process_time() - started < 1.0
    assert read_image(many_page_tiff(5), "a.tif", limits=InputLimits(max_image_pages=5)).kind == "tiff"
    with pytest.raises(DsaregInputError, match="more than 4 pages"):
        read_image(many_page_tiff(5), "a.tif", limits=InputLimits(max_image_pages=4))


def _tiff_preamble() -> bytes:
    """A little-endian TIFF header with one empty IFD, padded to the 128-byte DICOM preamble (PS3.10 7.5: a file
    may be TIFF and DICOM at once, as the NEMA WG04 XA samples are)."""
    return (b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 0) + b"\x00" * 4).ljust(128, b"\x00")


@pytest.mark.parametrize("compressed", [False, True])
def test_dual_personality_dicom_is_read_as_dicom(build, compressed):
    from pydicom import dcmread
    from pydicom.uid import RLELossless

    image, _ = build.dsa()
    dataset = dcmread(io.BytesIO(build.xa(image.astype(np.uint16) * 16, primary=30.0)))
    if compressed:
        dataset.compress(RLELossless, encoding_plugin="pydicom")
    dataset.preamble = _tiff_preamble()
    buffer = io.BytesIO()
    dataset.save_as(buffer, enforce_file_format=True)
    data = buffer.getvalue()
    assert data[:4] == b"II*\x00" and data[128:132] == b"DICM"
    loaded = read_image(data, "ap.dcm")
    assert loaded.kind == "dicom-xa" and loaded.geometry is not None and loaded.dicom is not None
    np.testing.assert_allclose(loaded.pixels, image * 16.0)


def test_dicom_monochrome1_12_bit_and_the_intensity_relationship_recorded(build):
    """12 bits stored in 16, MONOCHROME1 (higher = darker): read with vessels dark, LOG recorded."""
    from pydicom import dcmread

    image, truth = build.dsa()
    stored = (4095 - image.astype(np.float64) / image.max() * 4000).astype(np.uint16)  # vessels stored bright
    dataset = dcmread(io.BytesIO(build.xa(stored, monochrome1=True)))
    dataset.BitsStored, dataset.HighBit, dataset.PixelIntensityRelationship = 12, 11, "LOG"
    buffer = io.BytesIO()
    dataset.save_as(buffer, enforce_file_format=True)
    loaded = read_image(buffer.getvalue(), "ap.dcm")
    vessels = truth > 0
    assert loaded.pixels[vessels].mean() < loaded.pixels[~vessels].mean()
    assert loaded.reading["pixel_intensity_relationship"] == "LOG"


def test_pillow_warnings_become_the_image_s_warnings(build, monkeypatch):
    """A warning Pillow raises while decoding (corrupt EXIF, a truncated tag) is the image's, not stderr's."""
    import warnings

    from PIL import ImageFile

    original = ImageFile.ImageFile.load

    def load(self):
        warnings.warn("Possibly corrupt EXIF data", UserWarning, stacklevel=2)
        return original(self)

    monkeypatch.setattr(ImageFile.ImageFile, "load", load)
    image, _ = build.dsa()
    with warnings.catch_warnings(record=True) as leaked:
        warnings.simplefilter("always")
        loaded = read_image(_encode(image, "PNG"), "ap.png", field_name="ap")
    assert "ap: Possibly corrupt EXIF data" in loaded.warnings and not leaked
