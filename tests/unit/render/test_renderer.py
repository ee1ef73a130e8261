"""Silhouette renderer: gradients, agreement with an independent rasterization, edge cases."""

import numpy as np
import pytest
import torch
from skimage.draw import polygon as fill_polygon

from dsareg_engine.geometry.rig import ViewGeometry, view_from_detector_pose
from dsareg_engine.geometry.spec import load_rig
from dsareg_engine.metrics import iou
from dsareg_engine.simulation.phantom import make_vessel_phantom
from dsareg_engine.geometry.pose import make_transform, rotation_about_axis
from dsareg_engine.render import Camera, SilhouetteSettings, render_hard_silhouette, render_soft_silhouette


def reference_raster(view: ViewGeometry, vertices: np.ndarray, faces: np.ndarray, mesh_to_world: np.ndarray) -> np.ndarray:
    """Independent hard silhouette: fill every projected triangle with skimage (pixel centres)."""
    pixels = view.project(vertices @ mesh_to_world[:3, :3].T + mesh_to_world[:3, 3])
    image = np.zeros((view.height, view.width), bool)
    for face in faces:
        rows, cols = fill_polygon(pixels[face, 1], pixels[face, 0], shape=image.shape)
        image[rows, cols] = True
    return image


@pytest.fixture(scope="module")
def phantom():
    return make_vessel_phantom()


def test_hard_silhouette_matches_independent_raster(phantom):
    view = load_rig("paper").views["lat"].resized(300, 300)
    vertices, faces = phantom.torch(torch.float64)
    ours = render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view)[None], Camera.from_view(view))[0].numpy()
    reference = reference_raster(view, phantom.vertices, phantom.faces, np.eye(4))
    assert reference.sum() > 1000
    assert iou(ours, reference) >= 0.99


def test_mirrored_rad_style_view_matches_independent_raster(phantom):
    detector_to_world = make_transform(rotation_about_axis([0.2, 1.0, 0.1], 1.2), [-300.0, -100.0, 40.0])
    source = detector_to_world[:3, :3] @ np.array([60.0, 50.0, 900.0]) + detector_to_world[:3, 3]
    view = view_from_detector_pose((240, 200), (0.5, 0.5), detector_to_world, source)
    assert view.is_mirrored
    centre = view.source_position_world + 600.0 * (np.linalg.inv(view.world_to_view)[:3, 2])
    pose = make_transform(np.eye(3), centre)
    vertices, faces = phantom.torch(torch.float64)
    ours = render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ pose)[None], Camera.from_view(view))[0].numpy()
    reference = reference_raster(view, phantom.vertices, phantom.faces, pose)
    assert reference.sum() > 500
    assert iou(ours, reference) >= 0.99


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_soft_silhouette_gradcheck(backend):
    vertices = torch.tensor([[-3.0, -2.0, 0.0], [4.0, -1.0, 1.0], [0.5, 3.5, -1.0], [1.0, 0.0, 3.0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 1, 3]])
    camera = Camera((40.0, 40.0), (7.3, 6.8), 16, 14)
    settings = SilhouetteSettings(sigma_px=1.5, backend=backend)
    pose = torch.eye(4, dtype=torch.float64)[None].clone()
    pose[0, 2, 3] = 25.0

    def render(translation, verts):
        p = pose.clone()
        p[0, :3, 3] = p[0, :3, 3] + translation
        return render_soft_silhouette(verts, faces, p, camera, settings)

    translation = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64, requires_grad=True)
    verts = vertices.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(render, (translation, verts), eps=1e-6, atol=1e-5)


def test_numba_and_torch_backends_agree(phantom):
    view = load_rig("paper").views["ap"].resized(160, 160)
    vertices, faces = phantom.torch(torch.float64)
    results = {}
    for backend in ("numba", "torch"):
        pose = torch.as_tensor(view.world_to_view)[None].clone().requires_grad_(True)
        alpha = render_soft_silhouette(vertices, faces, pose, Camera.from_view(view), SilhouetteSettings(sigma_px=1.0, backend=backend))
        (alpha * torch.linspace(0, 1, alpha.numel(), dtype=torch.float64).view_as(alpha)).sum().backward()
        results[backend] = (alpha.detach(), pose.grad)
    assert torch.allclose(results["numba"][0], results["torch"][0], atol=1e-9)
    assert torch.allclose(results["numba"][1], results["torch"][1], rtol=1e-6, atol=1e-9)


