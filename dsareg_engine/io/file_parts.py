"""A volume's files read when they are used and not kept: :class:`FileParts`.

A whole-head CT series is 440 files and 0.23 GB (a 600-slice one 0.31 GB). Given as ``list[bytes]``, the files stay
in memory for the whole job: the caller, ``load_case``'s frames and the model key all hold the list, beside the
decoded grid and the reading's masks. A :class:`FileParts` holds how to read each file. It reads a file each time
an item is asked for, and keeps nothing. So the files are in memory only while the series is parsed and decoded
(:func:`.volume_io.read_volume`).

Wherever a volume may be given as a list of files, a :class:`FileParts` may be given instead (:data:`PART_LISTS`).
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

    def __init__(self, loaders: Iterable[Callable[[], bytes]]):
        self._loaders = tuple(loaders)

    @classmethod
    def from_paths(cls, paths: Iterable[str | Path]) -> FileParts:
        """The files at ``paths`` (read from disk on each access)."""
        return cls(partial(Path(path).read_bytes) for path in paths)

    def __len__(self) -> int:
        return len(self._loaders)

    @overload
    def __getitem__(self, index: int) -> bytes: ...

    @overload
    def __getitem__(self, index: slice) -> FileParts: ...

    def __getitem__(self, index: int | slice) -> bytes | FileParts:
        if isinstance(index, slice):
            return FileParts(self._loaders[index])
        return self._loaders[index]()

    def __repr__(self) -> str:
        return f"FileParts({len(self)} files, read when used)"


PART_LISTS = (list, tuple, FileParts)
"""The types a volume of several files comes as (``isinstance(data, PART_LISTS)``); one file comes as ``bytes``."""


def volume_parts(data: bytes | Sequence[bytes] | None) -> list[bytes]:
    """``data``'s files read now, in order: a list of ``bytes`` (``[]`` for ``None``, ``[data]`` for one file)."""
    if data is None:
        return []
    if isinstance(data, PART_LISTS):
        return [bytes(part) for part in data]
    return [data]
