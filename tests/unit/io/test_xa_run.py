"""Native XA runs → DSA (both run generators): native vs subtracted, recipe, masks found, motion, frames, refusals."""

from __future__ import annotations

import io

import numpy as np
import pydicom
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.io.image_io import read_image
from dsareg_engine.io.xa_run import RunReading
from dsareg_engine.simulation.native_run import to_bytes
from dsareg_engine.simulation.native_run_skull import SkullRunSettings, make_skull_run
from dsareg_engine.simulation.native_run_texture import TextureRunSettings, make_texture_run

SIZE = 96


@pytest.fixture(scope="module")
def skull():
    return make_skull_run(0, SkullRunSettings(size_px=SIZE))


@pytest.fixture(scope="module")
def texture():
    return make_texture_run(0, TextureRunSettings(size_px=SIZE))


def _vessel_correlation(pixels: np.ndarray, vessels: np.ndarray) -> float:
    return float(np.corrcoef(-pixels.ravel(), vessels.ravel())[0, 1])


def test_recipe_run_is_subtracted_in_the_log_domain_with_motion_corrected(skull):
    image = read_image(skull.files["ap"], "ap.dcm", field_name="ap")
    record = image.reading
    assert record["run"] == "native" and "Mask Subtraction Sequence" in record["why"]
    assert record["recipe"][0]["operation"] == "AVG_SUB" and record["mask_frame_numbers"] == [1, 2]
    assert record["frame_index"] == skull.peak_frame and record["pixel_intensity_relationship"] == "LIN"
    np.testing.assert_allclose(record["mask_shift_px"]["found_px"], skull.motion_px["ap"], atol=0.08)
    # the DSA image is the vessels, not the skull: it follows the true path length
    assert _vessel_correlation(image.pixels, skull.vessels["ap"]) > 0.9
    native_frame = pydicom.dcmread(io.BytesIO(skull.files["ap"])).pixel_array[skull.peak_frame].astype(float)
    assert _vessel_correlation(native_frame, skull.vessels["ap"]) < 0.5  # what was registered before
    np.testing.assert_allclose(image.geometry.world_to_view, skull.rig.views["ap"].world_to_view, atol=1e-6)


def test_motion_correction_improves_the_background(skull):
    corrected = read_image(skull.files["lat"], "lat.dcm", reading=RunReading()).pixels
    raw = read_image(skull.files["lat"], "lat.dcm", reading=RunReading(motion_correction=False)).pixels
    background = skull.vessels["lat"] == 0
    assert np.std(corrected[background]) < 0.8 * np.std(raw[background])


def test_run_without_recipe_is_told_native_and_its_masks_found(texture):
    image = read_image(texture.files["lat"], "lat.dcm", field_name="lat")
    record = image.reading
    assert record["run"] == "native" and "anatomy in every frame" in record["why"]
    assert record["mask_frame_indices"] == list(texture.mask_frames)
    assert record["pixel_intensity_relationship"] == "LOG" and record["sign"] == -1  # from the shared groups
    assert record["frame_index"] == texture.peak_frame
    np.testing.assert_allclose(record["mask_shift_px"]["found_px"], texture.motion_px["lat"], atol=0.1)
    assert _vessel_correlation(image.pixels, texture.vessels["lat"]) > 0.9


def test_enhanced_xa_geometry_comes_from_the_frame_used(texture):
    """The mask frames record the C-arm still settling; the peak frame's angles are the true ones."""
    image = read_image(texture.files["ap"], "ap.dcm")
    np.testing.assert_allclose(image.geometry.world_to_view, texture.rig.views["ap"].world_to_view, atol=1e-6)
    first = read_image(texture.files["ap"], "ap.dcm", reading=RunReading(subtraction="off", frame=0))
    turn = first.geometry.world_to_view[:3, :3] @ texture.rig.views["ap"].world_to_view[:3, :3].T
    assert np.degrees(np.arccos(np.clip((np.trace(turn) - 1) / 2, -1, 1))) == pytest.approx(0.6, abs=0.01)


