"""Serial twins of the numba kernels: chosen on a 1-thread budget, equal to the parallel kernels."""

import numba
import numpy as np
import pytest
import torch

from dsareg_engine.geometry.spec import load_rig
from dsareg_engine.simulation.phantom import make_vessel_phantom
from dsareg_engine.geometry.pose import make_transform, rotation_about_axis
from dsareg_engine.registration.search import initialization
from dsareg_engine.render import Camera, SilhouetteSettings, render_hard_silhouette, render_soft_silhouette, silhouette
from dsareg_engine.render.serial_kernels import KernelPair


@pytest.fixture
def one_thread():
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(before)


def _force(monkeypatch, which: str) -> None:
    """Make every kernel pair answer its ``which`` ('serial' or 'parallel') kernel, whatever the budget."""
    for pair in [*silhouette._KERNELS.values(), *initialization._SEARCH_KERNELS.values()]:
        monkeypatch.setattr(pair, "pick", lambda n, pair=pair: getattr(pair, which))


def _render(dtype: torch.dtype) -> dict[str, np.ndarray]:
    """Soft silhouettes of 3 poses of the phantom, their gradients (pose, vertices) and the hard silhouettes."""
    view = load_rig("paper").views["ap"].resized(96, 80)
    mesh = make_vessel_phantom()
    vertices, faces = mesh.torch(dtype)
    vertices = vertices.clone().requires_grad_()
    poses = np.stack([view.world_to_view @ make_transform(rotation_about_axis([0.3, 1.0, 0.2], a), [1.0, -2.0, 3.0])
                      for a in (0.0, 0.1, 0.25)])
    pose = torch.as_tensor(poses, dtype=dtype).requires_grad_()
    settings = SilhouetteSettings(sigma_px=1.2, backend="numba")
    soft = render_soft_silhouette(vertices, faces, pose, Camera.from_view(view), settings)
    target = torch.linspace(0.0, 1.0, soft.numel(), dtype=dtype).reshape(soft.shape)
    ((soft - target) ** 2).sum().backward()
    hard = render_hard_silhouette(vertices.detach(), faces, pose.detach(), Camera.from_view(view), settings)
    return {"soft": soft.detach().numpy(), "grad_pose": pose.grad.numpy(), "grad_vertices": vertices.grad.numpy(),
            "hard": hard.numpy()}


def test_one_thread_budget_picks_the_serial_twins(one_thread):
    for name, pair in silhouette._KERNELS.items():
        assert silhouette._kernel(name) == (pair.serial, 1)
        assert pair.pick(2) is pair.parallel
    assert initialization._SEARCH_KERNELS["splat_overlap"].pick(numba.get_num_threads()) is \
        initialization._SEARCH_KERNELS["splat_overlap"].serial


def test_twins_are_serial_builds_cached_under_their_own_name():
    pair = silhouette._KERNELS["soft_log_keep"]
    assert pair.parallel.targetoptions["parallel"] is True
    assert not pair.serial.targetoptions.get("parallel")
    assert pair.serial.targetoptions["fastmath"] == pair.parallel.targetoptions["fastmath"]
    assert pair.serial.py_func.__code__ is pair.parallel.py_func.__code__  # one source
    # numba's cache key ignores `parallel`: the same name would load the other build
    assert pair.serial._cache._cache_file._index_name != pair.parallel._cache._cache_file._index_name


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_serial_twins_render_what_the_parallel_kernels_render(monkeypatch, one_thread, dtype):
    _force(monkeypatch, "parallel")
    parallel = _render(dtype)
    _force(monkeypatch, "serial")
    serial = _render(dtype)
    assert parallel["hard"].sum() > 200 and np.abs(parallel["grad_pose"]).max() > 0
    np.testing.assert_array_equal(serial["hard"], parallel["hard"])
    for key in ("soft", "grad_pose", "grad_vertices"):
        # same operations in the same order; LLVM may still contract/vectorize a parallel loop body differently
        np.testing.assert_allclose(serial[key], parallel[key], rtol=1e-6 if dtype == torch.float32 else 1e-12,
                                   atol=1e-7 if dtype == torch.float32 else 1e-14, err_msg=key)


def test_serial_search_kernels_score_what_the_parallel_ones_score(one_thread):
    rng = np.random.default_rng(3)
    points = rng.normal(0.0, 5.0, (300, 3))
    turns = np.stack([rotation_about_axis(rng.normal(size=3), a) for a in rng.uniform(0, 3, 20)])
    offsets = np.column_stack([rng.normal(0, 2, 20), rng.normal(0, 2, 20), rng.uniform(400, 600, 20)])
    intrinsics = np.array([900.0, 900.0, 32.0, 30.0])
    target = rng.uniform(0.0, 1.0, (60, 64)).astype(np.float32)
    for name, extra in (("mean_pixels", ()), ("splat_overlap", (target,))):
        pair: KernelPair = initialization._SEARCH_KERNELS[name]
        outs = []
        for kernel in (pair.parallel, pair.serial):
            out = np.empty((20, 2))
            kernel(points, turns, offsets, intrinsics, *extra, out)
            outs.append(out)
        assert np.isfinite(outs[0]).all() and np.abs(outs[0]).max() > 0
        np.testing.assert_allclose(outs[1], outs[0], rtol=1e-12, atol=0, err_msg=name)
