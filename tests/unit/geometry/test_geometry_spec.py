"""The typed geometry: every accepted input parsed once, one canonical stored form, clear errors."""

import json
from unittest import mock

import numpy as np
import pytest

from dsareg_engine.geometry import spec as geometry_spec
from dsareg_engine.errors import DsaregInputError
from dsareg_engine.geometry.rig import Rig
from dsareg_engine.geometry.file import paper_rig
from dsareg_engine.geometry.spec import CANONICAL_PREFIX, GeometrySpec, is_canonical_geometry, parse_geometry


def _explicit() -> dict:
    return paper_rig().to_dict()


def _assert_same_rig(a: Rig, b: Rig) -> None:
    """Bit-for-bit equal: same views, same numbers, same initial pose (or none)."""
    assert a.views.keys() == b.views.keys()
    for name in a.views:
        va, vb = a.views[name], b.views[name]
        assert (va.image_size, va.pixel_spacing_mm, va.sid_mm, va.principal_point_px) == (
            vb.image_size, vb.pixel_spacing_mm, vb.sid_mm, vb.principal_point_px)
        assert np.array_equal(va.world_to_view, vb.world_to_view)
    assert a.initial_pose_given == b.initial_pose_given
    assert np.array_equal(a.initial_mesh_to_world, b.initial_mesh_to_world)


def _projection_and_turn() -> dict:
    """AP as a 3x4 projection matrix, LAT as the AP chain turned 75° about +y (both expanded when stored)."""
    ap = paper_rig().views["ap"]
    view = {"image_size": list(ap.image_size), "pixel_spacing_mm": list(ap.pixel_spacing_mm),
            "projection_matrix": ap.projection_matrix.tolist()}
    return {"views": {"ap": view}, "lat_from_ap": {"angle_deg": 75.0}}


ACCEPTED = {
    "preset name": ("paper", "preset"),
    "preset name with spaces": ("  paper\n", "preset"),
    "JSON text": (json.dumps(_explicit()), "json"),
    "JSON bytes": (json.dumps(_explicit()).encode(), "json"),
    "parsed object": (_explicit(), "json"),
    "projection matrix + lat_from_ap": (json.dumps(_projection_and_turn()), "json"),
    "no initial pose": (json.dumps({"views": _explicit()["views"]}), "json"),
}


@pytest.mark.parametrize("name", list(ACCEPTED))
def test_every_accepted_kind_is_parsed_once_and_round_trips(name):
    value, source = ACCEPTED[name]
    with mock.patch.object(geometry_spec, "rig_from_dict", wraps=geometry_spec.rig_from_dict) as validated, \
            mock.patch.dict(geometry_spec.PRESETS, {"paper": mock.Mock(wraps=paper_rig)}) as presets:
        spec = parse_geometry(value)
        assert validated.call_count + presets["paper"].call_count == 1  # decided and validated exactly once
        text = spec.to_json()
        loaded = GeometrySpec.from_json(text)
        assert validated.call_count + presets["paper"].call_count == 1  # loading re-decides nothing
    assert spec.source == source and loaded.source == source
    assert loaded.preset == ("paper" if source == "preset" else None)
    _assert_same_rig(spec.rig, loaded.rig)
    assert loaded.to_json() == text  # canonical: a fixed point
    assert is_canonical_geometry(text) and text.startswith(CANONICAL_PREFIX)


def test_the_canonical_form_is_explicit_and_keeps_the_preset_as_provenance_only():
    data = json.loads(parse_geometry("paper").to_json())
    assert set(data) == {"format", "views", "initial_mesh_to_world", "provenance"}
    assert data["provenance"] == {"source": "preset", "preset": "paper"}
    for view in data["views"].values():
        assert set(view) == {"image_size", "pixel_spacing_mm", "sid_mm", "principal_point_px", "world_to_view"}
    turned = json.loads(parse_geometry(json.dumps(_projection_and_turn())).to_json())
    assert "lat_from_ap" not in turned and "projection_matrix" not in turned["views"]["ap"]
    assert turned["initial_mesh_to_world"] is None
    # a stored preset does not depend on the preset's definition any more
    with mock.patch.dict(geometry_spec.PRESETS, {"paper": lambda: pytest.fail("preset looked up on load")}):
        _assert_same_rig(GeometrySpec.from_json(json.dumps(data)).rig, paper_rig())


