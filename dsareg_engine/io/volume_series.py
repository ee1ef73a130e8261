"""Which series of a DICOM folder is the volume: a folder sent as "the volume" often holds other series too
(the XA runs of the same study, a CT scout, a reformat).

:func:`pick_volume_series` groups the files by Series Instance UID and takes the volume series: of the CT / MR
series whose slices share one size, the one with the most slices (an enhanced multi-frame file: its frames). The
others are named in a warning. When two
such series are close in size (the second has at least ``AMBIGUOUS_SHARE`` of the first's slices: a soft-tissue
and a bone kernel, a CTA and an MRA), which one is meant cannot be told: the error names the series found
(number, modality, description, files) so the user can send one.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import DsaregInputError

VOLUME_MODALITIES = ("CT", "MR")
AMBIGUOUS_SHARE = 0.5
ACCEPTED = "the files of one CT or MR series (or a folder where one CT/MR series is clearly the volume)"


@dataclass(frozen=True)
class SeriesFound:
    """One series of a folder: its files' indices and what names it to a user."""

    uid: str
    number: str
    modality: str
    description: str
    indices: tuple[int, ...]
    sizes: frozenset
    slices: int = 0  # its files' frames (NumberOfFrames, 1 for a classic slice)

    def name(self) -> str:
        description = f" '{self.description}'" if self.description else ""
        return f"series {self.number or '?'} ({self.modality or 'no modality'}{description}, {len(self.indices)} file(s))"

    @property
    def is_volume(self) -> bool:
        return self.modality in VOLUME_MODALITIES and len(self.sizes) == 1 and self.slices >= 2


def group_series(headers: list) -> list[SeriesFound]:
    """The files' series (pydicom datasets, in file order), largest first."""
    groups: dict[str, list[int]] = {}
    for index, header in enumerate(headers):
        uid = str(getattr(header, "SeriesInstanceUID", "") or f"no-uid-{getattr(header, 'Modality', '')}")
        groups.setdefault(uid, []).append(index)
    found = []
    for uid, indices in groups.items():
        first = headers[indices[0]]
        sizes = frozenset((int(getattr(headers[i], "Rows", 0) or 0), int(getattr(headers[i], "Columns", 0) or 0))
                          for i in indices)
        slices = sum(_frames(headers[i]) for i in indices)
        found.append(SeriesFound(uid, str(getattr(first, "SeriesNumber", "") or ""),
                                 str(getattr(first, "Modality", "") or "").upper(),
                                 str(getattr(first, "SeriesDescription", "") or "")[:64], tuple(indices), sizes, slices))
    return sorted(found, key=lambda series: -series.slices)


def _frames(header) -> int:
    try:
        return max(1, int(getattr(header, "NumberOfFrames", 1) or 1))
    except (TypeError, ValueError):
        return 1


def pick_volume_series(headers: list, *, field_name: str = "volume") -> tuple[tuple[int, ...], list[str]]:
    """The indices of the volume series' files and the warnings naming the series left out.

    Raises:
        DsaregInputError: no CT/MR series of one slice size, or two of similar size (the series found named).
    """
    found = group_series(headers)
    if len(found) == 1:
        return found[0].indices, []
    named = "; ".join(series.name() for series in found)
    volumes = [series for series in found if series.is_volume]
    if not volumes:
        raise DsaregInputError(f"holds {len(found)} DICOM series and none is a CT or MR volume: {named}",
                               field=field_name, accepted=ACCEPTED)
    chosen = volumes[0]
    rivals = [series for series in volumes[1:] if series.slices >= AMBIGUOUS_SHARE * chosen.slices]
    if rivals:
        raise DsaregInputError(f"holds {len(volumes)} CT/MR series of similar size; which is the volume cannot be "
                               f"told: {named}", field=field_name, accepted=ACCEPTED)
    others = "; ".join(series.name() for series in found if series is not chosen)
    return chosen.indices, [f"{field_name}: took {chosen.name()} as the volume; left out {others}"]


__all__ = ["SeriesFound", "group_series", "pick_volume_series"]
