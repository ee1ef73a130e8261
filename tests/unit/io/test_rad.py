import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.rad import format_rad_header, parse_rad_header, read_raw, view_from_rad, volume_affine_from_rad

TPOS = np.array([[1.0, 0, 0, -60.0], [0, -1.0, 0, 40.0], [0, 0, -1.0, -300.0], [0, 0, 0, 1.0]])
SOURCE = np.array([3.0, -2.0, -1300.0])

HEADER = b"""Size[pixels]: 400 300\r
Step[mm]: 0.3 0.25\r
DataType: float\r
SourcePosition[mm]: 3.0 -2.0 -1300.0\r
TPosition:\r
1 0 0 -60\r
0 -1 0 40\r
0 0 -1 -300\r
0 0 0 1\r
"""


def test_parse_dataset_style_header():
    header = parse_rad_header(HEADER)
    assert header.size == (400, 300) and header.step_mm == (0.3, 0.25)
    assert header.dtype == np.dtype("<f4")
    np.testing.assert_allclose(header.tposition, TPOS)
    np.testing.assert_allclose(header.source_position, SOURCE)


def test_tolerant_variants_give_same_header():
    text = (
        "\ufeff# exported\nsize = 400, 300\nSTEP[MM]= 0.3 0.25\ndatatype : FLOAT\n"
        "SourcePosition [mm]: 3 -2 -1300\nTPosition: " + " ".join(str(x) for x in TPOS[:3].ravel()) + "\n"
    ).encode()
    header = parse_rad_header(text)
    assert header.size == (400, 300)
    np.testing.assert_allclose(header.tposition, TPOS)


def test_view_projects_source_ray_and_detector_pixels():
    view = view_from_rad(parse_rad_header(HEADER))
    assert view.image_size == (400, 300)
    np.testing.assert_allclose(view.source_position_world, SOURCE, atol=1e-9)
    # a world point on the detector plane at pixel (col 10, row 20) projects to (10, 20)
    detector_point = TPOS @ np.array([10 * 0.3, 20 * 0.25, 0.0, 1.0])
    np.testing.assert_allclose(view.project(detector_point[None, :3])[0], [10, 20], atol=1e-9)
    # a point midway between source and that detector pixel projects there too
    midway = 0.5 * (detector_point[:3] + SOURCE)
    np.testing.assert_allclose(view.project(midway[None])[0], [10, 20], atol=1e-9)


def test_round_trip_writer_and_raw():
    header = parse_rad_header(format_rad_header((4, 3), (0.5, 0.5), "ushort", TPOS, SOURCE))
    raw = np.arange(12, dtype="<u2").tobytes()
    pixels = read_raw(header, raw, max_bytes=1 << 20)
    assert pixels.shape == (3, 4) and pixels[1, 0] == 4 and pixels.dtype == np.float32
    with pytest.raises(DsaregInputError, match="needs 24"):
        read_raw(header, raw + b"\x00", max_bytes=1 << 20)
    with pytest.raises(DsaregInputError, match="limit"):
        read_raw(header, raw, max_bytes=10)


def test_volume_header_affine():
    header = parse_rad_header(format_rad_header((5, 6, 7), (0.4, 0.4, 0.8), "short", np.eye(4)))
    affine = volume_affine_from_rad(header)
    np.testing.assert_allclose(affine @ [1, 1, 1, 1], [0.4, 0.4, 0.8, 1])
    raw = np.arange(5 * 6 * 7, dtype="<i2").tobytes()
    voxels = read_raw(header, raw, max_bytes=1 << 20)
    assert voxels.shape == (5, 6, 7) and voxels[1, 0, 0] == 1 and voxels[0, 1, 0] == 5 and voxels[0, 0, 1] == 30


@pytest.mark.parametrize(
    "text, match",
    [
        (b"", "empty"),
        (b"\x00\x01binary", "binary"),
        (b"DataType: float\n", "missing"),
        (b"Size[pixels]: 10 x\nStep[mm]: 1 1\n", "Size"),
        (b"Size[pixels]: 10 10\nStep[mm]: 1 -1\n", "Step"),
        (b"Size[pixels]: 10 10\nStep[mm]: 1 1\nDataType: complex\n", "DataType"),
        (b"Size[pixels]: 10 10\nStep[mm]: 1 1\nTPosition:\n1 0 0 0\n0 1 0 0\n", "TPosition"),
    ],
)
def test_bad_headers(text, match):
    with pytest.raises(DsaregInputError, match=match):
        parse_rad_header(text)


def test_view_needs_pose_and_source():
    header = parse_rad_header(b"Size[pixels]: 10 10\nStep[mm]: 1 1\n")
    with pytest.raises(DsaregInputError, match="TPosition"):
        view_from_rad(header)
    wrong_side = format_rad_header((10, 10), (1, 1), "float", np.eye(4), [0, 0, -100])
    with pytest.raises(DsaregInputError, match="wrong side"):
        view_from_rad(parse_rad_header(wrong_side))
