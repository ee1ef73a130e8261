"""The closed result contract: /openapi.json publishes every result schema closed, an undeclared field is refused,
and the engine's own result for a small phantom case holds (tests/support/result_contract.py)."""

from __future__ import annotations

import copy
import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from dsareg_engine.geometry.spec import parse_geometry
from dsareg_engine.io.case import CaseFiles
from dsareg_engine.pipeline import run_case
from dsareg_engine.simulation.phantom import make_vessel_phantom
from service.app import create_app
from service.settings import ServiceSettings
from tests.support.result_contract import assert_result_contract, contract_errors, sweep_results


@pytest.fixture(scope="module")
def engine_result(build, tmp_path_factory) -> dict:
    """The engine's result.json for a small phantom case (two starts, a few iterations)."""
    phantom = make_vessel_phantom(depth=2)
    mesh = trimesh.Trimesh(phantom.vertices, phantom.faces, process=False).export(file_type="stl")
    png = build.png(build.dsa(height=100, width=100)[0])
    files = CaseFiles(ap=png, ap_name="ap.png", lat=png, lat_name="lat.png", mesh=mesh, mesh_name="tree.stl",
                      geometry=parse_geometry("paper"))
    out = tmp_path_factory.mktemp("engine")
    options = {"starts": 2, "max_iterations": 5, "ground_truth_mesh_to_world": np.eye(4).tolist()}
    run_case(files, options, out, dicom="off")
    return json.loads((out / "result.json").read_text())


def test_the_engines_result_holds_the_contract(engine_result):
    assert_result_contract(engine_result)
    assert engine_result["metrics"]["confidence"]["verdict"] in {"ok", "check", "failed"}


@pytest.mark.parametrize("where", [(), ("metrics",), ("metrics", "confidence", "signals"), ("views", "ap")])
def test_an_undeclared_field_breaks_the_contract_at_any_depth(engine_result, where):
    result = copy.deepcopy(engine_result)
    node = result
    for key in where:
        node = node[key]
    node["not_declared_mm"] = 1.0
    errors = contract_errors(result)
    assert errors == [".".join([*where, "not_declared_mm"]) + ": Extra inputs are not permitted"]
    with pytest.raises(AssertionError, match="not_declared_mm"):
        assert_result_contract(result)


def test_the_sweep_names_the_result_json_that_breaks_it(engine_result):
    with tempfile.TemporaryDirectory() as name:  # outside the session's folders, which the end-of-session sweep reads
        folder = Path(name)
        for sub, result in (("good", engine_result), ("bad", {**engine_result, "extra": 1})):
            (folder / sub).mkdir()
            (folder / sub / "result.json").write_text(json.dumps(result))
        assert sweep_results(folder) == {folder / "bad" / "result.json": ["extra: Extra inputs are not permitted"]}


def test_openapi_publishes_every_payload_closed_and_only_problems_open():
    schemas = create_app(ServiceSettings(), start_background=False).openapi()["components"]["schemas"]
    objects = {name: schema for name, schema in schemas.items() if "properties" in schema}
    open_ones = sorted(name for name, schema in objects.items() if schema.get("additionalProperties") is not False)
    assert open_ones == ["ProblemDetails"]
    assert {"RegistrationResult", "ResultMetrics", "InputDecisionRecord", "JobStatus", "Review"} <= set(objects)
