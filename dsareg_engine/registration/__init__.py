"""Two-view 3D/2D registration: options, schedule, optimization, result.

The heavy parts (torch, the renderer) load on first use, so importing the options alone —
as the HTTP API does to validate requests — stays light.
"""

from .options import CONFIGURATIONS, RegistrationOptions, parse_options

_LAZY = {
    "RegistrationCanceled": ".solver",
    "register": ".solver",
    "RegistrationResult": ".result",
    "ViewResult": ".result",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["CONFIGURATIONS", "RegistrationOptions", "parse_options", *_LAZY]
