"""Per-pixel pose Jacobian of the soft silhouette (forward-mode kernel) against autograd and differences."""

import numpy as np
import pytest
import torch

from dsareg_engine.geometry.spec import load_rig
from dsareg_engine.simulation.phantom import make_vessel_phantom
from dsareg_engine.registration.parameterization import PoseIncrement
from dsareg_engine.render import Camera, SilhouetteSettings, render_soft_silhouette
from dsareg_engine.render.jacobian import render_soft_silhouette_jacobian


@pytest.fixture(scope="module")
def case():
    """Phantom, a 200-px LAT view, a pose increment about an off-identity pose, and ∂mesh_to_view/∂δ (1, 6, 4, 4)."""
    phantom = make_vessel_phantom()
    view = load_rig("paper").views["lat"].resized(200, 200)
    base = PoseIncrement(np.eye(4)[None], phantom.centroid, 1.0).poses(torch.tensor([[0.02, -0.01, 0.03, 0.5, -0.3, 0.2]]))
    increment = PoseIncrement(base, phantom.centroid, 20.0)
    tangents = torch.as_tensor(view.world_to_view @ increment.tangents()[0])[None]
    return phantom, view, increment, tangents


def _mesh_to_view(view, increment, delta):
    return torch.as_tensor(view.world_to_view) @ increment(delta)


@pytest.mark.parametrize("sigma_px", [0.1, 0.5])
def test_jacobian_transposed_equals_the_backward_pass(case, sigma_px):
    phantom, view, increment, tangents = case
    vertices, faces = phantom.torch(torch.float64)
    camera, settings = Camera.from_view(view), SilhouetteSettings(sigma_px=sigma_px)
    delta = torch.zeros((1, 6), dtype=torch.float64, requires_grad=True)
    alpha = render_soft_silhouette(vertices, faces, _mesh_to_view(view, increment, delta), camera, settings)
    weights = torch.rand_like(alpha, generator=torch.Generator().manual_seed(0))
    (alpha * weights).sum().backward()
    ours, jacobian = render_soft_silhouette_jacobian(vertices, faces, _mesh_to_view(view, increment, delta.detach()),
                                                     tangents, camera, settings, min_log_keep=-np.inf)
    assert torch.allclose(ours, alpha.detach(), atol=1e-14)
    assert jacobian.shape == (1, 200, 200, 6) and jacobian.abs().sum() > 0
    assert torch.allclose((jacobian * weights[..., None]).sum(dim=(0, 1, 2)), delta.grad[0], rtol=1e-10, atol=1e-12)


def test_jacobian_matches_central_differences_and_skipping_deep_pixels_changes_little(case):
    phantom, view, increment, tangents = case
    vertices, faces = phantom.torch(torch.float64)
    camera, settings = Camera.from_view(view), SilhouetteSettings(sigma_px=0.5)
    zero = torch.zeros((1, 6), dtype=torch.float64)
    _, exact = render_soft_silhouette_jacobian(vertices, faces, _mesh_to_view(view, increment, zero), tangents, camera,
                                               settings, min_log_keep=-np.inf)
    for k in range(6):
        step = torch.zeros((1, 6), dtype=torch.float64)
        step[0, k] = 1e-6
        plus = render_soft_silhouette(vertices, faces, _mesh_to_view(view, increment, step), camera, settings)
        minus = render_soft_silhouette(vertices, faces, _mesh_to_view(view, increment, -step), camera, settings)
        difference = (plus - minus) / 2e-6
        assert torch.allclose(exact[..., k], difference, atol=1e-5 * difference.abs().max()), k
    _, skipped = render_soft_silhouette_jacobian(vertices, faces, _mesh_to_view(view, increment, zero), tangents, camera, settings)
    assert (skipped - exact).abs().max() < 1e-3 * exact.abs().max()  # exp(MIN_LOG_KEEP) ≈ 6e-6 × a bounded slope


