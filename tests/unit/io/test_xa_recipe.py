"""The Mask Subtraction Sequence as read (PS3.3 C.7.6.10): operations, frame numbers, shift sign, refusals."""

from __future__ import annotations

import pytest
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.xa_recipe import parse_recipe


def _run(*items: dict) -> Dataset:
    dataset = Dataset()
    sequence = []
    for fields in items:
        item = Dataset()
        for keyword, value in fields.items():
            setattr(item, keyword, value)
        sequence.append(item)
    dataset.MaskSubtractionSequence = Sequence(sequence)
    return dataset


def test_avg_sub_with_mask_frames_range_and_averaging():
    (item,) = parse_recipe(_run({"MaskOperation": "AVG_SUB", "MaskFrameNumbers": [1, 2],
                                 "ApplicableFrameRange": [3, 6, 9, 10], "ContrastFrameAveraging": 2}), 10)
    assert item.operation == "AVG_SUB" and item.mask_frames == (0, 1)  # DICOM 1-based → 0-based
    assert item.frames == (2, 3, 4, 5, 8, 9) and item.contrast_averaging == 2
    assert item.mask_of(4) == (0, 1)
    assert item.describe()["frames"] == "3-6, 9-10" and item.describe()["mask_frame_numbers"] == [1, 2]


def test_tid_and_rev_tid_masks():
    tid, rev = parse_recipe(_run({"MaskOperation": "TID", "TIDOffset": 2, "ApplicableFrameRange": [3, 8]},
                                 {"MaskOperation": "REV_TID", "TIDOffset": 3, "ApplicableFrameRange": [1, 4]}), 8)
    assert tid.mask_of(5) == (3,) and tid.tid_offset == 2
    assert rev.mask_of(0) == (3,)


def test_no_sequence_is_no_recipe():
    assert parse_recipe(Dataset(), 5) == []


def test_subpixel_shift_sign():
    """(row, column): + row moves the mask down, + column toward the left-hand columns."""
    (item,) = parse_recipe(_run({"MaskOperation": "AVG_SUB", "MaskFrameNumbers": [1], "MaskSubPixelShift": [0.5, 0.25]}), 4)
    assert item.mask_shift_px == (0.5, -0.25)  # (down, right)
    assert item.describe()["mask_subpixel_shift_rows_columns"] == [0.5, 0.25]


@pytest.mark.parametrize("fields, field, message", [
    ({"MaskOperation": "AVG_SUB", "MaskFrameNumbers": [1, 12]}, "MaskFrameNumbers", "frame 12, which does not exist"),
    ({"MaskOperation": "AVG_SUB"}, "MaskFrameNumbers", "needs Mask Frame Numbers"),
    ({"MaskOperation": "AVG_SUB", "MaskFrameNumbers": [1], "ApplicableFrameRange": [2, 11]}, "ApplicableFrameRange",
     "frame 11"),
    ({"MaskOperation": "AVG_SUB", "MaskFrameNumbers": [1], "ApplicableFrameRange": [2]}, "ApplicableFrameRange", "pairs"),
    ({"MaskOperation": "AVG_SUB", "MaskFrameNumbers": [1], "ApplicableFrameRange": [6, 3]}, "ApplicableFrameRange",
     "ends before"),
    ({"MaskOperation": "TID", "TIDOffset": 0}, "TIDOffset", "non-zero"),
    ({"MaskOperation": "TID", "TIDOffset": 20}, "TIDOffset", "no frame of the range"),
    ({"MaskOperation": "MAGIC"}, "MaskOperation", "not supported"),
])
def test_bad_recipes_are_refused_naming_the_field(fields, field, message):
    with pytest.raises(DsaregInputError, match=message) as info:
        parse_recipe(_run({"MaskOperation": "AVG_SUB", "MaskFrameNumbers": [1]}, fields), 10, field_name="ap")
    assert info.value.field == f"ap.MaskSubtractionSequence[1].{field}"
