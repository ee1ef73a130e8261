"""Telling CTA, TOF-MRA and 3D-DSA apart from the tags and the values, and the override."""

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.volume_io import read_volume
from dsareg_engine.io.volume_kind import VolumeReading, detect_volume_kind
from dsareg_engine.registration.options import parse_options
from dsareg_engine.simulation.synthetic_volume_dicom import cta_series, mra_series


def _head_like(air: bool) -> np.ndarray:
    """Values of a head in HU: air around (or not), tissue, a bright rim."""
    data = np.full((20, 20, 20), -1000.0 if air else 40.0, np.float32)
    data[3:17, 3:17, 3:17] = 40.0
    data[3, 3:17, 3:17] = 1200.0
    return data


SUBTRACTED = np.zeros((20, 20, 20), np.float32)
SUBTRACTED[8:12, 8:12, :] = 800.0


@pytest.mark.parametrize("tags, data, kind", [
    ({"Modality": "CT", "ContrastBolusAgent": "Iodine"}, _head_like(air=True), "cta"),
    ({"Modality": "CT", "ImageType": "ORIGINAL\\PRIMARY\\AXIAL"}, _head_like(air=True), "cta"),
    ({"Modality": "CT"}, SUBTRACTED, "3d-dsa"),  # the DICOM phantom study's series: no air, vessels only
    ({"Modality": "CT", "ImageType": "DERIVED\\SECONDARY\\SUBTRACTION"}, _head_like(air=True), "3d-dsa"),
    ({"Modality": "CT", "SeriesDescription": "3D-RA subtracted"}, _head_like(air=True), "3d-dsa"),
    ({"Modality": "XA"}, _head_like(air=True), "3d-dsa"),
    ({"Modality": "MR", "AngioFlag": "Y"}, SUBTRACTED, "mra"),
    ({"Modality": "MR", "SeriesDescription": "Head 3D T1 FFE"}, SUBTRACTED, "mra"),
    ({}, _head_like(air=True), "cta"),  # NIfTI / NRRD: HU values with air
    ({}, SUBTRACTED, "3d-dsa"),
])
def test_kind_from_tags_and_values(tags, data, kind):
    detected, why = detect_volume_kind(tags, data)
    assert detected == kind, why
    assert why


def test_the_series_tags_reach_the_detector():
    data = _head_like(air=True)
    affine = np.diag([1.0, 1.0, 1.0, 1.0])
    for variant in ("a", "b"):  # a: Contrast/Bolus Agent, unsigned + intercept; b: no contrast tag, signed, reversed
        volume = read_volume(cta_series(data, affine, variant)[0])
        assert volume.tags["Modality"] == "CT"
        assert ("ContrastBolusAgent" in volume.tags) == (variant == "a")
        assert detect_volume_kind(volume.tags, volume.data)[0] == "cta"
        np.testing.assert_allclose(volume.data, data, atol=0.5)
    for variant in ("a", "b"):  # a: axial, Angio Flag; b: sagittal slices, rescale slope, no angio tags
        volume = read_volume(mra_series(np.abs(data), affine, variant)[0])
        assert volume.tags["Modality"] == "MR" and ("AngioFlag" in volume.tags) == (variant == "a")
        assert detect_volume_kind(volume.tags, volume.data)[0] == "mra"


def test_the_override_is_validated_and_named():
    options = parse_options({"volume_kind": "mra", "volume_vessel_min": 300})
    reading = VolumeReading.from_options(options)
    assert (reading.kind, reading.vessel_min, reading.vessel_max) == ("mra", 300.0, None)
    assert VolumeReading.from_options(parse_options({})) == VolumeReading()
    with pytest.raises(DsaregInputError) as info:
        parse_options({"volume_kind": "pet"})
    assert info.value.field == "options.volume_kind"
    with pytest.raises(DsaregInputError) as info:
        VolumeReading("cta", vessel_min=800.0, vessel_max=700.0)
    assert info.value.field == "options.volume_vessel_min"
