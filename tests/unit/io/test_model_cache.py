"""A volume's model is kept for the next case on the same volume (issue 41: each job read a whole-head CTA again).

The second read of the same files with the same options takes the stored model (no pixel decoded, no extraction)
and gives the same surface, readout, decisions, warnings and DICOM identities; other files or other options are
another key; the store is bounded, and a damaged entry is a miss."""

from functools import cache

import numpy as np
import pytest

from dsareg_engine.io import case as case_module
from dsareg_engine.io.case import load_case
from dsareg_engine.io.model_cache import DirectoryModelStore, from_bytes, model_key, to_bytes
from dsareg_engine.io.volume_kind import VolumeReading
from dsareg_engine.simulation.synthetic_volumes import make_volume_case


@cache
def _case():
    return make_volume_case("cta", "a", voxel_mm=1.0, depth=2, image_px=160, pixel_spacing_mm=0.9,
                            min_head_mm=(30.0, 30.0, 40.0))


def _load(store, reading=None):
    case = _case()
    return load_case(volume=case.volume.parts, volume_name="series.dcm", ap=case.ap, ap_name="ap.dcm", lat=case.lat,
                     lat_name="lat.dcm", volume_reading=reading, model_store=store)


def test_the_second_case_on_a_volume_takes_its_model_without_reading_it(tmp_path, monkeypatch):
    store = DirectoryModelStore(tmp_path / "models")
    first = _load(store)
    assert len(list((tmp_path / "models").glob("*.npz"))) == 1

    def no_reading(*args, **kwargs):
        raise AssertionError("the volume was read again")

    monkeypatch.setattr(case_module, "read_volume", no_reading)
    monkeypatch.setattr(case_module, "extract_vessels", no_reading)
    second = _load(store)
    assert np.array_equal(second.mesh.vertices, first.mesh.vertices)
    assert np.array_equal(second.mesh.faces, first.mesh.faces)
    assert second.volume.to_dict() == first.volume.to_dict()
    assert second.decisions == first.decisions and second.warnings == first.warnings
    assert second.kinds == first.kinds
    assert second.sources.volume == first.sources.volume and len(first.sources.volume) > 0
    assert second.sources.unreadable == first.sources.unreadable


def test_other_options_or_other_files_are_another_key():
    parts = _case().volume.parts
    key = model_key(parts, "series.dcm", None, 20000)
    assert key == model_key(list(parts), "series.dcm", VolumeReading(), 20000)
    assert key != model_key(parts, "series.dcm", VolumeReading(vessel_min=250.0), 20000)
    assert key != model_key(parts, "series.dcm", None, 10000)
    assert key != model_key(parts[:-1] + [parts[-1] + b"\0"], "series.dcm", None, 20000)
    assert key != model_key(parts[::-1], "series.dcm", None, 20000)  # order: a two-file volume's roles differ


def test_the_store_is_bounded_and_a_damaged_entry_is_a_miss(tmp_path):
    store = DirectoryModelStore(tmp_path, max_entries=2)
    model = case_module._read_volume_model(_case().volume.parts, "series.dcm", case_module.DEFAULT_LIMITS, None)[0]
    assert from_bytes(to_bytes(model)).readout.to_dict() == model.readout.to_dict()
    keys = [f"{i:064x}" for i in range(3)]
    for key in keys:
        store.put(key, model)
    assert sorted(p.stem for p in tmp_path.glob("*.npz")) == keys[1:]  # the oldest went first
    (tmp_path / f"{keys[2]}.npz").write_bytes(b"not a model")
    assert store.get(keys[2]) is None and not (tmp_path / f"{keys[2]}.npz").exists()
    assert store.get(keys[1]) is not None
    with pytest.raises(ValueError):
        store.get("../../etc/passwd")


def test_a_killed_writers_temporary_file_is_removed_once_stale(tmp_path):
    """A process killed between its write and its rename (the validator, SIGKILLed mid-put) leaves a temporary
    file; the next put removes it once it is older than STALE_TEMPORARY_S, and never one being written now."""
    import os
    import time

    from dsareg_engine.io.model_cache import STALE_TEMPORARY_S

    store = DirectoryModelStore(tmp_path)
    old, fresh = tmp_path / ".model-old.tmp", tmp_path / ".model-fresh.tmp"
    old.write_bytes(b"half a model")
    fresh.write_bytes(b"being written")
    past = time.time() - STALE_TEMPORARY_S - 60
    os.utime(old, (past, past))
    model = case_module._read_volume_model(_case().volume.parts, "series.dcm", case_module.DEFAULT_LIMITS, None)[0]
    store.put(f"{1:064x}", model)
    assert not old.exists() and fresh.exists()
    assert store.get(f"{1:064x}") is not None
