"""The one model configuration of every payload the API serves: undeclared fields are refused.

``/openapi.json`` then publishes ``additionalProperties: false``, so a generated client sees every field
and a renamed one fails loudly. Problem details (RFC 9457) stay open and do not use it.
"""

from __future__ import annotations

from pydantic import ConfigDict

CLOSED = ConfigDict(extra="forbid")