def test_a_geometry_file_is_read_only_when_files_are_allowed(tmp_path):
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(_explicit()))
    spec = parse_geometry(str(path), files=True)
    assert spec.source == "file"
    _assert_same_rig(spec.rig, paper_rig())
    with pytest.raises(DsaregInputError, match="neither a preset nor JSON") as info:
        parse_geometry(str(path))  # a server never reads a path a client names
    assert info.value.field == "geometry" and "paper" in info.value.accepted


@pytest.mark.parametrize("value, field, message, accepted", [
    ("", "geometry", "is empty", "preset name"),
    ("   ", "geometry", "is empty", "preset name"),
    ("papr", "geometry", "'papr' is neither a preset nor JSON", "['paper']"),
    (b"\xff\xfe{", "geometry", "not UTF-8", "JSON object"),
    (42, "geometry", "has type int", "JSON object"),
    ("{not json", "geometry", "is not valid JSON", "JSON object"),
    ("{}", "geometry.views", "Field required", "preset name"),
    (('{"views": {"ap": {"image_size": [10, 10], "pixel_spacing_mm": [1, 1], "sid_mm": -5, "world_to_view": '
      '[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}}}'), "geometry.views.ap.sid_mm", "greater than 0", "preset name"),
    ('{"views": {"ap": {"image_size": [10, 10], "pixel_spacing_mm": [1, 1]}}}', "geometry.views.ap",
     "needs sid_mm and world_to_view", "preset name"),
    ('{"views": {"front": ' + json.dumps(_explicit()["views"]["ap"]) + '}}', "geometry.views", "unknown view",
     "'ap', 'lat'"),
    ('{"views": {}, "extra": 1}', "geometry.extra", "Extra inputs", "preset name"),
])
def test_bad_geometry_names_what_is_wrong_and_what_is_accepted(value, field, message, accepted):
    with pytest.raises(DsaregInputError) as info:
        parse_geometry(value)
    assert info.value.field == field
    assert message in info.value.message
    assert accepted in info.value.accepted


def test_cli_file_errors_name_the_option(tmp_path):
    with pytest.raises(DsaregInputError, match="not found") as info:
        parse_geometry(str(tmp_path / "missing.json"), field="--geometry", files=True)
    assert info.value.field == "--geometry" and "geometry JSON file" in info.value.accepted
    with pytest.raises(DsaregInputError, match="is a folder"):
        parse_geometry(str(tmp_path), field="--geometry", files=True)


def test_the_service_parser_is_used_for_json_text():
    calls = []

    def bounded(text):
        calls.append(text)
        return json.loads(text)

    parse_geometry(json.dumps(_explicit()), loads=bounded)
    parse_geometry("paper", loads=bounded)
    assert len(calls) == 1


@pytest.mark.parametrize("text, field", [
    ("paper", "geometry"),  # a preset name is an input, not a stored form
    (json.dumps(_explicit()), "geometry.format"),  # a geometry file is not the canonical form either
    (parse_geometry("paper").to_json().replace('"source":"preset"', '"source":"guess"'), "geometry.provenance.source"),
    (parse_geometry("paper").to_json().replace("dsareg.geometry/1", "dsareg.geometry/9"), "geometry.format"),
])
def test_loading_accepts_only_the_canonical_form(text, field):
    with pytest.raises(DsaregInputError, match="canonical form") as info:
        GeometrySpec.from_json(text)
    assert info.value.field == field
