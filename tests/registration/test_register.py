"""Two-view registration on the built-in phantom at small image sizes."""

import numpy as np
import pytest

from dsareg_engine.errors import DsaregInputError
from dsareg_engine.registration import RegistrationCanceled, RegistrationOptions, register


def test_two_view_registration_recovers_a_5deg_5mm_offset(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 400, 5.0, 5.0)
    events = []
    result = register(phantom, masks, rig, RegistrationOptions(starts=2, ground_truth_mesh_to_world=np.eye(4).tolist()), progress=events.append)
    truth = result.metrics["ground_truth"]
    assert truth["initial_mtre_mm"] > 4.0
    assert truth["rotation_error_deg"] < 0.5
    assert truth["add_mm"] < 0.3
    assert truth["translation_error_mm"] < 1.0
    assert result.metrics["converged"], result.metrics["reason"]
    assert min(view.dice for view in result.views.values()) > 0.95
    assert events and 0 < events[-1]["fraction"] < 1 and {"stage", "iteration", "loss"} <= set(events[-1])
    data = result.to_dict()
    assert np.allclose(np.asarray(data["views"]["ap"]["mesh_to_view"]), rig.views["ap"].world_to_view @ result.mesh_to_world)
    p = np.asarray(data["views"]["lat"]["projection_matrix"])
    point = np.append(phantom.vertices[0], 1.0)
    projected = p @ point
    assert np.allclose(projected[:2] / projected[2], rig.views["lat"].project((result.mesh_to_world @ point)[None, :3])[0])


def test_sequential_configuration_reports_both_phases(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 200, 3.0, 3.0)
    result = register(phantom, masks, rig, RegistrationOptions(configuration="lat_then_ap", starts=1, max_iterations=40))
    stages = list(result.metrics["iterations"])
    assert stages[0].startswith("lat:") and stages[-1].startswith("ap+lat:")
    assert set(result.metrics["seconds"]) >= set(stages) | {"total"}


def test_single_view_registration_runs_on_one_mask(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 200, 2.0, 2.0)
    result = register(phantom, {"ap": masks["ap"]}, rig, RegistrationOptions(configuration="ap", starts=1, max_iterations=30))
    assert set(result.views) == {"ap"}


def test_cancel_stops_between_iterations(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 200, 2.0, 2.0)
    calls = {"n": 0}

    def should_stop():
        calls["n"] += 1
        return calls["n"] > 3

    with pytest.raises(RegistrationCanceled):
        register(phantom, masks, rig, RegistrationOptions(starts=1), should_stop=should_stop)
    assert calls["n"] == 4


def test_mask_of_wrong_size_is_a_clear_error(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 200, 2.0, 2.0)
    masks["lat"] = masks["lat"][:100]
    with pytest.raises(DsaregInputError, match="lat.*200x100"):
        register(phantom, masks, rig)


def test_empty_mask_is_a_clear_error(phantom, synthetic_case):
    rig, masks = synthetic_case(phantom, 200, 2.0, 2.0)
    masks["ap"] = np.zeros_like(masks["ap"])
    with pytest.raises(DsaregInputError, match="empty"):
        register(phantom, masks, rig)