def test_frame_choice_minip_and_refusals(skull):
    chosen = read_image(skull.files["ap"], "ap.dcm", reading=RunReading(frame=5))
    assert chosen.reading["frame_index"] == 5 and chosen.reading["frame_indices"] == [5]
    minip = read_image(skull.files["ap"], "ap.dcm", reading=RunReading(frame="minip"))
    assert minip.reading["combined"] == "minip" and minip.reading["frame_index"] == skull.peak_frame
    assert minip.reading["frame_indices"][-1] == skull.peak_frame and len(minip.reading["frame_indices"]) > 1
    with pytest.raises(DsaregInputError, match="not a contrast frame") as info:
        read_image(skull.files["ap"], "ap.dcm", reading=RunReading(frame=1), field_name="ap")
    assert info.value.field == "ap"
    with pytest.raises(DsaregInputError, match="does not exist"):
        read_image(skull.files["ap"], "ap.dcm", reading=RunReading(frame=10))
    off = read_image(skull.files["ap"], "ap.dcm", reading=RunReading(subtraction="off"))
    assert off.reading["run"] == "subtracted" and off.reading["why"] == "read as stored"


def _edited(data: bytes, edit) -> bytes:
    dataset = pydicom.dcmread(io.BytesIO(data))
    edit(dataset)
    return to_bytes(dataset)


def test_run_without_contrast_is_refused(skull):
    def no_contrast(dataset):
        frames = dataset.pixel_array.copy()
        frames[:] = frames[0]
        dataset.PixelData = frames.tobytes()

    for data in (_edited(skull.files["ap"], no_contrast),
                 _edited(skull.files["ap"], lambda d: (no_contrast(d), delattr(d, "MaskSubtractionSequence")))):
        with pytest.raises(DsaregInputError, match="contrast") as info:
            read_image(data, "ap.dcm", field_name="ap")
        assert info.value.field == "ap"


def test_recipe_naming_missing_frames_is_refused(skull):
    def bad(dataset):
        dataset.MaskSubtractionSequence[0].MaskFrameNumbers = [1, 14]

    with pytest.raises(DsaregInputError, match="frame 14, which does not exist") as info:
        read_image(_edited(skull.files["lat"], bad), "lat.dcm", field_name="lat")
    assert info.value.field == "lat.MaskSubtractionSequence[0].MaskFrameNumbers"


def test_tid_recipe(skull):
    """TID with offset 6: the mask of frame 7 is frame 1 (0-based), a mask frame of the run."""
    def tid(dataset):
        item = dataset.MaskSubtractionSequence[0]
        item.MaskOperation, item.TIDOffset, item.ApplicableFrameRange = "TID", 6, [8, 8]
        del item.MaskFrameNumbers

    image = read_image(_edited(skull.files["ap"], tid), "ap.dcm")
    assert image.reading["frame_index"] == 7 and image.reading["mask_frame_indices"] == [1]
    assert _vessel_correlation(image.pixels, skull.vessels["ap"]) > 0.85


def test_subtracted_runs_are_read_as_before(skull):
    """A subtracted multi-frame run (no anatomy; vessels appearing) keeps today's frame choice."""
    frames = np.full((5, 40, 50), 3000.0)
    for k, strength in enumerate((0.0, 0.3, 0.7, 1.0, 0.5)):
        frames[k, 18:22, 5:45] -= 1500 * strength
    dataset = pydicom.dcmread(io.BytesIO(skull.subtracted["ap"]))
    dataset.Rows, dataset.Columns, dataset.NumberOfFrames = 40, 50, 5
    dataset.PixelData = frames.astype(np.uint16).tobytes()
    image = read_image(to_bytes(dataset), "run.dcm")
    assert image.reading["run"] == "subtracted" and image.reading["frame_index"] == 3
    np.testing.assert_array_equal(image.pixels, frames[3])


