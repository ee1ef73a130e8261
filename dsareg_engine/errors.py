"""The one exception type that carries a user-facing message.

Every reader, validator and geometry constructor in :mod:`dsareg_engine` raises
:class:`DsaregInputError` when the *input* is at fault. Its message says what was
wrong, which field, and what is accepted, so the CLI and the HTTP service can show
it to a person unchanged. Bugs in our own code stay ordinary exceptions.
"""

from __future__ import annotations


class DsaregInputError(ValueError):
    """An input cannot be used.

    Attributes:
        message: What was wrong, phrased for the person who supplied the input.
        field: The input or field at fault (``"geometry.views.ap.world_to_view"``,
            ``"mesh"``...), or ``None`` when it concerns the request as a whole.
        accepted: What would have been accepted, or ``None``.
    """

    def __init__(self, message: str, *, field: str | None = None, accepted: str | None = None):
        self.message = message
        self.field = field
        self.accepted = accepted
        text = message if field is None else f"{field}: {message}"
        if accepted:
            text = f"{text} (accepted: {accepted})"
        super().__init__(text)

    def with_field_prefix(self, prefix: str) -> "DsaregInputError":
        """The same error with ``prefix`` prepended to its field path."""
        field = prefix if self.field is None else f"{prefix}.{self.field}"
        return DsaregInputError(self.message, field=field, accepted=self.accepted)
