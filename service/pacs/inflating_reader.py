"""Bounded inflate of a Deflated Explicit VR Little Endian data set (PS3.5 A.5), chunk by chunk.

A deflated data set is raw deflate (RFC 1951, no zlib header). A few megabytes of it can inflate to
gigabytes, so it is never inflated whole: :func:`inflate_bounded` inflates ``CHUNK_BYTES`` at a time,
keeps only the first ``keep_bytes`` (enough for the header), counts the rest and stops with
:class:`InflateBoundExceeded` as soon as the total passes ``limit_bytes``. Memory stays at
``keep_bytes`` + one chunk, whatever the ratio.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Any

CHUNK_BYTES = 1 << 20  # inflated per step
INPUT_BYTES = 64 << 10  # deflated fed per step (zlib copies what a step leaves unconsumed)


class InflateError(ValueError):
    """The deflated stream is not valid raw deflate, or ends early."""


class InflateBoundExceeded(ValueError):
    """The data set inflates to more than the bound."""

    def __init__(self, limit_bytes: int):
        super().__init__(f"inflates to more than {limit_bytes} bytes")
        self.limit_bytes = limit_bytes


@dataclass(frozen=True)
class Inflated:
    prefix: bytes  # the first keep_bytes of the inflated data set (all of it when smaller)
    size_bytes: int  # the whole inflated size


def inflate_bounded(deflated: Any, limit_bytes: int, keep_bytes: int) -> Inflated:
    """Inflate ``deflated`` (raw deflate; bytes, a memory view or a map) counting its size; stop past ``limit_bytes``."""
    inflater = zlib.decompressobj(-zlib.MAX_WBITS)
    kept: list[bytes] = []
    kept_bytes = size = 0
    try:
        with memoryview(deflated) as view:
            for start in range(0, len(view), INPUT_BYTES):
                pending = bytes(view[start:start + INPUT_BYTES])
                while pending and not inflater.eof:
                    chunk = inflater.decompress(pending, CHUNK_BYTES)
                    pending = inflater.unconsumed_tail
                    size += len(chunk)
                    if size > limit_bytes:
                        raise InflateBoundExceeded(limit_bytes)
                    if kept_bytes < keep_bytes:
                        kept.append(chunk[:keep_bytes - kept_bytes])
                        kept_bytes += len(kept[-1])
                if inflater.eof:
                    break
        size += len(inflater.flush())
    except zlib.error as exc:
        raise InflateError(f"not valid deflate data ({exc})") from None
    if size > limit_bytes:
        raise InflateBoundExceeded(limit_bytes)
    if not inflater.eof:
        raise InflateError("the deflate stream ends before its last block")
    return Inflated(b"".join(kept), size)
