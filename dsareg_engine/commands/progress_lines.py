"""Progress and verdict helpers of the commands (``dsareg register``, ``dsareg submit``).

Progress goes to stderr, the summary (or ``--json``) to stdout, so ``dsareg … | jq`` and log
files read cleanly. On a terminal the progress is one bar redrawn in place (carriage return); on
anything else (a pipe, a file, a CI log) it is plain lines, one per stage and at most one every
``every_seconds`` within a stage, and never a carriage return.
"""

from __future__ import annotations

import sys
import time
from typing import IO, Any

VERDICT_RANK = {"failed": 0, "check": 1, "ok": 2}
REQUIRE_CHOICES = ("ok", "check")
VERDICT_NOT_MET_EXIT = 3
"""Exit status when the job ran but its verdict is below ``--require``."""


def verdict_meets(verdict: str | None, required: str | None) -> bool:
    """``verdict`` (ok / check / failed / None) is at least ``required`` (None: anything goes)."""
    if required is None:
        return True
    return VERDICT_RANK.get(verdict or "", -1) >= VERDICT_RANK[required]


def ground_truth_text(errors: dict[str, Any]) -> str:
    """The errors against a ground-truth pose, each saying what it measures (``metrics.ground_truth``).

    ADD is the figure to judge a pose by; the translation error is the paper's (where the X-ray source lies in
    the model's frame), about a metre from the vessels, so a rotation of a tenth of a degree moves it ~2 mm."""
    def number(key: str) -> float:
        value = errors.get(key)
        return float(value) if isinstance(value, (int, float)) else float("nan")

    return (f"vs ground truth: ADD {number('add_mm'):.4f} mm (mean distance of the model's points), rotation "
            f"{number('rotation_error_deg'):.4f} deg, source translation {number('translation_error_mm'):.4f} mm "
            "(the X-ray source in the model's frame, ~1 m away: grows with the rotation)")


class ProgressPrinter:
    """Show progress events ``{stage, iteration, loss, fraction}`` on ``stream`` (default stderr)."""

    def __init__(self, stream: IO[str] | None = None, *, every_seconds: float = 5.0, width: int = 30,
                 tty: bool | None = None):
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self._isatty() if tty is None else tty
        self.every_seconds, self.width = every_seconds, width
        self.last_stage: str | None = None
        self.last_line_at = float("-inf")
        self.drawn = False

    def _isatty(self) -> bool:
        try:
            return bool(self.stream.isatty())
        except (AttributeError, ValueError):
            return False

    @staticmethod
    def describe(event: dict[str, Any], status: str | None = None) -> tuple[str, str]:
        """``(stage, text)`` of one event (the text without any bar)."""
        stage = str(event.get("stage") or "")
        fraction = float(event.get("fraction") or 0.0)
        loss = event.get("loss")
        iteration = int(event.get("iteration") or 0)
        parts = [f"{fraction * 100:5.1f}%"]
        if status:  # padded to align the stages; alone when there is none (was "running  " and an empty stage)
            parts.append(f"{status:9s}" if stage else status)
        if not stage and status == "running":
            parts.append("(starting)")  # claimed by a worker, no stage reported yet
        if stage:  # a job not started yet has no stage: its status alone (was "queued     it 0")
            counted = iteration > 0 or isinstance(loss, (int, float))  # "outputs", "dicom": no iterations
            parts.append(f"{stage} it {iteration}" if counted else stage)
        if isinstance(loss, (int, float)):
            parts.append(f"loss {loss:.5f}")
        return stage, " ".join(parts)

    def update(self, event: dict[str, Any], status: str | None = None) -> None:
        stage, text = self.describe(event, status)
        if self.tty:
            filled = round(float(event.get("fraction") or 0.0) * self.width)
            self.stream.write(f"\r[{'#' * filled}{'.' * (self.width - filled)}] {text}"[:120].ljust(100))
            self.drawn = True
        else:
            now = time.monotonic()
            if stage == self.last_stage and now - self.last_line_at < self.every_seconds:
                return
            self.last_stage, self.last_line_at = stage, now
            self.stream.write(f"progress {text}\n")
        self.stream.flush()

    def message(self, text: str) -> None:
        """A line of its own (a warning), below the bar on a terminal."""
        self.close()
        self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.drawn:
            self.stream.write("\n")
            self.stream.flush()
            self.drawn = False
