"""The stages' optimizers without importing ``torch._dynamo``.

``torch.optim``'s optimizers import the compiler (``torch._dynamo``) on first use: their methods are wrapped to
disable it, and the wrapper imports it on its first call. That is 1.8 CPU s in every process that registers once
(a ``dsareg register`` run: its largest import, for a compiler nothing here uses).

- :class:`Adam`: Adam's update of one tensor (no weight decay, no AMSGrad), in the order and with the operations of
  ``torch.optim.Adam``'s one-tensor path: the same values bit for bit (five tensor operations).
- :func:`lbfgs`: ``torch.optim.LBFGS`` itself (its line search is not rewritten here), built with the compiler-off
  wrapper of ``Optimizer.add_param_group`` given its disabled function up front (the function itself: nothing is
  compiled), so the wrapper does not import the compiler. A torch whose wrapper works otherwise pays the import
  again, and ``tests/unit/registration/test_optim.py`` says so.
"""

from __future__ import annotations

import torch


class Adam:
    """Adam on ``parameter`` (a leaf tensor that requires grad): ``zero_grad()``, backward, ``step()``, as with
    ``torch.optim.Adam([parameter], lr, betas, eps)``."""

    def __init__(self, parameter: torch.Tensor, lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8):
        self.parameter, self.lr, self.betas, self.eps = parameter, float(lr), betas, float(eps)
        self.steps = 0
        self.exp_avg = torch.zeros_like(parameter, memory_format=torch.preserve_format)
        self.exp_avg_sq = torch.zeros_like(parameter, memory_format=torch.preserve_format)

    def zero_grad(self) -> None:
        self.parameter.grad = None

    @torch.no_grad()
    def step(self) -> None:
        grad = self.parameter.grad
        if grad is None:
            return
        beta1, beta2 = self.betas
        self.steps += 1
        step = float(self.steps)  # torch counts in a float tensor and reads it back as a Python float
        self.exp_avg.lerp_(grad, 1 - beta1)
        self.exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        step_size = self.lr / (1 - beta1 ** step)
        bias_correction2_sqrt = (1 - beta2 ** step) ** 0.5
        denom = (self.exp_avg_sq.sqrt() / bias_correction2_sqrt).add_(self.eps)
        self.parameter.addcdiv_(self.exp_avg, denom, value=-step_size)


def lbfgs(parameter: torch.Tensor, **settings) -> torch.optim.LBFGS:
    """``torch.optim.LBFGS([parameter], **settings)`` without importing the compiler; clear the gradient with
    ``parameter.grad = None`` (``zero_grad`` is wrapped too)."""
    add_param_group = getattr(torch.optim.Optimizer.add_param_group, "__wrapped__", None)
    if add_param_group is not None and getattr(add_param_group, "__dynamo_disable", None) is None:
        add_param_group.__dynamo_disable = add_param_group  # the wrapper's cache: call the function as it is
    return torch.optim.LBFGS([parameter], **settings)


__all__ = ["Adam", "lbfgs"]
