"""Sub-command functions named, not imported: a parser sets ``func=deferred("module:function")`` and the
module (torch, the renderer...) loads only when that command runs, so ``dsareg --help`` and argument
errors stay fast."""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable


def deferred(target: str) -> Callable[[argparse.Namespace], int]:
    """A ``(args) -> int`` that imports ``module`` and calls ``module.function`` of ``"module:function"``."""
    module_name, _, function_name = target.partition(":")

    def run(args: argparse.Namespace) -> int:
        return getattr(importlib.import_module(module_name), function_name)(args)

    run.__name__ = run.__qualname__ = function_name
    run.__module__ = module_name
    return run
