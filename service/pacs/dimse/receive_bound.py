"""A per-instance bound on the bytes a DIMSE peer may make us hold, enforced while they arrive.

pynetdicom gathers the P-DATA fragments of one message's data set in an in-memory buffer and only then
hands the C-STORE to its handler; nothing stops a peer from sending gigabytes. :func:`bound_association`
gives each new message of one association a :class:`BoundedBuffer` instead: past ``limit_bytes`` it
drops what it held and every later fragment (counting them), so the C-STORE handler sees
``exceeded`` and answers 0xA700 with nothing kept in memory or on disk. The association goes on: the
peer is told which instance failed and can send the others.
"""

from __future__ import annotations

import io
from typing import Any


class BoundedBuffer(io.BytesIO):
    """A data set buffer that keeps at most ``limit_bytes`` (``received_bytes`` counts everything)."""

    def __init__(self, limit_bytes: int):
        super().__init__()
        self.limit_bytes, self.received_bytes, self.exceeded = limit_bytes, 0, False

    def write(self, data: Any) -> int:
        count = len(data)
        self.received_bytes += count
        if self.exceeded:
            return count
        if self.received_bytes > self.limit_bytes:
            self.exceeded = True
            self.seek(0)
            self.truncate(0)
            return count
        return super().write(data)


def bound_association(assoc: Any, limit_bytes: int) -> None:
    """Every DIMSE message this association receives from now on gathers its data set in a BoundedBuffer."""
    from pynetdicom.dimse_messages import DIMSEMessage

    dimse = assoc.dimse
    receive = dimse.receive_primitive

    def bounded_receive(primitive: Any) -> None:
        if dimse.message is None:
            dimse.message = DIMSEMessage()
            dimse.message.data_set = BoundedBuffer(limit_bytes)
        receive(primitive)

    dimse.receive_primitive = bounded_receive