def test_backends_agree_on_large_sliver_and_degenerate_faces():
    """Faces far larger than the kernels' flat chunks, a sliver, a zero-area face, two poses."""
    vertices = torch.tensor(
        [[-30.0, -25.0, 0.0], [35.0, -20.0, 2.0], [5.0, 30.0, -1.0],  # covers most of the image
         [-20.0, 10.0, 0.0], [20.0, 10.4, 0.0], [-19.0, 10.1, 0.0],  # sliver
         [0.0, -5.0, 0.0], [4.0, -1.0, 0.0], [8.0, 3.0, 0.0]],  # collinear: zero area
        dtype=torch.float64,
    )
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    camera = Camera((60.0, 55.0), (47.5, 40.0), 96, 81)
    pose = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    pose[:, 2, 3] = torch.tensor([70.0, 90.0])
    pose[1, 0, 3] = 3.0
    weights = torch.rand((2, 81, 96), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    results = {}
    for backend in ("numba", "torch"):
        verts = vertices.clone().requires_grad_(True)
        alpha = render_soft_silhouette(verts, faces, pose, camera, SilhouetteSettings(sigma_px=2.0, backend=backend))
        (alpha * weights).sum().backward()
        results[backend] = (alpha.detach(), verts.grad)
    assert results["numba"][0].max() > 0.99 and results["numba"][0].min() < 0.01
    assert torch.allclose(results["numba"][0], results["torch"][0], atol=1e-9)
    # The zero-area face's edges overlap, so its vertex gradients are ambiguous (ties); not compared.
    assert torch.allclose(results["numba"][1][:6], results["torch"][1][:6], rtol=1e-6, atol=1e-9)


def test_float32_tables_close_to_exact(phantom):
    view = load_rig("paper").views["ap"].resized(160, 160)
    pose = torch.as_tensor(view.world_to_view)[None]
    images = [
        render_soft_silhouette(*phantom.torch(dtype), pose.to(dtype), Camera.from_view(view), SilhouetteSettings(sigma_px=1.0))
        for dtype in (torch.float32, torch.float64)
    ]
    assert torch.allclose(images[0].double(), images[1], atol=1e-4)


def test_soft_thresholded_agrees_with_hard_at_small_sigma(phantom):
    view = load_rig("paper").views["lat"].resized(300, 300)
    vertices, faces = phantom.torch(torch.float64)
    pose = torch.as_tensor(view.world_to_view)[None]
    hard = render_hard_silhouette(vertices, faces, pose, Camera.from_view(view))[0].numpy()
    soft = render_soft_silhouette(vertices, faces, pose, Camera.from_view(view), SilhouetteSettings(sigma_px=0.002))[0].numpy()
    assert iou(soft >= 0.5, hard) >= 0.99


def test_faces_behind_the_source_are_dropped_and_borders_are_clipped():
    camera = Camera((50.0, 50.0), (9.5, 9.5), 20, 20)
    # One triangle in front, straddling the right border; one crossing z = 0.
    vertices = torch.tensor(
        [[0.0, -2.0, 10.0], [8.0, -2.0, 10.0], [0.0, 2.0, 10.0], [1.0, 1.0, -5.0], [2.0, 1.0, 5.0], [1.0, 3.0, 5.0]],
        dtype=torch.float64,
    )
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])
    pose = torch.eye(4, dtype=torch.float64)[None]
    hard = render_hard_silhouette(vertices, faces, pose, camera)[0]
    soft = render_soft_silhouette(vertices, faces, pose, camera, SilhouetteSettings(sigma_px=0.5))[0]
    assert torch.isfinite(soft).all()
    # Only the front triangle is drawn: pixels with u ≥ 9.5, |v − 9.5| small, none from the other.
    columns = hard.any(dim=0).nonzero().flatten()
    assert columns.min() >= 9 and columns.max() == 19  # clipped at the right border
    behind_only = render_hard_silhouette(vertices, faces[1:], pose, camera)[0]
    assert not behind_only.any()


def test_batch_renders_each_pose(phantom):
    view = load_rig("paper").views["ap"].resized(100, 100)
    vertices, faces = phantom.torch(torch.float32)
    base = torch.as_tensor(view.world_to_view, dtype=torch.float32)
    shifted = base.clone()
    shifted[0, 3] += 20.0
    batch = render_soft_silhouette(vertices, faces, torch.stack([base, shifted]), Camera.from_view(view))
    single = render_soft_silhouette(vertices, faces, shifted[None], Camera.from_view(view))
    assert torch.allclose(batch[1], single[0])
    assert not torch.allclose(batch[0], batch[1])
