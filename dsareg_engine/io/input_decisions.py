"""Input decisions: what dsareg decided about an input, on which measure, and how close the call was.

Every reader that decides something about an input records one :class:`InputDecision`: the volume's
kind and vessel window, the bone threshold, a run read as native or subtracted, its mask frames, the
frames combined, the mesh's units, its handedness. They travel with the case (``Case.decisions``)
into the result (``result.input_decisions``, typed in the service's contract). A decision whose
measure lies inside its close-call band (``|measure - threshold| < band``) is a *close call*: the
registration still runs on the decision taken, but the verdict becomes at least ``check`` with the
decision's reason (:func:`with_close_calls`), so nobody relies on a pose resting on a coin toss.
"""

from __future__ import annotations

from dataclasses import dataclass

NO_OPTION = frozenset({"pieces in bone", "venous sinuses", "vessel shape"})
"""Decisions no option states (what the reading set aside, the shape it measured): a close call is checked only."""


@dataclass(frozen=True)
class InputDecision:
    """One decision about one input.

    Attributes:
        input: which input: ``"ap"``, ``"lat"``, ``"mesh"`` or ``"volume"``.
        what: what was decided, short and stable (``"run kind"``, ``"units"``, ``"volume kind"`` ...).
        chosen: the outcome (``"native"``, ``"mm"``, ``"cta"`` ...).
        basis: what the measure is, in words (``"vessel / anatomy contrast ratio"``).
        measure: the number decided on, or None for a decision given by the user or a tag.
        threshold: where the decision turns, in the measure's units, or None.
        band: half-width of the close-call band around ``threshold``, in the measure's units, or None.
        source: ``"measured"``, ``"tag"`` (read from the file) or ``"option"`` (given by the user).
    """

    input: str
    what: str
    chosen: str
    basis: str
    measure: float | None = None
    threshold: float | None = None
    band: float | None = None
    source: str = "measured"

    @property
    def margin(self) -> float | None:
        """``measure - threshold`` (signed, the measure's units), or None."""
        if self.measure is None or self.threshold is None:
            return None
        return float(self.measure - self.threshold)

    @property
    def close(self) -> bool:
        """Whether the measure lies inside the close-call band (only measured decisions can be close)."""
        margin = self.margin
        return self.source == "measured" and margin is not None and self.band is not None and abs(margin) < self.band

    def reason(self) -> str:
        """The verdict reason a close call gives."""
        state = "" if self.what in NO_OPTION else " or state it in the options"
        return (f"{self.input}: {self.what} read as {self.chosen!s} on a close call ({self.basis} "
                f"{self.measure:.3g}, threshold {self.threshold:.3g}); check that this is right{state}")

    def to_dict(self) -> dict:
        """JSON-ready (the ``result.input_decisions`` item)."""
        return {"input": self.input, "what": self.what, "chosen": self.chosen, "basis": self.basis,
                "measure": self.measure, "threshold": self.threshold, "band": self.band,
                "margin": self.margin, "close": self.close, "source": self.source}


def with_close_calls(data: dict, decisions: list[InputDecision]) -> dict:
    """``data`` (a result dict) with ``input_decisions`` set and, for each close call, its reason added to
    ``metrics.confidence.reasons`` and an ``ok`` verdict lowered to ``check`` (``failed`` stays)."""
    if not decisions:
        return data
    data["input_decisions"] = [decision.to_dict() for decision in decisions]
    close = [decision.reason() for decision in decisions if decision.close]
    confidence = (data.get("metrics") or {}).get("confidence")
    if close and isinstance(confidence, dict):
        confidence["reasons"] = list(confidence.get("reasons") or []) + close
        if confidence.get("verdict") == "ok":
            confidence["verdict"] = "check"
        if "verdict" in data:
            data["verdict"] = confidence["verdict"]
    return data
