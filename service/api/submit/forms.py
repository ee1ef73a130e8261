"""Request bodies read under one size policy, for every route that takes one.

* multipart/form-data (:func:`read_form`): Starlette's parser, checked where it is silent —
  every text part (``geometry``, ``options``; sent as a plain field *or* as a file part) is capped at
  :data:`MAX_TEXT_PART_BYTES` while it streams (413 naming the part, nothing buffered beyond the cap);
  a body that ends before its closing boundary is a 400 naming the cut part (python-multipart's
  ``finalize()`` does not check the final state, and Starlette then drops the cut part silently, so
  a job used to run with default options instead of the sent ones); the parser's own errors (too
  many files or fields, no boundary, malformed) are 400 problem+json instead of a bare message.
* a JSON body (:func:`read_body`): read in chunks and refused past its limit (413), never buffered whole.
"""

from __future__ import annotations

from typing import Any

from fastapi import Request
from starlette.datastructures import FormData
from starlette.formparsers import MultiPartException, MultiPartParser

from ...problems import Problem

MAX_TEXT_PART_BYTES = 1 << 20
"""``geometry`` and ``options`` (and any other part without a filename) at most: 1 MiB each."""
TEXT_PARTS = ("geometry", "options")
"""Parts read as text whatever the client sends them as (a form field or a file)."""


class _CheckedParser(MultiPartParser):
    """Starlette's multipart parser that knows which part it is in, caps text parts sent as files,
    and remembers whether the closing boundary arrived."""

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.ended = False
        self._text_file_bytes = 0

    def on_part_begin(self) -> None:
        super().on_part_begin()
        self._text_file_bytes = 0

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        name = self._current_part.field_name
        size = end - start
        over = len(self._current_part.data) + size > self.max_part_size if self._current_part.file is None else False
        if self._current_part.file is not None and name in TEXT_PARTS:
            self._text_file_bytes += size
            over = self._text_file_bytes > self.max_part_size
        if over:
            raise Problem(413, f"the part '{name}' is larger than {self.max_part_size} bytes", field=name,
                          kind="part-too-large", accepted=f"at most {self.max_part_size} bytes of UTF-8 JSON text")
        super().on_part_data(data, start, end)

    def on_end(self) -> None:
        self.ended = True

    def current_field(self) -> str | None:
        return self._current_part.field_name or None


async def read_form(request: Request, *, max_files: int, max_fields: int) -> FormData:
    """The multipart form of ``request``, checked as the module says (problem+json on every failure)."""
    parser = _CheckedParser(request.headers, request.stream(), max_files=max_files, max_fields=max_fields,
                            max_part_size=MAX_TEXT_PART_BYTES)
    try:
        form = await parser.parse()
    except MultiPartException as exc:
        raise Problem(400, f"the multipart body is malformed: {exc.message}", field=parser.current_field(),
                      kind="malformed-multipart", accepted="multipart/form-data (RFC 7578)") from None
    if not parser.ended:
        await form.close()
        cut = parser.current_field()
        where = f" (the part '{cut}' is cut)" if cut else ""
        raise Problem(400, f"the multipart body ends before its closing boundary{where}; nothing was accepted",
                      field=cut, kind="truncated-multipart", accepted="a complete multipart/form-data body")
    return form


async def read_body(request: Request, limit: int, field: str = "body") -> bytes:
    """The whole body of ``request``, refused (413 naming ``field``) as soon as it passes ``limit`` bytes."""
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise Problem(413, f"the request body is larger than {limit} bytes", field=field,
                          kind="body-too-large", accepted=f"at most {limit} bytes")
        chunks.append(chunk)
    return b"".join(chunks)
