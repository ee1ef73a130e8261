"""A picture renamed ``.dcm`` is named for what it is (dsareg_engine/io/image_io.py): it was read as the picture and
the job then failed on "no geometry was given and the ap image(s) carry none"."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.image_io import read_image


@pytest.mark.parametrize("fmt, name", [("PNG", "uploads/ap.dcm"), ("JPEG", "LAT.IMA")])
def test_a_picture_named_as_dicom_is_refused_naming_both(fmt, name):
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(buffer, format=fmt)
    with pytest.raises(DsaregInputError) as caught:
        read_image(buffer.getvalue(), name, field_name="ap")
    shown = name.rsplit("/", 1)[-1]
    assert caught.value.message == f"{shown} is a {fmt} image, not DICOM"
    assert caught.value.field == "ap"


def test_the_same_picture_under_its_own_name_is_read():
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(buffer, format="PNG")
    assert read_image(buffer.getvalue(), "ap.png").pixels.shape == (8, 8)
