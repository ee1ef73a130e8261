"""A per-instance bound on the bytes a DIMSE peer may make us hold, enforced while they arrive.

pynetdicom gathers the P-DATA fragments of one message's data set in an in-memory buffer and only then
hands the C-STORE to its handler; nothing stops a peer from sending gigabytes. :func:`bound_association`
gives each new message of one association a :class:`BoundedBuffer` instead:

* the first ``memory_bytes`` (8 MiB, at most a quarter of the bound) stay in memory; past them the data set goes to an unnamed temporary file
  in the data folder (gone with its file descriptor, even if the process is killed), so an
  association costs at most ``memory_bytes`` of RAM whatever it sends;
* past ``limit_bytes`` in all it drops what it held and every later fragment (counting them), and a
  write that fails (a full disk) does the same: the C-STORE handler sees ``exceeded`` / ``failed``
  and answers 0xA700 with nothing kept. The association goes on: the peer is told which instance
  failed and can send the others.
"""

from __future__ import annotations

import io
import mmap
import tempfile
from pathlib import Path
from typing import Any

MEMORY_BYTES = 8 << 20
CHUNK_BYTES = 1 << 20


class BoundedBuffer(io.BytesIO):
    """A data set buffer: ``memory_bytes`` in RAM, then a temporary file, at most ``limit_bytes`` in all.

    A BytesIO (pynetdicom accepts nothing else as a data set) whose own buffer is the in-memory part."""

    def __init__(self, limit_bytes: int, spill_dir: Path, memory_bytes: int = MEMORY_BYTES):
        super().__init__()
        self.limit_bytes, self.spill_dir = limit_bytes, Path(spill_dir)
        self.memory_bytes = min(memory_bytes, limit_bytes // 4)
        self.received_bytes, self.exceeded, self.failed = 0, False, False
        self._file: Any = None
        self._map: mmap.mmap | None = None

    def write(self, data: Any) -> int:
        count = len(data)
        self.received_bytes += count
        if self.exceeded or self.failed:
            return count
        if self.received_bytes > self.limit_bytes:
            self.exceeded = True
            self.release()
            return count
        try:
            if self._file is None and self.received_bytes > self.memory_bytes:
                self._spill()
            if self._file is not None:
                self._file.write(data)
            else:
                super().write(data)
        except OSError:  # ENOSPC while spilling: this instance fails, the association goes on
            self.failed = True
            self.release()
        return count

    def _spill(self) -> None:
        self.spill_dir.mkdir(parents=True, exist_ok=True)
        self._file = tempfile.TemporaryFile(dir=self.spill_dir, prefix="dimse-")  # noqa: SIM115 - see release()
        self._file.write(super().getbuffer())
        self.seek(0)
        self.truncate(0)

    def view(self) -> memoryview | mmap.mmap:
        """The data set's bytes without copying them (a memory view, or a read-only map of the file)."""
        if self._file is None:
            return super().getbuffer()
        self._file.flush()
        if self._map is None:
            self._map = mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ)
        return self._map

    def getvalue(self) -> bytes:
        """All of it as bytes (pynetdicom's ``encoded_dataset``; a copy)."""
        return bytes(self.view()) if self._file is not None else super().getvalue()

    def copy_to(self, out: Any) -> int:
        """Write the data set to the file object ``out`` (from its file in chunks, without mapping it into
        memory); the bytes written."""
        if self._file is None:
            with super().getbuffer() as view:
                return out.write(view)
        self._file.flush()
        self._file.seek(0)
        written = 0
        while chunk := self._file.read(CHUNK_BYTES):
            written += out.write(chunk)
        return written

    def reader(self, prefix: bytes = b"") -> io.RawIOBase:
        """A file object reading ``prefix`` then the data set (to store it without a copy in memory; a spilled one
        read from its file, never mapped: a map's pages read would count in the process's resident memory)."""
        if self._file is None:
            return _Chained(prefix, super().getbuffer())
        self._file.flush()
        self._file.seek(0)
        return _Chained(prefix, self._file)

    def release(self) -> None:
        """Drop what is held (the spilled file, the memory)."""
        if self._map is not None:
            try:
                self._map.close()
            except BufferError:  # a view of it is still held (a failed store): it closes when that goes
                pass
            self._map = None
        if self._file is not None:
            self._file.close()
            self._file = None
        try:
            self.seek(0)
            self.truncate(0)
        except BufferError:  # a memory view of it is still held
            pass


class _Chained(io.RawIOBase):
    """``prefix`` then ``body`` (a memory view, or a file read from where it is) as one readable stream."""

    def __init__(self, prefix: bytes, body: Any):
        self.parts, self.at = [memoryview(prefix), body], 0

    def readable(self) -> bool:
        return True

    def read(self, size: int = -1) -> bytes:
        if size is None or size < 0:
            return b"".join(iter(lambda: self.read(CHUNK_BYTES), b""))
        while self.parts:
            part = self.parts[0]
            if not isinstance(part, memoryview):  # a file
                chunk = part.read(size)
                if chunk:
                    return chunk
            elif self.at < len(part):
                end = min(len(part), self.at + size)
                chunk, self.at = bytes(part[self.at:end]), end
                return chunk
            self.parts.pop(0)
            self.at = 0
        return b""


def bound_association(assoc: Any, limit_bytes: int, spill_dir: Path) -> None:
    """Every DIMSE message this association receives from now on gathers its data set in a BoundedBuffer.

    pynetdicom's standard logging handler of received messages (bound to every association) calls ``getvalue()``
    on each data set to say whether one is present, whatever the log level: a whole copy in memory (a spilled one
    mapped and copied: twice its size). It is unbound from this association."""
    from pynetdicom import evt
    from pynetdicom._handlers import standard_dimse_recv_handler
    from pynetdicom.dimse_messages import DIMSEMessage

    assoc.unbind(evt.EVT_DIMSE_RECV, standard_dimse_recv_handler)
    dimse = assoc.dimse
    receive = dimse.receive_primitive

    def bounded_receive(primitive: Any) -> None:
        if dimse.message is None:
            dimse.message = DIMSEMessage()
            dimse.message.data_set = BoundedBuffer(limit_bytes, spill_dir)
        receive(primitive)

    dimse.receive_primitive = bounded_receive
