"""Images without headers given the wrong way round: the failed verdict says they look swapped."""

import numpy as np
import torch

from dsareg_engine.geometry.pose import make_transform, rotation_about_axis
from dsareg_engine.geometry.rig import Rig
from dsareg_engine.io.case import Case
from dsareg_engine.io.dicom_xa import view_from_angles
from dsareg_engine.pipeline import run_registration_case
from dsareg_engine.registration import RegistrationOptions
from dsareg_engine.render import Camera, render_hard_silhouette
from dsareg_engine.simulation.phantom import make_vessel_phantom


def test_a_swapped_pair_of_masks_fails_with_a_reason_that_says_swapped(tmp_path):
    phantom = make_vessel_phantom(depth=2, seed=3)
    views = {name: view_from_angles(angle, 0.0, 1100.0, 760.0, (1.0, 1.0), (96, 96))
             for name, angle in (("ap", 0.0), ("lat", 90.0))}
    truth = make_transform(rotation_about_axis(np.array([0.3, -0.5, 0.8]), np.radians(6.0)), np.array([3.0, -2.0, 3.5]))
    vertices, faces = phantom.torch(torch.float64)
    masks = {name: render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ truth)[None],
                                          Camera.from_view(view))[0].numpy().astype(bool) for name, view in views.items()}
    case = Case(mesh=phantom, masks={"ap": masks["lat"], "lat": masks["ap"]}, rig=Rig(views))
    options = RegistrationOptions(initialization="given", initial_mesh_to_world=truth.tolist(), starts=1, max_iterations=40,
                                  mirror_check=True)  # poor fits get their extra fits
    data = run_registration_case(case, options, tmp_path)
    assert data["verdict"] == "failed", data["metrics"]["confidence"]
    assert any("look swapped" in reason for reason in data["metrics"]["confidence"]["reasons"])
