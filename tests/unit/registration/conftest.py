import numpy as np
import pytest
import torch

from dsareg_engine.geometry.rig import Rig
from dsareg_engine.geometry.spec import load_rig
from dsareg_engine.simulation.phantom import make_vessel_phantom
from dsareg_engine.registration.parameterization import random_start_poses
from dsareg_engine.render import Camera, render_hard_silhouette


@pytest.fixture(scope="session")
def phantom():
    return make_vessel_phantom()


@pytest.fixture(scope="session")
def synthetic_case():
    return make_synthetic_case


def make_synthetic_case(mesh, size: int, offset_deg: float, offset_mm: float, seed: int = 1):
    """Paper rig resized to ``size``; masks at the identity pose; initial pose offset by the given amounts."""
    paper = load_rig("paper")
    initial = random_start_poses(np.eye(4), mesh.centroid, 2, offset_deg, offset_mm, seed=seed)[1]
    rig = Rig({name: view.resized(size, size) for name, view in paper.views.items()}, initial)
    vertices, faces = mesh.torch(torch.float64)
    masks = {
        name: render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view)[None], Camera.from_view(view))[0].numpy()
        for name, view in rig.views.items()
    }
    return rig, masks
