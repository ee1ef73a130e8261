"""Mesh units: GLB read in metres, options.mesh_units, a size no head artery tree has refused naming the unit."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.geometry.spec import parse_geometry
from dsareg_engine.io.case import load_case
from dsareg_engine.io.mesh_io import read_mesh_detailed
from dsareg_engine.io.mesh_units import MeshUnit, mesh_unit, unit_decision
from dsareg_engine.mesh import TriangleMesh
from dsareg_engine.simulation.phantom import make_vessel_phantom


@pytest.fixture(scope="module")
def phantom():
    return make_vessel_phantom(depth=2)


def _export(phantom, file_type: str, mm_per_unit: float) -> bytes:
    data = trimesh.Trimesh(phantom.vertices / mm_per_unit, phantom.faces, process=False).export(file_type=file_type)
    return data.encode() if isinstance(data, str) else data


def _same_surface(mesh, phantom) -> float:
    return float(cKDTree(mesh.vertices).query(phantom.vertices)[0].max())


def test_glb_is_read_in_metres_as_its_specification_says(phantom):
    result = read_mesh_detailed(_export(phantom, "glb", 1000.0), "tree.glb")
    assert result.unit == MeshUnit("m", "tag")
    assert _same_surface(result.mesh, phantom) < 1e-4  # the phantom's millimetres, not 1000x smaller


@pytest.mark.parametrize("unit, scale", [("mm", 1.0), ("cm", 10.0), ("m", 1000.0)])
def test_the_option_states_the_unit_of_any_format(phantom, unit, scale):
    result = read_mesh_detailed(_export(phantom, "stl", scale), "tree.stl", units=unit)
    assert result.unit == MeshUnit(unit, "option")
    assert _same_surface(result.mesh, phantom) < 1e-3 * scale


def test_the_option_wins_over_the_formats_unit(phantom):
    """An exporter that writes millimetres into a GLB regardless of glTF's metre."""
    result = read_mesh_detailed(_export(phantom, "glb", 1.0), "tree.glb", units="mm")
    assert _same_surface(result.mesh, phantom) < 1e-4


def test_formats_without_a_unit_are_millimetres_and_unknown_units_are_refused():
    assert mesh_unit("obj", None) == MeshUnit("mm", "measured")
    with pytest.raises(DsaregInputError) as info:
        mesh_unit("obj", "inch")
    assert info.value.field == "options.mesh_units" and "mm, cm, m" in info.value.accepted


def _box(side_mm: float) -> TriangleMesh:
    box = trimesh.creation.box(extents=(side_mm, side_mm / 2, side_mm / 3))
    return TriangleMesh(np.asarray(box.vertices), np.asarray(box.faces))


@pytest.mark.parametrize("side_mm, unit, hint", [(0.09, "mm", "m"), (9.0, "mm", "cm"), (90_000.0, "m", "mm"),
                                                  (900.0, "cm", "mm")])
def test_an_implausible_size_is_refused_naming_extent_unit_and_option(side_mm, unit, hint):
    with pytest.raises(DsaregInputError) as info:
        unit_decision(_box(side_mm), MeshUnit(unit, "measured"), "mesh")
    error = info.value
    assert error.field == "mesh"
    assert f"{side_mm:.3g} mm across" in error.message and f"in {unit}" in error.message
    assert "options.mesh_units" in error.accepted and f"probably {hint}" in error.accepted


def test_the_unit_is_a_decision_with_its_margin():
    decision = unit_decision(_box(120.0), MeshUnit("mm", "measured"), "mesh")
    assert (decision.input, decision.what, decision.chosen, decision.source) == ("mesh", "units", "mm", "measured")
    assert decision.measure == pytest.approx(120.0) and decision.threshold in (15.0, 400.0) and not decision.close
    assert unit_decision(_box(16.0), MeshUnit("mm", "measured"), "mesh").close  # a cm model would be 10x larger
    assert not unit_decision(_box(16.0), MeshUnit("mm", "option"), "mesh").close  # the user said so


def test_load_case_reads_a_glb_in_metres_and_refuses_an_stl_in_metres(phantom, build):
    image, _ = build.dsa(height=100, width=100)
    png = build.png(image)
    common = dict(ap=png, ap_name="ap.png", lat=png, lat_name="lat.png", geometry=parse_geometry("paper"))
    case = load_case(mesh=_export(phantom, "glb", 1000.0), mesh_name="tree.glb", **common)
    units = [d for d in case.decisions if d.what == "units"]
    assert [(d.input, d.chosen, d.source) for d in units] == [("mesh", "m", "tag")]
    assert np.ptp(case.mesh.vertices, axis=0).max() == pytest.approx(np.ptp(phantom.vertices, axis=0).max(), rel=1e-6)
    metres = _export(phantom, "stl", 1000.0)
    with pytest.raises(DsaregInputError) as info:
        load_case(mesh=metres, mesh_name="tree.stl", **common)
    assert info.value.field == "mesh" and "too small" in info.value.message and "probably m" in info.value.accepted
    assert load_case(mesh=metres, mesh_name="tree.stl", mesh_units="m", **common).mesh.n_faces == phantom.n_faces


def test_a_small_model_in_an_assumed_unit_is_a_close_call():
    """A body model in cm read as mm (SimVascular's 34.5-cm aorto-iliac tree: 34.5 "mm") passed as a plain mm model."""
    decision = unit_decision(_box(34.5), MeshUnit("mm", "measured"), "mesh")
    assert decision.close and "cm" in decision.basis and "close call" in decision.reason()
    assert not unit_decision(_box(34.5), MeshUnit("mm", "option"), "mesh").close  # stated: no doubt left
    assert not unit_decision(_box(40.0), MeshUnit("mm", "measured"), "mesh").close  # a circle-of-Willis crop


def test_the_simvascular_demo_model_in_cm_is_a_close_call():
    from pathlib import Path

    from dsareg_engine.io.mesh_io import read_mesh_detailed

    path = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "real-vessels" / "DemoProject_demo.vtp"
    if not path.is_file():
        pytest.skip("../shared/data is not here")
    result = read_mesh_detailed(path.read_bytes(), path.name)
    assert unit_decision(result.mesh, result.unit, "mesh").close
    stated = read_mesh_detailed(path.read_bytes(), path.name, units="cm")
    assert not unit_decision(stated.mesh, stated.unit, "mesh").close  # 345 mm in cm, as stated
