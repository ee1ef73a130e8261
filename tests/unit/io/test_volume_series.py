"""A DICOM folder holding the volume series and others (XA runs, a scout): the volume series is taken and the
others named; two CT/MR series of similar size are refused with the series named.

On main before it, such a folder was refused with "DICOM slices differ in size" (nothing named).
"""

import io

import numpy as np
import pydicom
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.volume_io import read_volume


def _tagged(parts, uid, number, description, modality=None):
    out = []
    for part in parts:
        ds = pydicom.dcmread(io.BytesIO(part))
        ds.SeriesInstanceUID, ds.SeriesNumber, ds.SeriesDescription = uid, number, description
        if modality:
            ds.Modality = modality
        buffer = io.BytesIO()
        ds.save_as(buffer)
        out.append(buffer.getvalue())
    return out


def _small_ct(build, slices=8, shift=0.0):
    affine = np.diag([0.5, 0.5, 0.8, 1.0])
    affine[2, 3] = shift
    volume = np.zeros((12, 10, slices), np.float32)
    volume[4:7, 3:6, :] = 300.0
    return build.ct_series(volume, affine), volume, affine


def test_the_volume_series_is_taken_from_a_mixed_folder(build):
    ct, volume, affine = _small_ct(build)
    ct = _tagged(ct, "1.2.3.1", 3, "CTA head")
    xa = _tagged([build.xa(np.zeros((64, 64), np.uint16)), build.xa(np.zeros((64, 64), np.uint16))],
                 "1.2.3.2", 10, "AP run")
    scout = _tagged(_small_ct(build, slices=1)[0], "1.2.3.3", 1, "Scout")
    loaded = read_volume(xa[:1] + ct[:4] + scout + ct[4:] + xa[1:])
    assert loaded.data.shape == volume.shape
    np.testing.assert_allclose(loaded.affine, affine, atol=1e-4)  # slice spacing 0.8 from the positions
    warning = " ".join(loaded.warnings)
    assert "series 3 (CT 'CTA head', 8 file(s))" in warning
    assert "series 10 (XA 'AP run', 2 file(s))" in warning and "series 1 (CT 'Scout', 1 file(s))" in warning


def test_two_volume_series_of_similar_size_are_named(build):
    first = _tagged(_small_ct(build)[0], "1.2.3.1", 3, "CTA soft")
    second = _tagged(_small_ct(build, slices=6)[0], "1.2.3.4", 4, "CTA bone")
    with pytest.raises(DsaregInputError) as info:
        read_volume(first + second)
    message = info.value.message
    assert info.value.field == "volume" and "series 3 (CT 'CTA soft', 8 file(s))" in message
    assert "series 4 (CT 'CTA bone', 6 file(s))" in message and "CT or MR series" in info.value.accepted
    xa_only = _tagged([build.xa(np.zeros((64, 64), np.uint16))] * 2, "1.2.3.2", 10, "AP run")
    with pytest.raises(DsaregInputError, match="none is a CT or MR volume"):
        read_volume(xa_only + _tagged([build.xa(np.zeros((64, 64), np.uint16))], "1.2.3.5", 11, "LAT run"))


def test_anisotropic_voxels_are_read_per_axis(build):
    parts, volume, affine = _small_ct(build, shift=-3.0)
    loaded = read_volume(parts[::-1])  # slices in any order: spacing from the positions, 0.5 x 0.5 x 0.8
    assert loaded.spacing_mm == pytest.approx((0.5, 0.5, 0.8), abs=1e-5)
    np.testing.assert_allclose(loaded.data, volume, atol=1e-3)


def test_an_enhanced_file_counts_its_frames_as_slices():
    """A single multi-frame CT is a volume series (its frames are its slices); beside a classic series of as many
    slices, which one is meant cannot be told."""
    from types import SimpleNamespace

    from dsareg_engine.io.volume_series import group_series, pick_volume_series

    def header(uid, modality, frames=None):
        return SimpleNamespace(SeriesInstanceUID=uid, Modality=modality, Rows=8, Columns=8, NumberOfFrames=frames)

    xa = [header("xa", "XA", 30), header("xa", "XA", 30)]
    assert [s.slices for s in group_series([*xa, header("ct", "CT", 40)])] == [60, 40]
    chosen, warnings = pick_volume_series([*xa, header("ct", "CT", 40)])
    assert chosen == (2,) and "XA" in warnings[0]
    with pytest.raises(DsaregInputError, match="similar size"):
        pick_volume_series([*xa, header("ct", "CT", 40), *(header("ct2", "CT") for _ in range(40))])
    with pytest.raises(DsaregInputError, match="none is a CT or MR volume"):
        pick_volume_series([*xa, header("one", "CT")])  # a single classic slice is no volume
