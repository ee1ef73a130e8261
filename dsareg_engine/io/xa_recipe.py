"""The subtraction recipe of a native XA run: DICOM PS3.3 C.7.6.10 Mask Subtraction Sequence (0028,6100).

A C-arm stores a DSA run unsubtracted and says how to subtract it: each item of the Mask
Subtraction Sequence names an operation and the frames it applies to. Frame numbers in DICOM
are 1-based; here every index is 0-based (``frame_number - 1``) once parsed.

* ``AVG_SUB``: the frames of Mask Frame Numbers (0028,6110) are averaged into one mask, which is
  subtracted from every contrast frame of the item's range.
* ``TID`` (time interval differencing): the mask of frame ``n`` is frame ``n − TID Offset``
  (0028,6120); ``REV_TID``: frame ``n + TID Offset``.
* Applicable Frame Range (0028,6102): pairs ``first, last`` (inclusive) of the frames the item
  applies to; absent: every frame.
* Mask Sub-pixel Shift (0028,6114): ``(row, column)`` px applied to the mask before subtracting;
  a positive row offset moves it toward the lower rows, a positive column offset toward the
  left-hand columns. Kept here as ``mask_shift_px = (down, right) = (row, −column)``.
* Contrast Frame Averaging (0028,6112): that many frames, from the current one on, are averaged
  before the subtraction.
* ``NONE``: no subtraction for the item's frames. A sequence whose every item is ``NONE`` (cardiac cines carry
  one) makes the run *unsubtracted*: its frames are read as stored (:mod:`.xa_run_kind`).

Anything that cannot be applied (an unknown operation, a frame number outside the run, an
AVG_SUB without mask frames, a TID without an offset) raises :class:`DsaregInputError` naming
the field, e.g. ``ap.MaskSubtractionSequence[0].MaskFrameNumbers``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydicom.multival import MultiValue

from ..errors import DsaregInputError

OPERATIONS = ("AVG_SUB", "TID", "REV_TID", "NONE")


@dataclass(frozen=True)
class SubtractionItem:
    """One item of the Mask Subtraction Sequence, 0-based.

    Attributes:
        operation: ``AVG_SUB``, ``TID``, ``REV_TID`` or ``NONE``.
        frames: the contrast frames it applies to (0-based, ascending).
        mask_frames: AVG_SUB: the frames averaged into the mask (0-based).
        tid_offset: TID / REV_TID: the frame distance to the mask.
        mask_shift_px: ``(down, right)`` px the mask is moved before subtracting.
        contrast_averaging: contrast frames averaged from the current one on (1: none).
    """

    operation: str
    frames: tuple[int, ...]
    mask_frames: tuple[int, ...] = ()
    tid_offset: int = 0
    mask_shift_px: tuple[float, float] = (0.0, 0.0)
    contrast_averaging: int = 1

    def mask_of(self, frame: int) -> tuple[int, ...]:
        """The frames whose mean is the mask of ``frame`` (empty: no subtraction)."""
        if self.operation == "AVG_SUB":
            return self.mask_frames
        if self.operation == "TID":
            return (frame - self.tid_offset,)
        if self.operation == "REV_TID":
            return (frame + self.tid_offset,)
        return ()

    def describe(self) -> dict:
        """JSON-ready, with DICOM 1-based frame numbers (what the file says)."""
        text: dict = {"operation": self.operation, "frames": _ranges([f + 1 for f in self.frames])}
        if self.operation == "AVG_SUB":
            text["mask_frame_numbers"] = [f + 1 for f in self.mask_frames]
        if self.operation in ("TID", "REV_TID"):
            text["tid_offset"] = self.tid_offset
        if any(self.mask_shift_px):
            text["mask_subpixel_shift_rows_columns"] = [self.mask_shift_px[0], -self.mask_shift_px[1]]
        if self.contrast_averaging > 1:
            text["contrast_frame_averaging"] = self.contrast_averaging
        return text


def _ranges(numbers: list[int]) -> str:
    """``[1, 2, 3, 7]`` → ``"1-3, 7"``."""
    parts, start = [], None
    for i, n in enumerate(numbers):
        if start is None:
            start = n
        if i == len(numbers) - 1 or numbers[i + 1] != n + 1:
            parts.append(str(start) if start == n else f"{start}-{n}")
            start = None
    return ", ".join(parts)


def _numbers(item, keyword: str, where: str) -> list[int] | None:
    if keyword not in item or item.data_element(keyword).value in (None, ""):
        return None
    value = item.data_element(keyword).value
    values = list(value) if isinstance(value, (list, tuple, MultiValue)) else [value]
    try:
        return [int(v) for v in values]
    except (TypeError, ValueError):
        raise DsaregInputError(f"{keyword} must be integers", field=f"{where}.{keyword}") from None


def _checked_frames(numbers: list[int], n_frames: int, keyword: str, where: str) -> tuple[int, ...]:
    bad = [n for n in numbers if not 1 <= n <= n_frames]
    if bad:
        raise DsaregInputError(
            f"{keyword} names frame {bad[0]}, which does not exist (the run has {n_frames} frames)",
            field=f"{where}.{keyword}", accepted=f"frame numbers 1..{n_frames}")
    return tuple(n - 1 for n in numbers)


def _frame_range(item, n_frames: int, where: str) -> tuple[int, ...]:
    bounds = _numbers(item, "ApplicableFrameRange", where)
    if bounds is None:
        return tuple(range(n_frames))
    if len(bounds) % 2 or not bounds:
        raise DsaregInputError("ApplicableFrameRange must be pairs of first, last frame numbers",
                               field=f"{where}.ApplicableFrameRange")
    frames: set[int] = set()
    for first, last in zip(bounds[::2], bounds[1::2]):
        low, high = _checked_frames([first, last], n_frames, "ApplicableFrameRange", where)
        if high < low:
            raise DsaregInputError(f"ApplicableFrameRange {first}-{last} ends before it starts",
                                   field=f"{where}.ApplicableFrameRange")
        frames.update(range(low, high + 1))
    return tuple(sorted(frames))


def _shift(item, where: str) -> tuple[float, float]:
    if "MaskSubPixelShift" not in item or item.MaskSubPixelShift in (None, ""):
        return (0.0, 0.0)
    try:
        row, column = (float(v) for v in item.MaskSubPixelShift)
    except (TypeError, ValueError):
        raise DsaregInputError("MaskSubPixelShift must be two numbers (row, column)",
                               field=f"{where}.MaskSubPixelShift") from None
    if not (np.isfinite(row) and np.isfinite(column)):
        raise DsaregInputError("MaskSubPixelShift is not finite", field=f"{where}.MaskSubPixelShift")
    return (row, -column)


def parse_item(item, n_frames: int, where: str) -> SubtractionItem:
    """One sequence item (a pydicom Dataset) → :class:`SubtractionItem`, checked against ``n_frames``."""
    operation = str(getattr(item, "MaskOperation", "") or "").strip().upper()
    if operation not in OPERATIONS:
        raise DsaregInputError(f"MaskOperation '{operation[:16]}' is not supported", field=f"{where}.MaskOperation",
                               accepted=", ".join(OPERATIONS))
    frames = _frame_range(item, n_frames, where)
    averaging = (_numbers(item, "ContrastFrameAveraging", where) or [1])[0]
    if averaging < 1:
        raise DsaregInputError("ContrastFrameAveraging must be 1 or more", field=f"{where}.ContrastFrameAveraging")
    fields = {"operation": operation, "frames": frames, "mask_shift_px": _shift(item, where),
              "contrast_averaging": averaging}
    if operation == "AVG_SUB":
        numbers = _numbers(item, "MaskFrameNumbers", where)
        if not numbers:
            raise DsaregInputError("AVG_SUB needs Mask Frame Numbers", field=f"{where}.MaskFrameNumbers",
                                   accepted=f"frame numbers 1..{n_frames}")
        fields["mask_frames"] = _checked_frames(numbers, n_frames, "MaskFrameNumbers", where)
    elif operation in ("TID", "REV_TID"):
        offset = _numbers(item, "TIDOffset", where)
        if not offset or offset[0] == 0:
            raise DsaregInputError(f"{operation} needs a non-zero TID Offset", field=f"{where}.TIDOffset")
        fields["tid_offset"] = offset[0]
    parsed = SubtractionItem(**fields)
    _check_masks_exist(parsed, n_frames, where)
    return parsed


def _check_masks_exist(item: SubtractionItem, n_frames: int, where: str) -> None:
    if item.operation not in ("TID", "REV_TID"):
        return
    usable = [f for f in item.frames if all(0 <= m < n_frames for m in item.mask_of(f))]
    if not usable:
        raise DsaregInputError(
            f"with {item.operation} offset {item.tid_offset}, no frame of the range has its mask frame in the run "
            f"({n_frames} frames)", field=f"{where}.TIDOffset")


def parse_recipe(dataset, n_frames: int, *, field_name: str = "image") -> list[SubtractionItem]:
    """The Mask Subtraction Sequence of ``dataset`` (empty list when there is none).

    Raises:
        DsaregInputError: an item that cannot be applied, naming ``<field>.MaskSubtractionSequence[i].<tag>``.
    """
    if "MaskSubtractionSequence" not in dataset:
        return []
    items = []
    for index, item in enumerate(dataset.MaskSubtractionSequence):
        items.append(parse_item(item, n_frames, f"{field_name}.MaskSubtractionSequence[{index}]"))
    return items
