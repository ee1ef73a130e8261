"""The field of view from the DICOM Shutter and X-Ray Collimator modules, and the overlay graphics."""

from __future__ import annotations

import io

import numpy as np
import pydicom
from pydicom.dataset import Dataset
from pydicom.pixels import pack_bits

from dsareg_engine.io.image_io import read_image
from dsareg_engine.io.xa_shutter import field_of_view_details, overlay_annotation_mask, shutter_field_of_view

SHAPE = (40, 50)


def _overlay(ds: Dataset, group: int, bits: np.ndarray, origin=(1, 1), kind: str = "G") -> None:
    ds.add_new((group, 0x0010), "US", bits.shape[0])
    ds.add_new((group, 0x0011), "US", bits.shape[1])
    ds.add_new((group, 0x0040), "CS", kind)
    ds.add_new((group, 0x0050), "SS", list(origin))
    ds.add_new((group, 0x0100), "US", 1)
    ds.add_new((group, 0x0102), "US", 0)
    ds.add_new((group, 0x3000), "OW", pack_bits(bits.astype(np.uint8).ravel()))


def test_no_shutter_no_field_of_view():
    assert shutter_field_of_view(Dataset(), SHAPE) is None


def test_circular_shutter_in_dicom_coordinates():
    ds = Dataset()
    ds.ShutterShape = "CIRCULAR"
    ds.CenterOfCircularShutter = [21, 26]  # row, column, 1-based: the pixel (20, 25) 0-based
    ds.RadiusOfCircularShutter = 10
    fov = shutter_field_of_view(ds, SHAPE)
    assert fov.shape == SHAPE and fov.dtype == bool
    assert fov[20, 25] and fov[20, 35] and not fov[20, 36] and fov[10, 25] and not fov[9, 25]
    assert abs(int(fov.sum()) - np.pi * 100) < 20


def test_rectangular_and_circular_shutters_intersect():
    ds = Dataset()
    ds.ShutterShape = ["RECTANGULAR", "CIRCULAR"]
    ds.ShutterLeftVerticalEdge, ds.ShutterRightVerticalEdge = 11, 30  # columns 10..29 (0-based)
    ds.ShutterUpperHorizontalEdge, ds.ShutterLowerHorizontalEdge = 6, 35
    ds.CenterOfCircularShutter, ds.RadiusOfCircularShutter = [21, 21], 100  # the whole image
    fov = shutter_field_of_view(ds, SHAPE)
    rows, columns = np.nonzero(fov)
    assert (rows.min(), rows.max(), columns.min(), columns.max()) == (5, 34, 10, 29)
    ds.RadiusOfCircularShutter = 5
    assert shutter_field_of_view(ds, SHAPE).sum() < 100


def test_polygonal_shutter_and_collimator():
    ds = Dataset()
    ds.ShutterShape = "POLYGONAL"
    ds.VerticesOfThePolygonalShutter = [1, 1, 1, 50, 40, 1]  # (row, column) pairs: the upper-left triangle
    fov = shutter_field_of_view(ds, SHAPE)
    assert fov[0, 0] and fov[2, 40] and not fov[39, 49] and 0.4 < fov.mean() < 0.6
    collimated = Dataset()
    collimated.CollimatorShape = "RECTANGULAR"
    collimated.CollimatorLeftVerticalEdge, collimated.CollimatorRightVerticalEdge = 1, 25
    collimated.CollimatorUpperHorizontalEdge, collimated.CollimatorLowerHorizontalEdge = 1, 40
    assert shutter_field_of_view(collimated, SHAPE).sum() == 25 * 40


def test_bitmap_shutter_from_its_overlay_plane_and_the_graphics_overlay():
    ds = Dataset()
    shuttered = np.ones(SHAPE, bool)
    shuttered[10:30, 10:40] = False
    ds.ShutterShape, ds.ShutterOverlayGroup = "BITMAP", 0x6000
    _overlay(ds, 0x6000, shuttered)
    marks = np.zeros((4, 6), bool)
    marks[1:3, 1:5] = True
    _overlay(ds, 0x6002, marks, origin=(3, 5))
    fov = shutter_field_of_view(ds, SHAPE)
    assert fov.sum() == 20 * 30 and fov[10:30, 10:40].all()
    annotation = overlay_annotation_mask(ds, SHAPE)
    assert annotation.sum() == 8 and annotation[3:5, 5:9].all()


def test_an_incomplete_shutter_is_left_out():
    ds = Dataset()
    ds.ShutterShape = "CIRCULAR"
    ds.CenterOfCircularShutter = [21, 26]  # no radius
    assert shutter_field_of_view(ds, SHAPE) is None


def test_read_image_gives_the_field_of_view_and_its_decision(build):
    data = build.xa(np.full(SHAPE, 1000, np.uint16))
    ds = pydicom.dcmread(io.BytesIO(data))
    ds.ShutterShape, ds.CenterOfCircularShutter, ds.RadiusOfCircularShutter = "CIRCULAR", [21, 26], 15
    buffer = io.BytesIO()
    ds.save_as(buffer)
    image = read_image(buffer.getvalue(), "ap.dcm", field_name="ap")
    assert image.field_of_view is not None and image.field_of_view.shape == SHAPE
    np.testing.assert_array_equal(image.field_of_view, shutter_field_of_view(ds, SHAPE))
    decision = next(d for d in image.decisions if d.what == "field of view")
    assert decision.chosen == "shutter CIRCULAR" and decision.source == "tag" and decision.input == "ap"
    assert read_image(data, "ap.dcm").field_of_view is None


def test_unknown_shape_is_a_warning():
    ds = Dataset()
    ds.ShutterShape = "HEXAGONAL"
    fov, applied, warnings = field_of_view_details(ds, SHAPE)
    assert fov is None and not applied and "HEXAGONAL" in warnings[0]