def test_no_recipe_run_with_rotation_masks_and_rotation_found():
    """No recipe, 3 mask frames, the head turned 0.5° and moved (0.8, −0.5) px at contrast arrival, a
    contrast-filled catheter: the masks are the three still frames, the rigid move is found."""
    fill = (0.0, 0.0, 0.0, 0.1, 0.3, 0.55, 0.8, 1.0, 1.2, 1.3)
    settings = SkullRunSettings(size_px=512, fill=fill, strength=(1.0,) * 10, mask_frames=(1, 2, 3),
                                motion_px=(0.8, -0.5), rotation_deg=0.5, recipe=False, catheter_mm=2.0)
    run = make_skull_run(1, settings)
    image = read_image(run.files["lat"], "lat.dcm", field_name="lat")
    record = image.reading
    assert record["run"] == "native" and record["mask_frame_indices"] == [0, 1, 2]
    assert record["mask_shift_px"]["rotation_deg"] == pytest.approx(0.5, abs=0.03)
    np.testing.assert_allclose(record["mask_shift_px"]["found_px"], (0.8, -0.5), atol=0.08)
    for frame, total in record["mask_shift_px_per_frame"].items():  # the phase's other frames, from the peak's move
        np.testing.assert_allclose(total, (0.8, -0.5), atol=0.08, err_msg=f"frame {frame}")
    kinds = {decision.what: decision for decision in image.decisions}
    assert kinds["run kind"].chosen == "native" and not kinds["run kind"].close
    assert kinds["mask frames"].chosen == "0,1,2" and not kinds["mask frames"].close
    assert _vessel_correlation(image.pixels, run.vessels["lat"]) > 0.8  # 512 px: lower dose per pixel


@pytest.mark.parametrize("bits, relationship, photometric", [(8, "DISP", "MONOCHROME2"), (10, "LOG", "MONOCHROME1"),
                                                             (16, "LIN", "MONOCHROME1")])
def test_encodings_without_recipe_read_native(bits, relationship, photometric):
    """Bits, intensity relationship and photometric interpretation as stored: native, vessels dark, masks found."""
    settings = SkullRunSettings(size_px=SIZE, recipe=False, bits=bits, relationship=relationship, photometric=photometric)
    run = make_skull_run(4, settings)
    image = read_image(run.files["ap"], "ap.dcm", field_name="ap")
    assert image.reading["run"] == "native" and image.reading["pixel_intensity_relationship"] == relationship
    assert image.reading["mask_frame_indices"] == list(run.mask_frames)
    assert _vessel_correlation(image.pixels, run.vessels["ap"]) > 0.9


def test_run_without_contrast_is_refused_for_every_frame_choice(skull):
    """Exposure settling and a catheter drifting 2 px a frame, no contrast (as a real 12-frame catheter cine):
    refused whatever frame is asked for, not only for some."""
    def drifting_catheter(dataset):
        first = dataset.pixel_array[0].astype(np.float64)
        rows, columns = np.mgrid[: first.shape[0], : first.shape[1]]
        noise = np.random.default_rng(1)
        frames = []
        for k in range(len(dataset.pixel_array)):
            frame = first * min(1.0, 0.85 + 0.05 * k) + noise.normal(0, 0.01 * first.mean(), first.shape)
            frame[np.abs(columns - (30 + 0.3 * rows + 2.0 * k)) < 1.5] *= 0.6
            frames.append(np.clip(frame, 0, 4095))
        dataset.PixelData = np.asarray(frames, np.uint16).tobytes()
        del dataset.MaskSubtractionSequence

    data = _edited(skull.files["ap"], drifting_catheter)
    for frame in (None, "minip", 5, 9):
        with pytest.raises(DsaregInputError, match="no contrast found") as info:
            read_image(data, "ap.dcm", frame=frame, field_name="ap")
        assert info.value.field == "ap"


def test_recipe_none_reads_the_frames_as_stored(skull):
    """A Mask Subtraction Sequence of one item MaskOperation NONE (legal: no subtraction, as cardiac cines carry it)."""
    def no_subtraction(dataset):
        item = dataset.MaskSubtractionSequence[0]
        item.MaskOperation = "NONE"
        del item.MaskFrameNumbers

    data = _edited(skull.files["ap"], no_subtraction)
    stored = pydicom.dcmread(io.BytesIO(data)).pixel_array
    image = read_image(data, "ap.dcm", frame=6, field_name="ap")
    assert image.reading["run"] == "unsubtracted" and "NONE" in image.reading["why"]
    np.testing.assert_array_equal(image.pixels, stored[6])
    assert image.decisions[0].chosen == "unsubtracted" and image.decisions[0].source == "tag"
    assert read_image(data, "ap.dcm").reading["frame_index"] is not None
