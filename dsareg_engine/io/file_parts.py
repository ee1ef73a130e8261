"""A volume's files read when they are used and not kept: :class:`FileParts`.

A whole-head CT series is 440 files and 0.23 GB (a 600-slice one 0.31 GB). Given as ``list[bytes]``, the files stay
in memory for the whole job: the caller, ``load_case``'s frames and the model key all hold the list, beside the
decoded grid and the reading's masks. A :class:`FileParts` holds how to read each file. It reads a file each time
an item is asked for, and keeps nothing. So the files are in memory only while the series is parsed and decoded
(:func:`.volume_io.read_volume`).

Wherever a volume may be given as a list of files, a :class:`FileParts` may be given instead (:data:`PART_LISTS`).

Two things make a :class:`FileParts` cheaper than reading every file whole each time (a worker reading a whole head
from the PostgreSQL blob table: 2.2 s a pass over its 440 files):

* **digests** (optional): each file's SHA-256 (hex) as a content-addressed store already knows it: a model key
  (:func:`.model_key.model_key`) takes them instead of reading and hashing the files;
* **heads** (optional): ``head(n)`` loaders giving a file's first ``n`` bytes (a local file's first bytes, a database
  row's first bytes): a series' headers are read from those (:func:`file_head`), its pixels from the whole files.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from functools import partial
from pathlib import Path
from typing import overload


class FileParts(Sequence[bytes]):
    """Files as ``bytes``, each read from its loader when it is asked for (``parts[i]``, iteration).

    The loaders are called again on every access, so two reads of a file cost two reads: a model key's digest and
    the series' parse each read every file once.
    """

    def __init__(self, loaders: Iterable[Callable[[], bytes]], *, digests: Iterable[str] | None = None,
                 heads: Iterable[Callable[[int], bytes]] | None = None):
        self._loaders = tuple(loaders)
        self.digests = None if digests is None else tuple(str(d) for d in digests)
        """Each file's SHA-256 (lower-case hex), as its store knows it, or ``None`` (unknown: hash the files)."""
        self._heads = None if heads is None else tuple(heads)
        for extra in (self.digests, self._heads):
            if extra is not None and len(extra) != len(self._loaders):
                raise ValueError(f"{len(extra)} digests or heads for {len(self._loaders)} files")

    @classmethod
    def from_paths(cls, paths: Iterable[str | Path]) -> FileParts:
        """The files at ``paths`` (read from disk on each access; a head reads only its bytes)."""
        paths = [Path(path) for path in paths]
        return cls((partial(path.read_bytes) for path in paths), heads=(partial(_read_head, path) for path in paths))

    def head(self, index: int, size: int) -> bytes:
        """File ``index``'s first ``size`` bytes (all of it when shorter): from its head loader when one was given,
        else the whole file read and cut."""
        if self._heads is None:
            return bytes(self._loaders[index]()[:size])
        return self._heads[index](size)

    def __len__(self) -> int:
        return len(self._loaders)

    @overload
    def __getitem__(self, index: int) -> bytes: ...

    @overload
    def __getitem__(self, index: slice) -> FileParts: ...

    def __getitem__(self, index: int | slice) -> bytes | FileParts:
        if isinstance(index, slice):
            return FileParts(self._loaders[index], digests=None if self.digests is None else self.digests[index],
                             heads=None if self._heads is None else self._heads[index])
        return self._loaders[index]()

    def __repr__(self) -> str:
        return f"FileParts({len(self)} files, read when used)"


PART_LISTS = (list, tuple, FileParts)
"""The types a volume of several files comes as (``isinstance(data, PART_LISTS)``); one file comes as ``bytes``."""


def _read_head(path: Path, size: int) -> bytes:
    with open(path, "rb") as stream:
        return stream.read(size)


def file_head(parts: Sequence[bytes], index: int, size: int) -> bytes:
    """The first ``size`` bytes of ``parts[index]`` (a :class:`FileParts` reads only those where it can)."""
    return parts.head(index, size) if isinstance(parts, FileParts) else bytes(parts[index][:size])


def file_digests(parts: Sequence[bytes]) -> list[str]:
    """Each file's SHA-256 (hex): a :class:`FileParts`' known digests, else each file read and hashed, one at a
    time."""
    import hashlib

    if isinstance(parts, FileParts) and parts.digests is not None:
        return list(parts.digests)
    return [hashlib.sha256(bytes(part)).hexdigest() for part in parts]


def volume_parts(data: bytes | Sequence[bytes] | None) -> list[bytes]:
    """``data``'s files read now, in order: a list of ``bytes`` (``[]`` for ``None``, ``[data]`` for one file)."""
    if data is None:
        return []
    if isinstance(data, PART_LISTS):
        return [bytes(part) for part in data]
    return [data]
