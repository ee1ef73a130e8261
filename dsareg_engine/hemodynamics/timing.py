"""When each frame of a run was acquired, from its DICOM header: each view's own clock and the offset between them.

Sources, in the order tried (the first that gives one time per frame wins):

* enhanced XA: per-frame Frame Content Sequence, Frame Acquisition DateTime (0018,9074), else Frame
  Reference DateTime (0018,9151);
* Frame Time Vector (0018,1065): increments in ms between frames (the first is 0);
* Frame Time (0018,1063): ms between frames;
* Cine Rate (0018,0040): frames per second.

Times are in seconds with ``t = 0`` at the run's first frame. The run's start, when the header says it
(Acquisition DateTime (0008,002A), else Acquisition Date/Time, else Content Date/Time; the first frame's
Frame Acquisition DateTime for enhanced XA), places the two runs on one clock: ``offset_s`` is how much
later the LAT run started than the AP run. A run of one frame, or without any of these, has no timing.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta

import numpy as np

from ..errors import DsaregInputError

TIMING_ACCEPTED = ("a multi-frame XA run with frame timing: Frame Time (0018,1063), Frame Time Vector (0018,1065), "
                   "Cine Rate (0018,0040) or per-frame Frame Acquisition DateTime (enhanced XA)")


@dataclass(frozen=True)
class RunTiming:
    """The acquisition times of a run's frames.

    Attributes:
        times_s: ``(T,)`` seconds from the first frame, increasing.
        source: the attribute they came from (``"FrameTime"``, ``"FrameTimeVector"``, ``"CineRate"``,
            ``"FrameAcquisitionDateTime"``, ``"FrameReferenceDateTime"``).
        start: when the first frame was acquired (naive, the header's local time), or None.
    """

    times_s: np.ndarray
    source: str
    start: datetime | None = None

    @property
    def frame_interval_s(self) -> float:
        """The median time between frames."""
        return float(np.median(np.diff(self.times_s))) if len(self.times_s) > 1 else 0.0

    def to_dict(self) -> dict:
        return {"times_s": [round(float(t), 4) for t in self.times_s], "source": self.source,
                "frame_interval_s": round(self.frame_interval_s, 4),
                "start": self.start.isoformat() if self.start is not None else None}


def parse_datetime(text: str) -> datetime | None:
    """A DICOM DT (``YYYYMMDDHHMMSS.FFFFFF``, an optional UTC offset dropped), or None."""
    text = str(text or "").strip()
    for sign in ("+", "-"):
        if sign in text[8:]:
            text = text[: 8 + text[8:].index(sign)]
    if len(text) < 8 or not text[:8].isdigit():
        return None
    date = datetime(int(text[:4]), int(text[4:6]), int(text[6:8]))
    seconds = parse_time_s(text[8:]) if len(text) > 8 else 0.0
    return None if seconds is None else date + timedelta(seconds=seconds)


def parse_time_s(text: str) -> float | None:
    """A DICOM TM (``HHMMSS.FFFFFF``, or the old ``HH:MM:SS``) as seconds since midnight, or None."""
    text = str(text or "").strip().replace(":", "")
    whole, _, fraction = text.partition(".")
    if not whole.isdigit() or len(whole) not in (2, 4, 6):
        return None
    parts = [int(whole[i:i + 2]) for i in range(0, len(whole), 2)] + [0, 0]
    return parts[0] * 3600.0 + parts[1] * 60.0 + parts[2] + (float("0." + fraction) if fraction.isdigit() else 0.0)


def run_start(dataset) -> datetime | None:
    """The run's start from Acquisition DateTime, Acquisition Date + Time or Content Date + Time."""
    found = parse_datetime(getattr(dataset, "AcquisitionDateTime", "") or "")
    if found is not None:
        return found
    for date_key, time_key in (("AcquisitionDate", "AcquisitionTime"), ("ContentDate", "ContentTime")):
        date, time = getattr(dataset, date_key, "") or "", getattr(dataset, time_key, "") or ""
        day, seconds = parse_datetime(str(date)[:8]), parse_time_s(time)
        if day is not None and seconds is not None:
            return day + timedelta(seconds=seconds)
    return None


def _per_frame_times(dataset, n_frames: int) -> tuple[np.ndarray, str, datetime] | None:
    """Enhanced XA: the per-frame Frame Content DateTimes."""
    groups = getattr(dataset, "PerFrameFunctionalGroupsSequence", None)
    if groups is None or len(groups) != n_frames:
        return None
    for keyword in ("FrameAcquisitionDateTime", "FrameReferenceDateTime"):
        stamps = []
        for group in groups:
            content = getattr(group, "FrameContentSequence", None)
            value = getattr(content[0], keyword, None) if content else None
            stamps.append(parse_datetime(value) if value else None)
        if all(stamp is not None for stamp in stamps):
            times = np.array([(stamp - stamps[0]).total_seconds() for stamp in stamps])
            return times, keyword, stamps[0]
    return None


def _numbers(value) -> list[float]:
    values = value if isinstance(value, (list, tuple)) or hasattr(value, "__iter__") and not isinstance(value, str) \
        else [value]
    return [float(v) for v in values]


def _regular_times(dataset, n_frames: int) -> tuple[np.ndarray, str] | None:
    """Frame Time Vector, Frame Time or Cine Rate."""
    vector = getattr(dataset, "FrameTimeVector", None)
    if vector is not None and len(_numbers(vector)) == n_frames:
        increments = np.array(_numbers(vector)) / 1000.0
        increments[0] = 0.0
        return np.cumsum(increments), "FrameTimeVector"
    frame_time = getattr(dataset, "FrameTime", None)
    if frame_time not in (None, "") and float(frame_time) > 0:
        return np.arange(n_frames) * float(frame_time) / 1000.0, "FrameTime"
    rate = getattr(dataset, "CineRate", None)
    if rate not in (None, "") and float(rate) > 0:
        return np.arange(n_frames) / float(rate), "CineRate"
    return None


def read_timing(dataset, n_frames: int, field_name: str = "image") -> RunTiming | None:
    """The frame times of a run (a pydicom Dataset of ``n_frames`` frames), or None when it has none.

    Raises:
        DsaregInputError: timing attributes that are present but not numbers, or times that do not increase.
    """
    if n_frames < 2:
        return None
    try:
        found = _per_frame_times(dataset, n_frames)
        if found is not None:
            times, source, start = found
        else:
            regular = _regular_times(dataset, n_frames)
            if regular is None:
                return None
            (times, source), start = regular, run_start(dataset)
    except (TypeError, ValueError) as exc:
        raise DsaregInputError(f"the frame timing cannot be read ({str(exc)[:80]})", field=field_name,
                               accepted=TIMING_ACCEPTED) from None
    if not np.all(np.diff(times) > 0):
        raise DsaregInputError(f"the frame times ({source}) do not increase from frame to frame", field=field_name,
                               accepted=TIMING_ACCEPTED)
    return RunTiming(np.asarray(times, float), source, start)


def require_timing(timing: RunTiming | None, n_frames: int, field_name: str) -> RunTiming:
    """``timing``, or the error hemodynamics gives for a still image or a run without timing."""
    if timing is not None:
        return timing
    what = "a single frame (a still image)" if n_frames < 2 else f"a run of {n_frames} frames without frame timing"
    raise DsaregInputError(f"hemodynamics needs a timed run, but the {field_name} view is {what}", field=field_name,
                           accepted=TIMING_ACCEPTED)


def run_offset_s(ap: RunTiming, lat: RunTiming) -> tuple[float, str]:
    """``(seconds the LAT run started after the AP run, how it is known)``; 0 when a start is missing."""
    if ap.start is not None and lat.start is not None:
        return (lat.start - ap.start).total_seconds(), "from the runs' start times"
    return 0.0, "start times not in both files: the two runs are taken to start together (biplane planes fire together)"
