"""The stages' optimizers (:mod:`dsareg_engine.registration.optim`): Adam gives torch.optim.Adam's values bit for
bit, and neither Adam nor L-BFGS stages import torch._dynamo."""

import subprocess
import sys

import pytest
import torch

from dsareg_engine.registration.optim import Adam


def _descend(make_optimizer, dtype, lr, steps=40):
    """``steps`` updates of a (3, 6) parameter on a fixed non-convex loss; the parameter after each."""
    generator = torch.Generator().manual_seed(7)
    target = torch.randn((3, 6), generator=generator, dtype=dtype)
    scale = torch.rand((3, 6), generator=generator, dtype=dtype) * 10 + 0.1
    parameter = torch.zeros((3, 6), dtype=dtype, requires_grad=True)
    optimizer = make_optimizer(parameter, lr)
    trail = []
    for _ in range(steps):
        optimizer.zero_grad()
        loss = (scale * (parameter - target) ** 2).sum() + torch.sin(3 * parameter).sum()
        loss.backward()
        optimizer.step()
        trail.append(parameter.detach().clone())
    return trail


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("lr", [0.5, 0.1, 0.003])
def test_the_same_values_as_torch_optim_adam(dtype, lr):
    ours = _descend(lambda p, rate: Adam(p, lr=rate), dtype, lr)
    torch_s = _descend(lambda p, rate: torch.optim.Adam([p], lr=rate), dtype, lr)
    for step, (a, b) in enumerate(zip(ours, torch_s)):
        assert torch.equal(a, b), f"step {step + 1} differs: {(a - b).abs().max()}"
    assert not torch.equal(ours[0], ours[-1])  # it moved


def test_a_step_without_a_gradient_changes_nothing():
    parameter = torch.ones(4, requires_grad=True)
    optimizer = Adam(parameter, lr=0.1)
    optimizer.step()
    assert torch.equal(parameter.detach(), torch.ones(4)) and optimizer.steps == 0


@pytest.mark.parametrize("runner", ["_run_adam", "_run_lbfgs"])
def test_a_registration_stage_does_not_import_the_compiler(runner):
    """torch.optim's optimizers import torch._dynamo on first use (1.8 CPU s); the stages must not."""
    code = (
        "import sys, torch\n"
        f"from dsareg_engine.registration.optimizers import {runner} as run\n"
        "from dsareg_engine.registration.schedule import Stage\n"
        "class P:\n"
        "    def loss(self, poses, stage, dtype): return (poses ** 2).sum(-1)\n"
        "    def target(self, view, stage, dtype): return type('T', (), {'target': torch.zeros(4, 4)})()\n"
        "stage = Stage('ap:1/1', 1.0, 0.5, 0.0, ('ap',), 'adam', 5, 0.1, True)\n"
        "delta = torch.ones((2, 6), dtype=torch.float64, requires_grad=True)\n"
        "run(P(), stage, lambda d: d, delta, torch.float64, lambda *a: None)\n"
        "assert float(delta.detach().abs().max()) < 1.0\n"
        "print('torch._dynamo' in sys.modules)\n"
    )
    shown = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert shown.returncode == 0, shown.stderr[-2000:]
    assert shown.stdout.strip() == "False"


def test_lbfgs_is_torchs_and_steps_as_before():
    """:func:`lbfgs` is torch.optim.LBFGS: the same minimum and evaluations as one built the usual way."""
    from dsareg_engine.registration.optim import lbfgs

    def minimise(make):
        parameter = torch.tensor([1.5, -0.7, 2.0], dtype=torch.float64, requires_grad=True)
        optimizer = make(parameter)
        losses = []

        def closure():
            parameter.grad = None
            loss = ((parameter - torch.tensor([0.3, 0.2, -0.1], dtype=torch.float64)) ** 4).sum() + (parameter ** 2).sum()
            loss.backward()
            losses.append(float(loss.detach()))
            return loss

        optimizer.step(closure)
        return parameter.detach(), losses

    settings = {"lr": 1.0, "max_iter": 40, "history_size": 10, "line_search_fn": "strong_wolfe"}
    ours, ours_losses = minimise(lambda p: lbfgs(p, **settings))
    theirs, their_losses = minimise(lambda p: torch.optim.LBFGS([p], **settings))
    assert isinstance(lbfgs(torch.zeros(1, requires_grad=True), **settings), torch.optim.LBFGS)
    assert torch.equal(ours, theirs) and ours_losses == their_losses and len(ours_losses) > 3