def test_float32_jacobian_is_close_to_float64(case):
    phantom, view, increment, tangents = case
    camera, settings = Camera.from_view(view), SilhouetteSettings(sigma_px=0.25)
    pose = _mesh_to_view(view, increment, torch.zeros((1, 6), dtype=torch.float64))
    results = [render_soft_silhouette_jacobian(*phantom.torch(dtype), pose.to(dtype), tangents.to(dtype), camera, settings)
               for dtype in (torch.float64, torch.float32)]
    assert results[1][1].dtype == torch.float32
    assert (results[1][0].double() - results[0][0]).abs().max() < 1e-5
    assert (results[1][1].double() - results[0][1]).abs().max() < 1e-4 * results[0][1].abs().max()


def test_pose_tangents_and_inverse_increment():
    rng = np.random.default_rng(1)
    base = PoseIncrement(np.eye(4)[None], np.array([1.0, 2.0, 3.0]), 1.0).poses(torch.as_tensor(rng.normal(size=(2, 6)) * 0.3))
    increment = PoseIncrement(base, np.array([5.0, -2.0, 7.0]), 33.0)
    delta = torch.as_tensor(rng.normal(size=(2, 6)))
    assert np.allclose(increment.delta_of(increment.poses(delta)), delta.numpy(), atol=1e-12)
    forward = torch.func.jacfwd(increment)(torch.zeros((2, 6), dtype=torch.float64))  # (2, 4, 4, 2, 6)
    expected = np.stack([forward[b, :, :, b, :].permute(2, 0, 1).numpy() for b in range(2)])
    assert np.allclose(increment.tangents(), expected, atol=1e-14)


def test_one_thread_budget_uses_serial_twins_that_match_the_parallel_kernels(case, monkeypatch):
    """A service worker tracks with a 1-thread budget: the Jacobian kernels run their serial twins
    (no numba pool hand-off, see serial_kernels) and give the parallel kernels' numbers. In float32 with the
    argument types tracking passes (gauss_newton.normal_equations: a window of the image as the target), the
    kernels ``dsareg warmup`` compiled for both budgets: loaded from the cache, not compiled here."""
    import numba

    from dsareg_engine.render import jacobian
    from dsareg_engine.render.jacobian_numba import normal_equations

    phantom, view, increment, tangents = case
    vertices, faces = phantom.torch(torch.float32)
    pose = _mesh_to_view(view, increment, torch.zeros((1, 6), dtype=torch.float64))
    camera = Camera.from_view(view)

    def run(n_threads: int):
        before = numba.get_num_threads()
        numba.set_num_threads(n_threads)
        try:
            kernel, used = jacobian.jacobian_kernel("normal_equations")
            log_keep, log_keep_tangents = jacobian.soft_log_keep_tangents(
                vertices, faces, pose.float(), tangents.float(), camera, SilhouetteSettings(sigma_px=0.5))
            hessian, gradient = np.zeros((6, 6)), np.zeros(6)
            target = np.zeros((log_keep.shape[1], log_keep.shape[2] + 1), np.float32)[:, 1:]
            target[80:120, 60:140] = 1.0
            loss = kernel(log_keep[0], log_keep_tangents[0], target, np.zeros((0, 0), np.float32), used, hessian,
                          gradient)
            return kernel, log_keep, log_keep_tangents, loss, hessian, gradient
        finally:
            numba.set_num_threads(before)

    serial, parallel = run(1), run(2) if numba.config.NUMBA_NUM_THREADS >= 2 else run(1)
    assert serial[0] is jacobian._KERNEL_PAIRS["normal_equations"].serial
    assert serial[0] is not normal_equations and not serial[0].targetoptions.get("parallel")
    assert serial[1].dtype == np.float32 and np.abs(serial[2]).max() > 0 and np.abs(serial[5]).max() > 0
    for ours, theirs in zip(serial[1:], parallel[1:]):
        np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-12)
