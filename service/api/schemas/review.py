"""The review of a finished job by a person: what is sent and what the job shows."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

Decision = Literal["approved", "rejected"]
ReviewFilter = Literal["none", "approved", "rejected"]
MAX_COMMENT_CHARS = 2000


class ReviewRequest(BaseModel):
    """``POST /v1/registrations/{job_id}/review``: a person's decision on a finished job."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"decision": "approved", "comment": "Contours follow the vessels in both views."}]})

    decision: Decision = Field(description="approved: the pose may be used (and exported); rejected: it may not.")
    comment: str = Field("", max_length=MAX_COMMENT_CHARS,
                         description=f"Why, in the reviewer's words (at most {MAX_COMMENT_CHARS} characters).")


class Review(BaseModel):
    """The latest review of the job; earlier ones stay in the job's audit log."""

    decision: Decision
    comment: str = Field(description="The reviewer's comment (may be empty).")
    by: str = Field(description="Who reviewed: 'key:' and the first 8 hex digits of the API key's SHA-256, "
                                "or 'anonymous' when the service runs without API keys.")
    at: str = Field(description="When, ISO 8601 UTC.")


def reviewer_label(principal: str) -> str:
    """A non-secret label of the caller: ``key:<8 hex of the key's SHA-256>`` or ``anonymous``."""
    if principal.startswith("key:"):
        return principal[:12]
    return principal


def review_model(record: dict[str, Any] | None) -> Review | None:
    if not record:
        return None
    at = datetime.fromtimestamp(float(record["at"]), tz=UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
    return Review(decision=record["decision"], comment=record.get("comment", ""), by=record["by"], at=at)
