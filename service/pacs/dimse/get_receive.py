"""The receiving side of a C-GET: the instances a peer sends back on dsareg's own association.

pynetdicom gathers a C-STORE's data set in memory, and making it a Part 10 file copied it again: a C-GET held
each instance two to three times in RAM while it arrived (a 200 MB instance: +401 MB resident). Here each data
set arrives in a :class:`~.receive_bound.BoundedBuffer` (at most 8 MiB in RAM, the rest in an unnamed temporary
file in ``data_dir/tmp``, gone with its descriptor whatever ends the process), is checked as the DICOM node
checks an instance it receives (:func:`.scp.check_received`: sizes as inflated, pixel dimensions, UIDs,
truncation), and a large one is kept as a Part 10 file in another unnamed temporary file, read into memory
once, when the retrieval is over (:meth:`GetReceiver.instances`).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from typing import Any

from ..instance_check import InstanceLimits, InstanceRefused
from .receive_bound import BoundedBuffer, bound_association
from .scp import OUT_OF_RESOURCES, SUCCESS, check_received, part10_prefix

SPOOL_PREFIX = "cget-"


class GetReceiver:
    """The C-STORE handler of one C-GET association; ``on_received(count)`` after each instance kept."""

    def __init__(self, settings: Any, on_received: Callable[[int], None] | None = None):
        self.limits = InstanceLimits.of(settings)
        self.room_bytes = settings.limits.max_upload_bytes  # all of one C-GET at most, as an upload
        self.spill_dir = settings.storage.data_dir / "tmp"
        self.on_received = on_received or (lambda count: None)
        self.kept: list[Any] = []  # Part 10 bytes (small instances) or unnamed files holding them
        self.refused: list[str] = []
        self.heard()

    def heard(self) -> None:
        """The peer sent something (an instance, a C-GET answer)."""
        self.heard_at = time.monotonic()

    def silent_s(self) -> float:
        """Seconds since the peer last sent something."""
        return time.monotonic() - self.heard_at

    def bind(self, assoc: Any) -> None:
        """Every data set this (requestor) association receives is held in a :class:`BoundedBuffer`."""
        bound_association(assoc, self.limits.max_instance_bytes, self.spill_dir)

    def on_store(self, event: Any) -> int:
        buffer = event.request.DataSet
        self.heard()
        try:
            return self._keep(event, buffer)
        finally:
            if isinstance(buffer, BoundedBuffer):
                buffer.release()

    def _keep(self, event: Any, buffer: Any) -> int:
        size = getattr(buffer, "received_bytes", None) or len(buffer.getbuffer())
        if size > self.room_bytes:
            self.refused.append("more than DSAREG_MAX_UPLOAD_BYTES in all")
            return OUT_OF_RESOURCES  # the peer is told; the C-GET ends with failures
        try:
            check_received(event, self.limits)
            self.kept.append(self._part10(event, buffer))
        except InstanceRefused as exc:
            self.refused.append(exc.reason)
            return exc.status
        except OSError as exc:  # a full disk while spooling
            self.refused.append(f"could not be kept ({exc.strerror or exc})")
            return OUT_OF_RESOURCES
        self.room_bytes -= size
        self.on_received(len(self.kept))
        return SUCCESS

    def _part10(self, event: Any, buffer: Any) -> Any:
        prefix = part10_prefix(event)
        if not isinstance(buffer, BoundedBuffer) or buffer.received_bytes <= buffer.memory_bytes:
            return prefix + buffer.getvalue()
        spool = tempfile.TemporaryFile(dir=self.spill_dir, prefix=SPOOL_PREFIX)  # noqa: SIM115 - closed in instances()
        try:
            spool.write(prefix)
            buffer.copy_to(spool)
        except BaseException:
            spool.close()
            raise
        return spool

    def instances(self) -> list[bytes]:
        """The instances kept, as Part 10 bytes, in the order they arrived (each spool file read once, then closed)."""
        out = []
        while self.kept:
            item = self.kept.pop(0)
            if isinstance(item, bytes):
                out.append(item)
                continue
            with item:
                item.seek(0)
                out.append(item.read())
        return out

    def close(self) -> None:
        """Drop what is kept (a failed retrieval)."""
        for item in self.kept:
            if not isinstance(item, bytes):
                item.close()
        self.kept.clear()
